"""The human summary of a ``mirror-fg/result@1``: what ``mirror-fg calibrate`` prints and the report echoes.

Each transform is printed with its own bounds in its own frame, and the frame is named, as Kalibr
prints every transform with its convention: ``T_base_cam`` (the camera's pose on the robot) with
``sigma3_base_cam`` about and along the *base* axes; ``T_cam_base`` (its inverse) with
``sigma3_cam_base`` about and along the *camera* axes. Residuals use one RMS, docs/formats.md's
``rms_px`` (the root mean square of each measurement's Euclidean reprojection error, about
``sqrt(2) sigma`` when the noise model holds); every other figure is named for what it is.
Metres, degrees, millimetres; residuals in pixels, or normalized units for a dataset without camera.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from mirror_fg.io.result import base_cam_sigma3, transforms, validate_result
from mirror_fg.report.units import units_lines
from mirror_fg.report.verdict import (  # noqa: F401 (unknown_count, without_target: public here too)
    NOISE_BAND,
    Verdict,
    cost_warning,
    judge,
    noise_note,
    stored_verdict,
    unknown_count,
    without_target,
)

__all__ = ["summary_lines", "rig_lines", "frame_convention", "cost_warning", "verdict_line", "noise_note", "unknown_count",
           "NOISE_BAND", "RMS_DEFINITION", "MAX_OUTLIER_LINES"]

#: The one RMS of the project (docs/formats.md ``rms_px``), as printed beside it.
RMS_DEFINITION = "of each measurement's reprojection-error length, ≈ √2·σ expected"
#: Outliers listed without ``verbose`` (all with it).
MAX_OUTLIER_LINES = 20


def frame_convention() -> list[str]:
    """The frame convention printed with the transforms (two lines)."""
    return [
        "frames: camera axes are OpenCV = ROS optical (x right, y down, z forward); T_a_b maps points of b",
        "        into a; its 3-sigma bounds are rotation errors about a's axes (R_true = Exp(dθ) R) and position errors along them",
    ]


def _vector(values: Iterable[float] | None, fmt: str) -> str:
    if values is None:
        return "–"
    return "[" + ", ".join(format(float(x), fmt) for x in values) + "]"


def _bounds(sigma: Mapping[str, Any] | None, axes: str, position_of: str) -> str:
    if not sigma:
        return "  3-sigma bounds: not computed (the result has no covariance)"
    return (f"  3-sigma bounds in {axes} axes (x, y, z): rotation ±{_vector(sigma.get('rotation_deg'), '.3f')} deg, "
            f"{position_of} ±{_vector(sigma.get('position_mm'), '.2f')} mm")


def _transform_lines(entry: Mapping[str, Any], R: np.ndarray, t: np.ndarray, full: bool) -> list[str]:
    lines = [f"  R  {_vector(row, ' .6f')}" for row in R] if full else []
    lines.append(f"  t  {_vector(t, ' .5f')} m")
    q = entry.get("q_xyzw") if entry else None
    if full:
        from mirror_fg.core.transform import rotation_to_quaternion_xyzw

        lines.append(f"  q_xyzw {_vector(q if q is not None else rotation_to_quaternion_xyzw(R), ' .6f')}")
    return lines


def summary_lines(result: Mapping[str, Any], *, verbose: bool = False, incremental: bool = False,
                  source: str = "result", pixel_sigma: float | None = None, verdict: Verdict | None = None) -> list[str]:
    """The summary of a result@1 dictionary as lines of text (no trailing newlines).

    ``verbose``: also the full ``T_cam_base`` rotation, the costs and every outlier (else the first
    MAX_OUTLIER_LINES). ``incremental``: the iteration count is of iSAM2 updates, not LM iterations.
    ``verdict``: the one verdict to print (the report passes its own), else the one the result carries,
    else judged from the result alone (``pixel_sigma``: the dataset's; :mod:`mirror_fg.report.verdict`).
    ``result`` is validated first (DatasetError naming ``source``).
    """
    result = validate_result(result, source)
    line = (verdict or stored_verdict(result) or judge(result, pixel_sigma=pixel_sigma)).line
    (R_cb, t_cb), (R_bc, t_bc) = transforms(result)
    if without_target(result):
        lines = ["no known target: the base frame is the camera frame (T_cam_base is the identity, not estimated) "
                 "and the dataset's scale fixes the lengths; the mirrors and points below are in it"]
        lines += _target_free_lines(result)
        lines += _residual_lines(result.get("residuals") or {}, verbose)
        lines += excluded_lines(result.get("excluded") or [], verbose)
        lines += _optimizer_lines(result.get("optimizer") or {}, verbose, incremental)
        lines.append(line)
        return lines
    lines = ["T_base_cam  the camera's pose on the robot: p_base = R p_cam + t (tf/URDF parent base, child camera)"]
    lines += _transform_lines(result.get("T_base_cam") or {}, R_bc, t_bc, full=True)
    lines.append(_bounds(base_cam_sigma3(result), "base", "camera position"))
    lines.append("T_cam_base  its inverse: p_cam = R p_base + t (t: the base origin in camera axes)")
    lines += _transform_lines(result["T_cam_base"], R_cb, t_cb, full=verbose)
    lines.append(_bounds(result.get("sigma3_cam_base"), "camera", "base origin"))
    lines += frame_convention()
    lines += units_lines(result)  # the error at the user's points, the held-out validation (report_units.py)
    if result.get("mounts"):  # a robot arm: T_base_cam is the camera's mount on its link
        from mirror_fg.report.robot_summary import mount_lines
        lines += mount_lines(result)
    if result.get("camera") is not None:
        lines += camera_lines(result["camera"], result.get("covariance_cam_base"))
    if result.get("cameras"):
        lines += rig_lines(result)
    lines += _residual_lines(result.get("residuals") or {}, verbose)
    lines += excluded_lines(result.get("excluded") or [], verbose)
    if result.get("inconsistency") is not None:
        lines.append(f"warning: {result['inconsistency']['message']}")
    lines += _optimizer_lines(result.get("optimizer") or {}, verbose, incremental)
    lines.append(line)
    return lines


def _target_free_lines(result: Mapping[str, Any]) -> list[str]:
    """Each mirror's distance and each point with their 3-sigma bounds (camera frame, millimetres)."""
    lines = []
    for entry in result.get("mirrors") or []:
        v = np.asarray(entry["v"], dtype=float)
        sigma = entry.get("sigma3_mm")
        lines.append(f"  mirror {entry['mirror']} placement {entry['config']}: {1000 * np.linalg.norm(v):.2f} mm from the "
                     f"camera, v {_vector(v, ' .5f')} m" + (f", 3-sigma ±{_vector(sigma, '.2f')} mm" if sigma else ""))
    for name, entry in list((result.get("points") or {}).items())[:20]:
        sigma = entry.get("sigma3_mm")
        lines.append(f"  point {name}: {_vector(entry['xyz'], ' .5f')} m"
                     + (f", 3-sigma ±{_vector(sigma, '.2f')} mm" if sigma else ""))
    return lines


def rig_lines(result: Mapping[str, Any]) -> list[str]:
    """Every camera of a multi-camera result (its ``T_base_cam`` with its own 3-sigma bounds about the base
    axes, the intrinsics it estimated) and every rig transform (Kalibr's ``T_cn_cnm1``) with its own bounds
    about the ``to`` camera's axes."""
    from mirror_fg.core.transform import rotation_to_quaternion_xyzw

    cameras = result["cameras"]
    names = list(cameras)
    lines = [f"cameras ({len(names)}; {names[0]} is the pose above): T_base_cam, each camera's pose on the robot"]
    for name, entry in cameras.items():
        T = entry.get("T_base_cam") or {}
        R_cb, t_cb = np.array(entry["T_cam_base"]["R"]), np.array(entry["T_cam_base"]["t"])
        R, t = (np.array(T["R"]), np.array(T["t"])) if T else (R_cb.T, -R_cb.T @ t_cb)
        q = T.get("q_xyzw") if T else None
        lines.append(f"  {name}: t {_vector(t, ' .5f')} m, q_xyzw "
                     f"{_vector(q if q is not None else rotation_to_quaternion_xyzw(R), ' .6f')}")
        lines.append("  " + _bounds(entry.get("sigma3_base_cam"), "base", "camera position"))
        block = entry.get("camera") or {}
        if block.get("estimated") and block != result.get("camera"):  # the top-level camera is printed above
            lines += ["    " + line for line in camera_lines(block, entry.get("covariance_cam_base"))]
    lines.append("rig (Kalibr's T_cn_cnm1): p_to = R p_from + t; bounds about and along the 'to' camera's axes")
    for entry in result.get("rig") or []:
        R, t = np.array(entry["T"]["R"]), np.array(entry["T"]["t"])
        q = entry["T"].get("q_xyzw")
        lines.append(f"  {entry['from']} -> {entry['to']}: t {_vector(t, ' .5f')} m (baseline "
                     f"{1e3 * float(np.linalg.norm(t)):.2f} mm), q_xyzw "
                     f"{_vector(q if q is not None else rotation_to_quaternion_xyzw(R), ' .6f')}")
        lines.append("  " + _bounds(entry.get("sigma3"), f"{entry['to']}'s", "position"))
    return lines


def verdict_line(result: Mapping[str, Any], pixel_sigma: float | None = None) -> str:
    """The console's one ``verdict:`` line: the verdict the result carries (``calibrate`` stores it), else
    :func:`mirror_fg.report.verdict.judge`'s from what the result holds (``pixel_sigma``: the dataset's)."""
    return (stored_verdict(result) or judge(result, pixel_sigma=pixel_sigma)).line


#: Intrinsics printed in pixels (the others, distortion terms, are unitless).
_PIXEL_INTRINSICS = ("fx", "fy", "cx", "cy")
_DIST_INDEX = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4}


def camera_lines(camera: Mapping[str, Any], pose_covariance: Any = None) -> list[str]:
    """The intrinsics estimated through the mirrors with their 3-sigma bounds, and the largest correlation
    of each with the pose (result@1 ``camera``)."""
    estimated = list(camera.get("estimated") or [])
    sigma3 = camera.get("sigma3") or {}
    dist = list(camera.get("dist") or [])
    lines = [f"camera intrinsics estimated through the mirrors ({camera.get('model', 'pinhole')} "
             f"{camera.get('width', '?')}x{camera.get('height', '?')}):"]
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"):
        if name in _PIXEL_INTRINSICS:
            value, unit = camera.get(name), " px"
        else:
            index = _DIST_INDEX[name]
            value, unit = (dist[index] if index < len(dist) else None), ""
        if value is None or (name not in estimated and name not in _PIXEL_INTRINSICS and value == 0.0):
            continue
        bound = f" ± {sigma3[name]:.4g}{unit} (3σ)" if name in estimated and name in sigma3 else " (kept)"
        lines.append(f"  {name} {float(value):.6g}{unit}{bound}")
    correlation = _pose_correlation(camera, pose_covariance)
    if correlation:
        lines.append("  largest correlation with T_cam_base: " + ", ".join(correlation))
    return lines


def _pose_correlation(camera: Mapping[str, Any], pose_P: Any) -> list[str]:
    """``fx~tz +0.83``-style entries: each estimated intrinsic's largest correlation with an axis of the
    pose ``[dtheta, dt]`` of ``T_cam_base`` (camera axes)."""
    P, C = camera.get("covariance"), camera.get("cross_covariance_cam_base")
    if P is None or C is None or pose_P is None:
        return []
    axes = ("θx", "θy", "θz", "tx", "ty", "tz")
    P, C, pose_P = np.asarray(P, dtype=float), np.asarray(C, dtype=float), np.asarray(pose_P, dtype=float)
    out = []
    for i, name in enumerate(camera.get("estimated") or []):
        denominator = np.sqrt(max(P[i, i], 1e-300) * np.maximum(np.diag(pose_P), 1e-300))
        rho = C[i] / denominator
        j = int(np.argmax(np.abs(rho)))
        out.append(f"{name}~{axes[j]} {rho[j]:+.2f}")
    return out


def excluded_lines(excluded: list[Mapping[str, Any]], verbose: bool) -> list[str]:
    """What was left out of the solve, each with its reason (result@1 ``excluded``)."""
    if not excluded:
        return []
    images = sum(1 for e in excluded if e.get("point") is None)
    lines = [f"left out: {images} image(s), {len(excluded) - images} measurement(s):"]
    shown = excluded if verbose else excluded[:MAX_OUTLIER_LINES]
    for e in shown:
        what = f"image '{e['image']}'" + (f" point '{e['point']}'" if e.get("point") is not None else "")
        sigmas = f" ({e['sigmas']:.1f} σ)" if e.get("sigmas") is not None and math.isfinite(e["sigmas"]) else ""
        lines.append(f"  {what}: {e['reason']}{sigmas}")
    if len(shown) < len(excluded):
        lines.append(f"  ... and {len(excluded) - len(shown)} more (-v lists all; the report has them)")
    return lines


def _residual_lines(res: Mapping[str, Any], verbose: bool) -> list[str]:
    if not res:
        return ["residuals: not in the result"]
    unit = "px" if res.get("units", "px") == "px" else "(normalized)"
    named = [f"RMS {_num(res.get('rms_px'))} {unit} ({RMS_DEFINITION})"]
    if res.get("mean_px") is not None:
        named.append(f"mean length {_num(res['mean_px'])} {unit}")
    named.append(f"largest {_num(res.get('max_px'))} {unit}")
    lines = [f"residuals: {', '.join(named)}"]
    outliers = res.get("outliers") or []
    if outliers:
        from mirror_fg.solver.model.residuals import OUTLIER_SIGMAS

        lines.append(f"{len(outliers)} measurement(s) above {OUTLIER_SIGMAS:g} σ after the solve:")
        shown = outliers if verbose else outliers[:MAX_OUTLIER_LINES]
        lines += [f"  image '{o['image']}' point '{o['point']}': {o['sigmas']:.1f} σ" for o in shown]
        if len(shown) < len(outliers):
            lines.append(f"  ... and {len(outliers) - len(shown)} more (-v lists all; the report has them)")
    return lines


def _optimizer_lines(opt: Mapping[str, Any], verbose: bool, incremental: bool) -> list[str]:
    if not opt:
        return []
    what = "iSAM2 updates" if incremental else "LM iterations"
    states: dict[bool | None, str] = {True: "converged", False: "NOT converged"}
    state = states.get(opt.get("converged"), "convergence unknown")
    lines = [f"optimizer: {opt.get('iterations', '–')} {what}, {state}"]
    if verbose:
        lines.append(f"  cost (0.5 χ²): initial {_num(opt.get('initial_error'))}, final {_num(opt.get('final_error'))}, "
                     f"expected at the optimum {_num(opt.get('expected_final_error'))}")
    warning = cost_warning(opt)
    return lines + ([f"warning: {warning}"] if warning else [])


def _num(x: Any) -> str:
    return "–" if x is None else f"{float(x):.3f}" if abs(float(x)) < 1e4 else f"{float(x):.4g}"
