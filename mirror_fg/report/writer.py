"""Calibration report: a self-contained HTML page and an A4 PDF (matplotlib, Agg) of a ``mirror-fg/result@1``.

This module decides what the report says (summary table, one-line verdict, input echo, flagged
measurements, figures, ROS snippets) as one list of blocks that :mod:`mirror_fg.report.pages`
renders twice, HTML and PDF, so both hold the same content; the residuals are computed in
:mod:`mirror_fg.report.residuals`, the figures drawn in :mod:`mirror_fg.report.figures` and
:mod:`mirror_fg.report.diagnostics`, the console summary is :mod:`mirror_fg.report.summary`'s.

Frames (docs/formats.md): {B} base, {C} camera (OpenCV: x right, y down, z forward); ``T_cam_base = (R, t)``
with ``Cp = R @ Bp + t``; the 3D scene is drawn in the base frame, metres. Residuals are
``predicted - observed`` in pixels when the dataset has a camera, else in normalized image
coordinates. There is one "RMS": the root mean square of the measurements' Euclidean residual lengths,
as ``residuals.rms_px`` in result@1 (``sqrt(2) pixel_sigma`` expected under the noise model); every other
statistic is named for what it is (mean length, per-coordinate standard deviation, ...).
"""
from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.transform import Transform, rotation_angle
from mirror_fg.io.output import OutputPlan
from mirror_fg.io.result import (
    base_cam_sigma3,
    pose,
    pose_covariance,
    transforms,
    validate_result,
)
from mirror_fg.io.ros import (
    DEFAULT_BASE_FRAME,
    DEFAULT_CAMERA_FRAME,
    check_frame_name,
    ros_outputs,
)
from mirror_fg.report.diagnostics import (
    figure_radial,
    figure_tracks,
    image_centre,
)
from mirror_fg.report.figures import (
    figure_correlation,
    figure_histogram,
    figure_per_image,
    figure_per_point,
    figure_scene,
)
from mirror_fg.report.general import (
    base_is_first_camera,
    camera_input_rows,
    console_lines,
    dataset_line,
    no_target_text,
    rig_ros_blocks,
    view_blocks,
)
from mirror_fg.report.pages import Block, RenderedFigure, html_page, pdf_document
from mirror_fg.report.screen import figure_gaze, gaze_screens
from mirror_fg.report.scene import figure_views_scene, pose_is_estimated
from mirror_fg.report.units import units_blocks
from mirror_fg.report.views import (
    ViewResiduals,
    figure_cameras,
    figure_orders,
    view_residuals,
)
from mirror_fg.report.residuals import (
    OUTLIER_FACTOR,
    Residuals,
    residuals_of_valid_result,
)
from mirror_fg.report.summary import RMS_DEFINITION, camera_lines
from mirror_fg.report.verdict import Verdict, judge, stored_verdict

if TYPE_CHECKING:
    from mirror_fg.data import Dataset

__all__ = ["write_report"]

#: Fiducial names listed in the input echo (the count is always given).
MAX_NAMES_ECHOED = 24


# --------------------------------------------------------------------------------------------------
# Summary
# --------------------------------------------------------------------------------------------------


def _fmt(values: Any, digits: int = 4) -> str:
    """Numbers as ``[a, b, c]`` with ``digits`` significant digits; a scalar alone; None as an en dash; text as it is."""
    if values is None:
        return "–"
    if isinstance(values, str):
        return values
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        return f"{float(arr):.{digits}g}"
    return "[" + ", ".join(f"{float(x):.{digits}g}" for x in arr.ravel()) + "]"


@dataclass
class _Summary:
    rows: list[tuple[str, str]]  # (label, value) for the table; a value's lines split on newlines
    verdict: str  # the headline and its reasons in one line (what the bullets say)
    good: bool
    notes: list[str]
    headline: str = ""  # the at-a-glance assessment
    reasons: list[str] = field(default_factory=list)  # one bullet each, problems first
    judged: Verdict | None = None  # the one verdict (report/verdict.py): the headline's, the console block's


def _summary(
    result: Mapping[str, Any], dataset: Dataset | None, residuals: Residuals | None, base_frame: str
) -> _Summary:
    """Summary table rows, a one-line verdict and notes (``result`` validated)."""
    (R_cb, t_cb), (R_bc, t_bc) = transforms(result)
    T_base_cam = Transform(R_bc, t_bc)
    notes: list[str] = []
    fixed = base_is_first_camera(result, dataset)
    s_bc = base_cam_sigma3(result) or {}
    s_cb = result.get("sigma3_cam_base") or {}
    if fixed:  # no known target: the pose is the base frame itself, its zero bounds are no estimate
        s_bc = s_cb = {k: "not estimated (the base frame is this camera's frame)" for k in ("rotation_deg", "position_mm")}
    rows = [
        (f"T_base_cam translation (camera centre in {base_frame}), m", _fmt(t_bc, 6)),
        ("T_base_cam quaternion (x, y, z, w)", _fmt(T_base_cam.quaternion_xyzw(), 6)),
        ("T_base_cam URDF rpy, deg", _fmt(np.rad2deg(T_base_cam.rpy()), 6)),
        (f"T_base_cam 3σ rotation about {base_frame} x, y, z, deg", _fmt(s_bc.get("rotation_deg"), 3)),
        (f"T_base_cam 3σ camera position along {base_frame} x, y, z, mm", _fmt(s_bc.get("position_mm"), 3)),
        ("T_cam_base R (rows)", "\n".join(_fmt(row, 6) for row in R_cb)),
        ("T_cam_base t (base origin in camera axes), m", _fmt(t_cb, 6)),
        ("T_cam_base 3σ rotation about camera x, y, z, deg", _fmt(s_cb.get("rotation_deg"), 3)),
        ("T_cam_base 3σ base origin along camera x, y, z, mm", _fmt(s_cb.get("position_mm"), 3)),
    ]
    if result.get("cameras"):  # several cameras: the rows above are the first camera's (each under "Cameras")
        names = list(result["cameras"])
        rows.insert(0, ("camera of the pose rows below", f"{names[0]} (the first of {len(names)} cameras: "
                        + ", ".join(names) + "; each camera's pose is under Cameras)"))
    res = result.get("residuals") or {}
    units = residuals.units if residuals is not None else str(res.get("units") or "px")
    rms = _fmt(res.get("rms_px"))
    if residuals is not None and res.get("rms_px") is not None and not math.isclose(
            residuals.rms, res["rms_px"], rel_tol=1e-6, abs_tol=1e-12):
        rms += f" (on this dataset: {_fmt(residuals.rms)})"
    rows.append((f"RMS reprojection error ({RMS_DEFINITION}), {units}", rms))
    if res.get("mean_px") is not None:
        rows.append((f"mean reprojection error length, {units}", _fmt(res["mean_px"])))
    rows.append((f"largest reprojection error, {units}", _fmt(res.get("max_px"))))
    if residuals is not None:
        rows.append(("measurements", str(int(np.sum(residuals.valid)))))
    if res.get("outliers") is not None:
        rows.append(("measurements flagged by the calibration", str(len(res["outliers"]))))
    opt = result.get("optimizer") or {}
    rows.append(("iterations", "–" if opt.get("iterations") is None else str(opt["iterations"])))
    converged: dict[bool | None, str] = {True: "yes", False: "NO"}
    rows.append(("converged", converged.get(opt.get("converged"), "–")))
    if "initial_error" in opt or "final_error" in opt:
        expected = f" (expected {_fmt(opt['expected_final_error'])})" if opt.get("expected_final_error") else ""
        rows.append(("cost ½χ² initial → final", f"{_fmt(opt.get('initial_error'))} → {_fmt(opt.get('final_error'))}"
                     + expected))
    analytic = (result.get("analytic") or {}).get("T_cam_base")
    if analytic is not None:
        R_a, t_a = pose(analytic)
        rows.append(("analytic vs MLE: rotation, deg", _fmt(math.degrees(rotation_angle(R_a, R_cb)))))
        dt = 1e3 * (t_a - t_cb)
        rows.append(("analytic vs MLE: translation, mm", f"{_fmt(np.linalg.norm(dt))} (Δt = {_fmt(dt)})"))
    else:
        notes.append("The result carries no analytic solution: no analytic vs MLE comparison.")
    if dataset is not None and not dataset.is_tree:
        rows.append(("dataset", dataset_line(result, dataset, units)))
    elif dataset is not None:
        configs = {(l + 1, m) for im in dataset.images for l, m in enumerate(im.mirror_configs)}
        rows.append(("dataset", f"{len(dataset.images)} images, {dataset.num_mirrors} mirror(s), {len(configs)} mirror "
                     f"configurations, {len(dataset.fiducials)} fiducials, {len(result.get('points') or {})} "
                     f"reconstruction points, σ = {_fmt(dataset.pixel_sigma)} {units}"))
    if fixed:
        notes.append(no_target_text(result, dataset))
    verdict = stored_verdict(result) or judge(result, dataset, residuals=residuals)
    reasons = verdict.reasons
    return _Summary(rows=rows, verdict="; ".join([verdict.headline, *reasons]), good=verdict.good, notes=notes,
                    headline=verdict.headline, reasons=reasons, judged=verdict)


def _inputs(result: Mapping[str, Any], dataset: Dataset | None, source: str, extra: Mapping[str, str] | None,
            stamp: str) -> list[tuple[str, str]]:
    """The echo of what the report was made from: files, camera, target, version, time."""
    from mirror_fg import __version__

    rows = [("result file", source)]
    if dataset is not None:
        rows.append(("dataset", f"{dataset.source} ({len(dataset.images)} images)"))
        cam = dataset.camera
        if dataset.cameras:
            rows += camera_input_rows(dataset)
        else:
            rows.append(("camera", "none: normalized image coordinates" if cam is None else
                         f"{cam.model} {cam.width}×{cam.height} px, fx {cam.fx:.6g}, fy {cam.fy:.6g}, "
                         f"cx {cam.cx:.6g}, cy {cam.cy:.6g}, dist {_fmt(cam.dist, 4)}"))
        names = list(dataset.fiducials)
        shown = ", ".join(names[:MAX_NAMES_ECHOED]) + (f", … ({len(names) - MAX_NAMES_ECHOED} more)"
                                                       if len(names) > MAX_NAMES_ECHOED else "")
        rows.append(("target", f"{len(names)} fiducials in the base frame: {shown}" if names else
                     "none (fiducials: {}): the base frame is the first camera's frame"))
        rows.append(("pixel sigma", _fmt(dataset.pixel_sigma)))
    if result.get("camera"):
        rows.append(("intrinsics estimated", ", ".join(result["camera"].get("estimated") or []) or "–"))
    rows += [(k, str(v)) for k, v in (extra or {}).items()]
    rows += [("mirror-fg version", __version__), ("generated", stamp)]
    return rows


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


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
    tracks: Mapping[str, Any] | None = None,
    inputs: Mapping[str, str] | None = None,
) -> dict[str, Path]:
    """Write ``out_dir/report.html`` (self-contained: CSS inline, figures as base64 PNG) and ``out_dir/report.pdf``
    (A4, the same content).

    ``result``: a result@1 dictionary. ``dataset``: the dataset it was computed from, or None (the
    residual figures are then left out with a note). ``progress``: a progress bar on stderr.
    ``base_frame``, ``camera_frame``: frame names in the ROS snippets. ``tracks``: the
    :class:`~mirror_fg.vision.tracking.Track` s that ``detect_capture(capture, tracks={})`` filled (each
    track's path and residuals over time are drawn), or None. ``inputs``: more ``{label: value}`` for
    the input echo (e.g. the capture file). Returns ``{"html": path, "pdf": path}``, both written
    atomically. ``source``: the result's file name, for messages. Raises DatasetError (before any work)
    on a malformed result (:func:`mirror_fg.io.result.validate_result`) and when the dataset does not
    belong to the result, ValueError on a bad frame name.
    """
    from tqdm import tqdm

    result = validate_result(result, source)
    paths = {kind: Path(out_dir) / f"report.{kind}" for kind in ("html", "pdf")}
    plan = OutputPlan()  # checked now; both written or neither, and a directory it made is removed on failure
    for path in paths.values():
        plan.add(path, "report")
    base_frame = check_frame_name(base_frame, "base frame")
    ros = ros_outputs(result, base_frame, camera_frame, source=source)  # checks the camera frame name
    title = title or "mirror-fg calibration report"
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    with tqdm(total=9, desc="report", unit="step", disable=not progress, file=sys.stderr, leave=False) as bar:
        view_notes: list[str] = []
        residuals: Residuals | None = None
        if dataset is not None and dataset.robot is not None:  # a robot arm (report/robot.py)
            from mirror_fg.report.robot import robot_residuals
            residuals = robot_residuals(result, dataset, source)
        elif dataset is not None and not dataset.is_tree:  # any reflection order, several cameras, no target
            residuals, view_notes = view_residuals(result, dataset, source)
        elif dataset is not None:
            residuals = residuals_of_valid_result(result, dataset, source)
        bar.update()
        summary = _summary(result, dataset, residuals, base_frame)
        bar.update()
        figures, notes = _figures(result, dataset, residuals, tracks, bar)
        blocks = _blocks(result, dataset, summary, summary.notes + view_notes + notes, figures, residuals, ros,
                         _inputs(result, dataset, source, inputs, stamp), base_frame)
        page, pdf = html_page(title, blocks), pdf_document(title, blocks)
        plan.commit({paths["html"]: page, paths["pdf"]: pdf})
        bar.update()
    return paths


def _figures(
    result: Mapping[str, Any], dataset: Dataset | None, residuals: Residuals | None,
    tracks: Mapping[str, Any] | None, bar: Any,
) -> tuple[list[tuple[str, Any, str]], list[str]]:
    """The report's figures as ``(heading, figure rendered to PNG, caption)`` and notes on what was left
    out; ``bar`` names each figure as it is drawn and rendered (most of the report's time)."""
    figures: list[tuple[str, Any, str]] = []
    notes: list[str] = []

    def add(heading: str, draw: Any, *args: Any, caption: str) -> None:
        bar.set_postfix_str(heading.lower())
        figures.append((heading, RenderedFigure(draw(*args)), caption))
    if residuals is None or dataset is None:
        notes.append("No dataset given: residual histogram, per-image and per-point residuals are left out.")
        bar.update(4)
    elif not np.any(residuals.valid):
        notes.append("The dataset has no measurement the result can predict: residual figures are left out.")
        bar.update(4)
    else:
        n_behind = int(np.sum(~residuals.valid))
        if n_behind:
            notes.append(f"{n_behind} measurement(s) are predicted behind the camera and left out of the residuals.")
        add("Residual distribution", figure_histogram, residuals,
            caption=f"Residual coordinates (predicted − observed, {residuals.units}) with the expected "
                        f"N(0, σ = {residuals.sigma:.3g}) density.")
        bar.update()
        add("Per-image residuals", figure_per_image, residuals,
            caption=f"RMS reprojection error of each image; red: above {OUTLIER_FACTOR:g} × the median.")
        bar.update()
        add("Per-point residuals", figure_per_point, residuals, dataset,
            caption="RMS reprojection error of each point, by name; all residual vectors with the 3σ circle; "
                    "residual arrows at the observed positions (magnified).")
        bar.update()
        if isinstance(residuals, ViewResiduals):
            add("Residuals by reflection order", figure_orders, residuals,
                caption="Residual lengths of the direct views and of the views through one, two, ... mirrors: RMS "
                        "and largest of each order (with the number of measurements and views), and each order's "
                        "distribution against the noise model's (|e| of e ~ N(0, σ² I)).")
            if len(set(residuals.cameras)) > 1:
                add("Residuals per camera", figure_cameras, residuals,
                    caption="RMS reprojection error of each camera, and each camera's residual vectors coloured "
                            "by reflection order with the 3σ circle.")
        profile = residuals.radial_profile(image_centre(dataset))
        if profile is not None:
            add("Residual vs distance from the image centre", figure_radial, residuals, profile,
                caption="Reprojection error length against the observed point's distance from the principal "
                            "point, with the RMS of each ring. Growth towards the edge is the signature of a wrong "
                            "or missing distortion model.")
        bar.update()
    if dataset is not None and dataset.robot is not None:  # a robot arm (report/robot.py)
        from mirror_fg.report.robot import figure_arm
        add("Arm, camera, mirrors and target", figure_arm, result, dataset,
            caption="The arm at some of its poses (each link's origin joined in the URDF's order; base link {B}, "
                    "metres), the camera's axes (x red, y green, z blue) and the target's points (orange) where "
                    "the calibrated mounts put them, and each mirror placement as a square on its plane in {B}.")
    elif dataset is not None and not dataset.is_tree or result.get("cameras"):
        add("3D scene", figure_views_scene, result, dataset,
            caption="Base frame {B} (x red, y green, z blue); every camera's frustum and axes at its T_base_cam with "
                    "its 3σ position ellipsoid (all magnified by the one factor in the title); each mirror placement "
                    "once, as a translucent square on its plane centred on its foot point (black edge: seen by "
                    "several cameras), dotted lines from each camera to the placements it saw; fiducials and "
                    "reconstruction points with axis-aligned 3σ ellipsoids. Metres.")
    else:
        add("3D scene", figure_scene, result, dataset,
            caption="Base frame {B} (x red, y green, z blue), the camera frustum at T_base_cam with its 3σ position "
                    "ellipsoid and optical-axis cone (magnified by the factors in the title and legend), every "
                    "mirror placement as a translucent square centred on its foot point (a sample of squares "
                    "where there are many), fiducials, and reconstruction points with axis-aligned 3σ "
                    "ellipsoids. Metres.")
    bar.update()
    if base_is_first_camera(result, dataset):
        notes.append("T_cam_base is the base frame itself (no known target), not an estimate: no correlation matrix.")
    elif pose_is_estimated(pose_covariance(result)):
        add("Covariance correlation", figure_correlation, result,
            caption="Correlation matrix of the 6×6 covariance of T_cam_base: [rx, ry, rz] rotation "
                        "about the camera axes (R_true = Exp(dθ) R), [x, y, z] translation (t_true = t + dt).")
    else:
        notes.append("The result carries no covariance: no correlation matrix.")
    for screen_name in gaze_screens(result):
        add("Gaze point error over the screen" + ("" if screen_name is None else f" {screen_name}"), figure_gaze,
            result, screen_name,
            caption="The screen's active area (mm, as the viewer sees it) with the 3σ ellipse of the point a gaze "
                    "ray hits, at the centre and the corners, for an eye on the normal through the centre at the "
                    "result's viewing distance (the ray known in the camera frame, the screen's pose uncertain); "
                    "each labelled with its 3σ along screen x and y in mm and in degrees at the eye.")
    if tracks:
        add("Tracked points", figure_tracks, tracks, dataset,
            caption="Each track:'s path on the image (refined positions thick, KLT's thin), the refinement's "
                        "fit residual and the refined − KLT distance over the frames.")
    elif tracks is not None:
        notes.append("The capture follows no point (no track: entries): no track figure.")
    bar.update()
    return figures, notes


_FRAMES = ("Frames: {B} base, {C} camera (OpenCV = ROS optical: x right, y down, z forward). T_cam_base maps base "
           "points into the camera (Cp = R Bp + t); T_base_cam is the camera's pose on the robot. Each transform's "
           "3σ bounds are in its own frame (docs/formats.md): rotation errors R_true = Exp(dθ) R about the axes "
           "of its first frame, t_true = t + dt along them — base axes for T_base_cam, camera axes for T_cam_base.")


def _blocks(result: Mapping[str, Any], dataset: Dataset | None, summary: _Summary, notes: list[str],
            figures: list[tuple[str, Any, str]], residuals: Residuals | None, ros: Mapping[str, Any],
            inputs: list[tuple[str, str]], base_frame: str) -> list[Block]:
    """Everything the report says, in order, for both renderings."""
    blocks = [Block("verdict", summary.headline, items=summary.reasons, good=summary.good), Block("h2", "Summary"),
              Block("table", rows=summary.rows, id="summary")]
    if base_is_first_camera(result, dataset):
        blocks.append(Block("p", no_target_text(result, dataset), id="no-target", css="flagged"))
    blocks += [Block("p", _FRAMES, id="frames"), Block("h2", "Console summary (mirror-fg calibrate)"),
               Block("pre", "\n".join(console_lines(result, dataset, summary.judged))),
               Block("h2", "Inputs"), Block("table", rows=inputs, id="inputs")]
    if dataset is not None and not dataset.is_tree or result.get("cameras"):
        blocks += view_blocks(result, dataset, residuals if isinstance(residuals, ViewResiduals) else None, base_frame)
    if residuals is not None:
        flagged = residuals.flagged_images()
        blocks.append(Block("h2", f"Flagged images (RMS > {OUTLIER_FACTOR:g} × median)"))
        blocks.append(Block("list", items=[f"{k}: RMS {v:.3g} {residuals.units}" for k, v in flagged.items()],
                            css="flagged", id="flagged-images") if flagged else Block("p", "None.", id="flagged-images"))
    outliers = (result.get("residuals") or {}).get("outliers") or []
    if outliers:
        blocks += [Block("h2", "Measurements flagged by the calibration"),
                   Block("list", items=[f"image {o['image']}, point {o['point']}: {_fmt(o['sigmas'], 3)} σ"
                                        for o in outliers], id="outlier-measurements")]
    excluded = result.get("excluded") or []
    if excluded:
        blocks += [Block("h2", "Left out of the solve"),
                   Block("list", items=[f"image {e['image']}" + (f", point {e['point']}" if e.get("point") else "")
                                        + f": {e['reason']}" + (f" ({_fmt(e['sigmas'], 3)} σ)" if e.get("sigmas") is not None else "")
                                        for e in excluded], css="flagged", id="excluded")]
    inconsistency = result.get("inconsistency")
    if inconsistency is not None:
        blocks += [Block("h2", "Inconsistent capture"), Block("p", inconsistency["message"], id="inconsistency"),
                   Block("list", items=[f"group {k + 1}: " + ", ".join(group) for k, group in enumerate(inconsistency["groups"])],
                         css="flagged", id="inconsistency-groups")]
    if result.get("camera") is not None:
        blocks += [Block("h2", "Camera intrinsics estimated through the mirrors"),
                   Block("pre", "\n".join(camera_lines(result["camera"], result.get("covariance_cam_base"))), id="camera")]
    if notes:
        blocks += [Block("h2", "Notes"), Block("list", items=notes, css="note")]
    for heading, fig, caption in figures:
        blocks += [Block("h2", heading), Block("figure", caption, figure=fig)]
    blocks += units_blocks(result, dataset)  # error at a point, its map, held-out validation (report_units.py)
    link = ros["camera_link"]
    blocks += [
        Block("h2", "ROS"),
        Block("p", f"URDF joint, {ros['frames']['base']} → {ros['frames']['camera']} (xyz in metres, rpy "
                   "fixed-axis in radians):"),
        Block("pre", ros["urdf_joint"]),
        Block("p", "ROS 2 static transform:"),
        Block("pre", ros["static_transform_publisher_command"]),
        Block("p", f"Where the camera's link is the body frame {link['frames']['link']} ({link['frames']['link_convention']}): "
                   f"the two joints {ros['frames']['base']} → {link['frames']['link']} → {link['frames']['optical']} "
                   "(REP 103 rotation applied) and their static transforms:"),
        Block("pre", link["urdf_joints"] + "\n" + "\n".join(link["static_transform_publisher_commands"])),
    ]
    return blocks + rig_ros_blocks(ros)
