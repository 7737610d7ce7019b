"""Detectors on one grayscale image: a chessboard's inner corners, AprilTag/ArUco tag corners (OpenCV).

Pixels follow OpenCV's convention (the centre of the top-left pixel is (0, 0)). A target seen through
an odd number of mirrors appears mirror-imaged; detectors that need handedness (ArUco/AprilTag
decoding, chessboard ordering) then run on ``cv2.flip(image, 1)`` and every x is mapped back with
``x = width - 1 - x_flipped``.

Chessboard: ``cv2.findChessboardCorners`` (adaptive threshold) refined by ``cv2.cornerSubPix`` (half
window 5 px, smaller on small squares), falling back to ``cv2.findChessboardCornersSB``. The order is
then made the one of capture@1 (:mod:`mirror_fg.io.target`) in every image: the rows run left to right
with the columns top to bottom in the un-mirrored view (handedness), and the square inside C00 is the
black one (the half turn, from the colours of all inner squares); an image whose square colours do not
tell is refused. A symmetric board (``cols + rows`` even) has no such colour cue: its squares must
still alternate, and of its symmetric labellings the detector returns the one showing the board most
upright (C00's row nearest the top of the image); :mod:`mirror_fg.solver.screen.labelling` then chooses
each image's labelling by consistency across the images. Tags: ``cv2.aruco.ArucoDetector`` finds and decodes the markers; by default
(``subpix``) each corner is then refined by ``cv2.cornerSubPix`` on the linearized image (inverse
sRGB, float) with a half window of half a tag cell (2 to 5 px): on gamma-encoded images OpenCV's own
``CORNER_REFINE_SUBPIX`` sits ~0.5 px inside the black square on each axis (measured on the rendered
test scene: 0.71 px median off; linearized: 0.21 px). ChArUco: ``cv2.aruco.CharucoDetector`` finds
the markers and interpolates and refines the chessboard corners between them (saddle points, which
the sRGB gamma does not move); every corner is named by its id, so no ordering is needed, and a
detection whose undistorted corners do not fit a plane is refused like a chessboard's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mirror_fg.core.camera import camera_from_dict
from mirror_fg.io.target import CharucoTarget, ChessboardTarget, TagTarget
from mirror_fg.vision.tracking import SRGB_TO_LINEAR

__all__ = [
    "Detection",
    "detect_chessboard",
    "detect_charuco",
    "charuco_detector",
    "detect_tags",
    "aruco_detector",
    "FOUND",
    "NOT_FOUND",
    "chessboard_size_hint",
    "REFUSED",
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

_REFINEMENT = {
    "subpix": "CORNER_REFINE_SUBPIX",
    "contour": "CORNER_REFINE_CONTOUR",
    "apriltag": "CORNER_REFINE_APRILTAG",
    "none": "CORNER_REFINE_NONE",
}


@dataclass
class Detection:
    """Observations (name -> pixel (2,)) in one image, or None with the status and reason."""

    points: dict[str, np.ndarray] = field(default_factory=dict)
    status: str = FOUND
    reason: str = ""


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
        return Detection(status=NOT_FOUND, reason=f"chessboard of {board.cols} x {board.rows} inner corners not found")
    grid = corners.reshape(board.rows, board.cols, 2)
    # Handedness: in the un-mirrored view the columns run right and the rows down (x cross y > 0).
    a, b = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:
        grid = grid[:, ::-1]
    first_dark, why = _first_square_dark(img, grid)
    if first_dark is None:
        what = "orientation" if not board.symmetric else "squares"
        return Detection(status=REFUSED, reason=f"cannot tell the board's {what}: {why}")
    if not board.symmetric and not first_dark:
        grid = grid[::-1, ::-1]  # the half turn: C00 is at the black corner square
    elif board.cols == board.rows and board.cols % 2 == 1 and not first_dark:
        grid = np.rot90(grid)  # odd square board: a quarter turn brings a dark square to C00 (handedness kept)
    pts = grid.reshape(-1, 2)
    if mirrored:
        pts = _unflip(pts, gray.shape[1])
    names = [board.name(c, r) for r in range(board.rows) for c in range(board.cols)]
    if board.symmetric:
        pts = _upright(pts, names, board)
    model = board.target_points()
    misfit = _plane_misfit(pts, np.array([model[n][:2] for n in names]), _min_spacing(grid), camera)
    if misfit:
        return Detection(status=REFUSED, reason=misfit)
    return Detection(points={n: p.astype(np.float64) for n, p in zip(names, pts)})


def _upright(pts: np.ndarray, names: list[str], board: ChessboardTarget) -> np.ndarray:
    """Corners (N, 2) of a symmetric board in the labelling, among its symmetric ones, that shows it most
    upright: the rows from C00's to the last run down the image (where that is the capture's one
    labelling is chosen across the images, :mod:`mirror_fg.solver.screen.labelling`)."""
    points = dict(zip(names, pts))
    top, bottom = board.top_and_bottom_rows()
    best, best_down = points, -np.inf
    for symmetry in board.symmetries():
        turned = symmetry.relabel(points)
        down = np.mean([turned[n] for n in bottom], axis=0) - np.mean([turned[n] for n in top], axis=0)
        downward = float(down[1]) / max(float(np.linalg.norm(down)), 1e-12)  # cosine with the image's down
        if downward > best_down:
            best, best_down = turned, downward
    return np.array([best[n] for n in names])


def _min_spacing(grid: np.ndarray) -> float:
    """Smallest distance between neighbouring corners of a (rows, cols, 2) grid (pixels)."""
    return min(
        float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
        float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()),
    )


def _plane_misfit(pixels: np.ndarray, board_xy: np.ndarray, spacing_px: float, camera: dict[str, Any] | None) -> str:
    """Why corners (N, 2) pixels are a false detection of the board points ``board_xy`` (N, 2), or ''.

    Refused when :func:`_misfit_px` is above GRID_MISFIT_MIN_PX and GRID_MISFIT_FRACTION of the corner
    spacing ``spacing_px``. Without a camera (``camera`` None or without ``fx``) nothing is checked.
    """
    if camera is None or camera.get("fx") is None:
        return ""
    misfit = _misfit_px(pixels, board_xy, camera)
    if misfit > max(GRID_MISFIT_MIN_PX, GRID_MISFIT_FRACTION * spacing_px):
        return f"the corners do not lie on a plane grid (homography misfit {misfit:.1f} px)"
    return ""


def _grid_misfit_px(pixels: np.ndarray, board: ChessboardTarget, camera: dict[str, Any]) -> float:
    """:func:`_misfit_px` of a chessboard's corners (capture@1 order)."""
    return _misfit_px(pixels, np.array([p[:2] for p in board.target_points().values()]), camera)


def _misfit_px(pixels: np.ndarray, board_xy: np.ndarray, camera: dict[str, Any]) -> float:
    """RMS distance (pixels, at the focal length) of the undistorted corners from the best homography
    of the board points ``board_xy``; inf where the camera model cannot undistort a corner."""
    size = {"width": camera.get("width") or 1, "height": camera.get("height") or 1}  # not used by normalize
    cam = camera_from_dict({**camera, **size}, "camera")
    normalized = cam.normalize(pixels)
    if not np.all(np.isfinite(normalized)):
        return float("inf")
    model = board_xy.astype(np.float64)
    H, _ = cv2.findHomography(model, normalized, 0)
    if H is None:
        return float("inf")
    fitted = cv2.perspectiveTransform(model[None], H)[0]
    return float(np.sqrt(np.mean(np.sum((fitted - normalized) ** 2, axis=1)))) * cam.fx


def chessboard_size_hint(gray: np.ndarray, board: ChessboardTarget, mirrored: bool, image: str = "this image") -> str:
    """When ``board`` is not in ``gray``: a sentence for a board given by its squares instead of its inner
    corners (``cols: 11, rows: 8`` for a 10 x 7-corner board), found by looking for cols - 1 x rows - 1
    corners; else one that says what cols and rows count."""
    counts = "cols and rows count inner corners (where four squares meet), one fewer than the squares along each side"
    if min(board.cols, board.rows) < 3:
        return counts
    img = cv2.flip(gray, 1) if mirrored else gray
    if _find_chessboard(img, board.cols - 1, board.rows - 1) is None:
        return counts
    return (f"{counts}: a board of {board.cols - 1} x {board.rows - 1} inner corners is in {image}; "
            f"did you count squares? (cols: {board.cols - 1}, rows: {board.rows - 1})")


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


#: Fewest ChArUco corners kept from one image (not all on one line).
MIN_CHARUCO_CORNERS = 4


def charuco_detector(target: CharucoTarget) -> Any:
    """A ``cv2.aruco.CharucoDetector`` for ``target``'s board."""
    return cv2.aruco.CharucoDetector(target.board())


def detect_charuco(
    gray: np.ndarray, target: CharucoTarget, mirrored: bool, camera: dict[str, Any] | None = None, detector: Any = None
) -> Detection:
    """ChArUco corners ``C{id:02d}`` found in ``gray``, or a not-found/refused Detection.

    ``mirrored``: seen through an odd number of mirrors (markers decode only on the flipped image).
    ``camera`` (optional): refuse corners whose undistorted positions do not fit a plane's homography.
    """
    detector = detector if detector is not None else charuco_detector(target)
    img = cv2.flip(gray, 1) if mirrored else gray
    corners, ids, _, marker_ids = detector.detectBoard(img)
    found = 0 if ids is None else len(ids)
    if found < MIN_CHARUCO_CORNERS:
        markers = 0 if marker_ids is None else len(marker_ids)
        return Detection(
            status=NOT_FOUND,
            reason=f"ChArUco board: {found} corner{'s' if found != 1 else ''} from {markers} {target.dictionary} "
            f"marker{'s' if markers != 1 else ''} (need {MIN_CHARUCO_CORNERS})",
        )
    ids = ids.ravel().astype(int)
    if target.board().checkCharucoCornersCollinear(ids.reshape(-1, 1).astype(np.int32)):
        return Detection(status=REFUSED, reason=f"the {found} ChArUco corners found lie on one line")
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if mirrored:
        pts = _unflip(pts, gray.shape[1])
    model = target.target_points()
    names = [target.name(int(i)) for i in ids]
    board_xy = np.array([model[n][:2] for n in names])
    spacing = target.square * float(np.median(_nearest(pts) / _nearest(board_xy)))  # pixels per square
    misfit = _plane_misfit(pts, board_xy, spacing, camera)
    if misfit:
        return Detection(status=REFUSED, reason=misfit)
    return Detection(points={n: p.copy() for n, p in zip(names, pts)})


def _nearest(points: np.ndarray) -> np.ndarray:
    """Distance (N,) from each point (N, 2) to its nearest other point."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def aruco_detector(target: TagTarget) -> Any:
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
    detector = detector if detector is not None else aruco_detector(target)
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
