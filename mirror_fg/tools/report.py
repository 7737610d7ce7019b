"""Calibration report: a self-contained HTML page and a PDF (matplotlib, Agg) of a ``mirror-fg/result@1``.

This module holds the summary (table rows and a one-line verdict) and assembles the page and the PDF;
the residuals are computed in :mod:`mirror_fg.tools.residuals`, the figures drawn in
:mod:`mirror_fg.tools.report_figures`.

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
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.transform import Transform, rotation_angle
from mirror_fg.io.output import atomic_write
from mirror_fg.io.result import mirror_vectors, pose, transforms, validate_result
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.io.ros import (
    DEFAULT_BASE_FRAME,
    DEFAULT_CAMERA_FRAME,
    check_frame_name,
    sigma3_base_cam,
    static_transform_publisher_args,
    urdf_joint,
)
from mirror_fg.tools.report_figures import (
    figure_correlation,
    figure_histogram,
    figure_per_image,
    figure_per_point,
    figure_scene,
    new_figure,
    png,
)
from mirror_fg.tools.residuals import OUTLIER_FACTOR, Residuals, residuals_of_valid_result

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.io.dataset import Dataset

__all__ = ["write_report"]


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
    T_base_cam = Transform(R_bc, t_bc)
    rows: list[tuple[str, str]] = []
    notes: list[str] = []
    rows.append((f"T_base_cam translation (camera centre in {base_frame}), m", _fmt(t_bc, 6)))
    rows.append(("T_base_cam quaternion (x, y, z, w)", _fmt(T_base_cam.quaternion_xyzw(), 6)))
    rows.append(("T_base_cam URDF rpy, deg", _fmt(np.rad2deg(T_base_cam.rpy()), 6)))
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
        rows.append(("analytic vs MLE: rotation, deg", _fmt(math.degrees(rotation_angle(R_a, R_cb)))))
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


def _figure_summary_page(summary: _Summary, title: str) -> Figure:
    """The summary table as a figure (first PDF page)."""
    fig = new_figure(8.27, 11.69)  # A4 portrait
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
    return "\n".join(textwrap.wrap(text, width)) or text


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


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
        residuals = residuals_of_valid_result(result, dataset, source) if dataset is not None else None
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
        figures.append(("Residual distribution", figure_histogram(residuals),
                        f"Residual coordinates (predicted − observed, {residuals.units}) with the expected "
                        f"N(0, σ = {residuals.sigma:.3g}) density."))
        bar.update()
        figures.append(("Per-image residuals", figure_per_image(residuals),
                        f"RMS residual length of each image; red: above {OUTLIER_FACTOR:g} × the median."))
        bar.update()
        figures.append(("Per-point residuals", figure_per_point(residuals, dataset),
                        "RMS residual length of each point; all residual vectors with the 3σ circle; residual "
                        "arrows at the observed positions (magnified)."))
        bar.update()
    figures.append(("3D scene", figure_scene(result, dataset),
                    "Base frame {B} (x red, y green, z blue), the camera frustum at T_base_cam, every mirror "
                    "placement as a translucent square centred on its foot point, fiducials, and reconstruction "
                    "points with axis-aligned 3σ ellipsoids. Metres."))
    bar.update()
    corr = figure_correlation(result)
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
        data = base64.b64encode(png(fig)).decode("ascii")
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
