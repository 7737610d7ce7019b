"""ROS-facing outputs of a ``mirror-fg/result@1``: a YAML with both transforms, a URDF ``<joint>`` and
``static_transform_publisher`` arguments.

Frames (docs/formats.md): ``T_cam_base = (R, t)`` maps base points into the camera, ``Cp = R @ Bp + t``; its
inverse ``T_base_cam`` is the camera's pose in the base frame, ``Bp = R' @ Cp + t'``: the transform from
the parent ``base_frame`` to the child ``camera_frame`` that a URDF joint or a tf2 static transform
wants. The camera frame is OpenCV's (x right, y down, z forward), which is ROS's *optical* frame
convention (REP 103), hence the default child name ``camera_optical_frame``. Translations in metres,
angles in radians unless a name says ``_deg``; 3-sigma bounds in degrees and millimetres.

URDF ``rpy`` is fixed-axis roll, pitch, yaw: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. Quaternions are
Hamilton, scalar last (``x, y, z, w``). Numbers are printed with ``repr`` (shortest string that reads
back to the same double) so a pasted transform is the computed one to the last bit.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.output import OutputPlan
from mirror_fg.io.result import transforms, validate_result
from mirror_fg.io.ros_rig import rig_camera_frame, rig_ros_outputs, rig_urdf_text
from mirror_fg.io.ros_snippets import (
    _CAMERA_CONVENTION,
    DEFAULT_BASE_FRAME,
    DEFAULT_CAMERA_FRAME,
    R_LINK_OPTICAL,
    _camera_link,
    _num,
    _transform_entry,
    _xml_comment,
    check_camera_frame_name,
    check_frame_name,
    link_frame_name,
    quoteattr,
    rotation_to_rpy,
    sigma3_base_cam,
    static_transform_publisher_args,
    urdf_joint,
    urdf_robot,
)

__all__ = [
    "ros_outputs",
    "write_ros_outputs",
    "rotation_to_rpy",
    "urdf_joint",
    "static_transform_publisher_args",
    "sigma3_base_cam",
    "check_frame_name",
    "check_camera_frame_name",
    "link_frame_name",
    "urdf_robot",
    "R_LINK_OPTICAL",
    "ros_output_paths",
    "ros_output_texts",
    "DEFAULT_BASE_FRAME",
    "DEFAULT_CAMERA_FRAME",
    "camera_info_text",
    "rig_camera_info_path",
]


def ros_outputs(
    result: Mapping[str, Any],
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
    *,
    source: str = "result",
    link_frame: str | None = None,
) -> dict[str, Any]:
    """The content of ``<stem>.ros.yaml`` for a result@1 dictionary.

    Keys: ``frames``; ``T_base_cam`` (camera pose in the base frame: ``p_base = R p_cam + t``) and
    ``T_cam_base`` (its inverse), each with ``matrix`` (4x4 homogeneous), ``translation`` (metres),
    ``quaternion_xyzw`` and URDF ``rpy`` (radians); ``sigma3`` (``rotation_deg``, ``position_mm`` of
    ``T_cam_base`` in docs/formats.md's convention, as in the result); ``sigma3_base_cam`` (the camera's pose
    in the base frame, when the result has a covariance); ``rms_px`` and ``max_px`` (pixels, or
    normalized units for a dataset without a camera); ``urdf_joint`` (XML text);
    ``static_transform_publisher`` (ROS 2 argument string) and ``static_transform_publisher_command``;
    ``camera_link``: the same pose for a description whose camera link is the body frame ``link_frame``
    (default :func:`link_frame_name`; REP 103, x forward): ``T_base_link`` = ``T_base_cam`` with the
    REP 103 rotation applied, the fixed ``T_link_optical``, both URDF joints and both publisher commands.
    ``camera_frame`` is the optical frame; a body-frame name is refused (:func:`check_camera_frame_name`).
    A result with ``cameras`` also gets ``cameras``, ``rig`` and ``static_transform_publisher_commands``
    (:func:`mirror_fg.io.ros_rig.rig_ros_outputs`); every frame is then named after its camera
    (``<name>_optical_frame``, ``<name>_link``: ``camera_frame`` and ``link_frame`` are not used) and the
    top-level keys are the first camera's.
    Raises DatasetError (a ValueError) naming ``source`` and the key on a malformed result
    (:func:`mirror_fg.io.result.validate_result`), ValueError on a bad frame name.
    """
    base_frame = check_frame_name(base_frame, "base frame")
    camera_frame = check_camera_frame_name(camera_frame, "camera frame")
    link_frame = check_frame_name(link_frame or link_frame_name(camera_frame), "camera link frame")
    result = validate_result(result, source)
    rig = None
    if result.get("cameras"):  # several cameras: each is named after its camera (io.ros_rig)

        rig = rig_ros_outputs(result, base_frame, source)
        camera_frame = next(iter(rig["cameras"].values()))["frames"]["camera"]
        link_frame = link_frame_name(camera_frame)
    (R_cb, t_cb), (R_bc, t_bc) = transforms(result)
    hint_cb = result["T_cam_base"].get("q_xyzw")
    hint_bc = (result.get("T_base_cam") or {}).get("q_xyzw")
    sigma = result.get("sigma3_cam_base") or {}
    residuals = result.get("residuals") or {}
    args = static_transform_publisher_args(R_bc, t_bc, base_frame, camera_frame)
    out: dict[str, Any] = {
        "frames": {"base": base_frame, "camera": camera_frame, "camera_convention": _CAMERA_CONVENTION},
        "T_base_cam": _transform_entry(
            R_bc, t_bc, hint_bc,
            f"pose of {camera_frame} in {base_frame} (parent {base_frame}, child {camera_frame}): "
            "p_base = R p_cam + t, metres",
        ),
        "T_cam_base": _transform_entry(
            R_cb, t_cb, hint_cb, f"inverse: p_cam = R p_base + t, metres ({camera_frame} <- {base_frame})"
        ),
        "sigma3": {
            "rotation_deg": sigma.get("rotation_deg"),
            "position_mm": sigma.get("position_mm"),
            "convention": "T_cam_base, docs/formats.md: R_true = Exp(dtheta) R (camera axes), t_true = t + dt",
        },
        "sigma3_base_cam": sigma3_base_cam(result, source),
        "rms_px": residuals.get("rms_px"),
        "max_px": residuals.get("max_px"),
        "urdf_joint": urdf_joint(R_bc, t_bc, base_frame, camera_frame),
        "static_transform_publisher": args,
        "static_transform_publisher_command": f"ros2 run tf2_ros static_transform_publisher {args}",
        "camera_link": _camera_link(R_bc, t_bc, base_frame, link_frame, camera_frame),
    }
    if rig is not None:
        out.update(rig)
    return out


#: YAML line width: never fold a long string (the publisher arguments are copied as one line).
_NO_WRAP = 1 << 16


class _Dumper(yaml.SafeDumper):
    """SafeDumper writing multi-line strings (the URDF joint) as literal blocks."""


def _str_representer(dumper: yaml.SafeDumper, data: str) -> yaml.ScalarNode:
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style="|" if "\n" in data else None)


_Dumper.add_representer(str, _str_representer)


def _yaml_text(content: Mapping[str, Any], header: str) -> str:
    """``header`` then ``content`` as YAML (innermost lists in flow style, keys in insertion order)."""
    body = yaml.dump(
        dict(content), Dumper=_Dumper, default_flow_style=None, sort_keys=False, width=_NO_WRAP, allow_unicode=True
    )
    return header + body


def ros_output_paths(result_path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``(<stem>.ros.yaml, <stem>.urdf.xml)`` beside ``result_path``."""
    p = Path(result_path)
    return p.with_name(f"{p.stem}.ros.yaml"), p.with_name(f"{p.stem}.urdf.xml")


def camera_info_path(result_path: str | os.PathLike[str]) -> Path:
    """``<stem>.camera_info.yaml`` beside ``result_path``: the camera estimated through the mirrors."""
    p = Path(result_path)
    return p.with_name(f"{p.stem}.camera_info.yaml")


def rig_camera_info_path(result_path: str | os.PathLike[str], camera: str) -> Path:
    """``<stem>.<camera>.camera_info.yaml`` beside ``result_path``: a rig camera estimated through the mirrors
    (its name as in its frame, ``ros_rig.rig_camera_frame``)."""

    p = Path(result_path)
    return p.with_name(f"{p.stem}.{rig_camera_frame(camera).removesuffix('_optical_frame')}.camera_info.yaml")


def ros_output_texts(
    result: Mapping[str, Any],
    result_path: str | os.PathLike[str],
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
    link_frame: str | None = None,
) -> dict[str, str]:
    """``{path: text}`` of ``<stem>.ros.yaml`` (:func:`ros_outputs`) and ``<stem>.urdf.xml`` (a minimal
    valid URDF robot: the two links and the joint, :func:`urdf_robot`).

    Nothing is written (the caller writes all its outputs together). Raises DatasetError naming
    ``result_path`` on a malformed result, ValueError on a bad frame name.
    """
    mounts = result.get("mounts") or {}
    if "camera" in mounts and base_frame == DEFAULT_BASE_FRAME:  # a robot arm: T_base_cam is on the camera's link
        base_frame = mounts["camera"]["link"]
    content = ros_outputs(result, base_frame, camera_frame, source=os.fspath(result_path), link_frame=link_frame)
    yaml_path, urdf_path = ros_output_paths(result_path)
    source = " ".join(Path(result_path).name.split())  # one line in a comment
    header = (
        f"# mirror-fg camera-to-base calibration from {source}.\n"
        f"# Frames: {base_frame} (base), {camera_frame} (camera: {_CAMERA_CONVENTION}).\n"
        "# Metres, radians; quaternions x y z w; URDF rpy fixed-axis: R = Rz(yaw) Ry(pitch) Rx(roll).\n"
    )
    if content.get("cameras"):

        frames = ", ".join(c["frames"]["camera"] for c in content["cameras"].values())
        header = header.replace(f"{camera_frame} (camera:", f"{frames} (cameras:", 1)
        return {os.fspath(yaml_path): _yaml_text(content, header), os.fspath(urdf_path): rig_urdf_text(content, base_frame, source)}
    link = content["camera_link"]["frames"]["link"]
    urdf = (
        '<?xml version="1.0"?>\n'
        f"<!-- mirror-fg calibration from {_xml_comment(source)}: pose of {camera_frame} in {base_frame}.\n"
        f"     {camera_frame} is the {_CAMERA_CONVENTION} frame. A complete robot (two links, one joint):\n"
        "     paste the joint into your robot description. Where the camera's link is the body frame\n"
        f"     {link} (x forward), use the two joints under camera_link.urdf_joints in the .ros.yaml. -->\n"
        + urdf_robot(content["urdf_joint"], base_frame, camera_frame)
    )
    links = {base_frame, camera_frame}
    for name, entry in (mounts.get("cameras") or {}).items():  # an arm's several cameras: each by its name
        R_lc, t_lc = (np.asarray(entry["T_link_cam"][k], dtype=float) for k in ("R", "t"))
        frame = f"{name}_optical_frame"
        extra = "".join(f"  <link name={quoteattr(f)}/>\n" for f in dict.fromkeys((entry["link"], frame)) if f not in links)
        links |= {entry["link"], frame}
        urdf = urdf.replace("</robot>\n", extra + urdf_joint(R_lc, t_lc, entry["link"], frame) + "</robot>\n")
    if "target" in mounts:  # the target's estimated mount too (docs/formats.md "Robot arms")
        target = mounts["target"]
        R_lt, t_lt = (np.asarray(target["T_link_target"][k], dtype=float) for k in ("R", "t"))
        extra = "".join(f"  <link name={quoteattr(f)}/>\n" for f in (target["link"], "calibration_target") if f not in links)
        urdf = urdf.replace("</robot>\n", extra + urdf_joint(R_lt, t_lt, target["link"], "calibration_target") + "</robot>\n")
    return {os.fspath(yaml_path): _yaml_text(content, header), os.fspath(urdf_path): urdf}


def write_ros_outputs(
    result: Mapping[str, Any],
    result_path: str | os.PathLike[str],
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
    link_frame: str | None = None,
) -> list[Path]:
    """Write :func:`ros_output_texts`: ``<stem>.ros.yaml`` and ``<stem>.urdf.xml`` beside ``result_path``.

    Both are written all-or-nothing (:class:`~mirror_fg.io.output.OutputPlan`). Returns the two paths.
    Raises DatasetError naming ``result_path`` on a malformed result, ValueError on a bad frame name
    (nothing is written then), OutputError (a DatasetError and an OSError) when a file cannot be written.
    """
    texts = ros_output_texts(result, result_path, base_frame, camera_frame, link_frame)
    plan = OutputPlan()
    for path in texts:
        plan.add(path, "ROS output")
    return plan.commit(texts)


#: ROS ``distortion_model`` of each OpenCV distortion vector length (pinhole) and of the fisheye model.
_DISTORTION_MODELS = {4: "plumb_bob", 5: "plumb_bob", 8: "rational_polynomial"}


def camera_info_text(camera: Camera, camera_name: str = "camera", sigma3: Mapping[str, float] | None = None) -> str:
    """A ``camera_info`` YAML (the ``camera_calibration_parsers`` format that ``camera_info_manager``
    loads) of ``camera``: ``K``, ``D``, identity ``R``, ``P = [K | 0]``; ``plumb_bob`` for OpenCV's
    ``k1, k2, p1, p2[, k3]``, ``rational_polynomial`` for 8 terms, ``equidistant`` for the fisheye model.
    ``sigma3``: 3-sigma of the estimated intrinsics, written as a comment. DatasetError for a
    distortion vector ROS has no model for (12 or 14 terms).
    """
    if camera.model == "fisheye":
        model = "equidistant"
    elif len(camera.dist) in _DISTORTION_MODELS:
        model = _DISTORTION_MODELS[len(camera.dist)]
    else:
        raise DatasetError(f"camera_info: ROS has no distortion model for {len(camera.dist)} OpenCV terms")
    check_frame_name(camera_name, "camera_name")
    dist = [float(x) for x in camera.dist]
    if model == "plumb_bob":
        dist = (dist + [0.0])[:5]  # k1, k2, p1, p2, k3
    fx, fy, cx, cy = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    content = {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera_name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]},
    }
    header = "# camera_info of the camera estimated through the mirrors by mirror-fg (pixels; OpenCV model)\n"
    if sigma3:
        header += "# 3-sigma: " + ", ".join(f"{name} {_num(value)}" for name, value in sigma3.items()) + "\n"
    return _yaml_text(content, header)
