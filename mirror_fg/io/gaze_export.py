"""A screen calibration in the files gaze tools read (``mirror-fg export``; docs/formats.md, "The answer in the
user's units", "Gaze exports").

Every format holds the screen-camera pose of a result@1 with a ``screen`` block: ``T_cam_base`` =
``T_cam_screen = (R, t)``, ``p_cam = R p_screen + t`` (metres), screen frame of
:mod:`mirror_fg.core.screen` (origin at the top-left corner of the active area, x right along the pixel
rows, y down, z into the screen). Each tool's conventions, as its own code reads the file:

* ``opengaze`` (OpenGaze, C++: ``InputHandler::readScreenConfiguration``): OpenCV FileStorage YAML with
  ``monitor_W``, ``monitor_H`` (the active area, mm), ``monitor_R`` (3 x 3) and ``monitor_T`` (3 x 1, mm)
  with ``p_cam = monitor_R p_monitor + monitor_T`` and the monitor frame's corners at (0, 0, 0),
  (W, 0, 0), (0, H, 0), (W, H, 0) mm: the screen frame above in millimetres. OpenGaze multiplies these
  matrices with ``Vec3f`` (``CV_32F``), so they are written as 32-bit floats (``dt: f``), as its own
  example files are.
* ``eth-xgaze`` (ETH-XGaze's ``mirror_position.xml``, read with ``cv2.FileStorage(...).getNode(...).mat()``
  like its camera files): ``screen_rotation`` (3 x 3 ``R``), ``screen_translation`` (3 x 1, ``t`` in mm),
  ``pix2mm`` (mm per pixel along x and y); screen pixel (u, v) is at ``R [u pix2mm_x, v pix2mm_y, 0] + t``
  mm in the camera frame. ETH-XGaze does not document these conventions; these are ours (the same keys
  as ``<stem>.screen.xml``).
* ``few-shot-gaze`` (NVlabs few_shot_gaze's demo, which ``pickle.load``s ``calib_cam<N>.pkl``, a dict
  with ``mtx`` (3 x 3) and ``dist`` (1 x 5), the camera's OpenCV intrinsics): the same dict with the
  screen added for a ``monitor`` replacement (docs/gaze_guide.md): ``monitor_R`` (3 x 3), ``monitor_T``
  (3, mm), ``w_mm``, ``h_mm``, ``w_pixels``, ``h_pixels``. Its ``monitor_to_camera(x, y)`` returns
  millimetres in the camera frame (OpenCV axes), which is ``monitor_R [x w_mm / w_pixels, y h_mm /
  h_pixels, 0] + monitor_T``. ``mtx`` and ``dist`` are written where the result holds the camera
  (intrinsics estimated) or ``camera`` is given; without them the demo would calibrate the camera itself.
  Pickle protocol 2, arrays as ``numpy.array(list)`` (readable by NumPy 1 and 2 alike).
"""
from __future__ import annotations

import io
import pickle
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError

__all__ = ["FORMATS", "export_text", "screen_pose_mm", "one_screen"]

#: The formats and what each holds (the command's help).
FORMATS = {
    "opengaze": "OpenGaze's monitor file (OpenCV YAML: monitor_W, monitor_H, monitor_R, monitor_T in mm)",
    "eth-xgaze": "ETH-XGaze's mirror_position.xml (OpenCV XML: screen_rotation, screen_translation in mm, pix2mm)",
    "few-shot-gaze": "few_shot_gaze's calib_cam pickle (mtx, dist) with the monitor's pose (monitor_R, monitor_T in mm)",
}
#: In the first lines of every text file written, so that a later export may replace it.
MARKER = "written by mirror-fg"


def screen_pose_mm(result: Mapping[str, Any], source: str) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """``(R, t_mm, screen block)`` of a result with a screen; DatasetError (one line) otherwise."""
    block = result.get("screen")
    if not isinstance(block, Mapping):
        raise DatasetError(f"{source}: has no 'screen' block: the gaze formats hold a screen-camera pose "
                           "(calibrate a capture whose target is kind: screen)")
    T = result["T_cam_base"]
    return np.array(T["R"], dtype=float), 1000.0 * np.array(T["t"], dtype=float), dict(block)


def one_screen(result: Mapping[str, Any], name: str, source: str) -> dict[str, Any]:
    """The result as if screen ``name`` of its ``screens`` (a capture with several screens) were its only
    screen: ``T_cam_base`` its ``T_cam_screen``, its block as ``screen`` and its bounds; DatasetError if absent."""
    screens = result.get("screens")
    if not isinstance(screens, Mapping) or name not in screens:
        have = ", ".join(screens) if isinstance(screens, Mapping) else "none (one screen: drop --screen)"
        raise DatasetError(f"{source}: --screen {name}: no such screen in the result (its screens: {have})")
    block = dict(screens[name])
    pose, sigma3 = block.pop("T_cam_screen"), block.pop("sigma3", None)
    block.pop("covariance", None)
    return {**result, "T_cam_base": pose, "screen": block, "sigma3_cam_base": sigma3}


def export_text(result: Mapping[str, Any], fmt: str, source: str, camera: Mapping[str, Any] | None = None) -> str | bytes:
    """The file of format ``fmt`` (:data:`FORMATS`) for a result@1 dictionary; ``camera``: intrinsics
    (a camera@1 object: fx, fy, cx, cy, dist) for formats that carry them, where the result has none."""
    if fmt not in FORMATS:
        raise DatasetError(f"--to: unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    R, t_mm, block = screen_pose_mm(result, source)
    if fmt == "opengaze":
        return _opengaze(R, t_mm, block)
    if fmt == "eth-xgaze":
        from mirror_fg.io.screen_result import screen_xml_text

        return screen_xml_text(result)
    return _few_shot_gaze(R, t_mm, block, result.get("camera") or camera)


def _opengaze(R: np.ndarray, t_mm: np.ndarray, block: Mapping[str, Any]) -> str:
    import cv2

    fs = cv2.FileStorage("monitor.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML)
    fs.writeComment(f"{MARKER}: the screen in the camera frame for OpenGaze (p_cam = monitor_R p_monitor + "
                    "monitor_T, mm; monitor frame: origin at the top-left corner of the active area, x right, y down)")
    fs.write("monitor_W", float(block["width_mm"]))
    fs.write("monitor_H", float(block["height_mm"]))
    fs.write("monitor_R", R.astype(np.float32))  # OpenGaze multiplies them with Vec3f: CV_32F
    fs.write("monitor_T", t_mm.reshape(3, 1).astype(np.float32))
    lines = fs.releaseAndGetString().split("\n")
    # the header of OpenGaze's own files: OpenCV 3 reads only "%YAML:1.x" (newer OpenCV writes "%YAML 1.2", "---")
    return "\n".join(["%YAML:1.0", *(line for line in lines[1:] if line != "---")])


def _few_shot_gaze(R: np.ndarray, t_mm: np.ndarray, block: Mapping[str, Any],
                   camera: Mapping[str, Any] | None) -> bytes:
    calib: dict[str, Any] = {
        "written_by": MARKER,  # first: a later export finds it in the file's first bytes
        "monitor_R": R, "monitor_T": t_mm,
        "w_mm": float(block["width_mm"]), "h_mm": float(block["height_mm"]),
        "w_pixels": int(block["width_px"]), "h_pixels": int(block["height_px"]),
    }
    if camera is not None:
        calib["mtx"] = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
        dist = np.zeros(5)
        given = np.asarray(camera.get("dist") or [], dtype=float)[:5]
        dist[:len(given)] = given
        calib["dist"] = dist.reshape(1, 5)
    buffer = io.BytesIO()
    _PortablePickler(buffer, protocol=2).dump(calib)
    return buffer.getvalue()


class _PortablePickler(pickle.Pickler):
    """Arrays pickled as ``numpy.array(nested list)``: any NumPy reads them (an ndarray's own pickle names
    ``numpy._core`` under NumPy 2, which NumPy 1 may not have); float64 values come back exact."""

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            return np.array, (obj.tolist(),)
        return NotImplemented
