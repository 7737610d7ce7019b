"""Live sessions (``mirror-fg live``): calibrate while the user moves the mirror (docs/formats.md, "Live sessions").

Per frame: detect the target (mirror-imaged, as ``detect``), then judge the frame:

- **not found**: fewer than four fiducials detected;
- **skipped, moving**: its corners moved more than ``MOTION_PX`` (mean) since the previous frame, so the
  mirror is still being moved (and the frame may be motion-blurred);
- **skipped, blurred**: its sharpness (variance of the Laplacian) is below ``BLUR_FRACTION`` of the
  added frames' median;
- **skipped, same placement**: its corners lie within ``SAME_PLACEMENT_PX`` (mean) of an added frame's:
  the mirror has not moved, so the frame adds nothing;
- **added**: a new placement of the mirror, given to the incremental (iSAM2) estimate; **refused** when
  the estimate's consensus leaves it out (with the reason, e.g. the board seen from behind).

After each added frame the 3-sigma bounds of ``T_base_cam`` and the next suggestion
(:mod:`mirror_fg.solver.information.suggest`) are updated; the session is ``done`` once every bound given by
``target_mm`` / ``target_deg`` is met. Before the analytical solution exists the frame's reason says
what the estimate waits for; degenerate motion (every placement tilted about one axis) is said too.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import cv2
import numpy as np

from mirror_fg.core.camera import camera_from_dict
from mirror_fg.core.errors import DatasetError, MirrorFgError, SolveError
from mirror_fg.core.transform import Transform
from mirror_fg.io.capture import Capture
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Calibration
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator
from mirror_fg.solver.start.pnp import pnp_candidates
from mirror_fg.solver.information.suggest import Reach, Suggestion
from mirror_fg.vision.detect import _Detector
from mirror_fg.vision.detectors import FOUND

__all__ = ["LiveSession", "FrameRecord", "LiveState", "next_state", "MOTION_PX", "SAME_PLACEMENT_PX", "BLUR_FRACTION"]

#: Mean corner motion (pixels) between consecutive frames above which the mirror is moving.
MOTION_PX = 1.5
#: Mean corner distance (pixels) to an added frame below which a frame shows the same placement.
SAME_PLACEMENT_PX = 6.0
#: Sharpness below this fraction of the added frames' median is a blurred frame.
BLUR_FRACTION = 0.5
#: Fiducials a frame needs (a unique PnP).
MIN_FIDUCIALS = 4
#: Placements the analytical solution needs (three of one mirror, Sect. 5).
MIN_PLACEMENTS = 3
#: Every placement is tilted about one axis (eqs. 14-15 degenerate) when the pairwise rotation axes
#: of the virtual views, weighted by the sines of their angles, spread less than this (the ratio of
#: their second to first singular value, ~ the tangent of the spread).
SAME_AXIS_SPREAD = 0.15
ONE_AXIS = ("every placement so far is tilted about one axis (the mirror normals lie in one plane): tilt the "
            "mirror in another direction")


@dataclass
class FrameRecord:
    """One JSON line of ``--json-lines`` (docs/formats.md, "Live sessions")."""

    frame: int
    t: float
    status: str
    reason: str = ""
    placements: int = 0
    sigma3_base_cam: dict | None = None
    next: dict | None = None
    done: bool = False

    def to_json(self) -> str:
        return json.dumps({"frame": self.frame, "t": round(self.t, 4), "status": self.status, "reason": self.reason,
                           "placements": self.placements, "sigma3_base_cam": self.sigma3_base_cam,
                           "next": self.next, "done": self.done})


@dataclass
class _Added:
    frame: int
    points: dict[str, np.ndarray]


@dataclass
class LiveState:
    """What the web page shows, replaced as a whole after each frame (read by the server thread)."""

    seq: int = 0
    status: dict = field(default_factory=dict)
    jpeg: bytes = b""


class LiveSession:
    """One mirror moved by hand in front of one camera (``num_mirrors`` 1), calibrated as frames arrive."""

    def __init__(self, capture: Capture, *, target_mm: float | None = None, target_deg: float | None = None,
                 on_added: Callable[[int, np.ndarray], None] | None = None, reach: Reach | None = None,
                 picture: bool = False):
        if capture.cameras:
            raise DatasetError(f"{capture.source}: cameras: a live session calibrates one camera (give camera)")
        if capture.num_mirrors != 1:
            raise DatasetError(f"{capture.source}: num_mirrors is {capture.num_mirrors}: a live session moves one mirror "
                               "(num_mirrors: 1)")
        self.capture = capture
        self.camera_dict = dict(capture.camera)
        self.detector = _Detector(capture, self.camera_dict)
        # The target read as not mirror-imaged: its printed face turned away from the mirror (from behind).
        self.behind = _Detector(replace(capture, num_mirrors=2), self.camera_dict)
        self.target_mm, self.target_deg = target_mm, target_deg
        self.on_added, self.reach, self.picture = on_added, reach, picture
        self.fiducials = capture.fiducials()
        self.calibrator: IncrementalCalibrator | None = None  # made at the first frame (its size)
        self.added: list[_Added] = []
        self.previous: dict[str, np.ndarray] | None = None
        self.sharpness: list[float] = []
        self.calibration: Calibration | None = None
        self.sigma3: dict | None = None
        self.suggestion: Suggestion | None = None
        self.counts: dict[str, int] = {}
        self.done = False
        self.began: float | None = None
        self.current_tilt: tuple[float, float] | None = None
        self._virtual_rotations: list[np.ndarray] = []  # each added frame's virtual-view A (PnP)
        self._view: tuple[np.ndarray, np.ndarray] | None = None  # this frame's PnP, once computed
        self.state = LiveState()
        self._last_picture = 0.0

    # --- per frame ---------------------------------------------------------------------------------

    def process(self, index: int, gray: np.ndarray) -> FrameRecord:
        """Judge one frame, add it when it is a new placement; the frame's record."""
        now = time.monotonic()
        self.began = now if self.began is None else self.began
        self._start(gray)
        status, reason, detection = self._judge(index, gray)
        record = FrameRecord(index, now - self.began, status, reason, len(self.added), self.sigma3,
                             self.suggestion.to_dict() if self.suggestion is not None else None, self.done)
        self.counts[status] = self.counts.get(status, 0) + 1
        if self.picture:
            self._publish(record, gray, detection)
        return record

    def _start(self, gray: np.ndarray) -> None:
        if self.calibrator is not None:
            return
        height, width = gray.shape[:2]
        if self.camera_dict.get("width") is None:
            self.camera_dict.update(width=width, height=height)
        elif (self.camera_dict["width"], self.camera_dict["height"]) != (width, height):
            raise DatasetError(f"{self.capture.source}: the source's frames are {width} x {height} pixels, the camera's "
                               f"{self.camera_dict['width']} x {self.camera_dict['height']}")
        self.camera = camera_from_dict(self.camera_dict, f"{self.capture.source}: camera")
        dataset = Dataset(num_mirrors=1, camera=self.camera, pixel_sigma=self.capture.pixel_sigma,
                          fiducials=self.fiducials, images=[], source=self.capture.source)
        self.calibrator = IncrementalCalibrator(dataset, points=())

    def _judge(self, index: int, gray: np.ndarray) -> tuple[str, str, dict[str, np.ndarray]]:
        detection = self.detector(gray)
        points = {n: p for n, p in detection.points.items() if n in self.fiducials} if detection.status == FOUND else {}
        previous, self.previous = self.previous, points or None
        if len(points) < MIN_FIDUCIALS:
            if len(points) == 0 and len(self.behind(gray).points) >= MIN_FIDUCIALS:
                return "not found", ("the board is seen from behind (it reads unmirrored through the mirror): turn its "
                                     "printed face towards the mirror"), points
            return "not found", detection.reason or f"{len(points)} fiducials found, {MIN_FIDUCIALS} needed", points
        self._view = None
        if self.picture and self.calibration is not None:  # only the page shows the mirror's tilt now
            self._track_tilt(points)
        moved = _mean_distance(points, previous)
        if moved is None or moved > MOTION_PX:
            return "skipped", ("moving" if moved is not None else "first sight") + (
                f" ({moved:.1f} px since the last frame): hold the mirror still" if moved is not None else
                ": hold the mirror still"), points
        sharp = float(cv2.Laplacian(gray[::2, ::2], cv2.CV_32F).var())
        if self.sharpness and sharp < BLUR_FRACTION * float(np.median(self.sharpness)):
            return "skipped", f"blurred (sharpness {sharp:.0f}, the added frames' median {np.median(self.sharpness):.0f})", points
        for added in self.added:
            distance = _mean_distance(points, added.points)
            if distance is not None and distance < SAME_PLACEMENT_PX:
                return "skipped", (f"same placement as frame {added.frame} ({distance:.1f} px): tilt or move the mirror "
                                   "to a new placement"), points
        return self._add(index, gray, points, sharp)

    def _add(self, index: int, gray: np.ndarray, points: dict[str, np.ndarray], sharp: float):
        assert self.calibrator is not None
        image_id = f"frame{index:06d}"
        refused_before = len(self.calibrator.excluded)
        try:
            calibration = self.calibrator.add_image({"id": image_id, "mirror_configs": [len(self.added)],
                                                     "observations": {n: [float(p[0]), float(p[1])] for n, p in points.items()}})
        except MirrorFgError as error:
            return "refused", str(error), points
        refusals = [e for e in self.calibrator.excluded[refused_before:] if e.image == image_id and e.point is None]
        if refusals:
            return "refused", refusals[0].reason, points
        self.added.append(_Added(index, points))
        if self.on_added is not None:  # e.g. --save: the frame is written now, not at the end
            self.on_added(index, gray)
        self.sharpness.append(sharp)
        view = self._virtual_view(points)
        if view is not None:
            self._virtual_rotations.append(view[0])
        reason = ""
        if calibration is not None:
            self.calibration = calibration
            self._update_bounds(calibration)
            reason = ONE_AXIS if self._one_axis() else ""
        else:
            reason = self._waiting_reason()
        return "added", reason, points

    def _update_bounds(self, calibration: Calibration) -> None:
        assert self.calibrator is not None
        if calibration.covariance is not None:
            base_cam = Transform(calibration.R_cam_base, calibration.t_cam_base).inverse_covariance(calibration.covariance)
            sigma = np.sqrt(np.maximum(np.diag(base_cam), 0.0))
            self.sigma3 = {"rotation_deg": [float(x) for x in np.degrees(3 * sigma[:3])],
                           "position_mm": [float(x) for x in 3000 * sigma[3:]]}
            self.done = self._targets_met()
        try:
            ranked = self.calibrator.suggest_next(count=1, reach=self.reach).suggestions
        except MirrorFgError:
            ranked = []
        self.suggestion = ranked[0] if ranked else None

    def _targets_met(self) -> bool:
        if self.sigma3 is None or (self.target_mm is None and self.target_deg is None):
            return False
        ok = self.target_mm is None or max(self.sigma3["position_mm"]) <= self.target_mm
        return ok and (self.target_deg is None or max(self.sigma3["rotation_deg"]) <= self.target_deg)

    def _waiting_reason(self) -> str:
        """Why there is no estimate yet, in the user's words."""
        assert self.calibrator is not None
        if len(self.added) < MIN_PLACEMENTS:
            return (f"waiting for the analytical start: {len(self.added)} of {MIN_PLACEMENTS} mirror placements; "
                    "tilt the mirror a different way for each")
        if self._one_axis():
            return ONE_AXIS
        error = self.calibrator.startup_error
        return f"waiting for the analytical start: {error}" if error is not None else "waiting for the analytical start"

    # --- the mirror's tilt in each frame (once the pose is known), and degenerate motion -------------

    def _virtual_view(self, points: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        """PnP of this frame (eqs. 10-12): its virtual view ``(A, b)``, computed once per frame, only for the
        frames that need it (added, or drawn on the page once there is an estimate)."""
        if self._view is None:
            names = list(points)
            base = np.array([self.fiducials[n] for n in names])
            candidates = pnp_candidates(base, self.camera.normalize(np.array([points[n] for n in names])), 1)
            self._view = candidates[0] if candidates else None
        return self._view

    def _track_tilt(self, points: dict[str, np.ndarray]) -> None:
        """The mirror of this frame with the estimate: ``v = (b - M t) / 2`` where ``M = A R^T`` (eqs. 5-8
        with one mirror)."""
        assert self.calibration is not None
        view = self._virtual_view(points)
        if view is None:
            self.current_tilt = None
            return
        A, b = view
        M = A @ self.calibration.R_cam_base.T
        self.current_tilt = _tilt(0.5 * (b - M @ self.calibration.t_cam_base))

    def _placement_tilts(self) -> list[tuple[float, float]]:
        """(tilt, azimuth) in degrees of every placement the estimate holds."""
        if self.calibration is None:
            return []
        return [_tilt(v) for v in self.calibration.mirror_vectors.values()]

    def _one_axis(self) -> bool:
        """Whether the added placements are all tilted about one axis: ``A_i A_j^T = M_i M_j`` turns
        about ``n_i x n_j``, and those axes are all parallel when the normals lie in one plane."""
        rotations = self._virtual_rotations
        if len(rotations) < MIN_PLACEMENTS:
            return False
        axes = []  # 2 sin(angle) times the unit axis of each pair's relative rotation
        for i in range(len(rotations)):
            for j in range(i + 1, len(rotations)):
                D = rotations[i] @ rotations[j].T
                axes.append([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
        singular = np.linalg.svd(np.array(axes), compute_uv=False)
        return bool(singular[0] > 1e-9 and singular[1] < SAME_AXIS_SPREAD * singular[0])

    # --- the page's state ------------------------------------------------------------------------------

    def _publish(self, record: FrameRecord, gray: np.ndarray, points: dict[str, np.ndarray]) -> None:
        status = json.loads(record.to_json())
        status.update(targets={"mm": self.target_mm, "deg": self.target_deg}, placements_tilt=self._placement_tilts(),
                      current_tilt=self.current_tilt, counts=dict(self.counts),
                      next_words=self.suggestion.words(max(self.sigma3["position_mm"])) if (
                          self.suggestion is not None and self.sigma3 is not None) else None)
        self.state, self._last_picture = next_state(self.state, status, gray, points, self._last_picture)

    # --- the end -----------------------------------------------------------------------------------

    def result(self) -> Calibration:
        """The final estimate over every added frame (``calibration(full=True)``)."""
        if self.calibrator is None or self.calibration is None:
            have = len(self.added)
            raise SolveError(f"{self.capture.source}: no estimate: {have} mirror placement(s) added, the analytical "
                             f"start needs {MIN_PLACEMENTS} tilted different ways")
        return self.calibrator.calibration(full=True)

    def summary(self) -> str:
        counts = ", ".join(f"{n} {status}" for status, n in sorted(self.counts.items()))
        return f"{sum(self.counts.values())} frames: {counts}; {len(self.added)} placements"

def next_state(state: LiveState, status: dict, gray: np.ndarray, points: dict[str, np.ndarray],
               last_picture: float) -> tuple[LiveState, float]:
    """The page's next :class:`LiveState` after a frame whose ``status`` (a record's JSON and the page's
    fields) and detections ``points`` are given, and the time of its picture: a new picture (the frame with
    its detections, green added, orange skipped, red otherwise) at most ~10 times a second."""
    now = time.monotonic()
    jpeg = state.jpeg
    if now - last_picture > 0.1 or not jpeg:  # at most ~10 pictures a second
        picture = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        kind = status.get("status")
        colour = (0, 200, 0) if kind == "added" else (0, 200, 255) if kind == "skipped" else (0, 0, 255)
        for p in points.values():
            cv2.circle(picture, (int(round(p[0])), int(round(p[1]))), 4, colour, 2)
        jpeg = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()
        last_picture = now
    return LiveState(state.seq + 1, status, jpeg), last_picture


def _tilt(mirror_vector: np.ndarray) -> tuple[float, float]:
    """Tilt from the optical axis and azimuth in the image (degrees) of a mirror vector (camera frame)."""
    v = np.asarray(mirror_vector, dtype=float)
    return (float(np.degrees(np.arccos(np.clip(v[2] / np.linalg.norm(v), -1.0, 1.0)))),
            float(np.degrees(np.arctan2(v[1], v[0])) % 360.0))


def _mean_distance(a: dict[str, np.ndarray], b: dict[str, np.ndarray] | None) -> float | None:
    """Mean distance (pixels) between the points two detections share; None when they share < half."""
    if not b:
        return None
    shared = [n for n in a if n in b]
    if len(shared) < max(MIN_FIDUCIALS, len(a) // 2):
        return None
    return float(np.mean([np.linalg.norm(a[n] - b[n]) for n in shared]))


def run(session: LiveSession, source: Any, *, on_record: Any = None, stop_when_done: bool = False,
        max_frames: int | None = None) -> dict[str, float]:
    """Feed ``source``'s frames to ``session`` until the source ends (or is stopped), ``done`` with
    ``stop_when_done``, or ``max_frames``; ``on_record(record)`` after each frame. Throughput figures:
    frames, seconds, frames per second, dropped and unreadable frames."""
    began = time.perf_counter()
    frames = 0
    try:
        for index, gray in source.frames():
            record = session.process(index, gray)
            frames += 1
            if on_record is not None:
                on_record(record)
            if (stop_when_done and record.done) or (max_frames is not None and frames >= max_frames):
                break
    finally:
        source.close()
    seconds = time.perf_counter() - began
    return {"frames": frames, "seconds": seconds, "fps": frames / seconds if seconds > 0 else 0.0,
            "dropped": source.dropped, "unreadable": source.unreadable}
