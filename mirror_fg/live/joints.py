"""Live sessions with a robot arm (docs/formats.md, "Live sessions" and "Robot arms"): each frame takes the
arm's joint state from a CSV another program appends to, and the arm's mounts are re-estimated as frames
are added.

**The joint stream** (:class:`JointStream`): the capture's ``joints: {file, max_dt}`` CSV
(``io/joint_table.py``: a header of joint names and an ``image`` or a ``time`` column) is read
incrementally: only complete new lines, from where the last read stopped. A frame is matched by the image
file's name (a folder source) or by its time (seconds: a video's frame ``k`` at ``k / fps``; a camera's
frame at the wall-clock time it was read, seconds since the epoch) to the nearest row within ``max_dt``.
A row not yet written (no row of that name; no row at or after the frame's time) makes the frame wait up
to ``wait_s`` seconds for it; then the frame is skipped with a note. A frame between two equally near rows,
or with none within ``max_dt``, is skipped with that note too.

**The session** (:class:`LiveArmSession`): a mirror placement stands still while the arm moves. Per frame:
no joint state -> ``skipped``; fewer than four fiducials -> ``not found``; the arm moved (any joint by more
than ``JOINT_STILL``) or the corners moved more than ``MOTION_PX`` since the previous frame -> ``skipped``
(moving); the same arm pose and corners as an added frame -> ``skipped`` (same); else ``added``. An added
frame at an arm pose already added in the current placement but showing the target elsewhere means the
mirror was moved: it begins the next placement (so move the mirror with the arm standing at a pose of the
placement before, e.g. its last). Once three placements hold three arm poses each, every added frame
re-solves the arm (``solver/batch/robot_solve.py``) and the camera mount's 3-sigma is the record's bound.
Radians (metres for prismatic joints), pixels, seconds.

**Saved and served** (``--save``, ``--serve``): each added frame goes to ``on_added`` with its placement
and joint states (``live/save.py`` keeps them in the folder's ``joints.csv``); with ``picture`` the page's
state (``live/session.LiveState``) is made after each frame: the record, the camera mount's 3-sigma, arm
poses per placement, each placement's tilt in the camera's frame and the next step in words.
"""
from __future__ import annotations

import csv
import io
import json
import time
from typing import Any, Callable

import numpy as np

from mirror_fg.core.errors import DatasetError, MirrorFgError, SolveError
from mirror_fg.io.capture import Capture
from mirror_fg.io.joint_table import JointTable, parse_header, parse_row
from mirror_fg.live.session import (MIN_FIDUCIALS, MOTION_PX, SAME_PLACEMENT_PX, FrameRecord, LiveState, _mean_distance,
                                    next_state)

__all__ = ["JointStream", "LiveArmSession", "frame_key", "WAIT_S", "JOINT_STILL"]

#: Seconds a frame waits for its joint state's row before it is skipped.
WAIT_S = 0.5
#: Poll interval (seconds) while a frame waits for its row.
POLL_S = 0.02
#: Largest change of any joint (radians or metres) between two frames of an arm standing still.
JOINT_STILL = 1e-3
#: Placements, each with this many arm poses, before the first solve (the analytical start's need).
MIN_PLACEMENTS, MIN_POSES = 3, 3


class JointStream:
    """A joint-state CSV read as it grows (module docstring)."""

    def __init__(self, path: str, name: str, max_dt: float, wait_s: float = WAIT_S):
        self.path, self.name, self.max_dt, self.wait_s = path, name, max_dt, wait_s
        self.table: JointTable | None = None
        self._offset = 0
        self._line = 0
        self._pending = b""
        self._columns: list[str] = []

    def poll(self) -> None:
        """Read the complete lines written since the last call (none where the file does not exist yet)."""
        try:
            with open(self.path, "rb") as handle:
                handle.seek(self._offset)
                chunk = handle.read()
        except FileNotFoundError:
            return
        except OSError as error:
            raise DatasetError(f"joints.file {self.name}: {error.strerror or error}") from None
        self._offset += len(chunk)
        data = self._pending + chunk
        cut = data.rfind(b"\n") + 1  # a line still being written waits for its end
        self._pending = data[cut:]
        for row in csv.reader(io.StringIO(data[:cut].decode("utf-8"))):
            self._line += 1
            if not row:
                continue
            if self.table is None:
                key, joints = parse_header(row, self.name)
                self.table = JointTable(self.name, key, joints)
                self._columns = [c.strip() for c in row]
                continue
            cells = dict(zip(self._columns, row))
            self.table.add(*parse_row(cells, self.table.key, self.table.joints, self.name, self._line), self._line)

    def _ready(self, key: str | float | None) -> bool:
        table = self.table
        if table is None or key is None:
            return False
        if table.key == "image":
            return isinstance(key, str) and key in table.by_image
        return table.last_time is not None and table.last_time >= float(key)

    def lookup(self, key: str | float | None, image: str) -> tuple[dict[str, float] | None, str]:
        """``(joints, "")`` of the frame named or timed ``key``, or ``(None, note)`` where it has none
        (waiting up to ``wait_s`` for its row)."""
        deadline = time.monotonic() + (self.wait_s if key is not None else 0.0)  # nothing to wait for without a key
        self.poll()
        while not self._ready(key) and time.monotonic() < deadline:
            time.sleep(POLL_S)
            self.poll()
        table = self.table
        if table is None:
            return None, f"{self.name} has no header yet: frame skipped"
        if key is None or isinstance(key, str) != (table.key == "image"):
            what = "an image name (a folder source)" if table.key == "image" else "a time (a camera or a video source)"
            return None, f"{self.name} is matched by {what}; this source gives none: frame skipped"
        if table.key == "image":
            if key in table.by_image:
                return dict(table.by_image[key]), ""
            return None, f"{self.name} has no row for {key!r} after {self.wait_s:g} s: frame skipped"
        try:
            joints = dict(table.nearest(float(key), self.max_dt, image))
        except DatasetError as error:
            return None, f"{error}: frame skipped"
        return joints, ""


def frame_key(source: Any, index: int) -> str | float | None:
    """What a frame of ``source`` is matched by: a folder's file name, a camera frame's wall-clock time, a
    video frame's ``index / fps``; None where the source gives neither."""
    import cv2

    if getattr(source, "frame_name", ""):
        return str(source.frame_name)
    if getattr(source, "frame_time", 0.0):
        return float(source.frame_time)
    capture = getattr(source, "capture", None)
    if capture is not None and hasattr(capture, "get"):
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        if fps > 0:
            return index / fps
    return None


class LiveArmSession:
    """A live session of an arm (module docstring): frames with joint states from a growing CSV."""

    def __init__(self, capture: Capture, *, target_mm: float | None = None, target_deg: float | None = None,
                 wait_s: float = WAIT_S, detect: Any = None, source: Any = None,
                 on_added: Callable[[int, np.ndarray, dict[str, Any]], None] | None = None, picture: bool = False):
        fields = capture.robot
        if not fields:
            raise DatasetError(f"{capture.source}: a live session of an arm needs robot and joints: {{file: ...}}")
        if capture.cameras or capture.num_mirrors != 1:
            raise DatasetError(f"{capture.source}: a live session of an arm calibrates one camera through one mirror "
                               "(camera, num_mirrors: 1)")
        self.capture = capture
        self.stream = JointStream(fields["path"], fields["file"], fields["max_dt"], wait_s)
        self.fields = fields
        self.target_mm, self.target_deg = target_mm, target_deg
        self.fiducials = {n: p for n, p in capture.fiducials().items()}
        if detect is None:
            from mirror_fg.live.session import LiveSession

            detect = LiveSession(capture).detector
        self.detect = detect
        self.source = source
        self.camera_dict = dict(capture.camera)
        self.images: list[dict[str, Any]] = []
        self.placement = 0
        self.previous: tuple[dict[str, float], dict[str, np.ndarray]] | None = None
        self.calibration: Any = None
        self.sigma3: dict | None = None
        self.counts: dict[str, int] = {}
        self.done = False
        self.began: float | None = None
        #: Called with each added frame, its picture and its ``{mirror_configs, joints}`` (``--save``).
        self.on_added = on_added
        #: The page's state (``--serve``), made after each frame where ``picture``.
        self.picture = picture
        self.state = LiveState()
        self._last_picture = 0.0
        self._shown: dict[str, np.ndarray] = {}
        self._joints_now: dict[str, float] | None = None
        self._solved: Any = None  # the dataset of the last estimate

    # --- per frame ---------------------------------------------------------------------------------

    def process(self, index: int, gray: np.ndarray, key: str | float | None = None) -> FrameRecord:
        """Judge one frame (``key``: its name or time; default from the bound source), add it when new."""
        now = time.monotonic()
        self.began = now if self.began is None else self.began
        if self.camera_dict.get("width") is None:
            self.camera_dict.update(width=gray.shape[1], height=gray.shape[0])
        if key is None and self.source is not None:
            key = frame_key(self.source, index)
        self._shown, self._joints_now = {}, None
        status, reason = self._judge(index, gray, key)
        self.counts[status] = self.counts.get(status, 0) + 1
        record = FrameRecord(index, now - self.began, status, reason, self.placement + 1 if self.images else 0,
                             self.sigma3, None, self.done)
        if self.picture:
            self._publish(record, gray)
        return record

    def _judge(self, index: int, gray: np.ndarray, key: str | float | None) -> tuple[str, str]:
        joints, note = self.stream.lookup(key, f"frame{index:06d}")
        if joints is None:
            return "skipped", note
        self._joints_now = joints
        detection = self.detect(gray)
        points = {n: np.asarray(p, float) for n, p in detection.points.items() if n in self.fiducials}
        self._shown = points
        previous, self.previous = self.previous, (joints, points)
        if len(points) < MIN_FIDUCIALS:
            return "not found", detection.reason or f"{len(points)} fiducials found, {MIN_FIDUCIALS} needed"
        if previous is not None and _joint_change(joints, previous[0]) > JOINT_STILL:
            return "skipped", "the arm is moving: hold it still"
        moved = _mean_distance(points, previous[1]) if previous is not None else None
        if moved is None or moved > MOTION_PX:
            return "skipped", ("first sight" if moved is None else f"moving ({moved:.1f} px since the last frame)") + \
                ": hold the mirror and the arm still"
        same_pose = [im for im in self.images if _joint_change(joints, im["_joints"]) <= JOINT_STILL]
        for image in same_pose:
            distance = _mean_distance(points, image["_points"])
            if distance is not None and distance < SAME_PLACEMENT_PX:
                return "skipped", f"same arm pose and mirror as {image['id']}: move the arm or the mirror"
        if any(im["mirror_configs"] == [self.placement] for im in same_pose):
            self.placement += 1  # the arm stood still and the target moved in the image: the mirror moved
        image_id = f"frame{index:06d}"
        self.images.append({"id": image_id, "mirror_configs": [self.placement], "joints": joints,
                            "observations": {n: [float(p[0]), float(p[1])] for n, p in points.items()},
                            "_joints": joints, "_points": points})
        if self.on_added is not None:  # e.g. --save: the frame and its joint states are written now
            self.on_added(index, gray, {"mirror_configs": [self.placement], "joints": dict(joints)})
        return "added", self._update()

    def _counts(self) -> list[int]:
        return [sum(im["mirror_configs"] == [k] for im in self.images) for k in range(self.placement + 1)]

    def _update(self) -> str:
        counts = self._counts()
        ready = sum(c >= MIN_POSES for c in counts)
        if ready < MIN_PLACEMENTS:
            return (f"waiting for the start: {ready} of {MIN_PLACEMENTS} mirror placements with {MIN_POSES} arm poses "
                    f"each (this placement: {counts[-1]}); move the arm, then, with the arm still, the mirror")
        from mirror_fg.solver.batch.robot_solve import calibrate_robot

        dataset = self.dataset()
        try:
            calibration = calibrate_robot(dataset)
        except MirrorFgError as error:
            return f"no estimate yet: {error}"
        self.calibration, self._solved = calibration, dataset
        entry = (calibration.robot or {}).get("mounts", {}).get("camera")
        if entry is not None and "sigma3" in entry:
            self.sigma3 = entry["sigma3"]
            ok = self.target_mm is None or max(self.sigma3["position_mm"]) <= self.target_mm
            ok = ok and (self.target_deg is None or max(self.sigma3["rotation_deg"]) <= self.target_deg)
            self.done = ok and (self.target_mm is not None or self.target_deg is not None)
        return ""

    def dataset(self):
        """The dataset@1 of the frames added so far."""
        from mirror_fg.io.dataset import dataset_from_dict

        fields = self.fields
        data = {"format": "mirror-fg/dataset@1", "num_mirrors": 1, "camera": self.camera_dict,
                "pixel_sigma": self.capture.pixel_sigma,
                "fiducials": {n: [float(x) for x in p] for n, p in self.fiducials.items()},
                "robot": fields["robot"], "images": [{k: v for k, v in im.items() if not k.startswith("_")}
                                                     for im in self.images]}
        if fields["mounts"] is not None:
            data["mounts"] = fields["mounts"]
        return dataset_from_dict(data, source=self.capture.source)

    # --- the page's state (--serve) ------------------------------------------------------------------

    def _publish(self, record: FrameRecord, gray: np.ndarray) -> None:
        status = json.loads(record.to_json())
        counts = self._counts() if self.images else []
        status.update(targets={"mm": self.target_mm, "deg": self.target_deg}, placements_tilt=self._placement_tilts(),
                      current_tilt=None, counts=dict(self.counts), next_words=self._next_words(counts),
                      arm={"poses": counts, "joints": self._joints_now})
        self.state, self._last_picture = next_state(self.state, status, gray, self._shown, self._last_picture)

    def _next_words(self, counts: list[int]) -> str:
        """What to do next, in words (the page's "next" line)."""
        if not counts or counts[-1] < MIN_POSES:
            have = counts[-1] if counts else 0
            return (f"move the arm to a new pose and hold it still ({have} of {MIN_POSES} arm poses at this mirror "
                    "placement)")
        return ("move the arm to a new pose and hold it still, or, with the arm still, move the mirror to a new "
                f"placement ({len(counts)} so far; {MIN_PLACEMENTS} with {MIN_POSES} arm poses each start the estimate)")

    def _placement_tilts(self) -> list[tuple[float, float]]:
        """(tilt, azimuth) in degrees of each placement the estimate holds, in the camera's frame at the last
        arm pose of that placement (``robot_views``: ``v_c = (d - n . t_C) R_C^T n``, ``C = F_c(q) M_c``)."""
        if self.calibration is None or self._solved is None:
            return []
        from mirror_fg.factors.robot import compose
        from mirror_fg.live.session import _tilt

        setup = self._solved.robot
        mount = setup.mounts["camera"].known
        entry = (self.calibration.robot or {}).get("mounts", {}).get("camera")
        if entry is not None:
            mount = (np.array(entry["T_link_cam"]["R"], float), np.array(entry["T_link_cam"]["t"], float))
        link = setup.mounts["camera"].link
        tilts = []
        for (_, m), v in sorted(self.calibration.mirror_vectors.items()):
            last = [im for im in self.images if im["mirror_configs"] == [m]]
            if not last or mount is None:
                continue
            F = setup.kinematics.placements(last[-1]["_joints"], [link])[link][0]
            R_C, t_C = compose((F[:3, :3], F[:3, 3]), mount)
            d = float(np.linalg.norm(v))
            n = np.asarray(v, float) / d
            tilts.append(_tilt((d - float(n @ t_C)) * (R_C.T @ n)))
        return tilts

    # --- the end -----------------------------------------------------------------------------------

    def result(self):
        """The estimate over every added frame."""
        if self.calibration is None:
            counts = self._counts() if self.images else []
            raise SolveError(f"{self.capture.source}: no estimate: arm poses per mirror placement {counts}; the start "
                             f"needs {MIN_PLACEMENTS} placements with {MIN_POSES} or more arm poses each")
        return self.calibration

    def summary(self) -> str:
        counts = ", ".join(f"{n} {status}" for status, n in sorted(self.counts.items()))
        return f"{sum(self.counts.values())} frames: {counts}; {len(self.images)} arm poses in {self.placement + 1 if self.images else 0} placements"


def _joint_change(a: dict[str, float], b: dict[str, float]) -> float:
    """The largest change of a joint between two states (joints in only one count as changed)."""
    if set(a) != set(b):
        return float("inf")
    return max((abs(a[n] - b[n]) for n in a), default=0.0)
