"""The arm's analytical start (solver/start/robot_start.py): noise-free, every start (all placements peeled at
once, and each triple's restart) is the truth; a first start that ends badly is followed by restarts."""
from __future__ import annotations

import logging

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.io.dataset import load_dataset  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.batch import robot_solve  # noqa: E402
from mirror_fg.solver.batch.robot_solve import calibrate_robot, start_estimate  # noqa: E402
from mirror_fg.solver.model.robot_views import RobotProblem  # noqa: E402


def _data(tmp_path, eye_in_hand, sigma):
    dataset, truth = simulate_arm("panda" if eye_in_hand else "arm6", eye_in_hand, placements=4, arm_poses=5,
                                  pixel_sigma=sigma, seed=9)
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    return load_dataset(path), truth


@pytest.mark.parametrize("eye_in_hand", [False, True])
def test_every_start_is_the_truth_without_noise(tmp_path, eye_in_hand) -> None:
    ds, truth = _data(tmp_path, eye_in_hand, 1e-6)
    starts = start_estimate(RobotProblem(ds), max_starts=5)
    assert len(starts) == 5  # all four placements, then the four triples
    for start in starts:
        for role, (_, (R, t)) in truth.mounts.items():
            assert np.allclose(start.mounts[role][0], R, atol=1e-5) and np.allclose(start.mounts[role][1], t, atol=1e-5)
        for p, v in truth.mirror_vectors.items():
            assert np.allclose(start.mirror_vectors[p], v, atol=1e-5)


def test_a_start_that_ends_badly_is_followed_by_restarts(tmp_path, monkeypatch, caplog) -> None:
    ds, truth = _data(tmp_path, False, 0.5)
    real = robot_solve.arm_start

    def first_wrong(images, eye_to_hand, source, max_starts=1):
        starts = real(images, eye_to_hand, source, max_starts)
        M_c, M_t, planes = starts[0]
        flipped = ({p: -0.3 * v for p, v in planes.items()})  # planes behind the camera: another minimum
        return [(M_c, M_t, flipped), *starts[1:]]

    monkeypatch.setattr(robot_solve, "arm_start", first_wrong)
    with caplog.at_level(logging.INFO, logger="mirror_fg"):
        result = calibrate_robot(ds)
    assert "restart" in caplog.text
    assert result.final_error < result.expected_final_error + 10 * np.sqrt(result.expected_final_error)
    t_true = truth.mounts["target"][1][1]
    assert np.allclose(result.robot["mounts"]["target"]["T_link_target"]["t"], t_true, atol=3e-3)


def test_a_gross_corner_is_left_out_and_named(tmp_path) -> None:
    import json

    from mirror_fg.solver.calibrate import calibrate

    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=5, pixel_sigma=0.5, seed=9)
    dataset["images"][4]["observations"]["F7"][0] += 25.0
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    result = calibrate(load_dataset(path))
    assert [(e.image, e.point) for e in result.excluded] == [("p0_004", "F7")]
    del dataset["images"][4]["observations"]["F7"]
    path.write_text(json.dumps(dataset))
    clean = calibrate(load_dataset(path))
    for role, key in (("camera", "T_link_cam"), ("target", "T_link_target")):
        assert np.allclose(result.robot["mounts"][role][key]["t"], clean.robot["mounts"][role][key]["t"], atol=1e-7)


def test_the_start_takes_the_screens_pnp_minima_where_the_image_is_unchanged(tmp_path, monkeypatch) -> None:
    from mirror_fg.solver.start import robot_start
    from mirror_fg.solver.screen.consensus import check_images

    ds, _ = _data(tmp_path, False, 0.5)
    problem = RobotProblem(ds)
    alone = start_estimate(problem, max_starts=5)
    minima = check_images(ds).minima
    changed = ds.images[0].id  # an image whose fiducials differ from the screen's: its PnP solved again
    minima[changed] = (minima[changed][0][1:], minima[changed][1])
    solved = []
    real = robot_start.pnp_candidates
    monkeypatch.setattr(robot_start, "pnp_candidates", lambda *a: solved.append(1) or real(*a))
    reused = start_estimate(problem, max_starts=5, minima=minima)
    assert len(solved) == 1  # only the changed image's
    for a, b in zip(alone, reused):
        for role in a.mounts:
            assert np.array_equal(a.mounts[role][0], b.mounts[role][0]) and np.array_equal(a.mounts[role][1], b.mounts[role][1])
        assert all(np.array_equal(a.mirror_vectors[p], b.mirror_vectors[p]) for p in a.mirror_vectors)
