"""Live sessions of an arm (docs/formats.md, "Live sessions"): joint states from a CSV another program
appends to (read incrementally, partial lines waited for), matched to each frame by time; a frame whose
row never comes is skipped with a note; a mirror moved with the arm still begins a new placement; the
estimate equals the simulated truth."""
from __future__ import annotations

import csv
import json
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.factors.robot import compose, inverse  # noqa: E402
from mirror_fg.io.capture import capture_from_dict  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402
from mirror_fg.robot.simulate import CAMERA, _board, _reflect, simulate_arm  # noqa: E402
from mirror_fg.live.joints import JointStream, LiveArmSession  # noqa: E402


def _scene():
    data, truth = simulate_arm("arm6", False, placements=3, arm_poses=4, pixel_sigma=0.5, seed=2)
    kin = load_kinematics(arm_urdf("arm6"))
    board = _board()
    names = list(board)
    X = np.array(list(board.values())).T

    def project(joints, placement):  # noise-free pixels of the board through mirror placement
        F = kin.placements(joints, ["tool0", "base_link"])
        poses = {r: compose((F[l][0][:3, :3], F[l][0][:3, 3]), m) for r, (l, m) in truth.mounts.items()}
        x = poses["target"][0] @ X + poses["target"][1][:, None]
        R, t = inverse(poses["camera"])
        xc = R @ _reflect(x, truth.mirror_vectors[(1, placement)]) + t[:, None]
        pix = (CAMERA.K @ (xc / xc[2]))[:2].T
        return {n: p for n, p in zip(names, pix)}

    poses = [[im["joints"] for im in data["images"] if im["mirror_configs"] == [k]] for k in range(3)]
    frames = []  # (joints, placement) per frame: two per arm pose (moving, then still)
    for k in range(3):
        for q in poses[k][(k > 0):] + ([poses[k + 1][0]] if k < 2 else []):
            frames += [(q, k), (q, k)]
        if k < 2:  # the mirror moved with the arm still at that last pose: two frames of it
            frames += [(poses[k + 1][0], k + 1)] * 2
    return data, truth, frames, project


def _write_slowly(path, header, rows, pause) -> threading.Thread:
    def run():
        with open(path, "w", newline="") as handle:
            handle.write(",".join(header) + "\n")
            handle.flush()
            for row in rows:
                line = ",".join(row) + "\n"
                handle.write(line[:7])  # half a line first: the reader must wait for its end
                handle.flush()
                time.sleep(pause)
                handle.write(line[7:])
                handle.flush()
    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_a_live_arm_session_reads_the_growing_csv_and_finds_the_truth(tmp_path) -> None:
    data, truth, frames, project = _scene()
    names = list(frames[0][0])
    times = [10.0 + 0.1 * j for j in range(len(frames))]
    rows = [[f"{t - 0.004:.3f}", *[repr(q[n]) for n in names]] for t, (q, _) in zip(times, frames)]
    capture = capture_from_dict({
        "format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": data["camera"], "pixel_sigma": 0.5,
        "target": {"kind": "points", "fiducials": data["fiducials"]},
        "robot": {**data["robot"], "urdf": arm_urdf("arm6")}, "mounts": data["mounts"], "joints": {"file": "joints.csv"},
    }, source="live.yaml", base_dir=str(tmp_path), media=False)
    assert capture.robot["table"] is None  # not read at loading: it is being written
    writer = _write_slowly(tmp_path / "joints.csv", ["time", *names], rows, pause=0.004)
    detections = [SimpleNamespace(points=project(q, k), reason="") for q, k in frames]
    session = LiveArmSession(capture, wait_s=5.0, detect=lambda gray: detections[int(gray[0, 0])])
    records = [session.process(j, np.full((1, 1), j), key=t) for j, t in enumerate(times)]
    writer.join()
    statuses = [r.status for r in records]
    assert statuses.count("added") == 5 + 5 + 4 and session.placement == 2, statuses
    assert [len([im for im in session.images if im["mirror_configs"] == [k]]) for k in range(3)] == [5, 5, 4]
    assert [r.reason for r in records[:2]][0].startswith("first sight")
    assert sum("the arm is moving" in r.reason for r in records) == 11
    # the analytical start waited for three placements of three poses; then the estimate is the truth
    assert records[-1].sigma3_base_cam is not None and records[0].sigma3_base_cam is None
    estimate = session.result().robot["mounts"]["camera"]["T_link_cam"]
    assert np.allclose(estimate["t"], truth.mounts["camera"][1][1], atol=1e-6)
    assert np.allclose(estimate["R"], truth.mounts["camera"][1][0], atol=1e-6)
    # a frame whose row never comes waits, then is skipped with a note
    session.stream.wait_s = 0.1
    began = time.monotonic()
    record = session.process(len(frames), np.full((1, 1), 0), key=times[-1] + 5.0)
    assert record.status == "skipped" and "no row within max_dt" in record.reason and time.monotonic() - began >= 0.1


def test_the_stream_matches_by_image_name_and_refuses_a_tie(tmp_path) -> None:
    path = tmp_path / "joints.csv"
    stream = JointStream(str(path), "joints.csv", 0.02, wait_s=0.05)
    assert stream.lookup("a.png", "a.png") == (None, "joints.csv has no header yet: frame skipped")
    path.write_text("image,j1\na.png,0.5\nb.png,0.7")  # b's line is not finished
    assert stream.lookup("a.png", "a.png") == ({"j1": 0.5}, "")
    joints, note = stream.lookup("b.png", "b.png")
    assert joints is None and "no row for 'b.png'" in note
    with open(path, "a") as handle:
        handle.write("\n")
    assert stream.lookup("b.png", "b.png") == ({"j1": 0.7}, "")
    timed = tmp_path / "timed.csv"
    timed.write_text("time,j1\n1.00,0\n1.02,1\n")
    stream = JointStream(str(timed), "timed.csv", 0.02, wait_s=0.05)
    joints, note = stream.lookup(1.01, "frame000003")
    assert joints is None and "two rows equally near" in note and "frame000003" in note
    assert stream.lookup(1.015, "frame000004") == ({"j1": 1.0}, "")


def test_mirror_fg_live_with_an_arm_matches_a_videos_frames_by_time(tmp_path, capsys) -> None:
    """The command: a 10 frames/s video's frames at k / 10 s; frames 0-2 have rows (no board in them: not
    found), frame 3's row is missing (skipped with a note); no estimate: exit 3."""
    import cv2

    from mirror_fg.cli import main

    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(4):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    data, _ = simulate_arm("arm6", False, placements=3, arm_poses=3, pixel_sigma=0.5, seed=2)
    names = list(data["images"][0]["joints"])
    with open(tmp_path / "joints.csv", "w", newline="") as handle:
        rows = csv.writer(handle)
        rows.writerow(["time", *names])
        for k in range(3):
            rows.writerow([f"{k / 10:.3f}", *[repr(v) for v in data["images"][k]["joints"].values()]])
    (tmp_path / "arm6.urdf").write_text(open(arm_urdf("arm6")).read())
    (tmp_path / "live.json").write_text(json.dumps({
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0},
        "target": {"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.03},
        "robot": data["robot"], "mounts": data["mounts"], "joints": {"file": "joints.csv"}}))
    lines = tmp_path / "frames.jsonl"
    code = main(["live", str(tmp_path / "live.json"), "--source", str(tmp_path / "run.avi"), "--json-lines", str(lines), "-q"])
    assert code == 3
    records = [json.loads(line) for line in lines.read_text().splitlines()]
    assert [r["status"] for r in records] == ["not found"] * 3 + ["skipped"]
    assert "no row within max_dt" in records[3]["reason"] or "joints.csv" in records[3]["reason"], records[3]
    capsys.readouterr()
    assert main(["live", str(tmp_path / "live.json"), "--source", str(tmp_path / "run.avi"), "--verify",
                 str(tmp_path / "old.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "old.json" in err and len(err.splitlines()) == 1  # --verify takes an arm's result: this one is missing
