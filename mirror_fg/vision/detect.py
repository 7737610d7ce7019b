"""Detection: photographs or a video of a capture@1 -> a dataset@1 dictionary, with OpenCV's detectors.

Pixels follow OpenCV's convention (the centre of the top-left pixel is (0, 0)). A target seen through
an odd number of mirrors appears mirror-imaged; detectors that need handedness (ArUco/AprilTag
decoding, chessboard ordering) then run on ``cv2.flip(image, 1)`` and every x is mapped back with
``x = width - 1 - x_flipped``.

Chessboard: ``cv2.findChessboardCorners`` (adaptive threshold) refined by ``cv2.cornerSubPix`` (half
window 5 px, smaller on small squares), falling back to ``cv2.findChessboardCornersSB``. The order is
then made the one of capture@1 in every image: the rows run left to right with the columns top to
bottom in the un-mirrored view (handedness), and the square inside C00 is the black one (the half
turn, from the colours of all inner squares); an image whose square colours do not tell is refused.
Tags: ``cv2.aruco.ArucoDetector`` finds and decodes the markers; by default (``subpix``) each corner
is then refined by ``cv2.cornerSubPix`` on the linearized image (inverse sRGB, float) with a half
window of half a tag cell (2 to 5 px): on gamma-encoded images OpenCV's own ``CORNER_REFINE_SUBPIX``
sits ~0.5 px inside the black square on each axis (measured on the rendered test scene: 0.71 px median
off; linearized: 0.21 px). Video: every frame is tracked (:mod:`mirror_fg.vision.tracking`: KLT, then
refinement onto the feature) and re-detected; fiducials that detection misses are carried as corners.
``track:`` points are followed through a video or through ``images`` in list order (a photo sequence),
each refined by its ``feature`` kind; a cut track is named, with the reason, in the next kept image's
report.

Noise of tracked points: dataset@1 has one ``pixel_sigma``. Each track has its own sigma (the
``track:`` entry's ``sigma``, else :meth:`~mirror_fg.vision.tracking.PointTracker.sigma`, never below
0.5 px, the default ``pixel_sigma``); ``detect_capture(..., tracks=...)`` hands back every track's
path, residuals and sigma for the report.
"""
from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mirror_fg.io.capture import (
    EACH,
    MAX_IMAGE_PIXELS,
    Capture,
    ChessboardTarget,
    ImageEntry,
    PointsTarget,
    TagTarget,
    _name,
    native_stderr,
    open_video,
)
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import DATASET_FORMAT
from mirror_fg.vision.tracking import SRGB_TO_LINEAR, KLTParams, PointTracker, Track

__all__ = [
    "ImageReport",
    "Detection",
    "detect_chessboard",
    "detect_tags",
    "detect_capture",
    "format_reports",
    "FOUND",
    "NOT_FOUND",
    "REFUSED",
    "MAX_IMAGE_PIXELS",
]

FOUND, NOT_FOUND, REFUSED = "found", "not found", "refused"

#: cornerSubPix half window (pixels) for chessboard corners, and its cap as a fraction of the
#: smallest corner spacing (the window must stay inside the four squares around a corner).
SUBPIX_HALF_WINDOW = 5
SUBPIX_MAX_FRACTION = 0.25
#: Square colours decide the board's half turn only when at least this fraction of the inner squares
#: is darker (or lighter) than its neighbours as its parity predicts...
COLOUR_AGREEMENT = 0.9
#: ... and squares differ from their neighbours by this many grey levels (of 255) on average.
COLOUR_CONTRAST = 10.0
#: A chessboard detection is refused as false when its undistorted corners miss the best plane
#: homography by more than this (RMS pixels, and fraction of the corner spacing, whichever is larger).
GRID_MISFIT_MIN_PX, GRID_MISFIT_FRACTION = 2.0, 0.1
#: Tag corner refinement: half window as a fraction of a tag cell, and its bounds (pixels).
TAG_WINDOW_FRACTION = 0.5
TAG_WINDOW_MIN, TAG_WINDOW_MAX = 2, 5
#: An image whose format Pillow cannot read from its header (so its size is unknown before decoding)
#: is decoded by OpenCV only up to this file size (bytes), which bounds what it can expand to.
MAX_UNSIZED_IMAGE_BYTES = 4 << 20

_REFINEMENT = {
    "subpix": "CORNER_REFINE_SUBPIX",
    "contour": "CORNER_REFINE_CONTOUR",
    "apriltag": "CORNER_REFINE_APRILTAG",
    "none": "CORNER_REFINE_NONE",
}


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


@dataclass
class Detection:
    """Observations (name -> pixel (2,)) in one image, or None with the status and reason."""

    points: dict[str, np.ndarray] = field(default_factory=dict)
    status: str = FOUND
    reason: str = ""


def format_reports(reports: list[ImageReport]) -> str:
    """Per-image lines and a closing count, for printing."""
    counts = {s: sum(r.status == s for r in reports) for s in (FOUND, NOT_FOUND, REFUSED)}
    lines = [r.line() for r in reports]
    lines.append(
        f"{len(reports)} image{'s' if len(reports) != 1 else ''}: {counts[FOUND]} found, "
        f"{counts[NOT_FOUND]} not found, {counts[REFUSED]} refused"
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# Detectors on one grayscale image
# --------------------------------------------------------------------------------------------------


def _unflip(points: np.ndarray, width: int) -> np.ndarray:
    out = np.array(points, dtype=np.float64, copy=True)
    out[..., 0] = width - 1 - out[..., 0]
    return out


def detect_chessboard(
    gray: np.ndarray, board: ChessboardTarget, mirrored: bool, camera: dict[str, Any] | None = None
) -> Detection:
    """Inner corners of ``board`` in capture@1 order (C00 first), or a not-found/refused Detection.

    ``mirrored``: the board is seen through an odd number of mirrors (detect on the flipped image).
    ``camera`` (dataset@1 camera dict, optional): when given, a grid whose undistorted corners do not
    fit a plane's homography is refused (a false detection).
    """
    img = cv2.flip(gray, 1) if mirrored else gray
    corners = _find_chessboard(img, board.cols, board.rows)
    if corners is None:
        return Detection(status=NOT_FOUND, reason=f"chessboard {board.cols} x {board.rows} not found")
    grid = corners.reshape(board.rows, board.cols, 2)
    # Handedness: in the un-mirrored view the columns run right and the rows down (x cross y > 0).
    a, b = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:
        grid = grid[:, ::-1]
    first_dark, why = _first_square_dark(img, grid)
    if first_dark is None:
        return Detection(status=REFUSED, reason=f"cannot tell the board's orientation: {why}")
    if not first_dark:
        grid = grid[::-1, ::-1]  # the half turn: C00 is at the black corner square
    pts = grid.reshape(-1, 2)
    if mirrored:
        pts = _unflip(pts, gray.shape[1])
    if camera is not None and camera.get("fx") is not None:
        misfit = _grid_misfit_px(pts, board, camera)
        spacing = _min_spacing(grid)
        if misfit > max(GRID_MISFIT_MIN_PX, GRID_MISFIT_FRACTION * spacing):
            return Detection(status=REFUSED, reason=f"the corners do not lie on a plane grid (homography misfit {misfit:.1f} px)")
    names = [board.name(c, r) for r in range(board.rows) for c in range(board.cols)]
    return Detection(points={n: p.astype(np.float64) for n, p in zip(names, pts)})


def _min_spacing(grid: np.ndarray) -> float:
    """Smallest distance between neighbouring corners of a (rows, cols, 2) grid (pixels)."""
    return min(
        float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
        float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()),
    )


def _grid_misfit_px(pixels: np.ndarray, board: ChessboardTarget, camera: dict[str, Any]) -> float:
    """RMS distance (pixels, at the focal length) of the undistorted corners from the best homography."""
    K = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
    dist = np.asarray(camera.get("dist", [0.0] * 5), dtype=np.float64)
    normalized = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    model = np.array([[c, r] for r in range(board.rows) for c in range(board.cols)], dtype=np.float64)
    H, _ = cv2.findHomography(model, normalized, 0)
    if H is None:
        return float("inf")
    fitted = cv2.perspectiveTransform(model[None], H)[0]
    return float(np.sqrt(np.mean(np.sum((fitted - normalized) ** 2, axis=1)))) * float(camera["fx"])


def _find_chessboard(img: np.ndarray, cols: int, rows: int) -> np.ndarray | None:
    """(rows*cols, 2) corners in OpenCV's order (rows of ``cols``), or None."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(img, (cols, rows), flags=flags)
    if ok:
        spacing = _min_spacing(corners.reshape(rows, cols, 2))
        half = int(max(2, min(SUBPIX_HALF_WINDOW, np.floor(SUBPIX_MAX_FRACTION * spacing))))
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        corners = cv2.cornerSubPix(img, corners, (half, half), (-1, -1), criteria)
        return corners.reshape(-1, 2).astype(np.float64)
    sb_flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    ok, corners = cv2.findChessboardCornersSB(img, (cols, rows), flags=sb_flags)
    if ok:
        return corners.reshape(-1, 2).astype(np.float64)
    return None


def _first_square_dark(img: np.ndarray, grid: np.ndarray) -> tuple[bool | None, str]:
    """Is the inner square between corners (0, 0) and (1, 1) dark? Decided from all inner squares.

    Samples each square's middle through the homography of the corner grid and checks that the
    squares alternate as a chessboard must; returns ``(None, reason)`` when they do not.
    """
    rows, cols = grid.shape[:2]
    gx, gy = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    H, _ = cv2.findHomography(np.stack([gx.ravel(), gy.ravel()], 1), grid.reshape(-1, 2), 0)
    if H is None:
        return None, "the corners do not form a plane grid"
    offsets = np.linspace(-0.2, 0.2, 5)
    ox, oy = np.meshgrid(offsets, offsets)
    ci, cj = np.meshgrid(np.arange(cols - 1) + 0.5, np.arange(rows - 1) + 0.5)  # square middles, row-major
    sx = (ci.ravel()[:, None] + ox.ravel()[None, :]).astype(np.float64)
    sy = (cj.ravel()[:, None] + oy.ravel()[None, :]).astype(np.float64)
    pts = cv2.perspectiveTransform(np.stack([sx.ravel(), sy.ravel()], 1)[None], H)[0]
    samples = cv2.remap(
        img.astype(np.float32),
        pts[:, 0].astype(np.float32).reshape(1, -1),
        pts[:, 1].astype(np.float32).reshape(1, -1),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    means = samples.reshape(-1, offsets.size**2).mean(axis=1).reshape(rows - 1, cols - 1)
    # Each square against the mean of its 4-neighbours (robust to light falling off across the board).
    padded = np.pad(means, 1, mode="constant", constant_values=np.nan)
    neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
    contrast = means - np.nanmean(neighbours, axis=0)  # < 0: darker than its neighbours
    parity = (np.add.outer(np.arange(rows - 1), np.arange(cols - 1)) % 2).astype(bool)
    signed = np.where(parity, -contrast, contrast)  # all < 0 when the squares of parity 0 are dark
    level = float(np.mean(np.abs(contrast)))
    if level < COLOUR_CONTRAST:
        return None, f"dark and light squares differ by only {level:.1f} grey levels"
    first_dark = float(np.mean(signed)) < 0
    agreement = float(np.mean((signed < 0) == first_dark))
    if agreement < COLOUR_AGREEMENT:
        return None, f"only {100 * agreement:.0f}% of the squares alternate in colour as a chessboard's do"
    return first_dark, ""


def _aruco_detector(target: TagTarget) -> Any:
    params = cv2.aruco.DetectorParameters()
    # "subpix" refines after detection (on the linearized image), so the detector itself does not.
    method = "none" if target.corner_refinement == "subpix" else target.corner_refinement
    params.cornerRefinementMethod = int(getattr(cv2.aruco, _REFINEMENT[method]))
    dictionary = cv2.aruco.getPredefinedDictionary(target.dictionary_id)
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_tags(gray: np.ndarray, target: TagTarget, mirrored: bool, detector: Any = None) -> Detection:
    """Corners ``T{id}_{k}`` of the listed tags found in ``gray``, or a not-found Detection.

    A listed id seen more than once is left out (which copy is the target is unknown).
    """
    detector = detector if detector is not None else _aruco_detector(target)
    img = cv2.flip(gray, 1) if mirrored else gray
    corners, ids, _ = detector.detectMarkers(img)
    if ids is None or len(ids) == 0:
        return Detection(status=NOT_FOUND, reason=f"no {target.dictionary} tag found")
    found: dict[int, list[np.ndarray]] = {}
    for tag_id, c in zip(ids.ravel().tolist(), corners):
        found.setdefault(int(tag_id), []).append(np.asarray(c, dtype=np.float64).reshape(4, 2))
    listed = {i: cs for i, cs in found.items() if i in target.tags}
    twice = sorted(i for i, cs in listed.items() if len(cs) > 1)
    points: dict[str, np.ndarray] = {}
    refine_on = None
    if target.corner_refinement == "subpix" and any(i not in twice for i in listed):
        refine_on = SRGB_TO_LINEAR[img] if target.image_gamma == "srgb" else img.astype(np.float32)
    for tag_id in sorted(listed):
        if tag_id in twice:
            continue
        c = listed[tag_id][0]
        if refine_on is not None:
            c = _refine_tag_corners(refine_on, c, target)
        if mirrored:
            c = _unflip(c, gray.shape[1])
        for k in range(4):
            points[TagTarget.corner_name(tag_id, k)] = c[k]
    notes = []
    if twice:
        notes.append(f"tag{'s' if len(twice) > 1 else ''} {_ids(twice)} seen more than once, left out")
    if not points:
        unlisted = sorted(set(found) - set(target.tags))
        if unlisted and not twice:
            reason = f"only tags not in target.tags seen ({_ids(unlisted)}; listed: {_ids(sorted(target.tags))})"
        else:
            reason = "; ".join(notes) or "no listed tag found"
        return Detection(status=NOT_FOUND, reason=reason)
    return Detection(points=points, reason="; ".join(notes))


def _refine_tag_corners(image: np.ndarray, corners: np.ndarray, target: TagTarget) -> np.ndarray:
    """cv2.cornerSubPix on the four corners (4, 2) of one tag, half window ~half a tag cell."""
    import math

    side = float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))
    bits = cv2.aruco.getPredefinedDictionary(target.dictionary_id).markerSize + 2  # data bits + black border
    half = int(min(TAG_WINDOW_MAX, max(TAG_WINDOW_MIN, math.floor(TAG_WINDOW_FRACTION * side / bits))))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    refined = cv2.cornerSubPix(image, corners.reshape(-1, 1, 2).astype(np.float32), (half, half), (-1, -1), criteria)
    return refined.reshape(4, 2).astype(np.float64)


def _ids(ids: list[int], limit: int = 8) -> str:
    text = ", ".join(str(i) for i in ids[:limit])
    return text + (", ..." if len(ids) > limit else "")


class _Detector:
    """The capture's detector bound to its target and mirror parity."""

    def __init__(self, capture: Capture, camera: dict[str, Any]):
        self.capture = capture
        self.camera = camera
        self.target = capture.target
        self.aruco = _aruco_detector(self.target) if isinstance(self.target, TagTarget) else None

    def __call__(self, gray: np.ndarray) -> Detection:
        if isinstance(self.target, ChessboardTarget):
            return detect_chessboard(gray, self.target, self.capture.mirrored, self.camera)
        if isinstance(self.target, TagTarget):
            return detect_tags(gray, self.target, self.capture.mirrored, self.aruco)
        return Detection(status=NOT_FOUND, reason="a points target detects nothing")


# --------------------------------------------------------------------------------------------------
# Whole capture
# --------------------------------------------------------------------------------------------------


@dataclass
class _Output:
    """A kept image before its ``each`` placements get their integers."""

    id: str
    configs: tuple[Any, ...]
    points: dict[str, np.ndarray]


def detect_capture(
    capture: Capture, progress: bool = True, tracks: dict[str, Track] | None = None
) -> tuple[dict[str, Any], list[ImageReport]]:
    """Detect the target in every image (or video frame) of ``capture``.

    Returns the dataset@1 dictionary (camera as a pixel model, fiducials in the base frame, images with
    ids = file stems or ``stem:frame``, ``each`` placements expanded into fresh integers) and one
    :class:`ImageReport` per image/frame in capture order. ``progress`` shows a tqdm bar on stderr when
    it is a terminal. An image that cannot be decoded, or is above MAX_IMAGE_PIXELS, is refused with the
    reason. ``tracks`` (optional, filled in): every ``track:`` point's :class:`~mirror_fg.vision.tracking.Track`
    (kind, history of KLT and refined pixels with residuals; ``.sigma()``). Raises DatasetError when no
    image is kept, or the video cannot be read.
    """
    camera = dict(capture.camera)
    outputs: list[_Output] = []
    reports: list[ImageReport] = []
    show = bool(progress) and sys.stderr.isatty()
    gamma = getattr(capture.target, "image_gamma", "srgb")
    tracker = PointTracker(KLTParams(), default_kind="corner", image_gamma=gamma)
    if capture.images is not None:
        _detect_images(capture, camera, outputs, reports, show, tracker)
    else:
        _detect_video(capture, camera, outputs, reports, show, tracker)
    if tracks is not None:
        tracks.update({name: t for name, t in tracker.tracks.items() if name in capture.track})

    if not outputs:
        reasons = "; ".join(r.line() for r in reports[:3]) + ("; ..." if len(reports) > 3 else "")
        raise DatasetError(f"{capture.source}: the target was found in none of the {len(reports)} images ({reasons})")
    if camera.get("width") is None or camera.get("height") is None:
        raise DatasetError(f"{capture.source}: camera: no image size (give width and height)")

    fiducials = capture.fiducials()
    return {
        "format": DATASET_FORMAT,
        "num_mirrors": capture.num_mirrors,
        "camera": camera,
        "pixel_sigma": capture.pixel_sigma,
        "fiducials": {name: [float(x) for x in p] for name, p in fiducials.items()},
        "images": [
            {
                "id": out.id,
                "mirror_configs": configs,
                "observations": {name: [float(p[0]), float(p[1])] for name, p in out.points.items()},
            }
            for out, configs in zip(outputs, _expand_each(capture, outputs))
        ],
    }, reports


def _expand_each(capture: Capture, outputs: list[_Output]) -> list[list[int]]:
    """``each`` -> fresh integers per mirror, above every integer the capture uses for that mirror."""
    declared: list[tuple[Any, ...]] = (
        [e.mirror_configs for e in capture.images] if capture.images is not None
        else [s.mirror_configs for s in capture.video.segments]  # type: ignore[union-attr]
    )
    next_free = [
        1 + max((c[l] for c in declared if c[l] != EACH), default=-1) for l in range(capture.num_mirrors)
    ]
    result = []
    for out in outputs:
        configs = []
        for l, m in enumerate(out.configs):
            if m == EACH:
                m = next_free[l]
                next_free[l] += 1
            configs.append(int(m))
        result.append(configs)
    return result


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


def _detect_images(
    capture: Capture, camera: dict[str, Any], outputs: list[_Output], reports: list[ImageReport], show: bool,
    tracker: PointTracker,
) -> None:
    """Each image detected on its own; ``track:`` points followed through the images in list order."""
    detector = _Detector(capture, camera)
    entries: list[ImageEntry] = capture.images or []
    starts = _track_starts(capture)
    cuts: list[str] = []
    with _progress(len(entries), "image", show) as bar:
        for index, entry in enumerate(entries):
            det = _detect_entry(entry, detector, capture, camera)
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
                outputs.append(_Output(entry.id, entry.mirror_configs, det.points))
                reports.append(ImageReport(entry.id, FOUND, det.reason, len(det.points)))
            else:
                status = det.status if det.status != FOUND else NOT_FOUND
                reports.append(ImageReport(entry.id, status, det.reason or "no observations"))
            bar.update(1)


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
    det = detector(gray)
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
    capture: Capture, camera: dict[str, Any], outputs: list[_Output], reports: list[ImageReport], show: bool,
    tracker: PointTracker,
) -> None:
    video = capture.video
    assert video is not None
    detector = _Detector(capture, camera)
    fiducial_names = set(capture.target.target_points())
    starts = _track_starts(capture)
    cuts: list[str] = []
    where = f"{capture.source}: video ({_name(os.path.basename(video.file))})"
    vc = open_video(video.file, where)
    total = sum(s.last - s.first + 1 for s in video.segments)
    position = 0  # index of the next frame vc.read() returns
    last_read = -2
    try:
        with _progress(total, "frame", show) as bar:
            for seg in video.segments:
                while position < seg.first:
                    with native_stderr():
                        grabbed = vc.grab()
                    if not grabbed:
                        break
                    position += 1
                if seg.first != last_read + 1:
                    tracker.reset()  # a gap in the frames: tracks cannot carry over
                outputs_of_seg = set(seg.output_frames())
                for frame in range(seg.first, seg.last + 1):
                    frame_id = f"{video.stem}:{frame}"
                    with native_stderr() as native:
                        ok, image = vc.read() if position == frame else (False, None)
                    if not ok:
                        why = f"frame could not be read from the video{native.detail}"
                        for f in range(frame, seg.last + 1):
                            if f in outputs_of_seg:
                                reports.append(ImageReport(f"{video.stem}:{f}", NOT_FOUND, why))
                        bar.update(seg.last + 1 - frame)
                        tracker.reset()
                        break
                    position += 1
                    last_read = frame
                    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
                    mismatch = _check_size(gray, camera)
                    if mismatch:
                        raise DatasetError(f"{where}: {mismatch}")
                    cuts += _cut_notes(tracker, tracker.step(gray, index=frame), capture)
                    det = detector(gray)
                    for name, p in det.points.items():
                        tracker.set(name, p, kind="corner")  # tag and chessboard corners
                    _start_tracks(tracker, starts.get(frame, []))
                    bar.update(1)
                    if frame not in outputs_of_seg:
                        continue
                    points = {n: p.copy() for n, p in tracker.points.items()}
                    if not points:
                        reports.append(ImageReport(frame_id, det.status if det.status != FOUND else NOT_FOUND,
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
                    outputs.append(_Output(frame_id, seg.mirror_configs, points))
                    reports.append(ImageReport(frame_id, FOUND, "; ".join(notes), len(points)))
    finally:
        vc.release()
