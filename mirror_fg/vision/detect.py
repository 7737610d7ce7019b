"""Detection: photographs or a video of a capture@1 -> a validated dataset, with OpenCV's detectors.

Pixels follow OpenCV's convention (the centre of the top-left pixel is (0, 0)). The detectors on one
image (chessboard, tags; mirror-imaged views) are :mod:`mirror_fg.vision.detectors`'. Images are
decoded only when their header says they fit :data:`~mirror_fg.io.fileio.MAX_IMAGE_PIXELS`; what the
native decoders complain about becomes the image's reason. Video: every frame is tracked
(:mod:`mirror_fg.vision.tracking`: KLT, then refinement onto the feature) and re-detected; fiducials
that detection misses are carried as corners. ``track:`` points are followed through a video or through ``images`` in list order (a photo sequence),
each refined by its ``feature`` kind; a cut track is named, with the reason, in the next kept image's
report.

A symmetric chessboard (``cols + rows`` even) gives each image's corners only up to a half (or
quarter) turn: after every image is detected, :func:`mirror_fg.solver.screen.labelling.choose_labellings`
labels each by consistency across the images; its report names the labelling (``labelling half
turn (...)``: turned from the detector's), and an image no labelling clearly fits is ``refused`` with
the reason. Every refused or not-found image is an :class:`ImageReport` with its ``id`` and ``reason``.

Noise of tracked points: each track's sigma goes into the dataset's ``point_sigma``
(:func:`~mirror_fg.vision.track_sigma.tracked_point_sigma`: the ``track:`` entry's ``sigma``, else the
tracker's, never below ``pixel_sigma``), so the solver weighs a tracked point by what the tracker does;
``detect_capture(..., tracks=...)`` hands back every track's path, residuals and sigma for the report.
"""
from __future__ import annotations

import logging
import os
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mirror_fg.io.robot_capture import add_robot_fields
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.capture import CAPTURE_FORMAT, Capture, ImageEntry, capture_from_file_data, open_video
from mirror_fg.io.capture_views import is_mirrored
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.data import Dataset
from mirror_fg.io.fileio import MAX_IMAGE_PIXELS, NotTextError, load_structured, native_stderr
from mirror_fg.io.output import OutputPlan
from mirror_fg.io.result import RESULT_FORMAT
from mirror_fg.io.target import CharucoTarget, ChessboardTarget, PointsTarget, TagTarget
from mirror_fg.core.values import short_path
from mirror_fg.vision.detectors import (
    FOUND,
    NOT_FOUND,
    REFUSED,
    Detection,
    aruco_detector,
    charuco_detector,
    chessboard_size_hint,
    detect_charuco,
    detect_chessboard,
    detect_tags,
)
from mirror_fg.vision.detect_views import DatasetParts, Output, dataset_dict, detect_in_views
from mirror_fg.vision.track_sigma import tracked_point_sigma
from mirror_fg.vision.tracking import KLTParams, PointTracker, Track

__all__ = [
    "load_input",
    "ImageReport",
    "detect_capture",
    "format_reports",
]

#: Library messages (per image: found at DEBUG, not found / refused with the reason at INFO; a closing
#: count at INFO). A child of the ``mirror_fg`` logger, which applications configure.
_log = logging.getLogger(__name__)

#: An image whose format Pillow cannot read from its header (so its size is unknown before decoding)
#: is decoded by OpenCV only up to this file size (bytes), which bounds what it can expand to.
MAX_UNSIZED_IMAGE_BYTES = 4 << 20


@dataclass
class ImageReport:
    """What detection made of one image or video frame.

    ``status``: ``found`` (kept in the dataset), ``not found`` or ``refused`` (left out); ``reason`` says
    why, or how (e.g. tracked rather than detected); ``num_points``: observations kept.
    """

    id: str
    status: str
    reason: str = ""
    num_points: int = 0

    def line(self) -> str:
        if self.status == FOUND:
            text = f"{self.id}: found, {self.num_points} point{'s' if self.num_points != 1 else ''}"
            return text + (f" ({self.reason})" if self.reason else "")
        return f"{self.id}: {self.status}: {self.reason}"


def _report(reports: list[ImageReport], report: ImageReport) -> None:
    """Keep ``report`` and log it (DEBUG when found, INFO when left out)."""
    reports.append(report)
    _log.log(logging.DEBUG if report.status == FOUND else logging.INFO, "%s", report.line())


def format_reports(reports: list[ImageReport]) -> str:
    """Per-image lines and a closing count, for printing."""
    return "\n".join([r.line() for r in reports] + [_count_line(reports)])


def _count_line(reports: list[ImageReport]) -> str:
    counts = {s: sum(r.status == s for r in reports) for s in (FOUND, NOT_FOUND, REFUSED)}
    return (
        f"{len(reports)} image{'s' if len(reports) != 1 else ''}: {counts[FOUND]} found, "
        f"{counts[NOT_FOUND]} not found, {counts[REFUSED]} refused"
    )


class _Detector:
    """The capture's detector bound to its target and mirror parity."""

    def __init__(self, capture: Capture, camera: dict[str, Any]):
        self.capture = capture
        self.camera = camera
        # a screen target is detected as the pattern it shows (same names; fiducials from the capture)
        self.target = getattr(capture.target, "pattern_target", capture.target)
        self.aruco = aruco_detector(self.target) if isinstance(self.target, TagTarget) else None
        self.charuco = charuco_detector(self.target) if isinstance(self.target, CharucoTarget) else None

    def __call__(self, gray: np.ndarray, mirrored: bool | None = None, camera: dict[str, Any] | None = None) -> Detection:
        """Detect in ``gray`` seen through an odd number of reflections when ``mirrored`` (default: the
        capture's ``num_mirrors``), checking the plane fit with ``camera`` (default: the bound one)."""
        mirrored = self.capture.mirrored if mirrored is None else mirrored
        camera = self.camera if camera is None else camera
        if isinstance(self.target, ChessboardTarget):
            return detect_chessboard(gray, self.target, mirrored, camera)
        if isinstance(self.target, CharucoTarget):
            return detect_charuco(gray, self.target, mirrored, camera, self.charuco)
        if isinstance(self.target, TagTarget):
            return detect_tags(gray, self.target, mirrored, self.aruco)
        return Detection(status=NOT_FOUND, reason="a points target detects nothing")


# --------------------------------------------------------------------------------------------------
# Whole capture
# --------------------------------------------------------------------------------------------------


def detect_capture(
    capture: Capture, progress: bool = True, tracks: dict[str, Track] | None = None
) -> tuple[Dataset, list[ImageReport]]:
    """Detect the target in every image (or video frame) of ``capture``.

    Returns the validated :class:`~mirror_fg.data.Dataset` (pixel observations with the capture's
    camera(s), fiducials in the base frame, images with ids = file stems or ``stem:frame`` (a view of a
    photograph: ``stem#k``), ``each`` placements expanded into fresh integers
    (:mod:`mirror_fg.vision.detect_views`); ``source`` is ``capture.source``) and one
    :class:`ImageReport` per image/frame in capture order. ``progress`` shows a tqdm bar on stderr when
    it is a terminal. An image that cannot be decoded, or is above MAX_IMAGE_PIXELS, is refused with the
    reason. ``tracks`` (optional, filled in): every ``track:`` point's :class:`~mirror_fg.vision.tracking.Track`
    (kind, history of KLT and refined pixels with residuals; ``.sigma()``). Raises DatasetError when no
    image is kept, the video cannot be read, or the dataset is refused (as ``dataset_from_dict`` would).
    """
    board = capture.target
    if isinstance(board, ChessboardTarget) and board.symmetric and capture.images is not None and (
            capture.cameras is not None or any(e.views is not None or not e.mirror_configs for e in capture.images)):
        raise DatasetError(f"{capture.source}: target: a symmetric chessboard (cols + rows = {board.cols + board.rows}, "
                           "even) is labelled across one camera's mirror_configs images only; with reflections, views "
                           "or cameras use a board with cols + rows odd, or ChArUco")
    camera = dict(capture.camera)
    cameras: dict[str | None, dict[str, Any]] = (
        {None: camera} if capture.cameras is None else {n: dict(c) for n, c in capture.cameras.items()})
    outputs: list[Output] = []
    reports: list[ImageReport] = []
    show = bool(progress) and sys.stderr.isatty()
    gamma = getattr(capture.target, "image_gamma", "srgb")
    tracker = PointTracker(KLTParams(), default_kind="corner", image_gamma=gamma)
    if capture.images is not None:
        _detect_images(capture, cameras, outputs, reports, show, tracker)
    else:
        _detect_video(capture, camera, outputs, reports, show, tracker)
    if tracks is not None:
        tracks.update({name: t for name, t in tracker.tracks.items() if name in capture.track})

    if not outputs:
        _log.info("%s: %s", capture.source, _count_line(reports))
        reasons = "; ".join(r.line() for r in reports[:3]) + ("; ..." if len(reports) > 3 else "")
        raise DatasetError(f"{capture.source}: the target was found in none of the {len(reports)} images ({reasons})"
                           + _size_hint(capture, reports))
    point_sigma = tracked_point_sigma(capture, tracker.tracks, (n for out in outputs for n in out.points))
    data = dataset_dict(capture, DatasetParts(cameras, outputs, point_sigma or {}))
    add_robot_fields(data, capture)  # a robot arm's joint states (docs/formats.md "Robot arms")
    dataset = dataset_from_dict(data, source=capture.source)
    if isinstance(capture.target, ChessboardTarget) and capture.target.symmetric:
        dataset = _label_symmetric(dataset, capture, reports)
    _log.info("%s: %s", capture.source, _count_line(reports))
    return dataset, reports


def _label_symmetric(dataset: Dataset, capture: Capture, reports: list[ImageReport]) -> Dataset:
    """Each image of a symmetric board labelled by consistency across the images
    (:func:`mirror_fg.solver.screen.labelling.choose_labellings`); the labelling, or why the image was left
    out (status ``refused``), is added to its report."""
    from mirror_fg.solver.screen.labelling import choose_labellings

    board = capture.target
    assert isinstance(board, ChessboardTarget)
    labelled, labels = choose_labellings(dataset, board.symmetries(), upright=board.top_and_bottom_rows())
    by_id = {r.id: r for r in reports}
    for label in labels:
        report = by_id[label.image]
        if label.excluded:
            report.status, report.reason, report.num_points = REFUSED, label.reason, 0
            _log.info("%s", report.line())
        else:
            report.reason = "; ".join([label.line()] + ([report.reason] if report.reason else []))
    if not labelled.images:
        reasons = "; ".join(r.line() for r in reports[:3]) + ("; ..." if len(reports) > 3 else "")
        raise DatasetError(
            f"{capture.source}: no image of the symmetric {board.cols} x {board.rows} board could be labelled ({reasons})"
        )
    return labelled


def _progress(total: int, unit: str, show: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc="detect", file=sys.stderr, disable=not show, leave=False)


def _check_size(gray: np.ndarray, camera: dict[str, Any]) -> str:
    """Fill a missing camera size from ``gray``; a reason string when the size differs."""
    h, w = gray.shape[:2]
    if camera.get("width") is None or camera.get("height") is None:
        camera["width"], camera["height"] = int(w), int(h)
        return ""
    if (w, h) != (camera["width"], camera["height"]):
        return f"image is {w} x {h} pixels, the camera {camera['width']} x {camera['height']}"
    return ""


def _start_tracks(tracker: PointTracker, starts: list[Any]) -> None:
    for start in starts:  # a hand-given pixel is snapped onto its feature (a template keeps it)
        tracker.set(start.name, start.pixel, kind=start.feature, snap=True)


def _track_starts(capture: Capture) -> dict[int, list[Any]]:
    starts: dict[int, list[Any]] = {}
    for start in capture.track.values():
        starts.setdefault(start.frame, []).append(start)
    return starts


def _cut_notes(tracker: PointTracker, dropped: list[str], capture: Capture) -> list[str]:
    return [f"track {name} cut at {tracker.cut[name]}" for name in dropped if name in capture.track]


def _size_hint(capture: Capture, reports: list[ImageReport]) -> str:
    """``"; <hint>"`` for a chessboard found in no image (the first one not found is looked at again
    for a board of one corner fewer each way), else ''."""
    if not isinstance(capture.target, ChessboardTarget) or not capture.images:
        return ""
    missed = {r.id for r in reports if r.status == NOT_FOUND}
    entry = next((e for e in capture.images if e.id in missed and e.file is not None), None)
    if entry is None:
        return ""
    gray = _read_gray(entry)[0] if entry.views is None else None  # a kaleidoscope's views: no hint
    return "" if gray is None else f"; {chessboard_size_hint(gray, capture.target, entry.mirrored, entry.id)}"


def _detect_images(
    capture: Capture, cameras: dict[str | None, dict[str, Any]], outputs: list[Output], reports: list[ImageReport],
    show: bool, tracker: PointTracker,
) -> None:
    """Each image detected on its own (a photograph with views: each view in its region);
    ``track:`` points followed through the images in list order."""
    detectors = {name: _Detector(capture, camera) for name, camera in cameras.items()}
    entries: list[ImageEntry] = capture.images or []
    starts = _track_starts(capture)
    cuts: list[str] = []
    with _progress(len(entries), "image", show) as bar:
        for index, entry in enumerate(entries):
            camera = cameras[entry.camera]
            if entry.views is not None:
                _detect_views(entry, detectors[entry.camera], camera, outputs, reports)
                bar.update(1)
                continue
            det = _detect_entry(entry, detectors[entry.camera], capture, camera)
            if capture.track:
                gray = _read_gray(entry)[0] if det.status != REFUSED else None  # decoded again: tracking only
                if gray is None:
                    tracker.reset()  # unreadable or of another size: tracks cannot cross it
                else:
                    cuts += _cut_notes(tracker, tracker.step(gray, index=index), capture)
                    _start_tracks(tracker, starts.get(index, []))
                    tracked = {n: p.copy() for n, p in tracker.points.items() if n in capture.track and n not in det.points}
                    if tracked and det.status == FOUND and det.points:
                        det.points.update(tracked)
                        cuts.insert(0, f"{len(tracked)} point{'s' if len(tracked) != 1 else ''} tracked")
                if det.status == FOUND and det.points and cuts:
                    det.reason = "; ".join(([det.reason] if det.reason else []) + cuts)
                    cuts = []
            if det.status == FOUND and det.points:
                outputs.append(Output(entry.id, entry.mirror_configs, det.points, entry.reflections, entry.camera))
                _report(reports, ImageReport(entry.id, FOUND, det.reason, len(det.points)))
            else:
                status = det.status if det.status != FOUND else NOT_FOUND
                _report(reports, ImageReport(entry.id, status, det.reason or "no observations"))
            bar.update(1)


def _detect_views(entry: ImageEntry, detector: _Detector, camera: dict[str, Any], outputs: list[Output],
                  reports: list[ImageReport]) -> None:
    """A kaleidoscope photograph: one output and one report per view (ids ``stem#k``); a photograph
    that cannot be read or is of another size refuses all its views with the reason."""
    gray, why = _read_gray(entry)
    why = why or (_check_size(gray, camera) if gray is not None else "")
    if gray is None or why:
        for view in entry.views or []:
            _report(reports, ImageReport(view.id, REFUSED, why))
        return
    for view, det in detect_in_views(entry, gray, detector, camera):
        if det.status == FOUND and det.points:
            outputs.append(Output(view.id, view.mirror_configs or (), det.points, view.reflections, entry.camera,
                                  group=entry.id))
            _report(reports, ImageReport(view.id, FOUND, det.reason, len(det.points)))
        else:
            _report(reports, ImageReport(view.id, det.status if det.status != FOUND else NOT_FOUND,
                                         det.reason or "no observations"))


def _detect_entry(entry: ImageEntry, detector: _Detector, capture: Capture, camera: dict[str, Any]) -> Detection:
    if isinstance(capture.target, PointsTarget):
        if entry.file is not None and camera.get("width") is None:
            gray, why = _read_gray(entry)
            if gray is None:
                return Detection(status=REFUSED, reason=why)
            _check_size(gray, camera)
        return Detection(points=dict(entry.observations))
    gray, why = _read_gray(entry)
    if gray is None:
        return Detection(status=REFUSED, reason=why)
    mismatch = _check_size(gray, camera)
    if mismatch:
        return Detection(status=REFUSED, reason=mismatch)
    det = detector(gray, entry.mirrored)
    if det.status != FOUND:
        if entry.observations:  # the given points alone
            return Detection(points=dict(entry.observations), reason=f"{det.reason}; given observations only")
        return det
    det.points.update(entry.observations)  # hand-given pixels win over detections of the same name
    return det


def _read_gray(entry: ImageEntry) -> tuple[np.ndarray | None, str]:
    """The image as 8-bit gray, or ``(None, reason)``: too large (from its header, before decoding),
    not an image, or damaged (the decoder's own complaint, e.g. ``Premature end of JPEG file``)."""
    assert entry.file is not None
    too_large = _too_large(entry.file)
    if too_large:
        return None, f"{entry.label}: {too_large}"
    with native_stderr() as native:
        gray = cv2.imread(entry.file, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return None, f"{entry.label}: cannot decode the image (not an image file OpenCV reads, or damaged){native.detail}"
    if native.problem:
        return None, f"{entry.label}: damaged image{native.detail}"
    return gray, ""


def _too_large(path: str) -> str:
    """Why the image at ``path`` must not be decoded (above MAX_IMAGE_PIXELS), or ''.

    The size comes from the header through Pillow, which reads no pixel data. A file Pillow cannot
    identify (not an image, or a format only OpenCV reads) is let through only when small.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                width, height = im.size
    except Image.DecompressionBombError:
        return f"image is above the limit of {MAX_IMAGE_PIXELS} pixels (from its header; not decoded)"
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError):
        try:
            small = os.path.getsize(path) <= MAX_UNSIZED_IMAGE_BYTES
        except OSError as exc:
            return f"cannot read the image: {exc.strerror or exc}"
        return "" if small else f"not an image format whose size can be read before decoding, and over {MAX_UNSIZED_IMAGE_BYTES} bytes"
    if width * height > MAX_IMAGE_PIXELS:
        return f"image is {width} x {height} pixels, above the limit of {MAX_IMAGE_PIXELS} (not decoded)"
    return ""


def _detect_video(
    capture: Capture, camera: dict[str, Any], outputs: list[Output], reports: list[ImageReport], show: bool,
    tracker: PointTracker,
) -> None:
    video = capture.video
    assert video is not None
    detector = _Detector(capture, camera)
    fiducial_names = set(capture.target.target_points())
    starts = _track_starts(capture)
    cuts: list[str] = []
    where = f"{capture.source}: video ({short_path(os.path.basename(video.file))})"
    vc = open_video(video.file, where)
    total = sum(s.last - s.first + 1 for s in video.segments)
    position = 0  # index of the next frame vc.read() returns
    last_read = -2
    try:
        with _progress(total, "frame", show) as bar:
            for seg in video.segments:
                while position < seg.first:  # a failed grab (a damaged frame) still passes that frame
                    with native_stderr():
                        vc.grab()
                    position += 1
                if seg.first != last_read + 1:
                    tracker.reset()  # a gap in the frames: tracks cannot carry over
                outputs_of_seg = set(seg.output_frames())
                for frame in range(seg.first, seg.last + 1):
                    frame_id = f"{video.stem}:{frame}"
                    with native_stderr() as native:
                        ok, image = vc.read() if position == frame else (False, None)
                    # A failed read consumes its frame too: OpenCV goes on with the next one, so the
                    # frames after a damaged stretch keep their indices.
                    position += 1
                    if not ok or image is None:
                        if frame in outputs_of_seg:
                            why = f"frame could not be read from the video (damaged or cut short){native.detail}"
                            _report(reports, ImageReport(frame_id, NOT_FOUND, why))
                        bar.update(1)
                        tracker.reset()  # tracks cannot cross a lost frame
                        continue
                    last_read = frame
                    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
                    mismatch = _check_size(gray, camera)
                    if mismatch:
                        raise DatasetError(f"{where}: {mismatch}")
                    cuts += _cut_notes(tracker, tracker.step(gray, index=frame), capture)
                    det = detector(gray, is_mirrored(seg.reflections))
                    for name, p in det.points.items():
                        tracker.set(name, p, kind="corner")  # tag and chessboard corners
                    _start_tracks(tracker, starts.get(frame, []))
                    bar.update(1)
                    if frame not in outputs_of_seg:
                        continue
                    points = {n: p.copy() for n, p in tracker.points.items()}
                    if not points:
                        _report(reports, ImageReport(frame_id, det.status if det.status != FOUND else NOT_FOUND,
                                                   det.reason or "nothing detected or tracked"))
                        continue
                    tracked_fids = sum(1 for n in points if n in fiducial_names and n not in det.points)
                    notes = []
                    if det.status != FOUND:
                        notes.append(f"{det.reason}; {tracked_fids} fiducial points tracked by KLT" if tracked_fids
                                     else f"{det.reason}")
                    elif tracked_fids:
                        notes.append(f"{tracked_fids} fiducial points tracked by KLT")
                    elif det.reason:
                        notes.append(det.reason)
                    notes, cuts = notes + cuts, []
                    outputs.append(Output(frame_id, seg.mirror_configs, points, seg.reflections))
                    _report(reports, ImageReport(frame_id, FOUND, "; ".join(notes), len(points)))
    finally:
        vc.release()


def load_input(
    path: str | os.PathLike[str], plan: OutputPlan, progress: bool = False, tracks: dict[str, Track] | None = None,
    capture_only: bool = False, on_capture: Callable[[Capture], None] | None = None,
) -> tuple[Dataset, list]:
    """A Dataset from a dataset@1 file, or from a capture@1 file after detection (read once), and the
    detection reports (empty for a dataset). The files a capture names are added to ``plan``'s inputs
    before any detection, so an output that would overwrite one of them is refused first. ``tracks``:
    filled with the capture's tracked points (:func:`detect_capture`). ``capture_only``: anything but a
    capture is a DatasetError. ``on_capture``: called with the capture once read, before detection (e.g.
    to plan the outputs its target needs: a screen's)."""
    source = os.fspath(path)
    try:
        data = load_structured(source)
    except NotTextError as error:
        if error.kind is None:
            raise
        raise DatasetError(f"{source}: is {error.kind}, not a capture: give the capture file (capture@1, YAML or "
                           "JSON) that lists the images, their mirror placements and the target (docs/capture_guide.md)"
                           ) from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt == RESULT_FORMAT:
        takes = "detect takes a capture" if capture_only else "calibrate takes a dataset or capture"
        raise DatasetError(f"{source}: this is a result (mirror-fg/result@1), written by calibrate; {takes} "
                           "(docs/formats.md)")
    if fmt == CAPTURE_FORMAT:
        capture = capture_from_file_data(data, source)
        plan.add_inputs(capture.input_files())
        if on_capture is not None:
            on_capture(capture)
        return detect_capture(capture, progress=progress, tracks=tracks)
    if capture_only:
        raise DatasetError(f"{source}: not a capture file (expected format {CAPTURE_FORMAT!r})")
    return dataset_from_dict(data, source=source), []
