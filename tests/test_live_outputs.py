"""``mirror-fg live``'s files at the command line: every output checked against every input and each
other before anything is written, unwritable outputs said in one line, and ``--save`` kept whole on
every catchable signal (a SIGKILL leaves a folder that ``detect`` names as incomplete)."""
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest
import yaml

from conftest import load_script

render = load_script("render_live")


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live_outputs")
    s = render.session(640, 480, placements=5, hold=3, move=2, seed=3)
    render.write_video(s, folder / "session.avi")
    (folder / "capture.yaml").write_text(yaml.safe_dump(render.capture_dict(s.camera), sort_keys=False))
    frames = folder / "frames"
    frames.mkdir()
    for k, frame in enumerate(render.frames(s)):
        cv2.imwrite(str(frames / f"f{k:04d}.png"), frame)
    return folder, s


def run_cli(*args, cwd, timeout=180):
    return subprocess.run([sys.executable, "-m", "mirror_fg", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("args,words", [
    (["--json-lines", "session.avi"], "input"),  # the --source video
    (["-o", "session.avi"], "input"),
    (["--json-lines", "capture.yaml"], "input"),
    (["-o", "capture.yaml"], "input"),
    (["--json-lines", "o/r.json", "-o", "o/r.json"], "same file"),
    (["--json-lines", "r.ros.yaml", "-o", "r.json"], "same file"),  # the result's ROS file
    (["-o", "s/capture.yaml", "--save", "s"], "--save s"),
    (["--json-lines", "s/frame000004.png", "--save", "s"], "--save s"),
    (["-o", "s", "--save", "s"], "--save s"),
    (["--save", "o", "--source", "o"], "--source folder"),  # an empty watched folder,
    (["--save", "capture.yaml"], "not a folder"),
    (["--save", "/dev/null"], "not a folder"),
    (["--save", "capture.yaml/inner"], "is a file"),
    (["--json-lines", "nodir/x.jsonl"], "nodir"),
])
def test_outputs_that_meet_an_input_or_each_other_are_refused_before_anything_is_written(session_dir, tmp_path,
                                                                                           args, words):
    folder, _ = session_dir
    work = tmp_path / "w"
    work.mkdir()
    for name in ("capture.yaml", "session.avi"):
        os.link(folder / name, work / name)
    (work / "frames").symlink_to(folder / "frames")
    (work / "o").mkdir()
    before = digest(work)
    arguments = ["--source", "session.avi", *args] if "--source" not in args else args
    proc = run_cli("live", "capture.yaml", *arguments, cwd=work)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and words in proc.stderr, proc.stderr
    assert digest(work) == before and sorted(p.name for p in work.iterdir()) == ["capture.yaml", "frames", "o",
                                                                                  "session.avi"]


def test_json_lines_to_a_full_device_is_one_line(session_dir):
    folder, _ = session_dir
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    proc = run_cli("live", "capture.yaml", "--source", "session.avi", "--json-lines", "/dev/full", cwd=folder)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "/dev/full" in proc.stderr and "cannot write" in proc.stderr


def start_folder_session(folder: Path, work: Path, frames: int) -> subprocess.Popen:
    """A session reading a folder that receives no more images (it waits): killed or stopped by a test."""
    source = work / "incoming"
    source.mkdir()
    for path in sorted((folder / "frames").iterdir())[:frames]:
        os.link(path, source / path.name)
    return subprocess.Popen([sys.executable, "-m", "mirror_fg", "live", str(folder / "capture.yaml"), "--source",
                             str(source), "--idle", "120", "--save", "saved", "-o", "live.json"], cwd=work,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_images(capture: Path, count: int, proc: subprocess.Popen) -> dict:
    deadline = time.monotonic() + 150
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        if capture.exists():
            data = yaml.safe_load(capture.read_text())
            if len(data["images"]) >= count:
                return data
        time.sleep(0.2)
    raise AssertionError(f"{capture}: fewer than {count} images written while the session runs")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_ends_the_session_with_its_frames_saved_and_its_result(session_dir, tmp_path, signum):
    folder, s = session_dir
    held = [k for k, p in enumerate(s.frame_placements) if p is not None]
    proc = start_folder_session(folder, tmp_path, frames=len(s.frame_placements))
    try:
        running = wait_for_images(tmp_path / "saved" / "capture.yaml", 5, proc)
        assert "incomplete" in running  # while it runs, the capture says it is not finished
        time.sleep(1.0)  # the source now waits for images that never come
        proc.send_signal(signum)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert f"stopped by {signal.Signals(signum).name}" in stdout
    saved = yaml.safe_load((tmp_path / "saved" / "capture.yaml").read_text())
    assert "incomplete" not in saved and len(saved["images"]) == 5
    for image in saved["images"]:
        frame = int(image["file"][5:11])
        assert frame in held and (tmp_path / "saved" / image["file"]).exists()
    assert json.loads((tmp_path / "live.json").read_text())["format"] == "mirror-fg/result@1"
    proc = run_cli("detect", "saved/capture.yaml", "-o", "saved.json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert len(json.loads((tmp_path / "saved.json").read_text())["images"]) == 5


def test_after_a_sigkill_detect_names_the_saved_folder_incomplete(session_dir, tmp_path):
    folder, _ = session_dir
    proc = start_folder_session(folder, tmp_path, frames=12)
    try:
        wait_for_images(tmp_path / "saved" / "capture.yaml", 2, proc)
        proc.kill()
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    proc = run_cli("detect", "saved/capture.yaml", "-o", "saved.json", cwd=tmp_path)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "incomplete" in proc.stderr and "saved/capture.yaml" in proc.stderr and "frame(s) so far" in proc.stderr
    assert not (tmp_path / "saved.json").exists()
    # Each frame the capture names was written whole before the capture named it.
    data = yaml.safe_load((tmp_path / "saved" / "capture.yaml").read_text())
    assert all(cv2.imread(str(tmp_path / "saved" / image["file"])) is not None for image in data["images"])


def test_live_help_points_at_the_documentation_a_user_has(tmp_path):
    proc = run_cli("live", "-h", cwd=tmp_path)
    assert proc.returncode == 0 and "SPEC" not in proc.stdout
    assert "docs/formats.md" in " ".join(proc.stdout.split())
