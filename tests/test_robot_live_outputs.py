"""``mirror-fg live`` with a robot arm's capture, ``--save`` and ``--serve`` (docs/formats.md, "Live
sessions"): rendered photographs of an AprilTag board on the arm's tool seen through a hand-held mirror
(scripts/render_live.py's board, posed by the arm's forward kinematics), joint states matched by each
frame's file name. The saved folder keeps each used frame's joint states (``joints.csv``) and calibrates
again to the live session's answer; the page's state says the arm session's progress."""
from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("pinocchio")

from conftest import load_script  # noqa: E402

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.factors.robot import compose, inverse  # noqa: E402
from mirror_fg.io.capture import capture_from_dict  # noqa: E402
from mirror_fg.live.joints import LiveArmSession  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402
from mirror_fg.robot.simulate import CAMERA, simulate_arm  # noqa: E402

render = load_script("render_live")
#: The printed board's frame in the simulated target's: half a turn about y, so that its printed face
#: (+z of render_live's board) is the simulated pattern's front (-z of the target), towards the mirror.
FLIP = (np.diag([-1.0, 1.0, -1.0]), np.zeros(3))


def _camera() -> dict:
    return {"model": "pinhole", "width": CAMERA.width, "height": CAMERA.height, "fx": CAMERA.fx, "fy": CAMERA.fy,
            "cx": CAMERA.cx, "cy": CAMERA.cy, "dist": [0.0] * 5}


def _in_view(T, v_c) -> bool:
    camera = _camera()
    return render._corners_in_view(camera, T[0], T[1], v_c, margin=30.0)


@pytest.fixture(scope="module")
def arm_session(tmp_path_factory):
    """A folder of rendered frames (two of each still arm pose; the mirror moved with the arm still), its
    joints.csv (an image column), the capture and the truth (the board's mount on tool0)."""
    folder = tmp_path_factory.mktemp("arm_live")
    data, truth = simulate_arm("arm6", False, placements=3, arm_poses=8, pixel_sigma=0.5, seed=2)
    kin = load_kinematics(arm_urdf("arm6"))
    mount_c = truth.mounts["camera"][1]
    mount_t = compose(truth.mounts["target"][1], FLIP)

    def view(joints, placement):  # the board in the camera (T = C^-1 D) and the plane in the camera's frame
        F = kin.placements(joints, ["tool0"])["tool0"][0]
        C, D = mount_c, compose((F[:3, :3], F[:3, 3]), mount_t)
        T = compose(inverse(C), D)
        v = truth.mirror_vectors[(1, placement)]
        d, n = float(np.linalg.norm(v)), v / np.linalg.norm(v)
        return T, (d - float(n @ C[1])) * (C[0].T @ n)

    poses = []
    for k in range(3):  # the arm poses whose whole board is seen through placement k, and through k + 1 (the last)
        seen = [im["joints"] for im in data["images"] if im["mirror_configs"] == [k] and _in_view(*view(im["joints"], k))]
        poses.append(seen)
    plan = []  # (joints, placement): each still arm pose twice; 4, 5 and 5 arm poses per placement
    for k in range(3):
        ours = poses[k][:4]
        if k < 2:  # the last arm pose of placement k is seen through placement k + 1 too: move the mirror there
            shared = next(q for q in poses[k][4:] if _in_view(*view(q, k + 1)))
            ours = ours[:3] + [shared]
        for q in ours:
            plan += [(q, k), (q, k)]
        if k < 2:
            plan += [(ours[-1], k + 1)] * 2
    texture = render.board_texture()
    rng = np.random.default_rng(1)
    frames = folder / "frames"
    frames.mkdir()
    names = list(plan[0][0])
    with open(folder / "joints.csv", "w", newline="") as handle:
        rows = csv.writer(handle)
        rows.writerow(["image", *names])
        for j, (q, k) in enumerate(plan):
            T, v_c = view(q, k)
            cv2.imwrite(str(frames / f"f{j:04d}.png"), render.render(_camera(), T[0], T[1], v_c, texture, rng))
            rows.writerow([f"f{j:04d}.png", *(repr(q[n]) for n in names)])
    (folder / "arm6.urdf").write_text(open(arm_urdf("arm6")).read())
    capture = {**render.capture_dict(_camera()), "robot": {"urdf": "arm6.urdf", "base_link": "base_link"},
               "mounts": {"camera": {"link": "base_link"}, "target": {"link": "tool0"}}, "joints": {"file": "joints.csv"}}
    (folder / "capture.yaml").write_text(yaml.safe_dump(capture, sort_keys=False))
    return folder, plan, truth, mount_t


def _pose(entry):
    return np.array(entry["R"], float), np.array(entry["t"], float)


def test_live_save_keeps_the_joint_states_and_calibrates_again_to_the_same_answer(arm_session, tmp_path, capsys):
    folder, plan, truth, mount_t = arm_session
    out, saved, lines = tmp_path / "live.json", tmp_path / "saved", tmp_path / "frames.jsonl"
    code = main(["live", str(folder / "capture.yaml"), "--source", str(folder / "frames"), "--idle", "1",
                 "-o", str(out), "--save", str(saved), "--json-lines", str(lines), "--serve", "0"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "serving the live page on http://127.0.0.1:" in printed.out
    records = [json.loads(line) for line in lines.read_text().splitlines()]
    added = [r for r in records if r["status"] == "added"]
    assert len(added) == 4 + 5 + 5 and records[-1]["placements"] == 3, [(r["status"], r["reason"]) for r in records]
    live = json.loads(out.read_text())
    # the live estimate: the truth within its 3-sigma
    for role, key, true in (("camera", "T_link_cam", truth.mounts["camera"][1]), ("target", "T_link_target", mount_t)):
        entry = live["mounts"][role]
        R, t = _pose(entry[key])
        sigma = np.sqrt(np.diag(np.array(entry["covariance"])))
        from scipy.spatial.transform import Rotation
        error = np.concatenate([Rotation.from_matrix(true[0] @ R.T).as_rotvec(), true[1] - t])
        assert np.all(np.abs(error) < 3.5 * sigma), (role, error / sigma)
    # the saved folder: each used frame, its joint states matched by the frame's file name, the capture
    capture = yaml.safe_load((saved / "capture.yaml").read_text())
    assert "incomplete" not in capture and capture["joints"] == {"file": "joints.csv"}
    assert (saved / capture["robot"]["urdf"]).resolve() == (folder / "arm6.urdf").resolve()
    assert [im["mirror_configs"] for im in capture["images"]] == [[0]] * 4 + [[1]] * 5 + [[2]] * 5
    with open(saved / "joints.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["image"] for row in rows] == [im["file"] for im in capture["images"]]
    used = [plan[r["frame"]][0] for r in added]
    assert all(float(row[n]) == q[n] for row, q in zip(rows, used) for n in q)  # exactly as recorded
    again = tmp_path / "again.json"
    assert main(["calibrate", str(saved / "capture.yaml"), "-o", str(again), "-q"]) == 0
    offline = json.loads(again.read_text())
    for role, key in (("camera", "T_link_cam"), ("target", "T_link_target")):
        R, t = _pose(live["mounts"][role][key])
        R2, t2 = _pose(offline["mounts"][role][key])
        sigma = np.sqrt(np.diag(np.array(offline["mounts"][role]["covariance"])))
        from scipy.spatial.transform import Rotation
        difference = np.concatenate([Rotation.from_matrix(R2 @ R.T).as_rotvec(), t2 - t])
        assert np.all(np.abs(difference) < 0.01 * sigma), (role, difference / sigma)


def test_the_arm_sessions_page_state(arm_session):
    folder, plan, truth, _ = arm_session
    from mirror_fg.io.fileio import load_structured

    data = load_structured(str(folder / "capture.yaml"), "capture.yaml")
    capture = capture_from_dict(data, source=str(folder / "capture.yaml"), base_dir=str(folder), media=False)
    kept = []
    session = LiveArmSession(capture, picture=True, target_mm=0.5,
                             on_added=lambda frame, gray, image: kept.append((frame, image)))
    states = []
    for j in range(len(plan)):
        gray = cv2.imread(str(folder / "frames" / f"f{j:04d}.png"), cv2.IMREAD_GRAYSCALE)
        session.process(j, gray, key=f"f{j:04d}.png")
        states.append(session.state)
    assert [s.seq for s in states] == list(range(1, len(plan) + 1))
    first, last = states[0].status, states[-1].status
    assert first["status"] == "skipped" and first["arm"]["joints"] == plan[0][0] and first["sigma3_base_cam"] is None
    assert "move the arm to a new pose" in first["next_words"]
    assert last["arm"]["poses"] == [4, 5, 5] and last["placements"] == 3 and last["targets"] == {"mm": 0.5, "deg": None}
    assert last["sigma3_base_cam"] is not None and len(last["placements_tilt"]) == 3
    # each placement's tilt in the camera's frame: the plane's normal against the optical axis, as drawn
    for (tilt, _), v in zip(last["placements_tilt"], [truth.mirror_vectors[(1, k)] for k in range(3)]):
        n_c = truth.mounts["camera"][1][0].T @ (v / np.linalg.norm(v))
        assert tilt == pytest.approx(math.degrees(math.acos(abs(n_c[2]))), abs=0.5)
    picture = cv2.imdecode(np.frombuffer(states[-1].jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert picture.shape[:2] == (CAMERA.height, CAMERA.width)
    assert [image["mirror_configs"] for _, image in kept] == [[0]] * 4 + [[1]] * 5 + [[2]] * 5
    assert all(image["joints"] == plan[frame][0] for frame, image in kept)
