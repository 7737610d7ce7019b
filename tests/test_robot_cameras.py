"""An arm with several cameras (docs/formats.md, "Robot arms", several cameras): ``mounts.cameras`` beside
``cameras``, each image's camera pose from its own camera's mount. The MLE (solver/batch/robot_solve.py)
against the independent reference (tests/robot_reference.py: scipy least_squares, yourdfpy kinematics)
within 0.05 sigma and 15 % in the covariances; the start needs no truth; the truth within its bounds over
a Monte Carlo (NEES in its chi-square band); bad mounts one line, exit 2; the result, its summary, URDF side
file and report read back."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pinocchio")
pytest.importorskip("yourdfpy")

from robot_reference import reference_mle  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.core.errors import DatasetError  # noqa: E402
from mirror_fg.io.dataset import dataset_from_dict, load_dataset  # noqa: E402
from mirror_fg.io.robot_fields import robot_to_dict  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.calibrate import calibrate  # noqa: E402

OFFSET = {"arm6": "shoulder_lift_joint", "panda": "panda_joint2"}
#: (arm, eye-in-hand, the second camera's link or None: the first's): two cameras on the base; two on the
#: tool; one on the base and one on the forearm (neither it nor the target on the base: placed from the other's start)
SETUPS = [("arm6", False, None), ("panda", True, None), ("arm6", False, "forearm_link")]


def _simulate(robot, eye_in_hand, link, seed, poses=6, sigma=0.5):
    return simulate_arm(robot, eye_in_hand, placements=3, arm_poses=poses, pixel_sigma=sigma,
                        joint_offsets_deg={OFFSET[robot]: 0.5}, seed=seed, cameras=2,
                        camera_links=(link,) if link else ())


def _solve(tmp_path: Path, dataset, truth):
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    return calibrate(load_dataset(path))


def _pose(entry):
    return np.array(entry["R"], float), np.array(entry["t"], float)


def _error(R_est, t_est, R_ref, t_ref):
    """``[dtheta, dt]`` with ``R_ref = Exp(dtheta) R_est``, ``t_ref = t_est + dt`` (the uncertainty convention)."""
    return np.concatenate([Rotation.from_matrix(R_ref @ R_est.T).as_rotvec(), t_ref - t_est])


def _mount_entries(result) -> dict:
    """``{role: (entry, pose key)}`` of the result's mounts, roles as the reference's (``camera:NAME``)."""
    mounts = result.robot["mounts"]
    out = {f"camera:{name}": (entry, "T_link_cam") for name, entry in mounts["cameras"].items()}
    out["target"] = (mounts["target"], "T_link_target")
    return out


@pytest.mark.parametrize("robot,eye_in_hand,link", SETUPS)
def test_mle_equals_the_independent_reference(tmp_path, robot, eye_in_hand, link) -> None:
    dataset, truth = _simulate(robot, eye_in_hand, link, seed=5, poses=4)
    assert {im["camera"] for im in dataset["images"]} == {"cam0", "cam1"}
    result = _solve(tmp_path, dataset, truth)
    start = {f"camera:{n}": pose for n, (_, pose) in truth.cameras.items()}
    start["target"] = truth.mounts["target"][1]
    ref = reference_mle(dataset, arm_urdf(robot), start, {m: v for (_, m), v in truth.mirror_vectors.items()})
    assert result.final_error == pytest.approx(ref.cost, rel=1e-6)
    entries = _mount_entries(result)
    assert set(entries) == set(ref.layout) - {0, 1, 2, "offsets"}
    for role, (entry, key) in entries.items():
        delta = _error(*_pose(entry[key]), *ref.mounts[role])
        C_ref = ref.covariance[ref.layout[role], ref.layout[role]]
        assert np.all(np.abs(delta) < 0.05 * np.sqrt(np.diag(C_ref))), (role, delta / np.sqrt(np.diag(C_ref)))
        C = np.array(entry["covariance"])
        assert np.allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(C_ref)), rtol=0.15), role
        assert np.linalg.norm(C - C_ref) < 0.15 * np.linalg.norm(C_ref), role
    for (l, m), v in result.mirror_vectors.items():
        C_ref = ref.covariance[ref.layout[m], ref.layout[m]]
        assert np.all(np.abs(v - ref.planes[m]) < 0.05 * np.sqrt(np.diag(C_ref)))
        assert np.allclose(np.sqrt(np.diag(result.mirror_covariances[(l, m)])), np.sqrt(np.diag(C_ref)), rtol=0.15)
    offset = result.robot["joint_offsets"][OFFSET[robot]]
    sigma_ref = math.degrees(math.sqrt(ref.covariance[ref.layout["offsets"], ref.layout["offsets"]][0, 0]))
    assert abs(offset["offset_deg"] - math.degrees(ref.offsets[0])) < 0.05 * sigma_ref
    assert offset["sigma3_deg"] / 3.0 == pytest.approx(sigma_ref, rel=0.15)
    # the top-level pose and mounts.camera are the first camera's mount (single-camera readers keep working)
    first = result.robot["mounts"]["cameras"]["cam0"]
    assert result.robot["mounts"]["camera"] == first
    R, t = _pose(first["T_link_cam"])
    assert np.allclose(result.R_base_cam, R) and np.allclose(result.t_base_cam, t)


def _nees(result, truth) -> tuple[float, int]:
    """The NEES of every mount and the joint offset against the truth, and its degrees of freedom."""
    total, dof = 0.0, 0
    true = {f"camera:{n}": pose for n, (_, pose) in truth.cameras.items()}
    true["target"] = truth.mounts["target"][1]
    for role, (entry, key) in _mount_entries(result).items():
        e = _error(*_pose(entry[key]), *true[role])
        total += float(e @ np.linalg.solve(np.array(entry["covariance"]), e))
        dof += 6
    for name, entry in result.robot["joint_offsets"].items():
        e = entry["offset_deg"] - math.degrees(truth.joint_offsets[name])
        total += (e / (entry["sigma3_deg"] / 3.0)) ** 2
        dof += 1
    return total, dof


def _monte_carlo(tmp_path: Path, runs: int, setups) -> None:
    total, dof, inside, components = 0.0, 0, 0, 0
    for k in range(runs):
        robot, eye_in_hand, link = setups[k % len(setups)]
        dataset, truth = _simulate(robot, eye_in_hand, link, seed=100 + k, poses=4)
        result = _solve(tmp_path, dataset, truth)
        nees, d = _nees(result, truth)
        total, dof = total + nees, dof + d
        true = {f"camera:{n}": pose for n, (_, pose) in truth.cameras.items()}
        true["target"] = truth.mounts["target"][1]
        for role, (entry, key) in _mount_entries(result).items():
            e = _error(*_pose(entry[key]), *true[role])
            inside += int(np.sum(np.abs(e) <= 3.0 * np.sqrt(np.diag(np.array(entry["covariance"])))))
            components += 6
    print(f"NEES {total:.1f} of {dof} degrees of freedom over {runs} runs; {inside} of {components} mount "
          "components within 3 sigma")
    assert chi2.ppf(0.005, dof) < total < chi2.ppf(0.995, dof), (total, dof)
    assert inside >= 0.98 * components, (inside, components)  # 99.7 % expected within 3 sigma


def test_truth_within_its_bounds_small_monte_carlo(tmp_path) -> None:
    _monte_carlo(tmp_path, 12, SETUPS)


@pytest.mark.slow
def test_truth_within_its_bounds_monte_carlo(tmp_path) -> None:
    _monte_carlo(tmp_path, 51, SETUPS)


# --- the format: bad mounts, round trip, outputs ---------------------------------------------------------------

@pytest.fixture(scope="module")
def two_cameras():
    return _simulate("arm6", False, None, seed=3, poses=4)


def _refused(tmp_path: Path, two_cameras, edit, capsys) -> str:
    dataset, truth = two_cameras
    dataset = json.loads(json.dumps(dataset))
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    edit(dataset)
    path.write_text(json.dumps(dataset))
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "-q"]) == 2
    assert not out.exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


def _single(d) -> None:
    d["camera"] = d.pop("cameras")["cam0"]
    for image in d["images"]:
        image.pop("camera")


@pytest.mark.parametrize("edit,words", [
    (lambda d: d["mounts"]["cameras"].pop("cam1"), ["mounts.cameras", "camera 'cam1' has no mount"]),
    (lambda d: d["mounts"]["cameras"].update(cam7={"link": "base_link"}), ["mounts.cameras", "'cam7'",
                                                                           "not one of the cameras (cam0, cam1)"]),
    (lambda d: d["mounts"].update(camera={"link": "base_link"}), ["mounts.camera", "several cameras",
                                                                  "mounts.cameras"]),
    (lambda d: d["mounts"].pop("cameras"), ["camera 'cam0' has no mount"]),
    (lambda d: (_single(d), d["mounts"].update(cameras={"cam0": {"link": "base_link"}})),
     ["mounts.cameras", "one camera"]),
    (lambda d: d["mounts"]["cameras"]["cam1"].update(link="tool9"), ["mounts.cameras.cam1", "'tool9'", "not a link"]),
    (lambda d: d["mounts"]["cameras"].update(cam1="base_link"), ["mounts.cameras.cam1", "expected an object"]),
])
def test_bad_camera_mounts_are_one_line_exit_2(tmp_path, two_cameras, capsys, edit, words) -> None:
    err = _refused(tmp_path, two_cameras, edit, capsys)
    for word in words:
        assert word in err, err


def test_the_format_round_trips(tmp_path, two_cameras) -> None:
    dataset, truth = two_cameras
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    ds = load_dataset(path)
    assert ds.robot.cameras is not None and list(ds.robot.cameras) == ["cam0", "cam1"]
    assert robot_to_dict(ds.robot)["mounts"] == dataset["mounts"]
    again = dataset_from_dict({**dataset, **robot_to_dict(ds.robot)}, str(path))
    assert robot_to_dict(again.robot) == robot_to_dict(ds.robot)


def test_cli_simulate_calibrate_report_outputs(tmp_path, capsys) -> None:
    data = tmp_path / "two.json"
    assert main(["simulate", "--robot", "arm6", "--cameras", "2", "--arm-poses", "4", "--sigma", "0.5",
                 "-o", str(data), "-q"]) == 0
    dataset = json.loads(data.read_text())
    assert list(dataset["cameras"]) == ["cam0", "cam1"] and list(dataset["mounts"]["cameras"]) == ["cam0", "cam1"]
    truth = json.loads((tmp_path / "two.truth.json").read_text())
    assert list(truth["mounts"]["cameras"]) == ["cam0", "cam1"] and "camera" not in truth["mounts"]
    out = tmp_path / "two.result.json"
    assert main(["calibrate", str(data), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "the camera 'cam0' on link base_link" in printed and "the camera 'cam1' on link base_link" in printed
    result = json.loads(out.read_text())
    for name in ("cam0", "cam1"):
        entry = result["mounts"]["cameras"][name]
        t_true = np.array(truth["mounts"]["cameras"][name]["T_link_cam"]["t"])
        sigma = np.sqrt(np.diag(np.array(entry["covariance"])))[3:]
        assert np.all(np.abs(np.array(entry["T_link_cam"]["t"]) - t_true) < 4 * sigma)
    urdf = (tmp_path / "two.result.urdf.xml").read_text()
    for name in ("cam0", "cam1"):
        assert f'<child link="{name}_optical_frame"/>' in urdf
    import xml.etree.ElementTree as ET
    ET.fromstring(urdf)  # a well-formed URDF


@pytest.mark.slow
def test_report_reads_each_cameras_mount(tmp_path, two_cameras) -> None:
    dataset, truth = two_cameras
    data = tmp_path / "two.json"
    write_arm_simulation(str(data), dataset, truth)
    out = tmp_path / "two.result.json"
    assert main(["calibrate", str(data), "-o", str(out), "-q"]) == 0
    report = tmp_path / "report"
    assert main(["report", str(out), str(data), "-o", str(report), "-q"]) == 0
    assert (report / "report.html").stat().st_size > 0


def test_report_residuals_through_each_cameras_mount(tmp_path, two_cameras) -> None:
    from mirror_fg.report.robot import robot_residuals

    dataset, truth = two_cameras
    data = tmp_path / "two.json"
    write_arm_simulation(str(data), dataset, truth)
    ds = load_dataset(data)
    result = calibrate(ds).to_dict()
    residuals = robot_residuals(result, ds, "result")
    assert np.sqrt(np.mean(np.sum((residuals.predicted - residuals.observed) ** 2, axis=1))) < 3 * 0.5
    swapped = json.loads(json.dumps(result))
    cams = swapped["mounts"]["cameras"]
    cams["cam0"], cams["cam1"] = cams["cam1"], cams["cam0"]  # each camera read from its own entry: now wrong
    wrong = robot_residuals(swapped, ds, "result")
    assert np.sqrt(np.nanmean(np.sum((wrong.predicted - wrong.observed) ** 2, axis=1))) > 10
    del swapped["mounts"]["cameras"]["cam1"]
    with pytest.raises(DatasetError, match="mounts.cameras.cam1"):
        robot_residuals(swapped, ds, "result")


def test_plan_bounds_every_cameras_mount(tmp_path, capsys) -> None:
    from mirror_fg.robot.plan import arm_bounds

    bounds = arm_bounds("arm6", False, 3, 4, 0.5, draws=1, seed=1, folder=str(tmp_path), cameras=2)
    assert list(bounds) == ["camera:cam0", "camera:cam1", "target"]
    assert all(0 < x < 20 for b in bounds.values() for x in b["position_mm"])
    assert main(["plan", "--robot", "arm6", "--cameras", "2", "--arm-poses", "4", "--draws", "1", "--sigma", "0.5"]) == 0
    printed = capsys.readouterr().out
    assert "camera cam0 mount 3-sigma" in printed and "camera cam1 mount 3-sigma" in printed


def test_joint_candidates_refuse_several_cameras_in_one_line(tmp_path, two_cameras, capsys) -> None:
    dataset, truth = two_cameras
    data = tmp_path / "two.json"
    write_arm_simulation(str(data), dataset, truth)
    names = list(dataset["images"][0]["joints"])
    (tmp_path / "reach.csv").write_text(",".join(names) + "\n" + ",".join("0.1" for _ in names) + "\n")
    assert main(["plan", "--next", str(data), "--joint-candidates", str(tmp_path / "reach.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "one camera" in err and len(err.splitlines()) == 1


def test_a_capture_with_cameras_and_joint_states_calibrates_as_its_dataset(tmp_path, two_cameras) -> None:
    import csv

    dataset, truth = two_cameras
    write_arm_simulation(str(tmp_path / "arm.json"), dataset, truth)
    names = list(dataset["images"][0]["joints"])
    with open(tmp_path / "joints.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["image", *names])
        for image in dataset["images"]:
            writer.writerow([image["id"], *[repr(image["joints"][n]) for n in names]])
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1, "cameras": dataset["cameras"], "pixel_sigma": 0.5,
        "target": {"kind": "points", "fiducials": dataset["fiducials"]},
        "robot": dataset["robot"], "mounts": dataset["mounts"], "joints": {"file": "joints.csv"},
        "images": [{"id": im["id"], "camera": im["camera"], "mirror_configs": im["mirror_configs"],
                    "observations": im["observations"]} for im in dataset["images"]],
    }
    (tmp_path / "capture.json").write_text(json.dumps(capture))
    assert main(["calibrate", str(tmp_path / "capture.json"), "-o", str(tmp_path / "a.json"), "-q", "--no-ros"]) == 0
    assert main(["calibrate", str(tmp_path / "arm.json"), "-o", str(tmp_path / "b.json"), "-q", "--no-ros"]) == 0
    a = json.loads((tmp_path / "a.json").read_text())["mounts"]["cameras"]
    b = json.loads((tmp_path / "b.json").read_text())["mounts"]["cameras"]
    for name in ("cam0", "cam1"):
        assert np.allclose(a[name]["T_link_cam"]["t"], b[name]["T_link_cam"]["t"], atol=1e-9)
        assert np.allclose(a[name]["covariance"], b[name]["covariance"], rtol=1e-6, atol=1e-15)
