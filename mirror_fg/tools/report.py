"""Calibration report: a self-contained HTML page and a PDF (matplotlib, Agg) of a ``mirror-fg/result@1``.

Frames (docs/formats.md): {B} base, {C} camera (OpenCV: x right, y down, z forward); ``T_cam_base = (R, t)``
with ``Cp = R @ Bp + t``; the 3D scene is drawn in the base frame, metres. Residuals are
``predicted - observed`` in pixels when the dataset has a camera, else in normalized image
coordinates. "RMS" is the root mean square of the measurements' Euclidean residual lengths, as
``residuals.rms_px`` in result@1 (``sqrt(2) pixel_sigma`` expected under the noise model); the
histogram shows the x and y coordinates, each expected N(0, pixel_sigma).
"""
from __future__ import annotations

import base64
import html
import io
import math
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import atomic_write
from mirror_fg.core.geometry import nested_transform, project
from mirror_fg.io.result import mirror_vectors, pose, pose_covariance, transforms, validate_result
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.io.ros import (
    DEFAULT_BASE_FRAME,
    DEFAULT_CAMERA_FRAME,
    check_frame_name,
    rotation_to_quaternion_xyzw,
    rotation_to_rpy,
    sigma3_base_cam,
    static_transform_publisher_args,
    urdf_joint,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.io.dataset import Dataset

__all__ = ["write_report", "compute_residuals", "Residuals", "OUTLIER_FACTOR"]

#: An image is flagged when its RMS residual exceeds this many times the median image RMS.
OUTLIER_FACTOR = 3.0
#: Resolution of the PNG figures embedded in the HTML (dots per inch).
PNG_DPI = 100
#: Covariance labels in docs/formats.md's order: rotation about the camera axes, then translation.
COVARIANCE_LABELS = ("rx", "ry", "rz", "x", "y", "z")
_MIRROR_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


# --------------------------------------------------------------------------------------------------
# Residuals
# --------------------------------------------------------------------------------------------------


@dataclass
class Residuals:
    """Per-measurement residuals of a result on a dataset, in dataset order.

    ``predicted``, ``observed`` (N, 2): pixels (``units == "px"``) or normalized image coordinates
    (``units == "normalized"``). ``residual = predicted - observed``. Measurements whose prediction lies
    behind the camera are kept with NaN predictions and left out of every statistic.
    """

    units: str
    image_ids: list[str]
    names: list[str]
    is_fiducial: np.ndarray
    predicted: np.ndarray
    observed: np.ndarray
    sigma: float

    @property
    def residual(self) -> np.ndarray:
        """(N, 2) ``predicted - observed``."""
        return self.predicted - self.observed

    @property
    def valid(self) -> np.ndarray:
        """(N,) measurements with a finite prediction."""
        return np.all(np.isfinite(self.predicted), axis=1)

    @property
    def rms(self) -> float:
        """RMS of the Euclidean residual lengths (result@1's ``rms_px``); expected ``sqrt(2) sigma``."""
        r = self.residual[self.valid]
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if r.size else float("nan")

    @property
    def expected_rms(self) -> float:
        """``sqrt(2) sigma``: the RMS residual length when the residuals are N(0, sigma^2 I)."""
        return math.sqrt(2.0) * self.sigma

    @property
    def largest(self) -> float:
        """Largest Euclidean residual of one measurement."""
        r = self.residual[self.valid]
        return float(np.max(np.linalg.norm(r, axis=1))) if r.size else float("nan")

    def _rms_by(self, keys: Sequence[str]) -> dict[str, float]:
        r = self.residual
        ok = self.valid
        out: dict[str, float] = {}
        for key in dict.fromkeys(keys):  # first-seen order
            sel = ok & (np.asarray(keys) == key)
            if np.any(sel):
                out[key] = float(np.sqrt(np.mean(np.sum(r[sel] ** 2, axis=1))))
        return out

    def per_image_rms(self) -> dict[str, float]:
        """RMS residual of each image (dataset order)."""
        return self._rms_by(self.image_ids)

    def per_point_rms(self) -> dict[str, float]:
        """RMS residual of each point over the images that saw it (first-seen order)."""
        return self._rms_by(self.names)

    def flagged_images(self, factor: float = OUTLIER_FACTOR) -> dict[str, float]:
        """Images whose RMS exceeds ``factor`` times the median image RMS."""
        per_image = self.per_image_rms()
        if not per_image:
            return {}
        median = float(np.median(list(per_image.values())))
        return {k: v for k, v in per_image.items() if v > factor * median}


def compute_residuals(result: Mapping[str, Any], dataset: Dataset, *, source: str = "result") -> Residuals:
    """Residuals of every observation in ``dataset`` under the estimates in ``result`` (eqs. 5-9).

    Per image, ``(A, b) = nested_transform(R_cam_base, t_cam_base, [v(l, m) for each mirror])``; a
    point ``Bp`` (a fiducial, or the result's reconstruction point) is predicted at
    ``project(A @ Bp + b)``, distorted to pixels with ``dataset.camera`` when there is one.
    Raises DatasetError naming ``source`` (the result's file) on a malformed result, and naming it
    and the dataset's file when the dataset is not the result's (other mirrors, or a mirror
    configuration or point the result lacks).
    """
    return _residuals(validate_result(result, source), dataset, source)


def _residuals(result: Mapping[str, Any], dataset: Dataset, source: str) -> Residuals:
    """:func:`compute_residuals` of a validated result."""
    (R, t), _ = transforms(result)
    mirrors = mirror_vectors(result)
    points = {name: xyz for name, (xyz, _) in reconstruction_points(result).items()}
    mismatch = f"{source} does not belong to {dataset.source}"
    num_mirrors = max((l for l, _ in mirrors), default=dataset.num_mirrors)
    if num_mirrors != dataset.num_mirrors:
        raise DatasetError(f"{mismatch}: the result has {num_mirrors} mirror(s), the dataset {dataset.num_mirrors}")
    image_ids: list[str] = []
    names: list[str] = []
    fiducial: list[bool] = []
    predicted: list[np.ndarray] = []
    observed: list[np.ndarray] = []
    for image in dataset.images:
        if len(image.mirror_configs) != dataset.num_mirrors:
            raise DatasetError(f"{dataset.source}: image {image.id!r} has {len(image.mirror_configs)} mirror configs")
        vectors = []
        for l, m in enumerate(image.mirror_configs, start=1):
            if (l, int(m)) not in mirrors:
                raise DatasetError(
                    f"{mismatch}: image {image.id!r} uses mirror {l} configuration {m}, which the "
                    "result has no mirror vector for"
                )
            vectors.append(mirrors[(l, int(m))])
        A, b = nested_transform(R, t, vectors)  # eqs. (5)-(8)
        obs_names = list(image.observations)
        if not obs_names:
            continue
        base = []
        for name in obs_names:
            if name in dataset.fiducials:
                base.append(dataset.fiducials[name])
            elif name in points:
                base.append(points[name])
            else:
                raise DatasetError(
                    f"{mismatch}: image {image.id!r} observes {name!r}, which is neither a fiducial "
                    "nor a point of the result"
                )
        camera_points = np.asarray(base, dtype=float) @ A.T + b
        normalized = project(camera_points)  # eq. (9)
        normalized[camera_points[:, 2] <= 0.0] = np.nan  # behind the camera: no image
        if dataset.camera is not None:
            pixels = np.full_like(normalized, np.nan)
            ok = np.all(np.isfinite(normalized), axis=1)
            if np.any(ok):
                pixels[ok] = dataset.camera.distort(normalized[ok])
            normalized = pixels
        for i, name in enumerate(obs_names):
            image_ids.append(image.id)
            names.append(name)
            fiducial.append(name in dataset.fiducials)
            predicted.append(normalized[i])
            observed.append(np.asarray(image.observations[name], dtype=float))
    return Residuals(
        units="px" if dataset.camera is not None else "normalized",
        image_ids=image_ids,
        names=names,
        is_fiducial=np.array(fiducial, dtype=bool),
        predicted=np.array(predicted, dtype=float).reshape(-1, 2),
        observed=np.array(observed, dtype=float).reshape(-1, 2),
        sigma=float(dataset.pixel_sigma),
    )


# --------------------------------------------------------------------------------------------------
# Summary
# --------------------------------------------------------------------------------------------------


def _fmt(values: Any, digits: int = 4) -> str:
    """Numbers as ``[a, b, c]`` with ``digits`` significant digits; a scalar alone; None as an en dash."""
    if values is None:
        return "–"
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        return f"{float(arr):.{digits}g}"
    return "[" + ", ".join(f"{float(x):.{digits}g}" for x in arr.ravel()) + "]"


def _rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (degrees) of the rotation ``R1 R2^T``."""
    c = (float(np.trace(R1 @ R2.T)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


@dataclass
class _Summary:
    rows: list[tuple[str, str]]  # (label, value) for the table
    verdict: str  # one line: the at-a-glance assessment
    good: bool
    notes: list[str]


def _summary(
    result: Mapping[str, Any], dataset: Dataset | None, residuals: Residuals | None, base_frame: str
) -> _Summary:
    """Summary table rows, a one-line verdict and notes (``result`` validated)."""
    (R_cb, t_cb), (R_bc, t_bc) = transforms(result)
    rows: list[tuple[str, str]] = []
    notes: list[str] = []
    rows.append((f"T_base_cam translation (camera centre in {base_frame}), m", _fmt(t_bc, 6)))
    rows.append(("T_base_cam quaternion (x, y, z, w)", _fmt(rotation_to_quaternion_xyzw(R_bc), 6)))
    rows.append(("T_base_cam URDF rpy, deg", _fmt(np.rad2deg(rotation_to_rpy(R_bc)), 6)))
    rows.append(("T_cam_base R (rows)", "<br>".join(_fmt(row, 6) for row in R_cb)))
    rows.append(("T_cam_base t (base origin in camera), m", _fmt(t_cb, 6)))
    sigma = result.get("sigma3_cam_base") or {}
    rows.append(("3σ rotation (about camera axes), deg", _fmt(sigma.get("rotation_deg"), 3)))
    rows.append(("3σ position of T_cam_base, mm", _fmt(sigma.get("position_mm"), 3)))
    s_bc = sigma3_base_cam(result)
    if s_bc is not None:
        rows.append((f"3σ camera position in {base_frame}, mm", _fmt(s_bc["position_mm"], 3)))
    res = result.get("residuals") or {}
    if residuals is not None:
        units = residuals.units
    else:
        units = str(res.get("units") or "px")
    rows.append((f"RMS residual (result file), {units}", _fmt(res.get("rms_px"))))
    rows.append((f"largest residual (result file), {units}", _fmt(res.get("max_px"))))
    if residuals is not None:
        rows.append(
            (f"RMS / largest residual (recomputed), {units}", f"{_fmt(residuals.rms)} / {_fmt(residuals.largest)}")
        )
        rows.append(("measurements", str(int(np.sum(residuals.valid)))))
    outliers = res.get("outliers")
    if outliers is not None:
        rows.append(("measurements flagged by the calibration", str(len(outliers))))
    opt = result.get("optimizer") or {}
    rows.append(("iterations", "–" if opt.get("iterations") is None else str(opt["iterations"])))
    rows.append(("converged", {True: "yes", False: "NO"}.get(opt.get("converged"), "–")))
    if "initial_error" in opt or "final_error" in opt:
        rows.append(("error initial → final", f"{_fmt(opt.get('initial_error'))} → {_fmt(opt.get('final_error'))}"))
    analytic = (result.get("analytic") or {}).get("T_cam_base")
    if analytic is not None:
        R_a, t_a = pose(analytic)
        rows.append(("analytic vs MLE: rotation, deg", _fmt(_rotation_angle_deg(R_a, R_cb))))
        dt = 1e3 * (t_a - t_cb)
        rows.append(("analytic vs MLE: translation, mm", f"{_fmt(np.linalg.norm(dt))} (Δt = {_fmt(dt)})"))
    else:
        notes.append("The result carries no analytic solution: no analytic vs MLE comparison.")
    if dataset is not None:
        configs = sorted({(l + 1, m) for im in dataset.images for l, m in enumerate(im.mirror_configs)})
        rows.append(
            (
                "dataset",
                f"{len(dataset.images)} images, {dataset.num_mirrors} mirror(s), {len(configs)} mirror "
                f"configurations, {len(dataset.fiducials)} fiducials, {len(result.get('points') or {})} "
                f"reconstruction points, σ = {_fmt(dataset.pixel_sigma)} {units}",
            )
        )

    good = opt.get("converged") is not False
    parts = ["optimizer converged" if opt.get("converged") else ("optimizer did NOT converge" if opt else "")]
    if residuals is not None and math.isfinite(residuals.rms) and residuals.sigma > 0:
        ratio = residuals.rms / residuals.expected_rms
        # At the MLE the residuals lose one degree of freedom per unknown: E[RMS^2] = 2 sigma^2 (1 - p / 2N).
        coordinates = 2 * int(np.sum(residuals.valid))
        unknowns = 6 + 3 * len(mirror_vectors(result)) + 3 * len(reconstruction_points(result))
        expected = math.sqrt(max(1.0 - unknowns / coordinates, 0.0)) if coordinates else 1.0
        flagged = residuals.flagged_images()
        parts.append(
            f"RMS residual = {ratio:.2f} × √2·σ ({expected:.2f} expected from {coordinates} coordinates and "
            f"{unknowns} unknowns when the noise model holds)"
        )
        parts.append(f"{len(flagged)} image(s) above {OUTLIER_FACTOR:g} × the median image RMS")
        good = good and expected > 0.0 and 0.5 < ratio / expected < 2.0 and not flagged
    verdict = "; ".join(p for p in parts if p) or "no optimizer or residual information in the result"
    return _Summary(rows=rows, verdict=verdict, good=good, notes=notes)


# --------------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------------


def _new_figure(width: float, height: float) -> Figure:
    """A matplotlib Figure on the Agg canvas (no pyplot, no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _figure_histogram(residuals: Residuals) -> Figure:
    """Histogram of residual coordinates with the N(0, sigma) density.

    The range is +/- 5 max(sigma, robust sigma = 1.4826 median |residual|); coordinates beyond it are
    counted in the outer bins and in the title, so that outliers do not squash the histogram.
    """
    r = residuals.residual[residuals.valid]
    fig = _new_figure(8.0, 4.5)
    ax = fig.add_subplot()
    values = r.ravel()
    s = residuals.sigma
    robust = 1.4826 * float(np.median(np.abs(values))) if values.size else 0.0
    lim = 5.0 * max(s, robust)
    outside = int(np.sum(np.abs(values) > lim))
    clipped = np.clip(r, -lim, lim)
    bins = int(np.clip(np.sqrt(values.size) * 2, 15, 80))
    for k, (axis, colour) in enumerate((("x", "tab:blue"), ("y", "tab:orange"))):
        ax.hist(clipped[:, k], bins=bins, range=(-lim, lim), density=True, alpha=0.55, color=colour, label=axis)
    xs = np.linspace(-lim, lim, 400)
    ax.plot(xs, np.exp(-0.5 * (xs / s) ** 2) / (s * math.sqrt(2.0 * math.pi)), "k-", lw=2, label=f"N(0, σ={s:.3g})")
    ax.set_xlim(-lim, lim)
    ax.set_xlabel(f"residual (predicted − observed), {residuals.units}")
    ax.set_ylabel("density")
    extra = f"; {outside} beyond ±{lim:.3g} in the outer bins" if outside else ""
    coordinate_rms = float(np.sqrt(np.mean(values**2))) if values.size else float("nan")
    ax.set_title(f"Residual coordinates: {values.size}, RMS {coordinate_rms:.3g} {residuals.units}{extra}")
    ax.legend()
    return fig


def _figure_per_image(residuals: Residuals) -> Figure:
    """Bar chart of per-image RMS; bars above OUTLIER_FACTOR x median in red."""
    per_image = residuals.per_image_rms()
    ids = list(per_image)
    values = np.array([per_image[k] for k in ids])
    median = float(np.median(values))
    flagged = values > OUTLIER_FACTOR * median
    fig = _new_figure(10.0, 4.5)
    ax = fig.add_subplot()
    colours = np.where(flagged, "tab:red", "tab:blue")
    ax.bar(np.arange(len(ids)), values, color=colours, width=0.8 if len(ids) < 100 else 1.0)
    ax.axhline(median, color="k", lw=1, ls="--", label=f"median {median:.3g}")
    ax.axhline(OUTLIER_FACTOR * median, color="tab:red", lw=1, ls=":", label=f"{OUTLIER_FACTOR:g} × median")
    ax.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    if len(ids) <= 40:
        ax.set_xticks(np.arange(len(ids)), ids, rotation=90, fontsize=7)
    else:
        ax.set_xlabel("image (dataset order)")
    ax.set_ylabel(f"RMS residual, {residuals.units}")
    ax.set_title(f"Per-image RMS residual: {int(flagged.sum())} of {len(ids)} image(s) flagged (red)")
    ax.legend(fontsize=8)
    return fig


def _figure_per_point(residuals: Residuals, dataset: Dataset) -> Figure:
    """Per-point RMS bars, residual vectors, and residual arrows on the image plane."""
    per_point = residuals.per_point_rms()
    names = list(per_point)
    fid = set(dataset.fiducials)
    ok = residuals.valid
    r = residuals.residual[ok]
    fig = _new_figure(10.0, 8.0)
    grid = fig.add_gridspec(2, 2)
    ax = fig.add_subplot(grid[0, :])
    colours = ["tab:gray" if n in fid else "tab:purple" for n in names]
    ax.bar(np.arange(len(names)), [per_point[n] for n in names], color=colours)
    ax.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    if len(names) <= 40:
        ax.set_xticks(np.arange(len(names)), names, rotation=90, fontsize=7)
    else:
        ax.set_xlabel("point (first-seen order)")
    ax.set_ylabel(f"RMS residual, {residuals.units}")
    ax.set_title("Per-point RMS residual (grey: fiducials, purple: reconstruction points)")
    ax.legend(fontsize=8)

    ax = fig.add_subplot(grid[1, 0])
    is_f = residuals.is_fiducial[ok]
    ax.scatter(r[is_f, 0], r[is_f, 1], s=6, c="tab:gray", label="fiducials")
    if np.any(~is_f):
        ax.scatter(r[~is_f, 0], r[~is_f, 1], s=10, c="tab:purple", label="reconstruction points")
    angles = np.linspace(0.0, 2.0 * math.pi, 200)
    ax.plot(3 * residuals.sigma * np.cos(angles), 3 * residuals.sigma * np.sin(angles), "g--", lw=1, label="3σ")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"x residual, {residuals.units}")
    ax.set_ylabel(f"y residual, {residuals.units}")
    ax.set_title("Residual vectors")
    ax.legend(fontsize=7)

    ax = fig.add_subplot(grid[1, 1])
    obs = residuals.observed[ok]
    lengths = np.linalg.norm(r, axis=1)
    if dataset.camera is not None:
        span = float(max(dataset.camera.width, dataset.camera.height))
    else:
        span = float(np.ptp(obs, axis=0).max()) if len(obs) > 1 else 1.0
    # A median residual is drawn 4 % of the image long; outliers stand out as long arrows.
    scale = 0.04 * span / max(float(np.median(lengths)) if lengths.size else 1.0, 1e-300)
    drawn = r * scale
    too_long = np.linalg.norm(drawn, axis=1) > 0.15 * span  # outliers: capped, the colour tells the length
    drawn[too_long] *= (0.15 * span / np.linalg.norm(drawn[too_long], axis=1))[:, None]
    ax.scatter(obs[:, 0], obs[:, 1], s=2, c="k")
    quiver = ax.quiver(obs[:, 0], obs[:, 1], drawn[:, 0], drawn[:, 1], lengths, angles="xy",
                       scale_units="xy", scale=1.0, cmap="plasma", width=0.005)
    fig.colorbar(quiver, ax=ax, shrink=0.8, label=f"|residual|, {residuals.units}")
    if dataset.camera is not None:
        ax.set_xlim(0, dataset.camera.width)
        ax.set_ylim(dataset.camera.height, 0)
    else:
        ax.invert_yaxis()
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"u, {residuals.units}")
    ax.set_ylabel(f"v, {residuals.units}")
    ax.set_title(f"Residuals on the image (× {scale:.3g}, long ones capped)")
    return fig


def _camera_corners(dataset: Dataset | None) -> np.ndarray:
    """Normalized coordinates (4, 2) of the image corners (a 90 x 70 degree view without a camera)."""
    if dataset is not None and dataset.camera is not None:
        c = dataset.camera
        px = np.array([[0.0, 0.0], [c.width, 0.0], [c.width, c.height], [0.0, c.height]])
        return np.column_stack([(px[:, 0] - c.cx) / c.fx, (px[:, 1] - c.cy) / c.fy])
    return np.array([[-1.0, -0.7], [1.0, -0.7], [1.0, 0.7], [-1.0, 0.7]])


def _orthonormal_pair(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to unit ``n``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _set_equal_3d(ax: Any, points: np.ndarray, margin: float = 0.05) -> None:
    """Cube limits around ``points`` (N, 3) so that the 3D axes have equal scale."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2.0
    half = max(float(np.max(hi - lo)) / 2.0, 1e-3) * (1.0 + margin)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))


def _draw_target(ax: Any, fiducials: np.ndarray, points: dict[str, tuple[np.ndarray, np.ndarray | None]]) -> None:
    """Fiducials (black triangles), reconstruction points (purple) and their axis-aligned 3σ ellipsoids."""
    if len(fiducials):
        ax.scatter(*fiducials.T, marker="^", c="k", s=14, depthshade=False, label="fiducials")
    if points:
        xyz = np.array([p for p, _ in points.values()])
        ax.scatter(*xyz.T, c="tab:purple", s=14, depthshade=False, label="reconstruction points")
    u, v = np.meshgrid(np.linspace(0, 2 * math.pi, 13), np.linspace(0, math.pi, 7))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    for p, s3 in points.values():
        if s3 is None or not np.all(np.isfinite(s3)):
            continue
        e = p[:, None, None] + 1e-3 * s3[:, None, None] * unit  # semi-axes 3σ, mm -> m
        ax.plot_wireframe(e[0], e[1], e[2], color="tab:purple", lw=0.5, alpha=0.7)


def _figure_scene(result: Mapping[str, Any], dataset: Dataset | None) -> Figure:
    """3D scene in the base frame: axes, camera frustum, mirror patches, fiducials, points, 3σ ellipsoids."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    (_, _), (R_bc, t_bc) = transforms(result)
    mirrors = mirror_vectors(result)
    points = reconstruction_points(result)
    fiducials = np.array(list(dataset.fiducials.values())).reshape(-1, 3) if dataset is not None else np.zeros((0, 3))
    target = np.vstack([fiducials, *[p[None] for p, _ in points.values()]]) if (len(fiducials) or points) else None

    feet = {k: R_bc @ v + t_bc for k, v in mirrors.items()}  # foot points in {B}
    everything = np.vstack([np.zeros((1, 3)), t_bc[None], *(f[None] for f in feet.values())]
                           + ([target] if target is not None else []))
    extent = float(np.max(np.ptp(everything, axis=0))) or 1.0
    distances = [float(np.linalg.norm(v)) for v in mirrors.values()]
    half_side = 0.3 * (float(np.median(distances)) if distances else extent)
    axis_len = 0.12 * extent

    fig = _new_figure(12.0, 6.5)
    panels = 2 if target is not None else 1
    ax = fig.add_subplot(1, panels, 1, projection="3d")
    # Base frame axes: x red, y green, z blue.
    for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(*np.column_stack([np.zeros(3), axis_len * np.eye(3)[k]]), color=colour, lw=2)
    ax.text(0, 0, 0, " {B}", fontsize=9)
    # Camera frustum at T_base_cam.
    depth = 0.15 * extent
    corners_c = np.column_stack([_camera_corners(dataset) * depth, np.full(4, depth)])
    corners_b = corners_c @ R_bc.T + t_bc
    for c in corners_b:
        ax.plot(*np.column_stack([t_bc, c]), color="k", lw=1)
    loop = np.vstack([corners_b, corners_b[:1]])
    ax.plot(*loop.T, color="k", lw=1)
    for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(*np.column_stack([t_bc, t_bc + 0.6 * axis_len * R_bc[:, k]]), color=colour, lw=1.5)
    ax.text(*t_bc, " {C}", fontsize=9)
    # Mirror placements: translucent squares centred on the foot point v, perpendicular to v.
    counts = {l: sum(1 for k in mirrors if k[0] == l) for l, _ in mirrors}
    for (l, m), v in mirrors.items():
        n = R_bc @ (v / np.linalg.norm(v))
        a, b = _orthonormal_pair(n)
        f = feet[(l, m)]
        quad = [f + half_side * (sa * a + sb * b) for sa, sb in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        colour = _MIRROR_COLOURS[(l - 1) % len(_MIRROR_COLOURS)]
        alpha = float(np.clip(1.0 / counts[l], 0.02, 0.12))  # many placements must not fill the view
        edge = colour if counts[l] <= 20 else "none"
        ax.add_collection3d(Poly3DCollection([quad], facecolor=colour, edgecolor=edge, alpha=alpha, lw=0.5))
        ax.scatter(*f, c=colour, s=8, depthshade=False)
    for l in sorted({l for l, _ in mirrors}):
        colour = _MIRROR_COLOURS[(l - 1) % len(_MIRROR_COLOURS)]
        ax.plot([], [], color=colour, lw=6, alpha=0.4, label=f"mirror {l} ({counts[l]} placements)")
    _draw_target(ax, fiducials, points)
    _set_equal_3d(ax, np.vstack([everything, corners_b]))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title("Scene in the base frame {B}")
    if ax.get_legend_handles_labels()[0]:  # a result without mirrors or target has nothing to label
        ax.legend(fontsize=7, loc="upper left")
    if target is not None:
        ax2 = fig.add_subplot(1, 2, 2, projection="3d")
        _draw_target(ax2, fiducials, points)
        span = float(np.max(np.ptp(target, axis=0))) if len(target) > 1 else 0.1
        for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax2.plot(*np.column_stack([np.zeros(3), 0.15 * span * np.eye(3)[k]]), color=colour, lw=2)
        _set_equal_3d(ax2, target, margin=0.15)
        ax2.set_xlabel("x (m)")
        ax2.set_ylabel("y (m)")
        ax2.set_zlabel("z (m)")
        has_ellipsoids = any(s3 is not None for _, s3 in points.values())
        ax2.set_title("Target close-up" + (" (3σ ellipsoids to scale)" if has_ellipsoids else ""))
    return fig


def _figure_correlation(result: Mapping[str, Any]) -> Figure | None:
    """Correlation matrix of ``covariance_cam_base`` ([rx, ry, rz, x, y, z], docs/formats.md convention)."""
    P = pose_covariance(result)
    if P is None:
        return None
    sd = np.sqrt(np.clip(np.diag(P), 1e-300, None))
    corr = P / np.outer(sd, sd)
    fig = _new_figure(6.0, 5.2)
    ax = fig.add_subplot()
    im = ax.imshow(corr, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    for i in range(6):
        for j in range(6):
            ax.text(j, i, f"{corr[i, j]:.2f}", ha="center", va="center", fontsize=8,
                    color="white" if abs(corr[i, j]) > 0.6 else "black")
    ax.set_xticks(range(6), COVARIANCE_LABELS)
    ax.set_yticks(range(6), COVARIANCE_LABELS)
    ax.set_title("Correlation of T_cam_base\n(rotation about camera axes, translation)")
    fig.colorbar(im, ax=ax, shrink=0.8)
    return fig


def _figure_summary_page(summary: _Summary, title: str) -> Figure:
    """The summary table as a figure (first PDF page)."""
    fig = _new_figure(8.27, 11.69)  # A4 portrait
    fig.text(0.05, 0.965, title, fontsize=15, weight="bold", va="top")
    colour = "darkgreen" if summary.good else "darkred"
    fig.text(0.05, 0.93, _wrap(summary.verdict, 95), fontsize=9, color=colour, va="top")
    y = 0.88
    for label, value in summary.rows:
        lines = value.replace("<br>", "\n").split("\n")
        fig.text(0.05, y, label, fontsize=8.5, va="top", weight="bold")
        for line in lines:
            for wrapped in _wrap(line, 60).split("\n"):
                fig.text(0.50, y, wrapped, fontsize=8.5, va="top", family="monospace")
                y -= 0.018
        y -= 0.006
    for note in summary.notes:
        fig.text(0.05, y, _wrap("Note: " + note, 100), fontsize=8, va="top", style="italic")
        y -= 0.03
    return fig


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)) or text


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    return buf.getvalue()


_CSS = """
body { font-family: 'DejaVu Sans', Arial, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table.summary { border-collapse: collapse; font-size: 0.9em; }
table.summary td { border: 1px solid #ddd; padding: 3px 8px; vertical-align: top; }
table.summary td.v { font-family: 'DejaVu Sans Mono', monospace; }
.verdict { padding: 0.6em 1em; border-radius: 4px; margin: 0.8em 0; }
.good { background: #e6f4e6; border: 1px solid #8c8; } .bad { background: #fbe9e7; border: 1px solid #d88; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
pre { background: #f6f6f6; padding: 0.6em; font-size: 0.8em; white-space: pre-wrap; overflow-wrap: anywhere; }
.note { font-style: italic; color: #666; } .flagged { color: #b00; }
"""


def write_report(
    result: Mapping[str, Any],
    dataset: Dataset | None,
    out_dir: str | os.PathLike[str],
    progress: bool = True,
    *,
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
    title: str | None = None,
    source: str = "result",
) -> dict[str, Path]:
    """Write ``out_dir/report.html`` (self-contained: CSS inline, figures as base64 PNG) and ``out_dir/report.pdf``.

    ``result``: a result@1 dictionary. ``dataset``: the dataset it was computed from, or None (the
    residual figures are then left out with a note). ``progress``: a progress bar on stderr.
    ``base_frame``, ``camera_frame``: frame names in the ROS snippets. Returns
    ``{"html": path, "pdf": path}``. Both files are written atomically. ``source``: the result's
    file name, for messages. Raises DatasetError (before any work) on a malformed result
    (:func:`mirror_fg.io.result.validate_result`) and when the dataset does not belong to the result,
    ValueError on a bad frame name.
    """
    from tqdm import tqdm

    result = validate_result(result, source)
    base_frame = check_frame_name(base_frame, "base frame")
    camera_frame = check_frame_name(camera_frame, "camera frame")
    title = title or "mirror-fg calibration report"
    with tqdm(total=8, desc="report", unit="step", disable=not progress, file=sys.stderr, leave=False) as bar:
        residuals = _residuals(result, dataset, source) if dataset is not None else None
        bar.update()
        summary = _summary(result, dataset, residuals, base_frame)
        (_, _), (R_bc, t_bc) = transforms(result)
        joint = urdf_joint(R_bc, t_bc, base_frame, camera_frame)
        publisher = static_transform_publisher_args(R_bc, t_bc, base_frame, camera_frame)
        bar.update()
        figures, notes = _figures(result, dataset, residuals, bar)
        notes = summary.notes + notes
        flagged = residuals.flagged_images() if residuals is not None else {}
        outliers = (result.get("residuals") or {}).get("outliers") or []
        page = _html(title, summary, figures, notes, flagged, outliers, joint, publisher, residuals)
        pdf = _pdf(title, summary, figures)
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"html": atomic_write(out / "report.html", page), "pdf": atomic_write(out / "report.pdf", pdf)}
        bar.update()
    return paths


def _figures(
    result: Mapping[str, Any], dataset: Dataset | None, residuals: Residuals | None, bar: Any
) -> tuple[list[tuple[str, Figure, str]], list[str]]:
    """The report's figures as ``(heading, figure, caption)`` and notes on what was left out."""
    figures: list[tuple[str, Figure, str]] = []
    notes: list[str] = []
    if residuals is None or dataset is None:
        notes.append("No dataset given: residual histogram, per-image and per-point residuals are left out.")
        bar.update(3)
    elif not np.any(residuals.valid):
        notes.append("The dataset has no measurement the result can predict: residual figures are left out.")
        bar.update(3)
    else:
        n_behind = int(np.sum(~residuals.valid))
        if n_behind:
            notes.append(f"{n_behind} measurement(s) are predicted behind the camera and left out of the residuals.")
        figures.append(("Residual distribution", _figure_histogram(residuals),
                        f"Residual coordinates (predicted − observed, {residuals.units}) with the expected "
                        f"N(0, σ = {residuals.sigma:.3g}) density."))
        bar.update()
        figures.append(("Per-image residuals", _figure_per_image(residuals),
                        f"RMS residual length of each image; red: above {OUTLIER_FACTOR:g} × the median."))
        bar.update()
        figures.append(("Per-point residuals", _figure_per_point(residuals, dataset),
                        "RMS residual length of each point; all residual vectors with the 3σ circle; residual "
                        "arrows at the observed positions (magnified)."))
        bar.update()
    figures.append(("3D scene", _figure_scene(result, dataset),
                    "Base frame {B} (x red, y green, z blue), the camera frustum at T_base_cam, every mirror "
                    "placement as a translucent square centred on its foot point, fiducials, and reconstruction "
                    "points with axis-aligned 3σ ellipsoids. Metres."))
    bar.update()
    corr = _figure_correlation(result)
    if corr is not None:
        figures.append(("Covariance correlation", corr,
                        "Correlation matrix of the 6×6 covariance of T_cam_base: [rx, ry, rz] rotation "
                        "about the camera axes (R_true = Exp(dθ) R), [x, y, z] translation (t_true = t + dt)."))
    else:
        notes.append("The result carries no covariance: no correlation matrix.")
    bar.update()
    return figures, notes


def _pdf(title: str, summary: _Summary, figures: list[tuple[str, Figure, str]]) -> bytes:
    """PDF bytes: the summary page, then one figure per page."""
    from matplotlib.backends.backend_pdf import PdfPages

    buf = io.BytesIO()
    with PdfPages(buf, metadata={"Title": title, "Creator": "mirror-fg"}) as pdf:
        pdf.savefig(_figure_summary_page(summary, title))
        for heading, fig, _ in figures:
            fig.suptitle(heading, fontsize=12, weight="bold")
            pdf.savefig(fig)
    return buf.getvalue()


def _html(
    title: str,
    summary: _Summary,
    figures: list[tuple[str, Figure, str]],
    notes: list[str],
    flagged: dict[str, float],
    outliers: list[Any],
    joint: str,
    publisher: str,
    residuals: Residuals | None,
) -> str:
    """The self-contained HTML page (no scripts, no external resources)."""
    e = html.escape
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    rows = "\n".join(
        f"<tr><td>{e(label)}</td><td class='v'>{'<br>'.join(e(p) for p in value.split('<br>'))}</td></tr>"
        for label, value in summary.rows
    )
    parts = [
        "<!DOCTYPE html>",
        "<html lang='en'><head><meta charset='utf-8'>",
        f"<title>{e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{e(title)}</h1><p class='note'>Generated {e(stamp)} by mirror-fg.</p>",
        f"<div class='verdict {'good' if summary.good else 'bad'}'>{e(summary.verdict)}</div>",
        "<h2>Summary</h2>",
        f"<table class='summary'>{rows}</table>",
        "<p class='note'>Frames: {B} base, {C} camera (OpenCV: x right, y down, z forward). T_cam_base maps "
        "base points into the camera (Cp = R Bp + t); T_base_cam is the camera's pose on the robot. 3σ bounds "
        "as in docs/formats.md: R_true = Exp(dθ) R (camera axes), t_true = t + dt.</p>",
    ]
    if residuals is not None:
        parts.append(f"<h2>Flagged images (RMS &gt; {OUTLIER_FACTOR:g} × median)</h2>")
        if flagged:
            items = "".join(
                f"<li class='flagged'>{e(k)}: RMS {v:.3g} {e(residuals.units)}</li>" for k, v in flagged.items()
            )
            parts.append(f"<ul id='flagged-images'>{items}</ul>")
        else:
            parts.append("<p id='flagged-images'>None.</p>")
    if outliers:
        items = "".join(
            f"<li>image {e(o['image'])}, point {e(o['point'])}: {_fmt(o['sigmas'], 3)} σ</li>" for o in outliers
        )
        parts.append(f"<h2>Measurements flagged by the calibration</h2><ul id='outlier-measurements'>{items}</ul>")
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li class='note'>{e(n)}</li>" for n in notes) + "</ul>")
    for heading, fig, caption in figures:
        data = base64.b64encode(_png(fig)).decode("ascii")
        parts.append(
            f"<h2>{e(heading)}</h2><figure><img alt='{e(heading)}' src='data:image/png;base64,{data}'>"
            f"<figcaption>{e(caption)}</figcaption></figure>"
        )
    parts += [
        "<h2>ROS</h2><p>URDF joint (xyz in metres, rpy fixed-axis in radians):</p>",
        f"<pre>{e(joint)}</pre>",
        "<p>ROS 2 static transform:</p>",
        f"<pre>ros2 run tf2_ros static_transform_publisher {e(publisher)}</pre>",
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"
