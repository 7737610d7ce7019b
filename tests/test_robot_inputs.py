"""Bad robot-arm inputs at the CLI (docs/formats.md, "Robot arms: joint states and mounts"): each one line
naming the image and joint (or the mount and link, the URDF), exit 2, nothing written."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

pytest.importorskip("pinocchio")

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402


@pytest.fixture(scope="module")
def arm_data():
    return simulate_arm("arm6", False, placements=3, arm_poses=4, seed=3)


def _write(tmp_path: Path, arm_data, edit) -> Path:
    dataset, truth = arm_data
    dataset = json.loads(json.dumps(dataset))
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    edit(dataset, tmp_path)
    path.write_text(json.dumps(dataset))
    return path


def _refused(tmp_path: Path, path: Path, capsys) -> str:
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "-q"]) == 2
    assert not out.exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


def _set_joint(name, value, image=1):
    def edit(d, _):
        d["images"][image]["joints"][name] = value
    return edit


@pytest.mark.parametrize("edit,words", [
    (_set_joint("elbow_joint", 4.0), ["image 'p0_001'", "'elbow_joint'", "outside its URDF limits"]),
    (_set_joint("elbow_jont", 0.1), ["image 'p0_001'", "'elbow_jont'", "not a movable joint"]),
    (_set_joint("elbow_joint", float("nan")), ["image 'p0_001'", "'elbow_joint'"]),
    (_set_joint("elbow_joint", None), ["image 'p0_001'", "'elbow_joint'", "expected a number"]),
    (lambda d, _: d["images"][2]["joints"].pop("wrist_2_joint"), ["image 'p0_002'", "'wrist_2_joint'", "missing"]),
    (lambda d, _: d["images"][0].pop("joints"), ["image 'p0_000'", "missing 'joints'"]),
    (lambda d, _: d["mounts"]["target"].update(link="wrist_1_link"),
     ["image 'p0_000'", "'wrist_2_joint'", "extra joint"]),
    (lambda d, _: d["mounts"]["target"].update(link="tool9"), ["mounts.target", "'tool9'", "not a link"]),
    (lambda d, t: (t / "arm6.urdf").write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'>"),
     ["urdf 'arm6.urdf'", "does not parse"]),
    (lambda d, _: d["robot"].update(urdf="missing.urdf"), ["missing.urdf", "no such URDF"]),
    (lambda d, _: d["robot"]["joint_offsets"].update(estimate=["elbow"]) if "joint_offsets" in d["robot"]
     else d["robot"].update(joint_offsets={"estimate": ["elbow"]}), ["joint_offsets", "unknown joint 'elbow'"]),
])
def test_bad_robot_input_is_one_line_exit_2(tmp_path, arm_data, capsys, edit, words) -> None:
    err = _refused(tmp_path, _write(tmp_path, arm_data, edit), capsys)
    for word in words:
        assert word in err, err


def test_mount_on_a_link_not_connected_through_recorded_joints(tmp_path, arm_data, capsys) -> None:
    urdf = Path(arm_urdf("arm6")).read_text().replace(
        "</robot>", '  <link name="cart"/><joint name="cart_joint" type="floating"><parent link="base_link"/>'
                    '<child link="cart"/></joint>\n</robot>')

    def edit(d, t):
        (t / "arm6.urdf").write_text(urdf)
        d["mounts"]["camera"] = {"link": "cart"}
    err = _refused(tmp_path, _write(tmp_path, arm_data, edit), capsys)
    assert "mounts.camera" in err and "'cart'" in err and "not connected to the base link" in err, err


def test_without_pinocchio_one_line_says_what_to_install(tmp_path, arm_data, capsys, monkeypatch) -> None:
    path = _write(tmp_path, arm_data, lambda d, t: d["robot"].update(urdf="other.urdf")
                  or (t / "other.urdf").write_text(Path(arm_urdf("arm6")).read_text()))
    monkeypatch.setitem(sys.modules, "pinocchio", None)  # import pinocchio raises ImportError
    err = _refused(tmp_path, path, capsys)
    assert "pip install 'mirror-fg[robot]'" in err, err


def test_the_simulated_data_load_and_round_trip(tmp_path, arm_data) -> None:
    from mirror_fg.io.dataset import dataset_to_dict, load_dataset

    path = _write(tmp_path, arm_data, lambda d, t: None)
    ds = load_dataset(path)
    assert ds.robot is not None and not ds.is_tree
    assert ds.robot.mounts["target"].link == "tool0" and ds.robot.mounts["camera"].known is None
    again = dataset_to_dict(ds)
    assert again["robot"] == arm_data[0]["robot"] and again["mounts"] == arm_data[0]["mounts"]
    assert [im["joints"] for im in again["images"]] == [im["joints"] for im in arm_data[0]["images"]]


def test_incremental_refuses_an_arm_in_one_line(tmp_path, arm_data, capsys) -> None:
    path = _write(tmp_path, arm_data, lambda d, t: None)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "--incremental", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "drop --incremental" in err, err
