"""Planning an arm (mirror_fg/robot/plan.py, plan --robot, plan --next --joint-candidates): the predicted
3-sigma after a candidate arm pose is what a solve with that image added gives; the CLI ranks candidates
and refuses a bad candidates file in one line."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.io.dataset import load_dataset  # noqa: E402
from mirror_fg.robot.plan import rank_joint_candidates  # noqa: E402
from mirror_fg.robot.simulate import NOMINAL, simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.batch.robot_solve import calibrate_robot, solve_robot  # noqa: E402


@pytest.fixture()
def arm(tmp_path):
    dataset, truth = simulate_arm("panda", True, placements=3, arm_poses=5, pixel_sigma=0.5, seed=21)
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    rng = np.random.default_rng(1)
    names = list(dataset["images"][0]["joints"])
    candidates = tmp_path / "candidates.csv"
    with open(candidates, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(names)
        for _ in range(30):
            writer.writerow(np.round(np.array(NOMINAL["panda"]) + rng.uniform(-0.3, 0.3, 7), 4))
    return path, candidates, names


def test_predicted_bounds_are_those_of_the_solve_with_the_image_added(arm) -> None:
    path, candidates, names = arm
    dataset = load_dataset(path)
    rows = [{n: float(r[n]) for n in names} for r in csv.DictReader(open(candidates))]
    solution = solve_robot(dataset)
    ranked, now = rank_joint_candidates(dataset, rows, solution)
    assert 3 <= len(ranked) <= len(rows)
    best, worst = ranked[0], ranked[-1]
    assert np.linalg.norm(best.position_mm) <= np.linalg.norm(worst.position_mm)
    assert np.linalg.norm(best.position_mm) < np.linalg.norm(now["position_mm"])
    for candidate in (best, worst):  # add the image, noise-free at the estimate: the optimum stays, the bounds shrink
        data = json.loads(path.read_text())
        from mirror_fg.factors.robot import RobotViewFactor  # the prediction through the same factor
        problem = solution.problem
        points = np.array([dataset.fiducials[n] for n in dataset.fiducials]).T
        factor = RobotViewFactor((now["placement"],), problem.mount_keys, problem.known, problem.mirror_keys,
                                 problem.forward(candidate.joints), None, 0, points, [-1] * points.shape[1],
                                 np.zeros((2, points.shape[1])), np.ones((2, points.shape[1])))
        z = factor.predict(solution.values)
        pixels = dataset.camera.distort(z.T)
        data["images"].append({"id": "next", "mirror_configs": [now["placement"][1]], "joints": candidate.joints,
                               "observations": {n: pixels[k].tolist() for k, n in enumerate(dataset.fiducials)}})
        path.with_name("more.json").write_text(json.dumps(data))
        more = calibrate_robot(load_dataset(path.with_name("more.json")), initial=solution.estimate)
        position = np.array(more.robot["mounts"]["camera"]["sigma3"]["position_mm"])
        assert np.allclose(position, candidate.position_mm, rtol=1e-3), (position, candidate.position_mm)


def test_plan_next_joint_candidates_at_the_cli(arm, capsys) -> None:
    path, candidates, _ = arm
    assert main(["plan", "--next", str(path), "--joint-candidates", str(candidates), "--count", "2"]) == 0
    out = capsys.readouterr().out
    assert "the camera mount now: 3-sigma position" in out and "\n1. row " in out and "\n2. row " in out
    assert "\n3. row " not in out


def test_bad_candidates_file_is_one_line_exit_2(arm, tmp_path, capsys) -> None:
    path, candidates, names = arm
    bad = tmp_path / "bad.csv"
    bad.write_text(",".join(names[:-1]) + "\n" + ",".join(["0.1"] * (len(names) - 1)) + "\n")
    assert main(["plan", "--next", str(path), "--joint-candidates", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"no column for joint {names[-1]!r}" in err, err


def test_plan_robot_bounds_at_the_cli(tmp_path, capsys) -> None:
    out = tmp_path / "bounds.json"
    assert main(["plan", "--robot", "arm6", "--placements", "3", "--arm-poses", "5", "--sigma", "0.5",
                 "--draws", "1", "--json", str(out)]) == 0
    bounds = json.loads(out.read_text())
    assert set(bounds) == {"camera", "target"}
    assert 0.1 < max(bounds["camera"]["position_mm"]) < 30
    assert "camera mount 3-sigma" in capsys.readouterr().out
