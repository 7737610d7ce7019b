"""ROS-facing outputs of a multi-camera ``mirror-fg/result@1`` (docs/formats.md "Several cameras"): every
camera's pose on the robot as a URDF joint, its ``camera_link`` variant and its ROS 2 static transform
publisher commands, and the URDF robot holding them all.

Each camera's optical frame (OpenCV = ROS optical, REP 103) is named after the camera:
``<name>_optical_frame`` (characters a frame id does not take become ``_``), its body frame
``<name>_link``. Every joint's parent is the base frame and its origin the camera's ``T_base_cam``
(``p_base = R p_cam + t``, metres; URDF rpy fixed-axis), as :mod:`mirror_fg.io.ros` does for one camera;
:func:`mirror_fg.io.ros.ros_outputs` and :func:`~mirror_fg.io.ros.ros_output_texts` call this module for
a result with ``cameras``.
"""
from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.ros_snippets import (
    _CAMERA_CONVENTION,
    _camera_link,
    _transform_entry,
    _xml_comment,
    link_frame_name,
    quoteattr,
    static_transform_publisher_args,
    urdf_joint,
)

__all__ = ["rig_camera_frame", "rig_camera_frames", "rig_ros_outputs", "rig_urdf_text"]

_NOT_FRAME_CHARACTER = re.compile(r"[^A-Za-z0-9_]")


def rig_camera_frame(name: str) -> str:
    """The optical frame of camera ``name``: ``<name>_optical_frame`` (other characters than letters, digits
    and ``_`` become ``_``)."""
    return _NOT_FRAME_CHARACTER.sub("_", name) + "_optical_frame"


def rig_camera_frames(result: Mapping[str, Any], base_frame: str, source: str = "result") -> dict[str, str]:
    """``{camera name: optical frame}`` of a validated result's ``cameras``; DatasetError naming ``source``
    where two cameras would get one frame, or one the base frame's name."""
    frames: dict[str, str] = {}
    for name in result["cameras"]:
        frame = rig_camera_frame(name)
        for other, taken in frames.items():
            if frame == taken or link_frame_name(frame) == link_frame_name(taken):
                raise DatasetError(f"{source}: cameras {other!r} and {name!r} would both be frame {frame!r} in the "
                                   "ROS outputs; rename one (letters, digits and _)")
        if base_frame in (frame, link_frame_name(frame)):
            raise DatasetError(f"{source}: camera {name!r}'s frame {frame!r} would be the base frame; rename it")
        frames[name] = frame
    return frames


def _pose(entry: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(entry["R"], dtype=float), np.array(entry["t"], dtype=float)


def rig_ros_outputs(result: Mapping[str, Any], base_frame: str, source: str = "result") -> dict[str, Any]:
    """The ``.ros.yaml`` keys of a validated result with ``cameras``: ``cameras`` (per camera its frames,
    ``T_base_cam`` and ``T_cam_base`` entries, both 3-sigma bounds, ``urdf_joint``, the publisher arguments
    and command, and its ``camera_link`` variant, as the top level has them for the first camera),
    ``rig`` (each ``T_cn_cnm1`` between the optical frames with its 3-sigma bounds) and
    ``static_transform_publisher_commands`` (one per camera)."""
    frames = rig_camera_frames(result, base_frame, source)
    cameras: dict[str, Any] = {}
    for name, entry in result["cameras"].items():
        frame = frames[name]
        R_cb, t_cb = _pose(entry["T_cam_base"])
        R_bc, t_bc = _pose(entry["T_base_cam"]) if entry.get("T_base_cam") else (R_cb.T, -R_cb.T @ t_cb)
        args = static_transform_publisher_args(R_bc, t_bc, base_frame, frame)
        cameras[name] = {
            "frames": {"base": base_frame, "camera": frame, "camera_convention": _CAMERA_CONVENTION},
            "T_base_cam": _transform_entry(
                R_bc, t_bc, (entry.get("T_base_cam") or {}).get("q_xyzw"),
                f"pose of {frame} in {base_frame} (parent {base_frame}, child {frame}): p_base = R p_cam + t, metres"),
            "T_cam_base": _transform_entry(R_cb, t_cb, entry["T_cam_base"].get("q_xyzw"),
                                           f"inverse: p_cam = R p_base + t, metres ({frame} <- {base_frame})"),
            "sigma3_base_cam": entry.get("sigma3_base_cam"),
            "sigma3_cam_base": entry.get("sigma3_cam_base"),
            "urdf_joint": urdf_joint(R_bc, t_bc, base_frame, frame),
            "static_transform_publisher": args,
            "static_transform_publisher_command": f"ros2 run tf2_ros static_transform_publisher {args}",
            "camera_link": _camera_link(R_bc, t_bc, base_frame, link_frame_name(frame), frame),
        }
    rig = []
    for entry in result.get("rig") or []:
        R, t = _pose(entry["T"])
        parent, child = frames[entry["from"]], frames[entry["to"]]
        rig.append({"from": parent, "to": child,
                    "T_cn_cnm1": _transform_entry(R, t, entry["T"].get("q_xyzw"),
                                                  f"p_{child} = R p_{parent} + t, metres (Kalibr's T_cn_cnm1)"),
                    "sigma3": entry.get("sigma3")})
    return {
        "cameras": cameras,
        "rig": rig,
        "static_transform_publisher_commands": [c["static_transform_publisher_command"] for c in cameras.values()],
    }


def rig_urdf_text(content: Mapping[str, Any], base_frame: str, source: str, name: str = "mirror_fg_calibration") -> str:
    """A minimal valid URDF robot of :func:`rig_ros_outputs`' ``content``: the base link, one link per
    camera's optical frame and the fixed joint from the base to each."""
    cameras = content["cameras"]
    frames = [c["frames"]["camera"] for c in cameras.values()]
    links = "".join(f"  <link name={quoteattr(f)}/>\n" for f in [base_frame, *frames])
    joints = "".join(c["urdf_joint"] for c in cameras.values())
    listed = ", ".join(frames)
    return (
        '<?xml version="1.0"?>\n'
        f"<!-- mirror-fg calibration from {_xml_comment(source)}: pose of each camera ({_xml_comment(listed)})\n"
        f"     in {base_frame}. Each camera frame is the {_CAMERA_CONVENTION} frame. A complete robot:\n"
        "     paste the joints into your robot description. Where a camera's link is its body frame\n"
        "     (<name>_link, x forward), use the two joints under cameras.<name>.camera_link.urdf_joints in the .ros.yaml. -->\n"
        f"<robot name={quoteattr(name)}>\n{links}{joints}</robot>\n"
    )
