"""Camera calibration files: OpenCV FileStorage (YAML/XML), ROS ``camera_info`` YAML, Kalibr camchains.

A capture@1 ``camera`` may be a path to one of these (docs/formats.md). :func:`camera_from_file` reads
it within bounds (at most :data:`MAX_CAMERA_FILE_BYTES`; FileStorage nodes read one by one, never
through ``mat()``, whose ``rows``/``cols`` could allocate gigabytes; the native parser's own lines kept
off stderr) and returns the camera object of :func:`mirror_fg.core.camera.check_camera`, pixels in
OpenCV's convention. Understood: ``camera_matrix``/``cameraMatrix``/``K``/``intrinsic_matrix``,
``distortion_coefficients``/``dist_coeffs``/``distCoeffs``/``D``/``distortion``, ``image_width``/
``image_height`` (or ``image_size``), and ``distortion_model`` where given (ROS: ``plumb_bob`` or
``rational_polynomial``, OpenCV's pinhole model; ``equidistant`` or ``fisheye``, OpenCV's fisheye model
with 4 coefficients); Kalibr ``cam0``... with ``camera_model: pinhole`` and ``distortion_model``
``radtan``, ``none`` or ``equidistant`` (the fisheye model, ``k1..k4``).
"""
from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.camera import check_camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.fileio import MAX_IMAGE_PIXELS, native_stderr, parse_structured
from mirror_fg.core.values import check_keys, clip, finite, is_int, short, type_name

__all__ = ["camera_from_file", "MAX_CAMERA_FILE_BYTES"]

#: Which camera of a camchain was used, at INFO (the CLI prints it); a child of the ``mirror_fg`` logger.
_log = logging.getLogger(__name__)
#: Largest camera calibration file read (bytes); real ones are a few hundred bytes.
MAX_CAMERA_FILE_BYTES = 1 << 20
#: Deepest nesting read from an OpenCV FileStorage file (a camera file needs 2 levels).
_MAX_FILESTORAGE_DEPTH = 8


def camera_from_file(path: str, name: str | None, where: str) -> dict[str, Any]:
    """Intrinsics from an OpenCV FileStorage file, a ROS camera_info YAML or a Kalibr camchain.

    Every format is first turned into plain data (mappings, lists, numbers, strings) and then read by
    one reader, :func:`_camera_from_mapping`, whose numbers all pass :func:`_real_array`; the camera
    object it makes passes :func:`~mirror_fg.core.camera.check_camera` (the image size may be missing:
    ``width`` and ``height`` are then None). ``name``: the camera of a Kalibr camchain (``cam0``...).
    DatasetError (one line starting ``where``) on any problem.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(MAX_CAMERA_FILE_BYTES + 1)
    except OSError as exc:
        raise DatasetError(f"{where}: cannot read file: {exc.strerror or exc}") from None
    if len(head) > MAX_CAMERA_FILE_BYTES:
        raise DatasetError(f"{where}: larger than {MAX_CAMERA_FILE_BYTES} bytes: not a camera calibration file")
    text = head[:4096].decode("utf-8", "replace")
    if text.lstrip().startswith(("%YAML:1", "<?xml")) or "opencv-matrix" in text:
        data = _filestorage_data(path, where)  # OpenCV parses FileStorage from the path itself
    else:
        try:
            data = parse_structured(head.decode("utf-8-sig"), path, where)
        except UnicodeDecodeError as exc:
            raise DatasetError(f"{where}: not UTF-8 text (byte {exc.start})") from None
    if not isinstance(data, Mapping):
        raise DatasetError(f"{where}: expected a mapping, got {type_name(data)}")
    return _camera_from_mapping(data, name, where)


def _camera_from_mapping(data: Mapping[Any, Any], name: str | None, where: str) -> dict[str, Any]:
    cams = sorted(k for k in data if isinstance(k, str) and k.startswith("cam") and isinstance(data[k], Mapping))
    if name is not None or (cams and "camera_model" in data[cams[0]]):
        if name is None and len(cams) > 1:  # a rig: cam0 is no better a guess than the others
            raise DatasetError(f"{where}: the camchain holds {len(cams)} cameras ({clip(', '.join(cams))}); say which "
                               f"one took the photographs: camera: {{file: ..., name: {cams[1]}}}")
        key = name if name is not None else cams[0]
        if key not in data or not isinstance(data[key], Mapping):
            raise DatasetError(f"{where}: no camera {short(key)} (has {short(', '.join(cams) or 'none')})")
        _log.info("%s: using camera %s of the camchain", where, clip(key))
        return _camera_from_kalibr(data[key], f"{where}: {short(key)}")
    if "intrinsics" in data and "camera_model" in data:
        return _camera_from_kalibr(data, where)
    K = _first(data, ("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix"))
    if K is None:
        raise DatasetError(
            f"{where}: not a camera file I know (no camera_matrix / K, no Kalibr cam0 with intrinsics)"
        )
    D = _first(data, ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion"))
    model = _distortion_model(data.get("distortion_model"), where)
    K = _matrix(K, f"{where}: camera_matrix")
    default = [0.0] * (4 if model == "fisheye" else 5)
    dist = default if D is None else _matrix(D, f"{where}: distortion_coefficients").ravel().tolist()
    width = _first(data, ("image_width", "imageWidth", "width"))
    height = _first(data, ("image_height", "imageHeight", "height"))
    size = _first(data, ("image_size", "imageSize"))
    if size is not None and width is None and height is None:
        if isinstance(size, Mapping):  # a FileStorage matrix {rows, cols, data}
            size = size.get("data")
        if not isinstance(size, list) or len(size) != 2:
            raise DatasetError(f"{where}: image_size must be [width, height], got {short(size)}")
        width, height = size
    return _camera_from_K(K, dist, width, height, where, model)


#: ``distortion_model`` names of ROS camera_info and OpenCV files -> our camera model.
_DISTORTION_MODELS = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole", "radtan": "pinhole",
                      "equidistant": "fisheye", "fisheye": "fisheye"}


def _distortion_model(name: Any, where: str) -> str:
    """The camera model of a ROS/OpenCV ``distortion_model`` (pinhole when absent)."""
    if name is None:
        return "pinhole"
    model = _DISTORTION_MODELS.get(name) if isinstance(name, str) else None
    if model is None:
        raise DatasetError(
            f"{where}: distortion_model {short(name)} is not supported "
            "(plumb_bob, rational_polynomial: OpenCV's pinhole model; equidistant: its fisheye model)"
        )
    return model


def _filestorage_data(path: str, where: str) -> dict[str, Any]:
    """An OpenCV FileStorage file (YAML/XML) as plain data; a matrix becomes ``{rows, cols, dt, data}``."""
    import cv2

    with native_stderr():
        try:
            fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as exc:  # SystemError wraps the cv2.error of a failed constructor
            raise DatasetError(f"{where}: not a valid OpenCV calibration file: {_cv_error(exc)}") from None
    try:
        root = fs.root() if fs.isOpened() else None
        if root is None or not root.isMap():
            raise DatasetError(f"{where}: cannot open as an OpenCV calibration file (no top-level mapping)")
        return {k: _filenode_value(root.getNode(k), f"{where}: {short(k)}", 1) for k in root.keys()}
    finally:
        fs.release()


def _filenode_value(node: Any, where: str, depth: int) -> Any:
    """A cv2.FileNode as plain data, without ``mat()`` (which trusts ``rows``/``cols`` and may allocate GBs)."""
    if depth > _MAX_FILESTORAGE_DEPTH:
        raise DatasetError(f"{where}: nested more than {_MAX_FILESTORAGE_DEPTH} levels deep")
    if node.isMap():
        return {k: _filenode_value(node.getNode(k), where, depth + 1) for k in node.keys()}
    if node.isSeq():
        return [_filenode_value(node.at(i), where, depth + 1) for i in range(node.size())]
    if node.isInt():
        value = node.real()
        if abs(value) >= 2.0**63 - 1:  # the parser clamps what overflows int64 (a 400-digit integer)
            raise DatasetError(f"{where}: integer out of range")
        return int(value)
    if node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    return None


def _cv_error(exc: BaseException) -> str:
    """The useful tail of an OpenCV exception's text (``line 6: Missing , between the elements``), short."""
    text = str(exc.__cause__ or exc).strip()
    text = text.splitlines()[-1] if text else type(exc).__name__
    m = re.search(r"\((\d+)\): (.*?)'?$", text)
    if m:
        text = f"line {m.group(1)}: {m.group(2)}"
    else:
        text = re.sub(r"^.*error: \([-\d]+:[^)]*\) ", "", text)
    return clip(text)


def _camera_from_kalibr(cam: Mapping[str, Any], where: str) -> dict[str, Any]:
    camera_model = cam.get("camera_model", "pinhole")
    if camera_model != "pinhole":
        raise DatasetError(
            f"{where}: camera_model {short(camera_model)} is not supported "
            "(pinhole, with radtan, none or equidistant distortion)"
        )
    intr = _real_array(cam.get("intrinsics"), f"{where}: intrinsics [fu, fv, pu, pv]")
    if intr.shape != (4,):
        raise DatasetError(f"{where}: intrinsics must be [fu, fv, pu, pv], got {short(cam.get('intrinsics'))}")
    dmodel = cam.get("distortion_model", "none")
    model = "pinhole"
    if dmodel in ("radtan", "plumb_bob"):
        coeffs = _real_array(cam.get("distortion_coeffs"), f"{where}: distortion_coeffs")
        if coeffs.shape not in ((4,), (5,)):
            raise DatasetError(
                f"{where}: radtan distortion_coeffs must be [k1, k2, r1, r2], got {short(cam.get('distortion_coeffs'))}"
            )
        dist = coeffs.tolist()
    elif dmodel == "equidistant":  # Kalibr's pinhole-equi: OpenCV's fisheye model, the same k1..k4
        coeffs = _real_array(cam.get("distortion_coeffs"), f"{where}: distortion_coeffs")
        if coeffs.shape != (4,):
            raise DatasetError(
                f"{where}: equidistant distortion_coeffs must be [k1, k2, k3, k4], "
                f"got {short(cam.get('distortion_coeffs'))}"
            )
        dist, model = coeffs.tolist(), "fisheye"
    elif dmodel in ("none", None):
        dist = [0.0] * 5
    else:
        raise DatasetError(
            f"{where}: distortion_model {short(dmodel)} is not supported "
            "(radtan, none: OpenCV's pinhole model; equidistant: its fisheye model)"
        )
    res = cam.get("resolution")
    width = height = None
    if res is not None:
        if not isinstance(res, list) or len(res) != 2:
            raise DatasetError(f"{where}: resolution must be [width, height], got {short(res)}")
        width, height = res
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]], dtype=float)
    return _camera_from_K(K, dist, width, height, where, model)


def _camera_from_K(
    K: np.ndarray, dist: list[float], width: Any, height: Any, where: str, model: str = "pinhole"
) -> dict[str, Any]:
    if K.size == 9 and K.ndim == 1:
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise DatasetError(f"{where}: camera matrix must be 3x3, got shape {K.shape}")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 0:
        raise DatasetError(f"{where}: camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    c = {"model": model, "width": width, "height": height,
         "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "dist": list(dist)}
    return check_camera(c, where, need_size=False, max_pixels=MAX_IMAGE_PIXELS)


def _first(data: Mapping[str, Any], names: tuple[str, ...]) -> Any:
    for n in names:
        if n in data:
            return data[n]
    return None


def _matrix(value: Any, where: str) -> np.ndarray:
    """A matrix given as (nested) lists or a ROS/OpenCV ``{rows, cols, data}`` mapping; numbers checked."""
    if not isinstance(value, Mapping):
        return _real_array(value, where)
    check_keys(value, ("rows", "cols", "data", "dt"), where)
    data = _real_array(value.get("data"), f"{where}: data")
    rows, cols = value.get("rows"), value.get("cols")
    if rows is None and cols is None:
        return data
    if not (is_int(rows) and is_int(cols) and rows >= 1 and cols >= 1):
        raise DatasetError(f"{where}: rows and cols must be positive integers, got {short(rows)} and {short(cols)}")
    if data.ndim != 1 or data.size != rows * cols:
        raise DatasetError(f"{where}: data has {data.size} numbers, rows x cols is {short(rows)} x {short(cols)}")
    return data.reshape(rows, cols)


def _real_array(value: Any, where: str) -> np.ndarray:
    """Finite real numbers from a list, or a list of equal-length lists (a matrix). Anything else (bools,
    strings, null, deeper nesting, numbers too large for a float, NaN, inf) is a DatasetError naming the entry."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or not value:
        raise DatasetError(f"{where}: expected a list of numbers, got {short(value)}")
    shape: tuple[int, ...]
    if all(isinstance(r, (list, tuple)) for r in value):
        widths = {len(r) for r in value}
        if len(widths) != 1:
            raise DatasetError(f"{where}: rows of different lengths: {short(value)}")
        flat, shape = [x for r in value for x in r], (len(value), widths.pop())
    else:
        flat, shape = list(value), (len(value),)
    numbers = [finite(x) for x in flat]
    if None in numbers:
        k = numbers.index(None)
        raise DatasetError(f"{where}: entry {k} is not a finite number: {short(flat[k])}")
    return np.array(numbers, dtype=float).reshape(shape)
