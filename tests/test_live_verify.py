"""``mirror-fg live --verify RESULT`` (mirror_fg/live/verify.py): the verdict as frames arrive, on
rendered hand-held sessions (scripts/render_live.py): the stored result from one session, then a second
session of the same camera, and one with the camera moved 4 cm along its x axis."""
import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import yaml

from conftest import load_script
from mirror_fg.io.capture import capture_from_dict
from mirror_fg.live.session import LiveSession, run
from mirror_fg.live.sources import VideoFileSource

render = load_script("render_live")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live_verify")
    stored = render.session(640, 480, placements=7, hold=3, move=2, seed=2)
    render.write_video(stored, folder / "stored.avi")
    capture = render.capture_dict(stored.camera)
    (folder / "capture.yaml").write_text(yaml.safe_dump(capture, sort_keys=False))
    session = LiveSession(capture_from_dict(capture, str(folder / "capture.yaml"), media=False))
    run(session, VideoFileSource(str(folder / "stored.avi")))
    (folder / "stored.result.json").write_text(json.dumps(session.result().to_dict()))
    today = render.session(640, 480, placements=3, hold=3, move=2, seed=5)
    render.write_video(today, folder / "today.avi")
    render.write_video(replace(today, t_cam_base=today.t_cam_base + np.array([0.04, 0.0, 0.0])), folder / "moved.avi")
    return folder


def live(folder, video, *extra):
    return subprocess.run([sys.executable, "-m", "mirror_fg", "live", "capture.yaml", "--source", video,
                           "--verify", "stored.result.json", *extra], capture_output=True, text=True, cwd=folder,
                          timeout=180)


def test_same_camera_is_never_moved(sessions):
    run_ = live(sessions, "today.avi")
    assert run_.returncode in (0, 5), run_.stderr
    assert run_.stdout.count("verify: camera:") == 3  # one verdict per added placement
    assert "MOVED" not in run_.stdout.replace("NOT MOVED", "")


def test_moved_camera_is_moved_from_the_first_placement(sessions):
    run_ = live(sessions, "moved.avi")
    assert run_.returncode == 4, run_.stderr
    verdicts = [line for line in run_.stdout.splitlines() if "verify: camera:" in line]
    assert verdicts and all(": moved (" in line for line in verdicts)
    assert "3 of 6 seen" in verdicts[0]


def test_verify_with_output_is_refused(sessions):
    run_ = live(sessions, "today.avi", "-o", "x.json")
    assert run_.returncode == 2 and "--verify" in run_.stderr and len(run_.stderr.strip().splitlines()) == 1
