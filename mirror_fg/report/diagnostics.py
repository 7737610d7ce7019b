"""Diagnostic figures of the calibration report: the residual against the distance from the image centre,
and the tracked points' paths and residuals over time.

Residuals as in :mod:`mirror_fg.report.residuals` (pixels, or normalized units without a camera; RMS as
result@1's ``rms_px``). Tracks are :class:`mirror_fg.vision.tracking.Track` (history of
:class:`~mirror_fg.vision.tracking.TrackSample`: frame, KLT pixel, refined pixel, refinement residual),
as ``mirror_fg.vision.detect.detect_capture(capture, tracks={})`` fills them.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.report.figures import new_figure
from mirror_fg.report.residuals import RADIAL_P_VALUE, RADIAL_RATIO, RadialProfile, Residuals

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.data import Dataset

__all__ = ["image_centre", "radial_verdict", "figure_radial", "figure_tracks", "MAX_TRACKS_DRAWN"]

#: Tracks drawn one by one (a legend entry each); beyond it, the worst ones by refinement residual.
MAX_TRACKS_DRAWN = 12


def image_centre(dataset: Dataset) -> tuple[float, float]:
    """The principal point (pixels), or (0, 0) for normalized observations."""
    return (dataset.camera.cx, dataset.camera.cy) if dataset.camera is not None else (0.0, 0.0)


def radial_verdict(profile: RadialProfile, units: str, estimated: Sequence[str] = ()) -> str:
    """One sentence for the report's verdict: does the residual grow towards the image edge? ``estimated``:
    the intrinsics the result estimated (the advice names the ``camera.estimate`` terms still to add)."""
    text = (f"residual RMS {profile.inner_rms:.3g} {units} in the inner third of the measurements by distance "
            f"from the image centre, {profile.outer_rms:.3g} {units} in the outer third")
    if profile.significant:
        more = [n for n in ("k1", "k2") if n not in estimated] or [n for n in ("k3", "p1", "p2") if n not in estimated]
        terms = ", ".join([*estimated, *more])
        advice = (f"or estimate the distortion with the mirrors: camera.estimate: [{terms}] in the dataset or capture"
                  if more else "the estimated distortion terms do not suffice: check the lens model")
        return (text + f" (× {profile.ratio:.2f}, one-sided F test p = {profile.p_value:.1e}): the residual grows towards "
                f"the edge — the signature of a wrong or missing distortion model (recalibrate the intrinsics, {advice})")
    return text + f" (× {profile.ratio:.2f}): no significant growth towards the edge"


def figure_radial(residuals: Residuals, profile: RadialProfile) -> Figure:
    """Residual length of every measurement against its distance from the image centre, with ring RMS."""
    fig = new_figure(9.0, 4.5)
    ax = fig.add_subplot()
    u = residuals.units
    ax.scatter(profile.radius, profile.length, s=4, c="tab:gray", alpha=0.35, label="each measurement")
    centres = 0.5 * (profile.edges[1:] + profile.edges[:-1])
    ax.plot(centres, profile.rms, "o-", color="tab:blue", lw=2, label="RMS in each ring")
    for x, y, n in zip(centres, profile.rms, profile.counts):
        if n:
            ax.annotate(f"n={n}", (x, y), textcoords="offset points", xytext=(0, 7), ha="center", fontsize=7)
    ax.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    top = float(np.nanmax([np.nanmax(profile.rms), residuals.expected_rms])) * 2.5
    ax.set_ylim(0.0, max(top, 1e-12))
    ax.set_xlabel(f"distance of the observed point from the image centre, {u}")
    ax.set_ylabel(f"reprojection error length, {u}")
    state = ("grows towards the edge: check the distortion model" if profile.significant
             else "no significant growth towards the edge")
    ax.set_title(f"Residual vs distance from the image centre — {state}\n(flagged when the outer third's RMS is "
                 f"> {RADIAL_RATIO:g} × the inner third's with p < {RADIAL_P_VALUE:g})", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    return fig


def figure_tracks(tracks: Mapping[str, Any], dataset: Dataset | None) -> Figure:
    """Each tracked point's path on the image (refined pixels; KLT's as a thin line) and, over the frames,
    the refinement's residual and how far it moved KLT's pixel."""
    items = [(name, t) for name, t in tracks.items() if t.history]
    if len(items) > MAX_TRACKS_DRAWN:
        items = sorted(items, key=lambda nt: -_worst_residual(nt[1]))[:MAX_TRACKS_DRAWN]
    fig = new_figure(11.0, 8.0)
    grid = fig.add_gridspec(2, 2)
    path_ax = fig.add_subplot(grid[:, 0])
    residual_ax = fig.add_subplot(grid[0, 1])
    shift_ax = fig.add_subplot(grid[1, 1], sharex=residual_ax)
    for k, (name, track) in enumerate(items):
        colour = f"C{k % 10}"
        frames = np.array([s.frame for s in track.history])
        refined = np.array([s.refined for s in track.history], dtype=float)
        raw = np.array([s.raw if s.raw is not None else s.refined for s in track.history], dtype=float)
        path_ax.plot(raw[:, 0], raw[:, 1], color=colour, lw=0.6, alpha=0.5)
        path_ax.plot(refined[:, 0], refined[:, 1], ".-", color=colour, ms=3, lw=1.2,
                     label=f"{name} ({track.kind}, {len(frames)} frames, σ {track.sigma():.2f} px)")
        path_ax.annotate(name, refined[0], fontsize=8, color=colour)
        fit = np.array([np.nan if s.residual_px is None else s.residual_px for s in track.history], dtype=float)
        residual_ax.plot(frames, fit, ".-", color=colour, ms=3, lw=1)
        shift_ax.plot(frames, [s.shift_px for s in track.history], ".-", color=colour, ms=3, lw=1)
    if dataset is not None and dataset.camera is not None:
        path_ax.set_xlim(0, dataset.camera.width)
        path_ax.set_ylim(dataset.camera.height, 0)
    else:
        path_ax.invert_yaxis()
    path_ax.set_aspect("equal", adjustable="box")
    path_ax.set_xlabel("u, px")
    path_ax.set_ylabel("v, px")
    shown = f"{len(items)} of {len(tracks)} (worst refinement residual first)" if len(items) < len(tracks) else str(len(items))
    path_ax.set_title(f"Paths of {shown} tracked point(s): refined (thick), KLT (thin)", fontsize=10)
    path_ax.legend(fontsize=7, loc="best")
    residual_ax.set_ylabel("refinement fit residual, px")
    residual_ax.set_title("Residual over time", fontsize=10)
    shift_ax.set_ylabel("refined − KLT distance, px")
    shift_ax.set_xlabel("frame")
    return fig


def _worst_residual(track: Any) -> float:
    fits = [s.residual_px for s in track.history if s.residual_px is not None]
    return max(fits) if fits else 0.0
