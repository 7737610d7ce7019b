"""Live sessions (``mirror-fg live``): a rendered hand-held session as a video, a folder and a web page.

The truth comes from scripts/render_live.py (the board's printed face mapped through each mirror
placement by its homography); the live result is compared with it through its own 3-sigma bounds, and
the saved capture's offline calibration with the live result.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import load_script, pose_difference
from mirror_fg.io.capture import capture_from_dict
from mirror_fg.live.session import LiveSession, run
from mirror_fg.live.sources import FolderSource, VideoFileSource
from test_live_page import CHROMIUM, chromium  # Chromium in a process group of its own

render = load_script("render_live")
STATUSES = {"added", "skipped", "not found", "refused"}


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live")
    s = render.session(640, 480, placements=7, hold=3, move=2, seed=2)
    render.write_video(s, folder / "session.avi")
    (folder / "capture.yaml").write_text(yaml.safe_dump(render.capture_dict(s.camera), sort_keys=False))
    return folder, s


def run_cli(*args, cwd, timeout=180):
    return subprocess.run([sys.executable, "-m", "mirror_fg", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def within_3_sigma(result: dict, s) -> np.ndarray:
    """Each pose component's error against the truth in units of its own sigma."""
    T = result["T_cam_base"]
    error = pose_difference(s.R_cam_base, s.t_cam_base, T["R"], T["t"])  # estimate minus truth (docs/formats.md convention)
    return np.abs(error) / np.sqrt(np.diag(np.array(result["covariance_cam_base"])))


def test_video_session_one_line_per_frame_result_within_3_sigma_and_saved_capture_repeats_it(session_dir, tmp_path):
    folder, s = session_dir
    work = tmp_path / "w"
    shutil.copytree(folder, work)
    proc = run_cli("live", "capture.yaml", "--source", "session.avi", "-o", "live.json", "--json-lines", "frames.jsonl",
                   "--save", "saved", cwd=work)
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in (work / "frames.jsonl").read_text().splitlines()]
    assert [line["frame"] for line in lines] == list(range(len(s.frame_placements)))  # one line per frame, in order
    assert all(line["status"] in STATUSES for line in lines)
    assert all(set(line) == {"frame", "t", "status", "reason", "placements", "sigma3_base_cam", "next", "done"}
               for line in lines)
    added = [line for line in lines if line["status"] == "added"]
    assert len(added) == 7  # each still placement once; moving and repeated frames skipped with a reason
    held = [k for k, p in enumerate(s.frame_placements) if p is not None]
    assert {line["frame"] for line in added} <= set(held)
    assert all(line["reason"] for line in lines if line["status"] == "skipped")
    assert any(line["next"] is not None for line in lines) and lines[-1]["sigma3_base_cam"] is not None
    live = json.loads((work / "live.json").read_text())
    assert np.all(within_3_sigma(live, s) < 3.0)
    # The saved capture repeats the session offline.
    saved = yaml.safe_load((work / "saved" / "capture.yaml").read_text())
    assert len(saved["images"]) == 7
    proc = run_cli("calibrate", "saved/capture.yaml", "-o", "offline.json", cwd=work)
    assert proc.returncode == 0, proc.stderr
    offline = json.loads((work / "offline.json").read_text())
    error = pose_difference(live["T_cam_base"]["R"], live["T_cam_base"]["t"], offline["T_cam_base"]["R"],
                            offline["T_cam_base"]["t"])
    assert np.all(np.abs(error) / np.sqrt(np.diag(np.array(offline["covariance_cam_base"]))) < 0.1)


def live_session(capture_file: Path, **options) -> LiveSession:
    data = yaml.safe_load(capture_file.read_text())
    return LiveSession(capture_from_dict(data, str(capture_file), str(capture_file.parent), media=False), **options)


def test_degenerate_sessions_are_said_live(tmp_path):
    s = render.session(640, 480, placements=4, hold=3, move=2, seed=4, same_tilt=True)
    render.write_video(s, tmp_path / "same.avi")
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(render.capture_dict(s.camera)))
    records = []
    run(live_session(tmp_path / "c.yaml"), VideoFileSource(str(tmp_path / "same.avi")), on_record=records.append)
    reasons = [r.reason for r in records if r.status == "added"]
    assert "1 of 3 mirror placements" in reasons[0] and "2 of 3" in reasons[1]
    assert any("tilted about one axis" in reason for reason in reasons[2:])
    behind = render.session(640, 480, placements=2, hold=2, move=1, seed=5, from_behind=True)
    render.write_video(behind, tmp_path / "behind.avi")
    records = []
    run(live_session(tmp_path / "c.yaml"), VideoFileSource(str(tmp_path / "behind.avi")), on_record=records.append)
    assert records and all(r.status == "not found" for r in records)
    held = [r for r in records if behind.frame_placements[r.frame] is not None]
    assert held and all("seen from behind" in r.reason for r in held)


def test_folder_source_reads_each_new_image_once_in_order(session_dir, tmp_path):
    folder, s = session_dir
    import cv2

    frames = list(render.frames(s))[:8]
    source = FolderSource(str(tmp_path), idle_s=1.0)
    seen = []

    def writer() -> None:
        for k, frame in enumerate(frames):
            cv2.imwrite(str(tmp_path / f".tmp{k}.png"), frame)
            os.replace(tmp_path / f".tmp{k}.png", tmp_path / f"f{k:03d}.png")  # as a camera program would
            time.sleep(0.05)

    thread = threading.Thread(target=writer)
    thread.start()
    for index, gray in source.frames():
        seen.append((index, gray))
    thread.join()
    assert [k for k, _ in seen] == list(range(8))
    assert all(np.array_equal(gray, frames[k]) for k, gray in seen)


def test_targets_met_ends_with_done(session_dir, tmp_path):
    folder, s = session_dir
    records = []
    run(live_session(folder / "capture.yaml", target_mm=1e4, target_deg=1e3), VideoFileSource(str(folder / "session.avi")),
        on_record=records.append, stop_when_done=True)
    assert records[-1].done and records[-1].status == "added" and sum(r.status == "added" for r in records) >= 3
    assert not any(r.done for r in records[:-1])


@pytest.mark.parametrize("args,words", [
    (["--source", "missing.avi"], "missing.avi"),
    (["--source", "session.avi", "--serve", "70000"], "--serve"),
])
def test_live_refusals(session_dir, args, words):
    folder, _ = session_dir
    proc = run_cli("live", "capture.yaml", *args, cwd=folder)
    assert proc.returncode == 2 and words in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (apt-get install chromium)")
def test_web_page_shows_the_picture_the_bars_and_the_suggestion(session_dir, tmp_path):
    from PIL import Image

    folder, _ = session_dir
    proc = subprocess.Popen([sys.executable, "-m", "mirror_fg", "live", "capture.yaml", "--source", "session.avi",
                             "--serve", "0", "--hold", "--target-mm", "40"], cwd=folder, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    url, ended = None, False
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not ended:
            line = proc.stdout.readline()
            if not line:
                break
            if "serving the live page on" in line:
                url = line.split()[-1]
            ended = "until Ctrl-C" in line
        assert url and ended, proc.stderr.read() if proc.poll() is not None else "no page"
        # a profile per run: a second run on the killed first one's profile can wait out its timeout
        dom = chromium(f"--user-data-dir={tmp_path / 'profile-dom'}", "--virtual-time-budget=1500", "--dump-dom", url)
        polar = dom[dom.index('<svg id="polar"'):]
        polar = polar[:polar.index("</svg>")]  # as drawn (the script in the DOM names the classes too)
        assert '<div class="bar">' in dom and "mm" in dom and 'class="placement"' in polar  # bars, the polar plot
        if 'id="stop" class="shown"' in dom:  # done: no placement is suggested any more
            assert "none needed" in dom and "tilt it" not in dom and 'class="suggested"' not in polar
        else:  # the suggestion in words and on the polar plot
            assert "tilt it" in dom and 'class="suggested"' in polar
        assert "/frame.jpg?seq=" in dom
        shot = tmp_path / "page.png"
        chromium(f"--user-data-dir={tmp_path / 'profile-shot'}", "--virtual-time-budget=1500", "--window-size=1280,900",
                 f"--screenshot={shot}", url)
        picture = np.asarray(Image.open(shot).convert("RGB")).astype(int)
        left = picture[80:500, 20:700]  # the live picture's panel
        assert len(np.unique(left.reshape(-1, 3), axis=0)) > 50  # a photograph, not an empty panel
        green = (picture[..., 1] > 140) & (picture[..., 0] < 80) & (picture[..., 2] < 100)
        assert green.sum() > 200  # bars that met their target (or the suggestion marker) in green
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0
