"""What the report says about general data (docs/formats.md "Views of any reflection order, and several
cameras") beyond a tree result's: the residuals by reflection order and by camera, every camera's pose on
the body and the rig between them, the placements and the cameras they tie, and — without a known target —
that the base frame is the first camera's frame, whose pose is not estimated.

Frames and conventions as :mod:`mirror_fg.report.writer`: ``T_cam_base = (R, t)``, ``Cp = R Bp + t``;
3σ bounds of ``T_base_cam`` about and along the base axes; the rig entry ``from -> to`` maps points of the
``from`` camera into the ``to`` camera (Kalibr's ``T_cn_cnm1``), its bounds about the ``to`` camera's axes.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.transform import Transform, rotation_angle
from mirror_fg.io.result import mirror_vectors, pose
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.report.pages import Block
from mirror_fg.report.scene import camera_position_covariances
from mirror_fg.report.views import (
    ViewResiduals,
    camera_stats,
    order_stats,
    placement_ties,
    result_camera_names,
)

if TYPE_CHECKING:
    from mirror_fg.data import Dataset

__all__ = ["base_is_first_camera", "no_target_text", "console_result", "view_unknown_count", "dataset_line",
           "view_blocks", "console_lines", "camera_input_rows", "rig_ros_blocks", "MAX_PLACEMENT_ROWS"]

#: Placements listed one row each up to this many (beyond it, the shared ones and the counts).
MAX_PLACEMENT_ROWS = 40
_BOUND_KEYS = ("covariance_cam_base", "sigma3_cam_base", "covariance_base_cam", "sigma3_base_cam",
               "covariance_base_cam_ros")


def _fmt(values: Any, digits: int = 4) -> str:
    if values is None:
        return "–"
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        return f"{float(arr):.{digits}g}"
    return "[" + ", ".join(f"{float(x):.{digits}g}" for x in arr.ravel()) + "]"


def base_is_first_camera(result: Mapping[str, Any], dataset: Dataset | None) -> bool:
    """Whether {B} is the first camera's frame: the dataset has no known target (``fiducials: {}``), or —
    without a dataset — the result's pose is the identity with a zero covariance (not estimated)."""
    if dataset is not None:
        return not dataset.fiducials
    R, t = pose(result["T_cam_base"])
    P = result.get("covariance_cam_base")
    return bool(np.allclose(R, np.eye(3)) and np.allclose(t, 0.0) and P is not None and not np.any(np.array(P)))


def _camera_word(name: str | None) -> str:
    return "the camera" if name is None else f"camera {name}"


def no_target_text(result: Mapping[str, Any], dataset: Dataset | None) -> str:
    """The page's statement of what the base frame is without a known target."""
    first = result_camera_names(result, dataset)[0]
    scale = getattr(dataset, "scale", None) if dataset is not None else None
    how = ""
    if scale is not None and scale.placement is not None:
        how = f" The scale is fixed by mirror {scale.placement[0]} configuration {scale.placement[1]}'s distance " \
              f"{scale.distance:.6g} m."
    elif scale is not None and scale.points is not None:
        how = f" The scale is fixed by the distance {scale.distance:.6g} m between {scale.points[0]} and {scale.points[1]}."
    return (f"No known target (fiducials: {{}}): the base frame {{B}} is the frame of {_camera_word(first)}, so its "
            "T_cam_base is the identity by definition and is not estimated — it has no uncertainty, and the "
            "zero bounds in the file are not a measurement. Every point is a reconstruction point, in that "
            "camera's frame." + how)


def console_result(result: Mapping[str, Any], dataset: Dataset | None) -> Mapping[str, Any]:
    """The result the console summary is printed from: without the top-level pose's covariances and
    bounds when that pose is the base frame itself (so that no zero bound is shown as an estimate)."""
    if not base_is_first_camera(result, dataset):
        return result
    return {k: v for k, v in result.items() if k not in _BOUND_KEYS}


def console_lines(result: Mapping[str, Any], dataset: Dataset | None, verdict: Any = None) -> list[str]:
    """The console summary (:func:`mirror_fg.report.summary.summary_lines`) of :func:`console_result`, its
    missing bounds said to be not estimated where the pose is the base frame itself; ``verdict``: the
    report's (:class:`mirror_fg.report.verdict.Verdict`), so that its line is the headline's verdict."""
    from mirror_fg.report.summary import summary_lines

    lines = summary_lines(console_result(result, dataset), verdict=verdict)
    if base_is_first_camera(result, dataset):
        lines = [line.replace("not computed (the result has no covariance)",
                              "not estimated (the base frame is this camera's frame: no known target)") for line in lines]
    return lines


def view_unknown_count(result: Mapping[str, Any], dataset: Dataset | None) -> int:
    """The general solve's unknowns p: 6 per estimated camera pose (all but the base frame's camera without
    a target), 3 per placement and reconstruction point, each estimated intrinsic, less one for a scale
    that a distance fixes."""
    names = result_camera_names(result, dataset)
    fixed = base_is_first_camera(result, dataset)
    estimated = len((result.get("camera") or {}).get("estimated") or []) if not result.get("cameras") else \
        sum(len(((e.get("camera") or {}).get("estimated")) or []) for e in result["cameras"].values())
    scale = dataset is not None and dataset.scale is not None
    return (6 * (len(names) - (1 if fixed else 0)) + 3 * len(mirror_vectors(result))
            + 3 * len(reconstruction_points(result)) + estimated - (1 if scale else 0))


def dataset_line(result: Mapping[str, Any], dataset: Dataset, units: str) -> str:
    """The summary's description of a general dataset: images, cameras, placements, views by order."""
    placements = {p for im in dataset.images for p in im.reflections}
    orders: dict[int, int] = {}
    for im in dataset.images:
        orders[len(im.reflections)] = orders.get(len(im.reflections), 0) + 1
    from mirror_fg.report.views import order_name

    views = ", ".join(f"{n} {order_name(k)}" for k, n in sorted(orders.items()))
    cameras = f"{len(dataset.cameras)} cameras, " if dataset.cameras else ""
    return (f"{len(dataset.images)} images ({views}), {cameras}{dataset.num_mirrors} mirror(s), {len(placements)} "
            f"mirror placements, {len(dataset.fiducials)} fiducials, {len(result.get('points') or {})} "
            f"reconstruction points, σ = {_fmt(dataset.pixel_sigma)} {units}")


def view_blocks(result: Mapping[str, Any], dataset: Dataset | None, residuals: ViewResiduals | None,
                base_frame: str) -> list[Block]:
    """The report's sections on general data: residuals by order and by camera, cameras, rig, placements."""
    blocks: list[Block] = []
    if residuals is not None and np.any(residuals.valid):
        u = residuals.units
        rows = [(f"{s.label} ({k} reflection{'s' if k != 1 else ''})",
                 f"RMS {s.rms:.3g} {u}, {s.count} measurements in {s.images} view(s), largest {s.largest:.3g} {u}")
                for k, s in order_stats(residuals).items()]
        blocks += [Block("h2", "Reflection orders: RMS, count, largest"), Block("table", rows=rows, id="orders")]
        per_camera = camera_stats(residuals)
        if len(per_camera) > 1 or (dataset is not None and dataset.cameras):
            rows = [(f"camera {c}", f"RMS {s.rms:.3g} {u}, {s.count} measurements in {s.images} image(s), "
                     f"largest {s.largest:.3g} {u}") for c, s in per_camera.items()]
            blocks += [Block("h2", "Cameras: RMS, count, largest"), Block("table", rows=rows, id="camera-residuals")]
    if result.get("cameras"):
        blocks += [Block("h2", f"Cameras (their poses on the body, in {base_frame})"),
                   Block("table", rows=_camera_rows(result, dataset, base_frame), id="cameras")]
    if result.get("rig"):
        blocks += [Block("h2", "Rig: each camera relative to the one before it (T_to_from, Kalibr's T_cn_cnm1)"),
                   Block("table", rows=_rig_rows(result["rig"]), id="rig")]
    if dataset is not None:
        blocks += _placement_blocks(dataset)
    return blocks


def _camera_rows(result: Mapping[str, Any], dataset: Dataset | None, base_frame: str) -> list[tuple[str, str]]:
    covariances = camera_position_covariances(result, dataset)
    rows = []
    for k, (name, entry) in enumerate(result["cameras"].items()):
        T = Transform(*pose(entry["T_cam_base"])).inverse()
        s3 = entry.get("sigma3_base_cam") or {}
        fixed = covariances.get(name) is None
        bounds = ("not estimated: the base frame itself (no known target)" if fixed and base_is_first_camera(result, dataset)
                  else "–" if fixed else f"rotation {_fmt(s3.get('rotation_deg'), 3)} deg, position "
                  f"{_fmt(s3.get('position_mm'), 3)} mm")
        top = " (the top-level T_base_cam)" if k == 0 else ""
        rows.append((f"camera {name}{top}: position in {base_frame}, m; URDF rpy, deg",
                     f"{_fmt(T.t, 6)}\n{_fmt(np.rad2deg(T.rpy()), 6)}"))
        rows.append((f"camera {name}: T_base_cam 3σ about / along {base_frame} x, y, z", bounds))
    return rows


def _rig_rows(rig: list[Mapping[str, Any]]) -> list[tuple[str, str]]:
    rows = []
    for entry in rig:
        R, t = pose(entry["T"])
        T = Transform(R, t)
        s3 = entry.get("sigma3") or {}
        pair = f"{entry['from']} → {entry['to']}"
        rows += [(f"{pair}: translation t ({entry['from']}'s origin in {entry['to']}'s axes), m", _fmt(t, 6)),
                 (f"{pair}: baseline |t|, mm; rotation angle, deg",
                  f"{1e3 * float(np.linalg.norm(t)):.4g}; {np.degrees(rotation_angle(R, np.eye(3))):.4g}"),
                 (f"{pair}: URDF rpy, deg", _fmt(np.rad2deg(T.rpy()), 6))]
        rows.append((f"{entry['from']} → {entry['to']}: 3σ about / along {entry['to']}'s x, y, z",
                     f"rotation {_fmt(s3.get('rotation_deg'), 3)} deg, position {_fmt(s3.get('position_mm'), 3)} mm"
                     if s3 else "–"))
    return rows


def _placement_blocks(dataset: Dataset) -> list[Block]:
    """Placements x cameras: how many views of each camera saw each placement; shared ones tie cameras."""
    ties = placement_ties(dataset)
    if not ties:
        return []
    several = dataset.cameras is not None and len(dataset.cameras) > 1

    def who(seen: Mapping[str | None, int]) -> str:
        text = ", ".join(f"{n} view(s)" if c is None else f"{c}: {n} view(s)" for c, n in seen.items())
        return text + (" — shared: ties " + " and ".join(str(c) for c in seen) if len(seen) > 1 else "")

    items = list(ties.items())
    shown = items if len(items) <= MAX_PLACEMENT_ROWS else [(p, s) for p, s in items if len(s) > 1][:MAX_PLACEMENT_ROWS]
    rows = [(f"mirror {p[0]} config {p[1]}", who(s)) for p, s in shown]
    if len(shown) < len(items):
        listed = {p for p, _ in shown}
        shared = sum(1 for p, seen in items if p not in listed and len(seen) > 1)
        alone = sum(1 for p, seen in items if p not in listed and len(seen) <= 1)
        rows.append((f"the other {len(items) - len(shown)} placement(s)",
                     f"{shared} more shared by several cameras, {alone} seen by one camera each"))
    heading = "Mirror placements and the cameras that saw them" if several else "Mirror placements and their views"
    blocks = [Block("h2", heading), Block("table", rows=rows, id="placements")]
    if several:
        pairs: dict[tuple[str, str], int] = {}
        for seen in ties.values():
            names = [c for c in seen if c is not None]
            for i, a in enumerate(names):
                for b in names[i + 1:]:
                    pairs[(a, b)] = pairs.get((a, b), 0) + 1
        assert dataset.cameras is not None
        lines = [f"{a} – {b}: {n} shared placement(s)" for (a, b), n in pairs.items()]
        unshared = [c for c in dataset.cameras if not any(c in key for key in pairs)]
        lines += [f"{c}: no placement shared with another camera (tied to the others only through the target)"
                  for c in unshared]
        blocks += [Block("p", "Cameras tied by shared placements (a shared placement is one plane seen by both):"),
                   Block("list", items=lines, id="ties")]
    return blocks


def camera_input_rows(dataset: Dataset) -> list[tuple[str, str]]:
    """The input echo's rows of a dataset with several cameras: one per camera, its intrinsics."""
    return [(f"camera {name}", f"{c.model} {c.width}×{c.height} px, fx {c.fx:.6g}, fy {c.fy:.6g}, cx {c.cx:.6g}, "
             f"cy {c.cy:.6g}, dist {_fmt(c.dist, 4)}") for name, c in (dataset.cameras or {}).items()]


def rig_ros_blocks(ros: Mapping[str, Any]) -> list[Block]:
    """The ROS snippets of every camera of a multi-camera result (``ros_outputs``' ``cameras``), if any."""
    cameras = ros.get("cameras")
    if not isinstance(cameras, Mapping) or not cameras:
        return []
    blocks = [Block("p", "Every camera (frames named after the cameras): URDF joints and ROS 2 static transforms:")]
    joints = [str(e.get("urdf_joint", "")).strip() for e in cameras.values() if isinstance(e, Mapping)]
    commands = [str(e.get("static_transform_publisher_command", "")) for e in cameras.values() if isinstance(e, Mapping)]
    blocks.append(Block("pre", "\n".join(j for j in joints if j) + "\n" + "\n".join(c for c in commands if c),
                        id="ros-cameras"))
    return blocks
