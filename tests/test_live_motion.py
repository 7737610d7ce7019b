"""A live session's judgement of motion (tools/live.py): a frame whose corners moved more than
``MOTION_PX`` since the previous one is skipped as "moving"; a still one (sub-pixel jitter) is used.

The corners are a real detection of a rendered frame (scripts/render_live.py), shifted per frame by a
known number of pixels, so the distance the session measures is known exactly."""
import numpy as np
import pytest
import yaml

from conftest import load_script
from mirror_fg.io.capture import capture_from_dict
from mirror_fg.tools.live import LiveSession
from mirror_fg.vision.detectors import Detection

render = load_script("render_live")


@pytest.fixture(scope="module")
def still_frame():
    s = render.session(640, 480, placements=1, hold=1, move=0, seed=6)
    frame = next(iter(render.frames(s)))
    return s, frame


def shifted_session(s, frame, shift_px_per_frame: np.ndarray) -> LiveSession:
    data = yaml.safe_load(yaml.safe_dump(render.capture_dict(s.camera)))
    session = LiveSession(capture_from_dict(data, "capture.yaml", ".", media=False))
    found = session.detector(frame)
    assert len(found.points) >= 8
    calls = iter(range(1000))

    def detector(gray):  # the real corners, moved by the same amount again at each frame
        k = next(calls)
        return Detection({n: p + k * shift_px_per_frame for n, p in found.points.items()})

    session.detector = detector
    return session


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.6, -0.8)])
def test_corners_shifting_5_px_per_frame_are_skipped_as_moving(still_frame, direction):
    s, frame = still_frame
    session = shifted_session(s, frame, 5.0 * np.array(direction))
    records = [session.process(k, frame) for k in range(5)]
    assert records[0].status == "skipped" and "first sight" in records[0].reason
    for record in records[1:]:
        assert record.status == "skipped" and record.reason.startswith("moving (5.0 px"), record.reason
    assert not session.added


def test_corners_jittering_half_a_pixel_are_still(still_frame):
    s, frame = still_frame
    session = shifted_session(s, frame, np.array([0.5, 0.0]))
    records = [session.process(k, frame) for k in range(3)]
    assert records[1].status == "added", records[1].reason  # still: a new placement
    assert records[2].status == "skipped" and "same placement" in records[2].reason
