"""Robot arms end to end (docs/formats.md, "Robot arms: joint states and mounts"): simulate -> calibrate at
the CLI from the analytical start (no truth) -> result@1 mounts, joint offsets and the URDF side file; the
truth within 3 sigma over a Monte Carlo (NEES in its band); one rotation axis only said in words (exit 3)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

pytest.importorskip("pinocchio")

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.io.dataset import load_dataset  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.calibrate import calibrate  # noqa: E402

KEYS = {"camera": "T_link_cam", "target": "T_link_target"}
OFFSET = {"arm6": "shoulder_lift_joint", "panda": "panda_joint2"}


def _error(entry, truth_pose):
    """[dtheta, dt] of the truth about the estimate (R_true = Exp(dtheta) R_est, t_true = t_est + dt)."""
    R, t = np.array(entry["R"]), np.array(entry["t"])
    return np.concatenate([Rotation.from_matrix(truth_pose[0] @ R.T).as_rotvec(), truth_pose[1] - t])


@pytest.mark.parametrize("robot,eye_in_hand", [("arm6", False), ("panda", True)])
def test_simulate_then_calibrate_at_the_cli(tmp_path, robot, eye_in_hand) -> None:
    data = tmp_path / "arm.json"
    argv = ["simulate", "--robot", robot, "-o", str(data), "--sigma", "0.5", "--seed", "4", "-q"]
    assert main(argv + (["--eye-in-hand"] if eye_in_hand else [])) == 0
    assert (tmp_path / f"{robot}.urdf").exists() and (tmp_path / "arm.truth.json").exists()
    out = tmp_path / "result.json"
    assert main(["calibrate", str(data), "-o", str(out), "-q"]) == 0
    result = json.loads(out.read_text())
    truth = json.loads((tmp_path / "arm.truth.json").read_text())
    for role, key in KEYS.items():
        entry = result["mounts"][role]
        assert entry["link"] == truth["mounts"][role]["link"]
        true_pose = tuple(np.array(truth["mounts"][role][key][k]) for k in ("R", "t"))
        delta = _error(entry[key], true_pose)
        sigma = np.sqrt(np.diag(entry["covariance"]))
        assert np.all(np.abs(delta) < 4 * sigma), delta / sigma
        assert np.allclose(3 * sigma[3:] * 1000, entry["sigma3"]["position_mm"])
    camera = result["mounts"]["camera"]["T_link_cam"]
    assert np.allclose(result["T_base_cam"]["R"], camera["R"]) and np.allclose(result["T_base_cam"]["t"], camera["t"])
    assert all(m["frame"] == "base_link" for m in result["mirrors"])
    yourdfpy = pytest.importorskip("yourdfpy")
    side = yourdfpy.URDF.load(str(tmp_path / "result.urdf.xml"), build_scene_graph=True, load_meshes=False)
    camera_link = result["mounts"]["camera"]["link"]
    assert np.allclose(side.get_transform("camera_optical_frame", camera_link)[:3, 3], camera["t"], atol=1e-9)
    target = result["mounts"]["target"]
    assert np.allclose(side.get_transform("calibration_target", target["link"])[:3, 3], target["T_link_target"]["t"],
                       atol=1e-9)


def test_one_rotation_axis_is_said_in_words_exit_3(tmp_path, capsys) -> None:
    dataset, truth = simulate_arm("arm6", False, arm_poses=6, moving=("wrist_3_joint",), spread_rad=0.8, seed=2)
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "-q"]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and not out.exists()
    assert "target mount's position (T_link_target) along the axis [0.00, 0.00, 1.00] of link 'tool0'" in err, err
    assert "add arm poses that rotate it about another axis" in err, err


def _monte_carlo(tmp_path, robot, eye_in_hand, runs):
    nees = {"camera": [], "target": [], "offset": []}
    for seed in range(runs):
        dataset, truth = simulate_arm(robot, eye_in_hand, placements=3, arm_poses=8, pixel_sigma=1.0,
                                      joint_offsets_deg={OFFSET[robot]: 0.5}, seed=100 + seed)
        path = tmp_path / f"mc{seed}.json"
        write_arm_simulation(str(path), dataset, truth)
        result = calibrate(load_dataset(path)).robot
        for role, (_, pose) in truth.mounts.items():
            entry = result["mounts"][role]
            e = _error(entry[KEYS[role]], pose)
            nees[role].append(float(e @ np.linalg.solve(np.array(entry["covariance"]), e)))
        offset = result["joint_offsets"][OFFSET[robot]]
        nees["offset"].append(((offset["offset_deg"] - 0.5) / (offset["sigma3_deg"] / 3)) ** 2)
    return nees


def _in_band(values, dof, runs, alpha=0.001) -> bool:
    lo, hi = chi2.ppf(alpha / 2, dof * runs) / runs, chi2.ppf(1 - alpha / 2, dof * runs) / runs
    return lo <= float(np.mean(values)) <= hi


@pytest.mark.parametrize("robot,eye_in_hand", [("arm6", False), ("panda", True)])
def test_monte_carlo_fast(tmp_path, robot, eye_in_hand) -> None:
    runs = 8
    nees = _monte_carlo(tmp_path, robot, eye_in_hand, runs)
    for key, dof in (("camera", 6), ("target", 6), ("offset", 1)):
        assert _in_band(nees[key], dof, runs), (key, np.mean(nees[key]))


@pytest.mark.slow
@pytest.mark.parametrize("robot,eye_in_hand", [("arm6", False), ("panda", True), ("panda", False), ("arm6", True)])
def test_monte_carlo_truth_within_3_sigma(tmp_path, robot, eye_in_hand) -> None:
    runs = 50
    nees = _monte_carlo(tmp_path, robot, eye_in_hand, runs)
    for key, dof in (("camera", 6), ("target", 6), ("offset", 1)):
        assert _in_band(nees[key], dof, runs, alpha=0.01), (key, np.mean(nees[key]))
        # 3 sigma: the 0.27 % two-sided tail per degree of freedom, allowing for the runs' chance
        assert np.mean(np.array(nees[key]) > chi2.ppf(0.9973, dof)) <= 0.06, key
    print(robot, eye_in_hand, {k: round(float(np.mean(v)), 3) for k, v in nees.items()})


def test_the_readme_arm_example_runs_and_holds_the_truth(tmp_path) -> None:
    from conftest import REPO

    example = REPO / "examples" / "arm6" / "arm6_mirror.json"
    assert "mirror-fg calibrate examples/arm6/arm6_mirror.json" in (REPO / "README.md").read_text()
    out = tmp_path / "arm.json"
    assert main(["calibrate", str(example), "-o", str(out), "-q"]) == 0
    result = json.loads(out.read_text())
    truth = json.loads(example.with_name("arm6_mirror.truth.json").read_text())
    for role, key in KEYS.items():
        entry = result["mounts"][role]
        true_pose = tuple(np.array(truth["mounts"][role][key][k]) for k in ("R", "t"))
        delta = _error(entry[key], true_pose)
        bounds = np.concatenate([np.radians(entry["sigma3"]["rotation_deg"]), np.array(entry["sigma3"]["position_mm"]) / 1000])
        assert np.all(np.abs(delta) < bounds), (role, delta / bounds)


def test_report_of_an_arm_predicts_through_the_kinematics(tmp_path) -> None:
    from conftest import REPO
    from mirror_fg.report.robot import figure_arm, robot_residuals

    example = REPO / "examples" / "arm6" / "arm6_mirror.json"
    out = tmp_path / "arm.json"
    assert main(["calibrate", str(example), "-o", str(out), "-q"]) == 0
    result = json.loads(out.read_text())
    residuals = robot_residuals(result, load_dataset(example), str(out))
    assert residuals.rms == pytest.approx(result["residuals"]["rms_px"], rel=1e-6)
    figure = figure_arm(result, load_dataset(example))
    assert "arm poses in base_link" in figure.axes[0].get_title()
    assert main(["report", str(out), str(example), "-o", str(tmp_path / "report")]) == 0
    assert "Arm, camera, mirrors and target" in (tmp_path / "report" / "report.html").read_text()


def test_the_summary_names_each_mount_on_its_link(tmp_path, capsys) -> None:
    from conftest import REPO

    example = REPO / "examples" / "arm6" / "arm6_mirror.json"
    assert main(["calibrate", str(example), "-o", str(tmp_path / "arm.json"), "--no-ros"]) == 0
    out = capsys.readouterr().out
    assert "T_link_cam  the camera on link base_link" in out and "T_link_target  the target on link tool0" in out
    assert "3-sigma bounds in tool0 axes" in out
