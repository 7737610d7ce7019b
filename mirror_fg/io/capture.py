"""Capture files (``mirror-fg/capture@1``): what a user writes to go from photographs or a video to a dataset.

A capture file is YAML or JSON. Paths in it are relative to the capture file. Top-level keys:

``format``
    ``mirror-fg/capture@1``.
``num_mirrors``
    Integer >= 1: how many mirrors the light meets between the target and the camera.
``camera`` (or a rig's ``cameras: {name: camera}``)
    Either the dataset@1 camera object (``model: pinhole`` or ``fisheye``, ``width``, ``height``, ``fx``,
    ``fy``, ``cx``, ``cy`` in pixels, OpenCV ``dist``: ``(k1, k2, p1, p2[, k3, ...])``, fisheye ``(k1, k2,
    k3, k4)``) or a path to a calibration file,
    or ``{file: PATH, name: cam1}``: an OpenCV ``FileStorage`` YAML/XML, ROS ``camera_info`` YAML or
    Kalibr camchain (:mod:`mirror_fg.io.camera_files`). Where a file gives no image size, the size of
    the first image read is used. Both pass :func:`mirror_fg.core.camera.check_camera`.
``pixel_sigma``
    Optional measurement standard deviation in pixels (0.5 when absent).
``target``
    What is detected: ``kind: chessboard`` (``cols``, ``rows``, ``square``), ``kind: charuco`` (``cols``,
    ``rows``, ``square``, ``marker``, ``dictionary``), ``kind: apriltag`` / ``aruco``
    (``dictionary``, ``tag_size``, ``tags`` or ``grid``, optional ``corner_refinement`` and
    ``image_gamma``) or ``kind: points`` (``fiducials``); :mod:`mirror_fg.io.target` says what each
    means, which corner is which fiducial, and how the order is made the same in every image (for a
    symmetric chessboard, ``cols + rows`` even, by consistency across the images).
``T_base_target``
    Optional ``{R: 3x3, t: [3]}`` (or ``{q_xyzw: [4], t: [3]}``): the target frame in the base frame,
    ``Bp = R @ p_target + t``, for chessboard, ChArUco, tag grid and points targets; identity when absent. Tag
    poses under ``tags`` are already in the base frame and do not take it.
``images``
    A list of ``{file, mirror_configs, observations?, id?}``. ``mirror_configs[l-1]`` is the placement
    of mirror l: a non-negative integer, or ``each`` (a placement of its own, given a fresh integer in
    the dataset). ``observations`` (optional; required with a points target, where ``file`` may then be
    left out) gives measured pixels ``{name: [u, v]}`` inline or as a file: JSON/YAML of that shape, or
    text with one ``name u v`` or ``u v`` per line (the latter in the order of the target's fiducials,
    like a hand-measured ``inputN.txt``). Names that are not fiducials are reconstruction points. The
    image id in the dataset is ``id`` if given, else the stem of ``file`` (else of the observations
    file). ``reflections`` instead of ``mirror_configs``, kaleidoscope ``views`` and a rig's ``camera``:
    :mod:`mirror_fg.io.capture_views`.
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

Everything is checked on loading; :func:`load_capture` raises :class:`~mirror_fg.data.DatasetError`
with one line naming the file, the entry and the problem.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.io.robot_capture import capture_robot_fields
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.capture_views import (
    EACH, Config, Placement, ViewEntry, camera_entry, image_camera, image_placements, image_views, is_mirrored,
    rig_cameras,
)
from mirror_fg.io.fileio import load_structured, open_video, resolve_path, video_frame_count
from mirror_fg.io.observations import observations_from
from mirror_fg.io.target import PointsTarget, TagTarget, Target, pose_from_dict, target_from_dict
from mirror_fg.io.point_sigma import measurement_sigma
from mirror_fg.core.values import absolute_path, check_format, check_keys, finite, is_int, short, short_path, type_name, vector

__all__ = [
    "CAPTURE_FORMAT",
    "EACH",
    "Capture",
    "ImageEntry",
    "VideoSegment",
    "VideoSpec",
    "TrackStart",
    "load_capture",
    "capture_from_file_data",
    "capture_from_dict",
    "open_video",
]

CAPTURE_FORMAT = "mirror-fg/capture@1"
#: Library messages (a capture loaded, at INFO); a child of the ``mirror_fg`` logger.
_log = logging.getLogger(__name__)
DEFAULT_PIXEL_SIGMA = 0.5
#: Feature kinds a ``track:`` entry may name (mirror_fg.vision.tracking refines onto them; ``klt``, no
#: refinement, is for the API only).
TRACK_FEATURES = ("corner", "blob", "dot", "template")


# --------------------------------------------------------------------------------------------------
# Value objects
# --------------------------------------------------------------------------------------------------


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
    #: The placements the light meets, in order (:mod:`mirror_fg.io.capture_views`); ``mirror_configs``
    #: is ``()`` when the image gave ``reflections`` (or ``views``) instead.
    reflections: tuple[Placement, ...] = ()
    #: A kaleidoscope photograph's views (each detected in its region of interest), else None.
    views: list[ViewEntry] | None = None
    #: The camera that took it (a capture with ``cameras``), else None.
    camera: str | None = None

    def __post_init__(self) -> None:
        if not self.reflections and self.mirror_configs:
            self.reflections = tuple((l + 1, m) for l, m in enumerate(self.mirror_configs))

    @property
    def mirrored(self) -> bool:
        """Seen through an odd number of reflections (for an image with ``views``: per view)."""
        return is_mirrored(self.reflections)


@dataclass
class VideoSegment:
    """Frames ``first..last`` (inclusive, 0-based); every ``step``-th one becomes an image."""

    first: int
    last: int
    mirror_configs: tuple[Config, ...]
    step: int = 1
    where: str = "video.segments[0]"
    #: As :attr:`ImageEntry.reflections` (``mirror_configs`` is ``()`` when the segment gave these).
    reflections: tuple[Placement, ...] = ()

    def __post_init__(self) -> None:
        if not self.reflections and self.mirror_configs:
            self.reflections = tuple((l + 1, m) for l, m in enumerate(self.mirror_configs))

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
    #: A rig's ``{name: camera}`` in the file's order (``camera`` is then the first), else None.
    cameras: dict[str, dict[str, Any]] | None = None
    #: The calibration file of each rig camera read from one.
    camera_files: dict[str, str] = field(default_factory=dict)
    #: A robot arm's ``robot``, ``mounts`` and joint rows (:mod:`mirror_fg.io.robot_capture`), else None.
    robot: dict[str, Any] | None = None

    def input_files(self) -> list[str]:
        """Absolute paths of every file this capture reads, once each: the capture file, the camera file,
        then per image its image and observations files, or the video. Symbolic links are not resolved."""
        paths = [self.file, self.camera_file, *self.camera_files.values()]
        for e in self.images or []:
            paths += [e.file, e.observations_file]
        if self.video is not None:
            paths.append(self.video.file)
        return list(dict.fromkeys(os.path.abspath(p) for p in paths if p is not None))

    @property
    def mirrored(self) -> bool:
        """True when the target is seen through an odd number of mirrors (the image is mirror-imaged), for
        ``mirror_configs`` data; an image or view with ``reflections`` has its own (``ImageEntry.mirrored``,
        :func:`~mirror_fg.io.capture_views.is_mirrored`)."""
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
    return capture_from_file_data(load_structured(source, source), source)


def capture_from_file_data(data: Any, source: str, media: bool = True) -> Capture:
    """The capture of file ``source`` whose parsed content is ``data`` (read once by the caller).

    Relative paths are taken from the file's directory, or from the working directory when the capture
    comes through standard input or a pipe (``-``, ``/dev/stdin``, ``/dev/fd/N``, or not a regular file).
    ``media``: as in :func:`capture_from_dict`.
    """
    streamed = source == "-" or os.path.abspath(source).startswith(("/dev/", "/proc/")) or not os.path.isfile(source)
    base_dir = os.getcwd() if streamed else os.path.dirname(os.path.abspath(source))
    cap = capture_from_dict(data, source=source, base_dir=base_dir, media=media)
    cap.file = os.path.abspath(source)
    if cap.images is not None:
        inputs = f"{len(cap.images)} images"
    else:
        inputs = f"video of {cap.video.frame_count} frames" if cap.video is not None else "no images"
    _log.info(
        "%s: capture loaded: %d mirror%s, %s target, %s camera%s, %s",
        source, cap.num_mirrors, "s" if cap.num_mirrors != 1 else "", cap.target.kind, cap.camera["model"],
        f" from {short_path(cap.camera_file)}" if cap.camera_file else "", inputs,
    )
    return cap


def capture_from_dict(d: Any, source: str = "<capture>", base_dir: str = ".", media: bool = True) -> Capture:
    """Validate a capture@1 dictionary; relative paths are taken from ``base_dir``. ``media=False``: the
    camera, pixel_sigma, target and T_base_target only; images, video and track are not read (planning
    before the photographs exist)."""
    check_format(d, CAPTURE_FORMAT, source)
    if "incomplete" in d:  # a `live --save` session not finished (docs/formats.md#live-sessions-mirror-fg-live)
        said = d["incomplete"]
        said = " ".join(said.split())[:240] if isinstance(said, str) else short(said)
        raise DatasetError(f"{source}: incomplete: {said}")
    if isinstance(d, Mapping) and "screens" in d:  # several screens: mirror_fg.io.screens_capture
        raise DatasetError(f"{source}: screens: a capture of several screens is calibrated by mirror-fg calibrate from "
                           "a file (not standard input; not detect, report or calibrate-many: report from the result alone)")
    check_keys(d, ("format", "num_mirrors", "camera", "cameras", "pixel_sigma", "target", "T_base_target", "images",
                   "video", "track", "robot", "mounts", "joints"), source)

    num_mirrors = d.get("num_mirrors")
    if not is_int(num_mirrors) or num_mirrors < 1:
        raise DatasetError(f"{source}: num_mirrors must be an integer >= 1, got {short(num_mirrors)}")

    cameras, camera_files = None, dict[str, str]()
    if d.get("cameras") is not None:
        if "camera" in d:
            raise DatasetError(f"{source}: give 'camera' (one camera) or 'cameras' (a rig, {{name: camera}}), not both")
        cameras, camera_files = rig_cameras(d["cameras"], source, base_dir)
        first = next(iter(cameras))
        camera, camera_file = cameras[first], camera_files.get(first)
    elif "camera" not in d:
        raise DatasetError(f"{source}: missing 'camera' (intrinsics, or a path to a calibration file)")
    else:
        camera, camera_file = camera_entry(d["camera"], f"{source}: camera", base_dir)

    pixel_sigma = measurement_sigma(d.get("pixel_sigma", DEFAULT_PIXEL_SIGMA), (camera["width"], camera["height"]),
                                    f"{source}: pixel_sigma")

    if "target" not in d:
        raise DatasetError(f"{source}: missing 'target' (chessboard, charuco, apriltag, aruco or points)")
    target = target_from_dict(d["target"], source)

    if d.get("T_base_target") is not None:
        if isinstance(target, TagTarget) and target.frame == "base":
            raise DatasetError(
                f"{source}: T_base_target: tag poses under target.tags are already in the base frame; "
                "give T_base_target with a chessboard, a ChArUco board, a tag grid or points"
            )
        if target.kind == "screen":
            raise DatasetError(f"{source}: T_base_target: with a screen target the base frame is the screen's "
                               "(origin at the top-left corner of the active area); drop T_base_target")
        R, t = pose_from_dict(d["T_base_target"], f"{source}: T_base_target")
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
        cameras=cameras,
        camera_files=camera_files,
    )

    cap.robot = capture_robot_fields(d, source, base_dir, read=media)
    if not media:
        return cap
    has_images, has_video = d.get("images") is not None, d.get("video") is not None
    if has_images == has_video:
        raise DatasetError(f"{source}: give exactly one of 'images' and 'video'")
    if has_images:
        cap.images = _images(d["images"], cap, base_dir)
    else:
        if isinstance(target, PointsTarget):
            raise DatasetError(f"{source}: video: a points target needs 'images' with per-image observations")
        if cameras is not None:
            raise DatasetError(f"{source}: video: a rig ('cameras') needs 'images', each naming its camera")
        cap.video = _video(d["video"], cap, base_dir)
    if d.get("track") is not None:
        if cap.images is not None and any(e.file is None for e in cap.images):
            raise DatasetError(
                f"{source}: track: tracking needs image files; without them give the pixels under each image's 'observations'"
            )
        if cap.images is not None and any(e.views is not None for e in cap.images):
            raise DatasetError(f"{source}: track: tracking through photographs with 'views' is not supported; "
                               "track in photographs without views")
        cap.track = _track(d["track"], cap)
    return cap


# --- images, video, tracks --------------------------------------------------------------------------


def _images(value: Any, cap: Capture, base_dir: str) -> list[ImageEntry]:
    source = cap.source
    if not isinstance(value, list) or not value:
        raise DatasetError(f"{source}: images must be a non-empty list of {{file, mirror_configs}}")
    points_target = isinstance(cap.target, PointsTarget)
    entries: list[ImageEntry] = []
    seen: dict[str, str] = {}
    missing: list[tuple[str, str]] = []  # every image file not found (where, path), named together after the loop
    for index, e in enumerate(value):
        where = f"{source}: images[{index}]"
        if not isinstance(e, Mapping):
            raise DatasetError(f"{where}: expected {{file, mirror_configs}}, got {type_name(e)}")
        check_keys(e, ("file", "mirror_configs", "reflections", "views", "camera", "observations", "id", "time"), where)
        file = e.get("file")
        path = None
        if file is not None:
            if not isinstance(file, str) or not file:
                raise DatasetError(f"{where}: file must be a path, got {short(file)}")
            where = f"{source}: images[{index}] ({short_path(file)})"
            path = resolve_path(file, base_dir)
            if not os.path.isfile(path):
                missing.append((where, path))
        elif not points_target:
            raise DatasetError(f"{where}: missing 'file' (the image)")
        camera_name = image_camera(e, cap.cameras, where)
        if e.get("views") is None:
            configs, reflections = image_placements(e, cap.num_mirrors, where)
        elif points_target or e.get("observations") is not None or "mirror_configs" in e or "reflections" in e:
            raise DatasetError(f"{where}: views: give each view its reflections, and detect them (a points target, "
                               "or observations, go with images without views: one image per view, each with an 'id')")
        obs_value = e.get("observations")
        obs_file = None
        if obs_value is None:
            if points_target:
                raise DatasetError(f"{where}: missing 'observations' (pixels of the fiducials; a points target detects nothing)")
            observations: dict[str, np.ndarray] = {}
        else:
            if isinstance(obs_value, str):
                obs_file = obs_value
            observations = observations_from(obs_value, cap.target, base_dir, where)
        image_id = e.get("id")
        if image_id is None:
            stem_of = file if file is not None else obs_file
            if stem_of is None:
                raise DatasetError(f"{where}: give 'file' or 'id' (the image id)")
            image_id = Path(stem_of).stem
        if not isinstance(image_id, str) or not image_id:
            raise DatasetError(f"{where}: id must be a non-empty string, got {short(image_id)}")
        if image_id in seen:
            raise DatasetError(f"{where}: image id {short(image_id)} is also that of {seen[image_id]}; give each an 'id'")
        seen[image_id] = f"images[{index}]"
        label = where.removeprefix(f"{source}: ")
        obs_path = resolve_path(obs_file, base_dir) if obs_file is not None else None
        views = None
        if e.get("views") is not None:
            camera = cap.camera if cap.cameras is None else cap.cameras[str(camera_name)]
            views = image_views(e["views"], image_id, cap.num_mirrors, (camera["width"], camera["height"]), where)
            configs, reflections = (), ()
            for view in views:  # the views are the dataset's images: their ids are unique too
                if view.id in seen:
                    raise DatasetError(f"{where}: {view.label.rsplit(' ', 1)[-1]}: image id {short(view.id)} is also "
                                       f"that of {seen[view.id]}; give the view an 'id'")
                seen[view.id] = view.label
        entries.append(ImageEntry(image_id, path, configs or (), observations, where, label, obs_path,
                                  reflections=reflections, views=views, camera=camera_name))
    folder = absolute_path(base_dir)
    if len(missing) == 1:
        raise DatasetError(f"{missing[0][0]}: image file not found (looked for {absolute_path(missing[0][1])}"
                           f"; a relative path is taken from the capture's folder, {folder})")
    if missing:
        more = f" and {len(missing) - 4} more" if len(missing) > 4 else ""
        named = ", ".join(m.removeprefix(f"{source}: ") for m, _ in missing[:4])
        raise DatasetError(f"{source}: {len(missing)} image files not found: {named}{more} (looked in {folder}: a "
                           "relative path is taken from the capture's folder)")
    return entries


def _video(v: Any, cap: Capture, base_dir: str) -> VideoSpec:
    source = cap.source
    where = f"{source}: video"
    if not isinstance(v, Mapping):
        raise DatasetError(f"{where}: expected {{file, segments}}, got {type_name(v)}")
    check_keys(v, ("file", "segments"), where)
    file = v.get("file")
    if not isinstance(file, str) or not file:
        raise DatasetError(f"{where}: file must be a path, got {short(file)}")
    path = resolve_path(file, base_dir)
    where = f"{source}: video ({short_path(file)})"
    if not os.path.isfile(path):
        raise DatasetError(f"{where}: video file not found")
    frame_count = video_frame_count(path, where)
    segs = v.get("segments")
    if not isinstance(segs, list) or not segs:
        raise DatasetError(f"{where}: segments must be a non-empty list of {{frames: [first, last], mirror_configs}}")
    segments: list[VideoSegment] = []
    for i, s in enumerate(segs):
        sw = f"{where}: segments[{i}]"
        if not isinstance(s, Mapping):
            raise DatasetError(f"{sw}: expected {{frames, mirror_configs}}, got {type_name(s)}")
        check_keys(s, ("frames", "mirror_configs", "reflections", "step"), sw)
        fr = s.get("frames")
        if not isinstance(fr, (list, tuple)) or len(fr) != 2 or not all(is_int(x) and x >= 0 for x in fr) or fr[0] > fr[1]:
            raise DatasetError(f"{sw}: frames must be [first, last] with 0 <= first <= last, got {short(fr)}")
        if fr[1] >= frame_count:
            raise DatasetError(f"{sw}: frame {fr[1]} is past the end of the video ({frame_count} frames, 0-{frame_count - 1})")
        step = s.get("step", 1)
        if not is_int(step) or step < 1:
            raise DatasetError(f"{sw}: step must be an integer >= 1, got {short(step)}")
        configs, reflections = image_placements(s, cap.num_mirrors, sw)
        segments.append(VideoSegment(int(fr[0]), int(fr[1]), configs or (), int(step), where=sw, reflections=reflections))
    ordered = sorted(segments, key=lambda s: s.first)
    for a, b in zip(ordered, ordered[1:]):
        if b.first <= a.last:
            raise DatasetError(f"{where}: segments frames [{a.first}, {a.last}] and [{b.first}, {b.last}] overlap")
    return VideoSpec(path, ordered, frame_count)


def _track(t: Any, cap: Capture) -> dict[str, TrackStart]:
    where = f"{cap.source}: track"
    if not isinstance(t, Mapping):
        raise DatasetError(f"{where}: expected {{name: {{frame, pixel: [u, v]}}}}, got {type_name(t)}")
    fiducials = cap.target.target_points()
    out: dict[str, TrackStart] = {}
    for name, spec in t.items():
        pw = f"{where}: {short(name)}"
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{where}: point name must be a non-empty string, got {short(name)}")
        if name in fiducials:
            raise DatasetError(f"{pw}: is a fiducial name; tracked points are unknown points with names of their own")
        if not isinstance(spec, Mapping):
            raise DatasetError(f"{pw}: expected {{frame, pixel: [u, v]}}, got {type_name(spec)}")
        check_keys(spec, ("frame", "pixel", "feature", "sigma"), pw)
        frame = spec.get("frame")
        if not is_int(frame) or frame < 0:
            raise DatasetError(f"{pw}: frame must be a non-negative integer, got {short(frame)}")
        if cap.video is not None and not any(s.first <= frame <= s.last for s in cap.video.segments):
            raise DatasetError(f"{pw}: frame {frame} is in no video segment")
        if cap.images is not None and frame >= len(cap.images):
            raise DatasetError(f"{pw}: frame {frame} is past the last image (images[{len(cap.images) - 1}]); with images, frame is the position in the list")
        feature = spec.get("feature", "corner")
        if feature not in TRACK_FEATURES:
            raise DatasetError(f"{pw}: feature must be one of {', '.join(TRACK_FEATURES)}, got {short(feature)}")
        sigma = spec.get("sigma")
        if sigma is not None and (finite(sigma) is None or sigma <= 0):
            raise DatasetError(f"{pw}: sigma must be a finite number > 0 (pixels), got {short(sigma)}")
        out[name] = TrackStart(name, int(frame), vector(spec.get("pixel"), 2, f"{pw}: pixel"), str(feature),
                               None if sigma is None else float(sigma))
    return out
