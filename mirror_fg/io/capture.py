"""Capture files (``mirror-fg/capture@1``): what a user writes to go from photographs or a video to a dataset.

A capture file is YAML or JSON. Paths in it are relative to the capture file. Top-level keys:

``format``
    ``mirror-fg/capture@1``.
``num_mirrors``
    Integer >= 1: how many mirrors the light meets between the target and the camera.
``camera``
    Either the dataset@1 camera object (``model: pinhole``, ``width``, ``height``, ``fx``, ``fy``, ``cx``,
    ``cy`` in pixels, OpenCV ``dist`` ``(k1, k2, p1, p2[, k3, ...])``) or a path to a calibration file,
    or ``{file: PATH, name: cam1}``. Files understood: OpenCV ``FileStorage`` YAML/XML
    (``camera_matrix``/``cameraMatrix``/``K``, ``distortion_coefficients``/``dist_coeffs``/``D``,
    ``image_width``/``image_height``), ROS ``camera_info`` YAML, and Kalibr camchains (``cam0``...;
    ``camera_model: pinhole`` with ``distortion_model`` ``radtan`` or ``none``). Where a file gives no
    image size, the size of the first image read is used.
``pixel_sigma``
    Optional measurement standard deviation in pixels (0.5 when absent).
``target``
    What is detected, one of:

    * ``kind: chessboard`` with ``cols``, ``rows`` (inner corners) and ``square`` (metres). Inner corner
      (col, row) is fiducial ``C{row*cols+col:02d}`` at ``(col*square, row*square, 0)`` in the board
      frame. ``cols + rows`` must be odd (one count odd, the other even): only then do the square
      colours tell the board's two half-turn orientations apart. Corner C00: look at the printed face
      with the rows (``cols + 1`` squares each) horizontal and turn the board so that its top-left
      corner square is black; C00 is the inner corner of that square, C01, C02, ... run to the right
      along the top row, row 1 is the next row down. The board frame has x to the right, y down and z
      into the board. The detector enforces this order in every image (handedness from the number of
      mirrors, the half turn from the colour of the squares) or refuses the image with the reason.
    * ``kind: apriltag`` (or ``aruco``) with ``dictionary`` (``tag36h11``, ``tag25h9``, ``tag16h5``,
      ``tag36h10`` or an OpenCV ArUco name such as ``DICT_4X4_50``), ``tag_size`` (metres, edge of the
      black square) and either ``tags: {id: {R, t}}``, each tag's frame in the base frame
      (``Bp = R @ p_tag + t``), or ``grid: {cols, rows, spacing, first_id}``: tag ``first_id +
      row*cols + col`` at ``(col*spacing, -row*spacing, 0)`` in the target frame, whose axes are those
      of every tag (``spacing`` is centre to centre, metres; tag ``first_id`` is top left). The tag
      frame is OpenCV's ArUco marker frame (origin at the centre of the black square, x right and y up
      on the printed face, z out of it). Fiducial ``T{id}_{k}`` is corner k in cv2.aruco's order, at
      ``(-s/2, s/2, 0)``, ``(s/2, s/2, 0)``, ``(s/2, -s/2, 0)``, ``(-s/2, -s/2, 0)`` in the tag frame.
      Tags not listed are ignored. Optional ``corner_refinement``: ``subpix`` (default: markers found
      by ``cv2.aruco``, corners refined by ``cv2.cornerSubPix``), ``contour``, ``apriltag`` or ``none``
      (OpenCV's own ``CORNER_REFINE_*``); optional ``image_gamma``: ``srgb`` (default; images encoded
      like a camera's JPEG/PNG, linearized before ``subpix`` refinement, which otherwise pulls corners
      about 0.5 px into the black square) or ``linear``.
    * ``kind: points`` with ``fiducials: {name: [x, y, z]}`` (metres, target frame); each image then
      gives its pixels under ``observations`` instead of detection.
``T_base_target``
    Optional ``{R: 3x3, t: [3]}`` (or ``{q_xyzw: [4], t: [3]}``): the target frame in the base frame,
    ``Bp = R @ p_target + t``, for chessboard, tag grid and points targets; identity when absent. Tag
    poses under ``tags`` are already in the base frame and do not take it.
``images``
    A list of ``{file, mirror_configs, observations?, id?}``. ``mirror_configs[l-1]`` is the placement
    of mirror l: a non-negative integer, or ``each`` (a placement of its own, given a fresh integer in
    the dataset). ``observations`` (optional; required with a points target, where ``file`` may then be
    left out) gives measured pixels ``{name: [u, v]}`` inline or as a file: JSON/YAML of that shape, or
    text with one ``name u v`` or ``u v`` per line (the latter in the order of the target's fiducials,
    like a hand-measured ``inputN.txt``). Names that are not fiducials are reconstruction points. The
    image id in the dataset is ``id`` if given, else the stem of ``file`` (else of the observations
    file).
``video``
    Instead of ``images``: ``{file, segments: [{frames: [first, last], mirror_configs, step?}]}`` with
    inclusive frame ranges (0-based) that do not overlap. Every frame of a segment is tracked (KLT,
    forward-backward checked) and re-detected; every ``step``-th frame (1 when absent) becomes an image
    ``stem:frame``. ``each`` means a new placement of that mirror in every such frame.
``track``
    Optional: ``{name: {frame, pixel: [u, v], feature?, sigma?}}`` unknown points that the tracker
    (:mod:`mirror_fg.vision.tracking`: KLT, then refinement onto the feature) follows from the given starting
    pixel of that frame to the end of its run of frames. With a video ``frame`` is a video frame; with
    ``images`` (a photo sequence, in list order) it is the image's 0-based position in the list.
    ``feature``: ``corner`` (default), ``blob`` / ``dot`` or ``template`` (what the refinement fits);
    ``sigma``: the track's pixel sigma (pixels), overriding the tracker's own estimate.

Everything is checked on loading; :func:`load_capture` raises :class:`~mirror_fg.io.dataset.DatasetError`
with one line naming the file, the entry and the problem.
"""
from __future__ import annotations

import math
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import _is_int, _is_number, _short, check_format, check_keys  # shared value checks and messages

__all__ = [
    "CAPTURE_FORMAT",
    "EACH",
    "Capture",
    "ChessboardTarget",
    "TagTarget",
    "PointsTarget",
    "ImageEntry",
    "VideoSegment",
    "VideoSpec",
    "TrackStart",
    "load_capture",
    "capture_from_dict",
    "tag_dictionary",
    "native_stderr",
    "open_video",
    "MAX_IMAGE_PIXELS",
]

CAPTURE_FORMAT = "mirror-fg/capture@1"
#: ``mirror_configs`` entry meaning "a placement of its own in this image / frame".
EACH = "each"
DEFAULT_PIXEL_SIGMA = 0.5
#: Feature kinds a ``track:`` entry may name (mirror_fg.vision.tracking refines onto them; ``klt``, no
#: refinement, is for the API only).
TRACK_FEATURES = ("corner", "blob", "dot", "template")
#: Largest ``|R^T R - I|`` entry accepted for a rotation matrix typed into a capture file.
ROTATION_TOL = 1e-4
#: Largest image or video frame read (width x height, pixels): 8000 x 6000 photographs pass; a larger
#: image is refused from its header before it is decoded (a 20000 x 20000 PNG of 2 MB decodes to GBs).
MAX_IMAGE_PIXELS = 100_000_000
#: Largest camera calibration file read (bytes); real ones are a few hundred bytes.
MAX_CAMERA_FILE_BYTES = 1 << 20
#: Deepest nesting read from an OpenCV FileStorage file (a camera file needs 2 levels).
_MAX_FILESTORAGE_DEPTH = 8
#: User-given names (files, keys) are quoted in messages up to this many characters.
_NAME_LIMIT = 80

#: Short AprilTag family names -> OpenCV dictionary attribute.
_APRILTAG_NAMES = {
    "tag16h5": "DICT_APRILTAG_16h5",
    "tag25h9": "DICT_APRILTAG_25h9",
    "tag36h10": "DICT_APRILTAG_36h10",
    "tag36h11": "DICT_APRILTAG_36h11",
}
_CORNER_REFINEMENTS = ("subpix", "contour", "apriltag", "none")
_IMAGE_GAMMAS = ("srgb", "linear")


# --------------------------------------------------------------------------------------------------
# Value objects
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChessboardTarget:
    """Chessboard of ``cols`` x ``rows`` inner corners, ``square`` metres; fiducial ``C{row*cols+col:02d}``."""

    cols: int
    rows: int
    square: float
    kind: str = "chessboard"

    def name(self, col: int, row: int) -> str:
        """Fiducial name of inner corner (col, row)."""
        return f"C{row * self.cols + col:02d}"

    def target_points(self) -> dict[str, np.ndarray]:
        """Corner positions in the board frame (metres), row-major."""
        return {
            self.name(c, r): np.array([c * self.square, r * self.square, 0.0])
            for r in range(self.rows)
            for c in range(self.cols)
        }


@dataclass(frozen=True)
class TagTarget:
    """AprilTag/ArUco markers: ``tags`` maps an id to its frame ``(R, t)`` in the frame named by ``frame``.

    ``frame`` is ``"base"`` for tags listed under ``tags`` and ``"target"`` for a grid (then
    ``T_base_target`` applies). ``dictionary_id`` is the ``cv2.aruco.DICT_*`` constant.
    """

    dictionary: str
    dictionary_id: int
    tag_size: float
    tags: dict[int, tuple[np.ndarray, np.ndarray]]
    frame: str = "base"
    corner_refinement: str = "subpix"
    image_gamma: str = "srgb"
    kind: str = "apriltag"

    @staticmethod
    def corner_name(tag_id: int, k: int) -> str:
        """Fiducial name of corner k (cv2.aruco order) of tag ``tag_id``."""
        return f"T{tag_id}_{k}"

    def corners_in_tag(self) -> np.ndarray:
        """(4, 3) corners in the tag frame, cv2.aruco order (metres)."""
        h = self.tag_size / 2.0
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    def target_points(self) -> dict[str, np.ndarray]:
        """Every listed tag's corners in the frame of ``tags`` (metres)."""
        corners = self.corners_in_tag()
        out: dict[str, np.ndarray] = {}
        for tag_id in sorted(self.tags):
            R, t = self.tags[tag_id]
            for k in range(4):
                out[self.corner_name(tag_id, k)] = R @ corners[k] + t
        return out


@dataclass(frozen=True)
class PointsTarget:
    """Points measured on the robot (target frame, metres); pixels come with each image."""

    fiducials: dict[str, np.ndarray]
    kind: str = "points"

    def target_points(self) -> dict[str, np.ndarray]:
        return {name: p.copy() for name, p in self.fiducials.items()}


Target = ChessboardTarget | TagTarget | PointsTarget
Config = int | str  # an integer placement or EACH


@dataclass
class ImageEntry:
    """One listed image. ``file`` is absolute (None for a points capture without image files)."""

    id: str
    file: str | None
    mirror_configs: tuple[Config, ...]
    observations: dict[str, np.ndarray] = field(default_factory=dict)
    where: str = "images[0]"
    #: ``where`` without the capture file: ``images[3] (img3.png)``, for per-image reasons.
    label: str = "images[0]"
    #: Absolute path of the observations file, when the pixels come from one.
    observations_file: str | None = None


@dataclass
class VideoSegment:
    """Frames ``first..last`` (inclusive, 0-based); every ``step``-th one becomes an image."""

    first: int
    last: int
    mirror_configs: tuple[Config, ...]
    step: int = 1
    where: str = "video.segments[0]"

    def output_frames(self) -> range:
        return range(self.first, self.last + 1, self.step)


@dataclass
class VideoSpec:
    file: str
    segments: list[VideoSegment]
    frame_count: int

    @property
    def stem(self) -> str:
        return Path(self.file).stem


@dataclass
class TrackStart:
    """An unknown point to track: its pixel (OpenCV convention) in video frame ``frame`` (with
    ``images``: the image at that position), the ``feature`` kind the refinement fits, and an optional
    pixel ``sigma`` given by the user (None: the tracker's)."""

    name: str
    frame: int
    pixel: np.ndarray
    feature: str = "corner"
    sigma: float | None = None


@dataclass
class Capture:
    """A validated ``mirror-fg/capture@1``.

    ``camera`` is the dataset@1 camera dictionary (``width``/``height`` None when a calibration file
    did not give them: the first image read fills them in). ``R_base_target``, ``t_base_target``:
    ``Bp = R @ p_target + t``. Exactly one of ``images`` and ``video`` is set. ``file`` is the capture
    file's absolute path (None when built from a dictionary), ``camera_file`` that of the calibration
    file the camera came from (None for inline intrinsics).
    """

    source: str
    num_mirrors: int
    camera: dict[str, Any]
    pixel_sigma: float
    target: Target
    R_base_target: np.ndarray
    t_base_target: np.ndarray
    images: list[ImageEntry] | None = None
    video: VideoSpec | None = None
    track: dict[str, TrackStart] = field(default_factory=dict)
    file: str | None = None
    camera_file: str | None = None

    def input_files(self) -> list[str]:
        """Absolute paths of every file this capture reads, once each: the capture file, the camera file,
        then per image its image and observations files, or the video. Symbolic links are not resolved."""
        paths = [self.file, self.camera_file]
        for e in self.images or []:
            paths += [e.file, e.observations_file]
        if self.video is not None:
            paths.append(self.video.file)
        return list(dict.fromkeys(os.path.abspath(p) for p in paths if p is not None))

    @property
    def mirrored(self) -> bool:
        """True when the target is seen through an odd number of mirrors (the image is mirror-imaged)."""
        return self.num_mirrors % 2 == 1

    def fiducials(self) -> dict[str, np.ndarray]:
        """Fiducials in the BASE frame (metres): ``T_base_target`` applied where it applies."""
        points = self.target.target_points()
        if isinstance(self.target, TagTarget) and self.target.frame == "base":
            return points
        return {name: self.R_base_target @ p + self.t_base_target for name, p in points.items()}


# --------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------


def load_capture(path: str | os.PathLike[str]) -> Capture:
    """Read and validate a capture@1 file (YAML or JSON). Raises DatasetError (one line) on any problem.

    Image, observation and video files must exist; the video must open and hold the listed frames.
    """
    source = os.fspath(path)
    data = _load_structured(source, source)
    cap = capture_from_dict(data, source=source, base_dir=os.path.dirname(os.path.abspath(source)))
    cap.file = os.path.abspath(source)
    return cap


def capture_from_dict(d: Any, source: str = "<capture>", base_dir: str = ".") -> Capture:
    """Validate a capture@1 dictionary; relative paths are taken from ``base_dir``."""
    check_format(d, CAPTURE_FORMAT, source)
    check_keys(d, ("format", "num_mirrors", "camera", "pixel_sigma", "target", "T_base_target", "images", "video",
                   "track"), source)

    num_mirrors = d.get("num_mirrors")
    if not _is_int(num_mirrors) or num_mirrors < 1:
        raise DatasetError(f"{source}: num_mirrors must be an integer >= 1, got {_short(num_mirrors)}")

    if "camera" not in d:
        raise DatasetError(f"{source}: missing 'camera' (intrinsics, or a path to a calibration file)")
    camera, camera_file = _camera(d["camera"], source, base_dir)

    pixel_sigma = d.get("pixel_sigma", DEFAULT_PIXEL_SIGMA)
    if _finite(pixel_sigma) is None or pixel_sigma <= 0:
        raise DatasetError(f"{source}: pixel_sigma must be a finite number > 0 (pixels), got {_short(pixel_sigma)}")

    if "target" not in d:
        raise DatasetError(f"{source}: missing 'target' (chessboard, apriltag or points)")
    target = _target(d["target"], source)

    if d.get("T_base_target") is not None:
        if isinstance(target, TagTarget) and target.frame == "base":
            raise DatasetError(
                f"{source}: T_base_target: tag poses under target.tags are already in the base frame; "
                "give T_base_target with a chessboard, a tag grid or points"
            )
        R, t = _pose(d["T_base_target"], f"{source}: T_base_target")
    else:
        R, t = np.eye(3), np.zeros(3)

    cap = Capture(
        source=source,
        num_mirrors=int(num_mirrors),
        camera=camera,
        pixel_sigma=float(pixel_sigma),
        target=target,
        R_base_target=R,
        t_base_target=t,
        camera_file=camera_file,
    )

    has_images, has_video = d.get("images") is not None, d.get("video") is not None
    if has_images == has_video:
        raise DatasetError(f"{source}: give exactly one of 'images' and 'video'")
    if has_images:
        cap.images = _images(d["images"], cap, base_dir)
    else:
        if isinstance(target, PointsTarget):
            raise DatasetError(f"{source}: video: a points target needs 'images' with per-image observations")
        cap.video = _video(d["video"], cap, base_dir)
    if d.get("track") is not None:
        if cap.images is not None and any(e.file is None for e in cap.images):
            raise DatasetError(
                f"{source}: track: tracking needs image files; without them give the pixels under each image's 'observations'"
            )
        cap.track = _track(d["track"], cap)
    return cap


# --- camera ---------------------------------------------------------------------------------------


def _camera(value: Any, source: str, base_dir: str) -> tuple[dict[str, Any], str | None]:
    """The camera dictionary and the calibration file it was read from (None for inline intrinsics)."""
    where = f"{source}: camera"
    if isinstance(value, str) or (isinstance(value, Mapping) and "file" in value):
        name = None
        if isinstance(value, Mapping):
            extra = sorted(str(k) for k in value if k not in ("file", "name"))
            if extra:
                raise DatasetError(f"{where}: unknown key {_short(extra[0])} next to 'file' (expected 'name')")
            name = value.get("name")
            if name is not None and not isinstance(name, str):
                raise DatasetError(f"{where}: name must be a camera name such as 'cam0', got {_short(name)}")
            value = value["file"]
            if not isinstance(value, str) or not value:
                raise DatasetError(f"{where}: file must be a path, got {_short(value)}")
        path = _resolve(value, base_dir)
        if not os.path.isfile(path):
            raise DatasetError(f"{where}: calibration file {_name(value)!r} not found")
        return _camera_from_file(path, name, f"{where} ({_name(value)})"), path
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected intrinsics or a path to a calibration file, got {_kind(value)}")
    return _camera_dict(value, where, need_size=True), None


def _camera_dict(c: Mapping[str, Any], where: str, need_size: bool) -> dict[str, Any]:
    model = c.get("model", "pinhole")
    if model != "pinhole":
        raise DatasetError(f"{where}: unsupported model {_short(model)} (only 'pinhole')")
    keys = ("width", "height", "fx", "fy", "cx", "cy") if need_size else ("fx", "fy", "cx", "cy")
    missing = [k for k in keys if k not in c]
    if missing:
        raise DatasetError(f"{where}: missing {', '.join(repr(k) for k in missing)}")
    out: dict[str, Any] = {"model": "pinhole"}
    if (c.get("width") is None) != (c.get("height") is None):
        raise DatasetError(f"{where}: gives only one of the image width and height")
    for key in ("width", "height"):
        v = c.get(key)
        if v is None and not need_size:
            out[key] = None
            continue
        if not _is_int(v) or v < 1:
            raise DatasetError(f"{where}: {key} must be a positive integer (pixels), got {_short(v)}")
        out[key] = int(v)
    if out["width"] is not None and out["width"] * out["height"] > MAX_IMAGE_PIXELS:
        raise DatasetError(
            f"{where}: image size {_short(out['width'])} x {_short(out['height'])} is above the limit of "
            f"{MAX_IMAGE_PIXELS} pixels"
        )
    for key in ("fx", "fy", "cx", "cy"):
        v = _finite(c[key])
        if v is None or (key in ("fx", "fy") and v <= 0):
            cond = "> 0" if key in ("fx", "fy") else "finite"
            raise DatasetError(f"{where}: {key} must be a {cond} number (pixels), got {_short(c[key])}")
        out[key] = v
    dist = c.get("dist", [0.0] * 5)
    if isinstance(dist, np.ndarray):
        dist = dist.ravel().tolist()
    values = [_finite(x) for x in dist] if isinstance(dist, (list, tuple)) else [None]
    if len(values) not in (4, 5, 8, 12, 14) or None in values:
        raise DatasetError(
            f"{where}: dist must be 4, 5, 8, 12 or 14 finite numbers (OpenCV k1, k2, p1, p2[, k3, ...]), got {_short(dist)}"
        )
    out["dist"] = values
    return out


def _camera_from_file(path: str, name: str | None, where: str) -> dict[str, Any]:
    """Intrinsics from an OpenCV FileStorage file, a ROS camera_info YAML or a Kalibr camchain.

    Every format is first turned into plain data (mappings, lists, numbers, strings) and then read by
    one reader, :func:`_camera_from_mapping`, whose numbers all pass :func:`_real_array`.
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
        data = _filestorage_data(path, where)
    else:
        data = _load_structured(path, where)
    if not isinstance(data, Mapping):
        raise DatasetError(f"{where}: expected a mapping, got {_kind(data)}")
    return _camera_from_mapping(data, name, where)


def _camera_from_mapping(data: Mapping[Any, Any], name: str | None, where: str) -> dict[str, Any]:
    cams = sorted(k for k in data if isinstance(k, str) and k.startswith("cam") and isinstance(data[k], Mapping))
    if name is not None or (cams and "camera_model" in data[cams[0]]):
        key = name if name is not None else cams[0]
        if key not in data or not isinstance(data[key], Mapping):
            raise DatasetError(f"{where}: no camera {_short(key)} (has {_short(', '.join(cams) or 'none')})")
        return _camera_from_kalibr(data[key], f"{where}: {_short(key)}")
    if "intrinsics" in data and "camera_model" in data:
        return _camera_from_kalibr(data, where)
    K = _first(data, ("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix"))
    if K is None:
        raise DatasetError(
            f"{where}: not a camera file I know (no camera_matrix / K, no Kalibr cam0 with intrinsics)"
        )
    D = _first(data, ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion"))
    K = _matrix(K, f"{where}: camera_matrix")
    dist = [0.0] * 5 if D is None else _matrix(D, f"{where}: distortion_coefficients").ravel().tolist()
    width = _first(data, ("image_width", "imageWidth", "width"))
    height = _first(data, ("image_height", "imageHeight", "height"))
    size = _first(data, ("image_size", "imageSize"))
    if size is not None and width is None and height is None:
        if isinstance(size, Mapping):  # a FileStorage matrix {rows, cols, data}
            size = size.get("data")
        if not isinstance(size, list) or len(size) != 2:
            raise DatasetError(f"{where}: image_size must be [width, height], got {_short(size)}")
        width, height = size
    return _camera_from_K(K, dist, width, height, where)


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
        return {k: _filenode_value(root.getNode(k), f"{where}: {_short(k)}", 1) for k in root.keys()}
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
    return _clip(text)


def _camera_from_kalibr(cam: Mapping[str, Any], where: str) -> dict[str, Any]:
    model = cam.get("camera_model", "pinhole")
    if model != "pinhole":
        raise DatasetError(f"{where}: camera_model {_short(model)} is not supported (only pinhole)")
    intr = _real_array(cam.get("intrinsics"), f"{where}: intrinsics [fu, fv, pu, pv]")
    if intr.shape != (4,):
        raise DatasetError(f"{where}: intrinsics must be [fu, fv, pu, pv], got {_short(cam.get('intrinsics'))}")
    dmodel = cam.get("distortion_model", "none")
    if dmodel in ("radtan", "plumb_bob"):
        coeffs = _real_array(cam.get("distortion_coeffs"), f"{where}: distortion_coeffs")
        if coeffs.shape not in ((4,), (5,)):
            raise DatasetError(
                f"{where}: radtan distortion_coeffs must be [k1, k2, r1, r2], got {_short(cam.get('distortion_coeffs'))}"
            )
        dist = coeffs.tolist()
    elif dmodel in ("none", None):
        dist = [0.0] * 5
    else:
        raise DatasetError(
            f"{where}: distortion_model {_short(dmodel)} is not supported (radtan or none; OpenCV's pinhole model)"
        )
    res = cam.get("resolution")
    width = height = None
    if res is not None:
        if not isinstance(res, list) or len(res) != 2:
            raise DatasetError(f"{where}: resolution must be [width, height], got {_short(res)}")
        width, height = res
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]], dtype=float)
    return _camera_from_K(K, dist, width, height, where)


def _camera_from_K(K: np.ndarray, dist: list[float], width: Any, height: Any, where: str) -> dict[str, Any]:
    if K.size == 9 and K.ndim == 1:
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise DatasetError(f"{where}: camera matrix must be 3x3, got shape {K.shape}")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 0:
        raise DatasetError(f"{where}: camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    c = {"model": "pinhole", "width": width, "height": height,
         "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "dist": list(dist)}
    return _camera_dict(c, where, need_size=False)


def _first(data: Mapping[str, Any], names: tuple[str, ...]) -> Any:
    for n in names:
        if n in data:
            return data[n]
    return None


def _matrix(value: Any, where: str) -> np.ndarray:
    """A matrix given as (nested) lists or a ROS/OpenCV ``{rows, cols, data}`` mapping; numbers checked."""
    if not isinstance(value, Mapping):
        return _real_array(value, where)
    _only(value, ("rows", "cols", "data", "dt"), where)
    data = _real_array(value.get("data"), f"{where}: data")
    rows, cols = value.get("rows"), value.get("cols")
    if rows is None and cols is None:
        return data
    if not (_is_int(rows) and _is_int(cols) and rows >= 1 and cols >= 1):
        raise DatasetError(f"{where}: rows and cols must be positive integers, got {_short(rows)} and {_short(cols)}")
    if data.ndim != 1 or data.size != rows * cols:
        raise DatasetError(f"{where}: data has {data.size} numbers, rows x cols is {_short(rows)} x {_short(cols)}")
    return data.reshape(rows, cols)


def _real_array(value: Any, where: str) -> np.ndarray:
    """Finite real numbers from a list, or a list of equal-length lists (a matrix). Anything else (bools,
    strings, null, deeper nesting, numbers too large for a float, NaN, inf) is a DatasetError naming the entry."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or not value:
        raise DatasetError(f"{where}: expected a list of numbers, got {_short(value)}")
    if all(isinstance(r, (list, tuple)) for r in value):
        widths = {len(r) for r in value}
        if len(widths) != 1:
            raise DatasetError(f"{where}: rows of different lengths: {_short(value)}")
        flat, shape = [x for r in value for x in r], (len(value), widths.pop())
    else:
        flat, shape = list(value), (len(value),)
    numbers = [_finite(x) for x in flat]
    if None in numbers:
        k = numbers.index(None)
        raise DatasetError(f"{where}: entry {k} is not a finite number: {_short(flat[k])}")
    return np.array(numbers, dtype=float).reshape(shape)


# --- target ---------------------------------------------------------------------------------------


def tag_dictionary(name: Any, where: str = "dictionary") -> tuple[str, int]:
    """``(canonical name, cv2.aruco.DICT_* value)`` of an AprilTag family or ArUco dictionary name."""
    import cv2

    if not isinstance(name, str) or not name:
        raise DatasetError(f"{where}: must be a name such as 'tag36h11' or 'DICT_4X4_50', got {_short(name)}")
    key = name.strip()
    attr = _APRILTAG_NAMES.get(key.lower())
    if attr is None:
        upper = key.upper()
        candidates = [upper, "DICT_" + upper, "DICT_APRILTAG_" + upper.removeprefix("TAG")]
        attr = next((c for c in candidates if hasattr(cv2.aruco, c)), None)
    if attr is None or not hasattr(cv2.aruco, attr):
        raise DatasetError(
            f"{where}: unknown dictionary {_short(name)} (AprilTag: tag16h5, tag25h9, tag36h10, tag36h11; "
            "ArUco: DICT_4X4_50 ... DICT_7X7_1000, DICT_ARUCO_ORIGINAL)"
        )
    return key, int(getattr(cv2.aruco, attr))


def _target(t: Any, source: str) -> Target:
    where = f"{source}: target"
    if not isinstance(t, Mapping):
        raise DatasetError(f"{where}: expected a mapping with 'kind', got {_kind(t)}")
    kind = t.get("kind")
    if kind == "chessboard":
        _only(t, ("kind", "cols", "rows", "square"), where)
        cols, rows, square = t.get("cols"), t.get("rows"), t.get("square")
        for key, v in (("cols", cols), ("rows", rows)):
            if not _is_int(v) or v < 3:
                raise DatasetError(f"{where}: {key} must be an integer >= 3 (inner corners), got {_short(v)}")
        if _finite(square) is None or square <= 0:
            raise DatasetError(f"{where}: square must be a number > 0 (metres), got {_short(square)}")
        if (cols + rows) % 2 == 0:
            raise DatasetError(
                f"{where}: a {cols} x {rows}-corner board looks the same turned half a turn (cols + rows is even), "
                "so its corner order cannot be told from an image; use a board with one count odd and the other even"
            )
        return ChessboardTarget(int(cols), int(rows), float(square))
    if kind in ("apriltag", "aruco"):
        _only(t, ("kind", "dictionary", "tag_size", "tags", "grid", "corner_refinement", "image_gamma"), where)
        name, dict_id = tag_dictionary(t.get("dictionary"), f"{where}: dictionary")
        import cv2

        num_ids = int(cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0])
        size = t.get("tag_size")
        if _finite(size) is None or size <= 0:
            raise DatasetError(f"{where}: tag_size must be a number > 0 (metres, edge of the black square), got {_short(size)}")
        refine = t.get("corner_refinement", "subpix")
        if refine not in _CORNER_REFINEMENTS:
            raise DatasetError(f"{where}: corner_refinement must be one of {', '.join(_CORNER_REFINEMENTS)}, got {_short(refine)}")
        gamma = t.get("image_gamma", "srgb")
        if gamma not in _IMAGE_GAMMAS:
            raise DatasetError(f"{where}: image_gamma must be one of {', '.join(_IMAGE_GAMMAS)}, got {_short(gamma)}")
        if (t.get("tags") is None) == (t.get("grid") is None):
            raise DatasetError(f"{where}: give exactly one of 'tags' (each tag's pose) and 'grid'")
        if t.get("tags") is not None:
            tags_in = t["tags"]
            if not isinstance(tags_in, Mapping) or not tags_in:
                raise DatasetError(f"{where}: tags must be a non-empty mapping {{id: {{R, t}}}}, got {_short(tags_in)}")
            tags: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            for key, pose in tags_in.items():
                tag_id = _tag_id(key, num_ids, name, f"{where}: tags")
                if tag_id in tags:
                    raise DatasetError(f"{where}: tags: tag {tag_id} is listed twice")
                tags[tag_id] = _pose(pose, f"{where}: tags[{tag_id}]")
            frame = "base"
        else:
            tags = _grid(t["grid"], num_ids, name, f"{where}: grid")
            frame = "target"
        return TagTarget(name, dict_id, float(size), tags, frame=frame, corner_refinement=refine, image_gamma=gamma)
    if kind == "points":
        _only(t, ("kind", "fiducials"), where)
        fids = t.get("fiducials")
        if not isinstance(fids, Mapping) or not fids:
            raise DatasetError(f"{where}: fiducials must be a non-empty mapping {{name: [x, y, z]}} (metres)")
        out = _named_vectors(fids, 3, where, "fiducial")
        if len(out) < 3:
            raise DatasetError(f"{where}: needs at least 3 fiducials, got {len(out)}")
        return PointsTarget(out)
    raise DatasetError(f"{where}: kind must be 'chessboard', 'apriltag' or 'points', got {_short(kind)}")


def _tag_id(key: Any, num_ids: int, dict_name: str, where: str) -> int:
    if isinstance(key, str) and key.strip().isdigit():
        key = int(key)
    if not _is_int(key) or key < 0:
        raise DatasetError(f"{where}: tag id must be a non-negative integer, got {_short(key)}")
    if key >= num_ids:
        raise DatasetError(f"{where}: tag id {key} is not in dictionary {dict_name} (ids 0-{num_ids - 1})")
    return int(key)


def _grid(g: Any, num_ids: int, dict_name: str, where: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    if not isinstance(g, Mapping):
        raise DatasetError(f"{where}: expected {{cols, rows, spacing, first_id}}, got {_kind(g)}")
    _only(g, ("cols", "rows", "spacing", "first_id"), where)
    cols, rows, spacing, first = g.get("cols"), g.get("rows"), g.get("spacing"), g.get("first_id", 0)
    for key, v in (("cols", cols), ("rows", rows)):
        if not _is_int(v) or v < 1:
            raise DatasetError(f"{where}: {key} must be an integer >= 1, got {_short(v)}")
    if _finite(spacing) is None or spacing <= 0:
        raise DatasetError(f"{where}: spacing must be a number > 0 (metres, centre to centre), got {_short(spacing)}")
    if not _is_int(first) or first < 0:
        raise DatasetError(f"{where}: first_id must be a non-negative integer, got {_short(first)}")
    last = first + cols * rows - 1
    if last >= num_ids:
        raise DatasetError(f"{where}: tag ids {first}-{last} are not all in dictionary {dict_name} (ids 0-{num_ids - 1})")
    return {
        first + r * cols + c: (np.eye(3), np.array([c * spacing, -r * spacing, 0.0]))
        for r in range(rows)
        for c in range(cols)
    }


def _pose(value: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` from ``{R: 3x3, t: [3]}`` or ``{q_xyzw: [4], t: [3]}``; R must be a rotation."""
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected {{R: 3x3, t: [x, y, z]}}, got {_kind(value)}")
    _only(value, ("R", "t", "q_xyzw"), where)
    if "t" not in value:
        raise DatasetError(f"{where}: missing 't' (metres)")
    t = _vector(value["t"], 3, f"{where}: t")
    if ("R" in value) == ("q_xyzw" in value):
        raise DatasetError(f"{where}: give exactly one of 'R' (3x3) and 'q_xyzw'")
    if "q_xyzw" in value:
        q = _vector(value["q_xyzw"], 4, f"{where}: q_xyzw")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > 1e-3:
            raise DatasetError(f"{where}: q_xyzw must be a unit quaternion, has norm {n:.6g}")
        x, y, z, w = q / n
        R = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        return R, t
    rows = value["R"]
    if not isinstance(rows, (list, tuple)) or len(rows) != 3:
        raise DatasetError(f"{where}: R must be 3 rows of 3 numbers, got {_short(rows)}")
    R = np.array([_vector(r, 3, f"{where}: R row {i}") for i, r in enumerate(rows)])
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOL or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: R is not a rotation matrix (|R^T R - I| = {err:.2g}, det = {np.linalg.det(R):.4g})")
    u, _, vt = np.linalg.svd(R)
    return u @ vt, t


# --- images, video, tracks --------------------------------------------------------------------------


def _configs(value: Any, num_mirrors: int, where: str) -> tuple[Config, ...]:
    if not isinstance(value, (list, tuple)):
        raise DatasetError(f"{where}: mirror_configs must be a list of {num_mirrors} integers or 'each', got {_short(value)}")
    if len(value) != num_mirrors:
        raise DatasetError(f"{where}: mirror_configs has {len(value)} entries, expected {num_mirrors} (num_mirrors)")
    out: list[Config] = []
    for l, m in enumerate(value):
        if m == EACH:
            out.append(EACH)
        elif _is_int(m) and m >= 0:
            out.append(int(m))
        else:
            raise DatasetError(
                f"{where}: mirror_configs[{l}] (mirror {l + 1}) must be a non-negative integer or 'each', got {_short(m)}"
            )
    return tuple(out)


def _images(value: Any, cap: Capture, base_dir: str) -> list[ImageEntry]:
    source = cap.source
    if not isinstance(value, list) or not value:
        raise DatasetError(f"{source}: images must be a non-empty list of {{file, mirror_configs}}")
    points_target = isinstance(cap.target, PointsTarget)
    entries: list[ImageEntry] = []
    seen: dict[str, str] = {}
    for index, e in enumerate(value):
        where = f"{source}: images[{index}]"
        if not isinstance(e, Mapping):
            raise DatasetError(f"{where}: expected {{file, mirror_configs}}, got {_kind(e)}")
        _only(e, ("file", "mirror_configs", "observations", "id"), where)
        file = e.get("file")
        path = None
        if file is not None:
            if not isinstance(file, str) or not file:
                raise DatasetError(f"{where}: file must be a path, got {_short(file)}")
            where = f"{source}: images[{index}] ({_name(file)})"
            path = _resolve(file, base_dir)
            if not os.path.isfile(path):
                raise DatasetError(f"{where}: image file not found")
        elif not points_target:
            raise DatasetError(f"{where}: missing 'file' (the image)")
        if "mirror_configs" not in e:
            raise DatasetError(f"{where}: missing 'mirror_configs'")
        configs = _configs(e["mirror_configs"], cap.num_mirrors, where)
        obs_value = e.get("observations")
        obs_file = None
        if obs_value is None:
            if points_target:
                raise DatasetError(f"{where}: missing 'observations' (pixels of the fiducials; a points target detects nothing)")
            observations: dict[str, np.ndarray] = {}
        else:
            if isinstance(obs_value, str):
                obs_file = obs_value
            observations = _observations(obs_value, cap, base_dir, where)
        image_id = e.get("id")
        if image_id is None:
            stem_of = file if file is not None else obs_file
            if stem_of is None:
                raise DatasetError(f"{where}: give 'file' or 'id' (the image id)")
            image_id = Path(stem_of).stem
        if not isinstance(image_id, str) or not image_id:
            raise DatasetError(f"{where}: id must be a non-empty string, got {_short(image_id)}")
        if image_id in seen:
            raise DatasetError(f"{where}: image id {_short(image_id)} is also that of {seen[image_id]}; give each an 'id'")
        seen[image_id] = f"images[{index}]"
        label = where.removeprefix(f"{source}: ")
        obs_path = _resolve(obs_file, base_dir) if obs_file is not None else None
        entries.append(ImageEntry(image_id, path, configs, observations, where, label, obs_path))
    return entries


def _observations(value: Any, cap: Capture, base_dir: str, where: str) -> dict[str, np.ndarray]:
    """Pixels ``{name: [u, v]}`` inline or from a file (JSON/YAML mapping, or ``name u v`` / ``u v`` lines)."""
    if isinstance(value, str):
        path = _resolve(value, base_dir)
        fwhere = f"{where}: observations file {_name(value)!r}"
        if not os.path.isfile(path):
            raise DatasetError(f"{fwhere} not found")
        if path.lower().endswith((".json", ".yaml", ".yml")):
            value = _load_structured(path, fwhere)
            where = fwhere
        else:
            return _observations_text(path, cap, fwhere)
    if not isinstance(value, Mapping) or not value:
        raise DatasetError(f"{where}: observations must be a non-empty mapping {{name: [u, v]}} or a file, got {_short(value)}")
    return _named_vectors(value, 2, where, "point")


def _observations_text(path: str, cap: Capture, where: str) -> dict[str, np.ndarray]:
    try:
        with open(path, encoding="utf-8") as f:
            lines = [(n + 1, ln.split()) for n, ln in enumerate(f) if ln.strip() and not ln.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{where}: cannot read: {exc}") from None
    names = list(cap.target.target_points())
    out: dict[str, np.ndarray] = {}
    unnamed = [ln for ln in lines if len(ln[1]) == 2]
    if unnamed and len(unnamed) != len(lines):
        raise DatasetError(f"{where}: mixes 'u v' and 'name u v' lines")
    if unnamed and len(lines) != len(names):
        raise DatasetError(
            f"{where}: has {len(lines)} 'u v' lines but the target has {len(names)} fiducials (one line each, in order)"
        )
    for k, (lineno, parts) in enumerate(lines):
        if len(parts) == 2:
            name, nums = names[k], parts
        elif len(parts) == 3:
            name, nums = parts[0], parts[1:]
        else:
            raise DatasetError(f"{where}: line {lineno}: expected 'u v' or 'name u v'")
        try:
            uv = np.array([float(x) for x in nums])
        except ValueError:
            raise DatasetError(f"{where}: line {lineno}: not numbers: {_short(' '.join(nums))}") from None
        if not np.all(np.isfinite(uv)):
            raise DatasetError(f"{where}: line {lineno}: not finite")
        if name in out:
            raise DatasetError(f"{where}: line {lineno}: point {_short(name)} given twice")
        out[name] = uv
    if not out:
        raise DatasetError(f"{where}: no observations in the file")
    return out


def _video(v: Any, cap: Capture, base_dir: str) -> VideoSpec:
    source = cap.source
    where = f"{source}: video"
    if not isinstance(v, Mapping):
        raise DatasetError(f"{where}: expected {{file, segments}}, got {_kind(v)}")
    _only(v, ("file", "segments"), where)
    file = v.get("file")
    if not isinstance(file, str) or not file:
        raise DatasetError(f"{where}: file must be a path, got {_short(file)}")
    path = _resolve(file, base_dir)
    where = f"{source}: video ({_name(file)})"
    if not os.path.isfile(path):
        raise DatasetError(f"{where}: video file not found")
    frame_count = _video_frame_count(path, where)
    segs = v.get("segments")
    if not isinstance(segs, list) or not segs:
        raise DatasetError(f"{where}: segments must be a non-empty list of {{frames: [first, last], mirror_configs}}")
    segments: list[VideoSegment] = []
    for i, s in enumerate(segs):
        sw = f"{where}: segments[{i}]"
        if not isinstance(s, Mapping):
            raise DatasetError(f"{sw}: expected {{frames, mirror_configs}}, got {_kind(s)}")
        _only(s, ("frames", "mirror_configs", "step"), sw)
        fr = s.get("frames")
        if not isinstance(fr, (list, tuple)) or len(fr) != 2 or not all(_is_int(x) and x >= 0 for x in fr) or fr[0] > fr[1]:
            raise DatasetError(f"{sw}: frames must be [first, last] with 0 <= first <= last, got {_short(fr)}")
        if fr[1] >= frame_count:
            raise DatasetError(f"{sw}: frame {fr[1]} is past the end of the video ({frame_count} frames, 0-{frame_count - 1})")
        step = s.get("step", 1)
        if not _is_int(step) or step < 1:
            raise DatasetError(f"{sw}: step must be an integer >= 1, got {_short(step)}")
        if "mirror_configs" not in s:
            raise DatasetError(f"{sw}: missing 'mirror_configs'")
        configs = _configs(s["mirror_configs"], cap.num_mirrors, sw)
        segments.append(VideoSegment(int(fr[0]), int(fr[1]), configs, int(step), where=sw))
    ordered = sorted(segments, key=lambda s: s.first)
    for a, b in zip(ordered, ordered[1:]):
        if b.first <= a.last:
            raise DatasetError(f"{where}: segments frames [{a.first}, {a.last}] and [{b.first}, {b.last}] overlap")
    return VideoSpec(path, ordered, frame_count)


def open_video(path: str, where: str) -> Any:
    """An opened ``cv2.VideoCapture`` whose frames are within MAX_IMAGE_PIXELS (from the container's
    header, before any frame is decoded); DatasetError otherwise. The caller releases it."""
    import cv2

    with native_stderr() as native:
        vc = cv2.VideoCapture(path)
    if not vc.isOpened():
        vc.release()
        raise DatasetError(f"{where}: cannot open the video (unknown or broken format){native.detail}")
    w, h = vc.get(cv2.CAP_PROP_FRAME_WIDTH), vc.get(cv2.CAP_PROP_FRAME_HEIGHT)
    if not (math.isfinite(w) and math.isfinite(h)) or w * h > MAX_IMAGE_PIXELS:
        vc.release()
        raise DatasetError(f"{where}: frames of {w:.0f} x {h:.0f} pixels are above the limit of {MAX_IMAGE_PIXELS} pixels")
    return vc


def _video_frame_count(path: str, where: str) -> int:
    import cv2

    vc = open_video(path, where)
    try:
        with native_stderr() as native:
            ok, _ = vc.read()
        if not ok:
            raise DatasetError(f"{where}: cannot read a frame from the video{native.detail}")
        reported = vc.get(cv2.CAP_PROP_FRAME_COUNT)
        count = int(reported) if math.isfinite(reported) else 0
    finally:
        vc.release()
    if count <= 0:
        raise DatasetError(f"{where}: the video reports no frame count")
    return count


def _track(t: Any, cap: Capture) -> dict[str, TrackStart]:
    where = f"{cap.source}: track"
    if not isinstance(t, Mapping):
        raise DatasetError(f"{where}: expected {{name: {{frame, pixel: [u, v]}}}}, got {_kind(t)}")
    fiducials = cap.target.target_points()
    out: dict[str, TrackStart] = {}
    for name, spec in t.items():
        pw = f"{where}: {_short(name)}"
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{where}: point name must be a non-empty string, got {_short(name)}")
        if name in fiducials:
            raise DatasetError(f"{pw}: is a fiducial name; tracked points are unknown points with names of their own")
        if not isinstance(spec, Mapping):
            raise DatasetError(f"{pw}: expected {{frame, pixel: [u, v]}}, got {_kind(spec)}")
        _only(spec, ("frame", "pixel", "feature", "sigma"), pw)
        frame = spec.get("frame")
        if not _is_int(frame) or frame < 0:
            raise DatasetError(f"{pw}: frame must be a non-negative integer, got {_short(frame)}")
        if cap.video is not None and not any(s.first <= frame <= s.last for s in cap.video.segments):
            raise DatasetError(f"{pw}: frame {frame} is in no video segment")
        if cap.images is not None and frame >= len(cap.images):
            raise DatasetError(f"{pw}: frame {frame} is past the last image (images[{len(cap.images) - 1}]); with images, frame is the position in the list")
        feature = spec.get("feature", "corner")
        if feature not in TRACK_FEATURES:
            raise DatasetError(f"{pw}: feature must be one of {', '.join(TRACK_FEATURES)}, got {_short(feature)}")
        sigma = spec.get("sigma")
        if sigma is not None and (_finite(sigma) is None or sigma <= 0):
            raise DatasetError(f"{pw}: sigma must be a finite number > 0 (pixels), got {_short(sigma)}")
        out[name] = TrackStart(name, int(frame), _vector(spec.get("pixel"), 2, f"{pw}: pixel"), str(feature),
                               None if sigma is None else float(sigma))
    return out


# --------------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------------


def _resolve(path: str, base_dir: str) -> str:
    path = os.path.expanduser(path)
    return os.path.normpath(path if os.path.isabs(path) else os.path.join(base_dir, path))


def _only(m: Mapping[str, Any], allowed: tuple[str, ...], where: str) -> None:
    check_keys(m, allowed, where)


def _load_structured(path: str, where: str) -> Any:
    """Parse a YAML or JSON file once, within fileio's bounds; duplicate keys are an error."""
    from mirror_fg.io.fileio import load_structured

    return load_structured(path, where)


def _vector(value: Any, n: int, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n or not all(_is_number(x) for x in value):
        raise DatasetError(f"{where}: expected {n} numbers, got {_short(value)}")
    numbers = [_finite(x) for x in value]
    if None in numbers:
        raise DatasetError(f"{where}: not finite: {_short(value)}")
    return np.array(numbers)


def _named_vectors(value: Mapping[Any, Any], n: int, where: str, what: str) -> dict[str, np.ndarray]:
    """``{name: [n numbers]}`` with non-empty string names; ``what`` names an entry in messages."""
    out: dict[str, np.ndarray] = {}
    for name, v in value.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{where}: {what} name must be a non-empty string, got {_short(name)}")
        out[name] = _vector(v, n, f"{where}: {what} {_short(name)}")
    return out


def _finite(x: Any) -> float | None:
    """``x`` as a finite float; None for what is not a real number (bools, strings, null), NaN, inf, or an
    integer too large for a float (a 400-digit integer)."""
    if not _is_number(x):
        return None
    try:
        value = float(x)
    except (OverflowError, ValueError, TypeError):
        return None
    return value if math.isfinite(value) else None


def _clip(text: str, limit: int = _NAME_LIMIT) -> str:
    """One line of at most ``limit`` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _name(path: str) -> str:
    """A user-given path for messages, on one line; a long one keeps its end (the file name)."""
    path = " ".join(path.split())
    return path if len(path) <= _NAME_LIMIT else "..." + path[-(_NAME_LIMIT - 3):]


class NativeOutput:
    """What native code (libpng, libjpeg, FFmpeg, OpenCV) wrote to stderr inside :func:`native_stderr`."""

    def __init__(self) -> None:
        self.text = ""

    @property
    def problem(self) -> str:
        """The first line that is not marked as a mere warning (a decode error, corrupt data), short; ''."""
        for line in self.text.splitlines():
            if line.strip() and "warn" not in line.lower():
                return _clip(line.strip())
        return ""

    @property
    def detail(self) -> str:
        """``": <problem>"`` to end a message with, or ''."""
        return f": {self.problem}" if self.problem else ""


@contextmanager
def native_stderr() -> Iterator[NativeOutput]:
    """Divert file descriptor 2 to a temporary file during native decoding; the text is kept, not printed.

    Native libraries write their own lines (``libpng error: IDAT: CRC error``) straight to fd 2, which
    would precede our one-line message. After the block, ``.text`` holds what they wrote (first 4 kB).
    When fd 2 cannot be duplicated (closed), nothing is diverted. Not thread-safe: fd 2 is per process.
    """
    out = NativeOutput()
    try:
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:
        yield out
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
            tmp.seek(0)
            out.text = tmp.read(4096).decode("utf-8", "replace")
    finally:
        os.close(saved)


def _kind(x: Any) -> str:
    names = {dict: "a mapping", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    for t, name in names.items():
        if isinstance(x, t):
            return name
    return "a number" if _is_number(x) else type(x).__name__
