"""A live session's judgement of motion (live/session.py): a frame whose corners moved more than
``MOTION_PX`` since the previous one is skipped as "moving"; a still one (sub-pixel jitter) is used.

The corners are a real detection of a rendered frame (scripts/render_live.py), shifted per frame by a
known number of pixels, so the distance the session measures is known exactly."""
import numpy as np
import pytest
import yaml

from conftest import load_script
from mirror_fg.io.capture import capture_from_dict
from mirror_fg.live.session import LiveSession
from mirror_fg.vision.detectors import Detection

render = load_script("render_live")


@pytest.fixture(scope="module")
def still_frame():
    s = render.session(640, 480, placements=1, hold=1, move=0, seed=6)
    frame = next(iter(render.frames(s)))
    return s, frame


def shifted_session(s, frame, shifts_px: list) -> LiveSession:
    """A session whose k-th detection is the real corners moved by ``shifts_px[k]`` (pixels, (2,))."""
    data = yaml.safe_load(yaml.safe_dump(render.capture_dict(s.camera)))
    session = LiveSession(capture_from_dict(data, "capture.yaml", ".", media=False))
    found = session.detector(frame)
    assert len(found.points) >= 8
    calls = iter(shifts_px)

    def detector(gray):
        shift = np.asarray(next(calls), float)
        return Detection({n: p + shift for n, p in found.points.items()})

    session.detector = detector
    return session


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.6, -0.8)])
def test_corners_shifting_5_px_per_frame_are_skipped_as_moving(still_frame, direction):
    s, frame = still_frame
    session = shifted_session(s, frame, [5.0 * k * np.array(direction) for k in range(5)])
    records = [session.process(k, frame) for k in range(5)]
    assert records[0].status == "skipped" and "first sight" in records[0].reason
    for record in records[1:]:
        assert record.status == "skipped" and record.reason.startswith("moving (5.0 px"), record.reason
    assert not session.added


def test_corners_jittering_half_a_pixel_are_still(still_frame):
    s, frame = still_frame
    session = shifted_session(s, frame, [[0.5 * k, 0.0] for k in range(3)])
    records = [session.process(k, frame) for k in range(3)]
    assert records[1].status == "added", records[1].reason  # still: a new placement
    assert records[2].status == "skipped" and "same placement" in records[2].reason


def test_a_still_mirror_a_few_pixels_from_a_placement_is_that_placement(still_frame):
    """Held still 4 px from an added placement (within SAME_PLACEMENT_PX, 6): the same placement; held
    still 12 px away: a new one, given to the estimate."""
    s, frame = still_frame
    session = shifted_session(s, frame, [[0, 0], [0, 0], [4, 0], [4, 0], [0, 12], [0, 12]])
    records = [session.process(k, frame) for k in range(6)]
    assert [r.status for r in records[:2]] == ["skipped", "added"]
    assert records[2].status == "skipped" and records[2].reason.startswith("moving (4.0 px")
    assert records[3].status == "skipped" and "same placement as frame 1 (4.0 px)" in records[3].reason
    assert records[4].status == "skipped" and records[4].reason.startswith("moving")
    assert records[5].status in ("added", "refused"), records[5].reason  # a placement of its own
