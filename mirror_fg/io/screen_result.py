"""The screen in a result: result@1's ``screen`` block, its check, and the file gaze pipelines read.

A calibration from a capture whose target is a screen (:mod:`mirror_fg.io.screen_target`) has
``T_cam_base = T_cam_screen``. :func:`screen_block` makes the result's ``screen`` block (docs/formats.md,
"Screens"): the active area's corners (top-left, top-right, bottom-right, bottom-left) and the normal
towards the viewer, camera frame, metres. :func:`check_screen_block` is the validator's schema of it and
:func:`check_screen_pose` checks that its corners are those of ``T_cam_base``.

:func:`screen_xml_text` writes ``<result stem>.screen.xml``, an OpenCV FileStorage file with what gaze
pipelines use, under the key names of ETH-XGaze's ``mirror_position.xml`` (in these conventions): ``screen_rotation`` (3 x 3, ``R`` of the screen in the camera
frame: ``p_cam = R p_screen + t``), ``screen_rotation_vector`` (the same as a Rodrigues vector),
``screen_translation`` (``t``, **millimetres**: the screen's top-left corner in the camera frame),
``pix2mm`` (mm per pixel along x and y), ``screen_size_px``, ``screen_size_mm`` and
``screen_sigma3_rotation_deg`` / ``screen_sigma3_translation_mm`` (3-sigma, camera axes). A pixel
(u, v) (pixel-edge coordinates) is at ``R @ [u * pix2mm[0], v * pix2mm[1], 0] + t`` mm in the camera.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.core.gaze_error import DEFAULT_VIEWING_DISTANCE_M, gaze_block
from mirror_fg.core.screen import Screen
from mirror_fg.core.transform import Transform
from mirror_fg.io.result_checks import _child, _fields, _integer, _Invalid, _number, _vector, _vector3
from mirror_fg.io.screen_target import ScreenTarget

__all__ = ["screen_of", "screen_block", "check_screen_block", "check_screen_pose", "screen_xml_path", "screen_xml_text",
           "SCREEN_TOL_M"]

#: The ``screen`` block's corners must be those of ``T_cam_base`` to this (metres).
SCREEN_TOL_M = 1e-6
#: In the first lines of the side file, so that a later run may replace it.
MARKER = "written by mirror-fg"


def screen_of(target: ScreenTarget, result: Mapping[str, Any]) -> Screen:
    """The :class:`~mirror_fg.core.screen.Screen` of a result@1 dictionary calibrated with ``target``."""
    T = result["T_cam_base"]
    cov = result.get("covariance_cam_base")
    return Screen(target.width_px, target.height_px, target.width_mm, target.height_mm,
                  Transform(np.array(T["R"], dtype=float), np.array(T["t"], dtype=float)),
                  None if cov is None else np.array(cov, dtype=float))


def screen_block(target: ScreenTarget, result: Mapping[str, Any],
                 viewing_distance_m: float = DEFAULT_VIEWING_DISTANCE_M) -> dict[str, Any]:
    """The result@1 ``screen`` block of a result calibrated with the screen target ``target``, with the gaze
    point's error for an eye ``viewing_distance_m`` in front of the screen (:mod:`mirror_fg.core.gaze_error`)."""
    screen = screen_of(target, result)
    return {**screen.to_dict(), **gaze_block(screen, viewing_distance_m)}


def check_screen_block(value: Any, path: str) -> dict[Any, Any]:
    """The validator's schema of ``screen``: sizes > 0, four corners, a unit normal."""
    positive_int = lambda x, p: _integer(x, p, 1)  # noqa: E731
    positive = lambda x, p: _number(x, p, minimum=1e-300)  # noqa: E731
    corners = lambda x, p: [_vector3(c, _child(p, k)) for k, c in enumerate(_four(x, p))]  # noqa: E731
    out = _fields(value, path,
                  {"width_px": positive_int, "height_px": positive_int, "width_mm": positive, "height_mm": positive,
                   "corners_cam": corners, "normal_cam": _vector3},
                  {"mm_per_px": lambda x, p: _vector(x, 2, p)})
    if abs(float(np.linalg.norm(out["normal_cam"])) - 1.0) > 1e-6:
        raise _Invalid(_child(path, "normal_cam"), f"not a unit vector (norm {np.linalg.norm(out['normal_cam']):.6g})")
    return out


def _four(value: Any, path: str) -> list[Any]:
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        raise _Invalid(path, "expected 4 corners [[x, y, z], ...] (top-left, top-right, bottom-right, bottom-left)")
    return list(value)


def check_screen_pose(result: Mapping[str, Any]) -> None:
    """The ``screen`` block's corners and normal are those of ``T_cam_base`` (raises _Invalid)."""
    block = result["screen"]
    T = result["T_cam_base"]
    screen = Screen(block["width_px"], block["height_px"], block["width_mm"], block["height_mm"],
                    Transform(np.array(T["R"]), np.array(T["t"])))
    off = float(np.max(np.abs(screen.corners_cam - np.array(block["corners_cam"]))))
    if off > SCREEN_TOL_M:
        raise _Invalid("screen.corners_cam", f"not the corners of T_cam_base's screen (off by {off:.3g} m)")
    off = float(np.max(np.abs(screen.normal_cam - np.array(block["normal_cam"]))))
    if off > SCREEN_TOL_M:
        raise _Invalid("screen.normal_cam", f"not -z of T_cam_base's screen frame (off by {off:.3g})")


def screen_xml_path(result_path: str | os.PathLike[str]) -> str:
    """``result.json`` -> ``result.screen.xml`` (same folder)."""
    return os.fspath(Path(result_path).with_suffix("")) + ".screen.xml"


def screen_xml_text(result: Mapping[str, Any]) -> str:
    """The OpenCV FileStorage (XML) text of a result's screen (module docstring)."""
    import cv2

    block = result["screen"]
    R = np.array(result["T_cam_base"]["R"], dtype=float)
    t_mm = 1000.0 * np.array(result["T_cam_base"]["t"], dtype=float)
    fs = cv2.FileStorage("screen.xml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment(f"{MARKER}: the screen in the camera frame (p_cam = R p_screen + t); screen frame: origin at "
                    "the top-left corner of the active area, x right, y down, z into the screen; t in mm")
    fs.write("screen_rotation", R)
    fs.write("screen_rotation_vector", cv2.Rodrigues(R)[0])
    fs.write("screen_translation", t_mm.reshape(3, 1))
    fs.write("pix2mm", np.array([[block["width_mm"] / block["width_px"], block["height_mm"] / block["height_px"]]]))
    fs.write("screen_size_px", np.array([[block["width_px"], block["height_px"]]], dtype=np.int32))
    fs.write("screen_size_mm", np.array([[block["width_mm"], block["height_mm"]]], dtype=float))
    sigma3 = result.get("sigma3_cam_base")
    if sigma3 is not None:
        fs.write("screen_sigma3_rotation_deg", np.array([sigma3["rotation_deg"]], dtype=float))
        fs.write("screen_sigma3_translation_mm", np.array([sigma3["position_mm"]], dtype=float))
    return fs.releaseAndGetString()
