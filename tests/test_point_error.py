"""The error at a point (solver/result/point_error.py, ``Calibration.point_error``, result@1 ``at``): against a Monte
Carlo of the result's own covariance and against the simulator's truth (NEES over simulated runs)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from mirror_fg.core.transform import Transform
from mirror_fg.io.result import validate_result
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.result.point_error import parse_point, point_error
from mirror_fg.simulate.tree import simulate_base_case

GRASPS = [(0.0, 0.0, 0.6), (0.3, -0.2, 1.0), (-0.5, 0.4, 2.0)]


@pytest.fixture(scope="module")
def calibration():
    dataset, truth = simulate_base_case(num_images=60, seed=3)
    return calibrate(dataset, diagnose=False), truth


def test_point_error_matches_a_monte_carlo_of_the_results_own_covariance(calibration):
    """Sampled from ``covariance_cam_base`` (camera axes), each sample's ``T_cam_base`` inverted exactly and
    applied to the point: the spread of the point in {B} is the first-order covariance within 3 %."""
    cal, _ = calibration
    result = cal.to_dict()
    T_cam_base = Transform(np.array(result["T_cam_base"]["R"]), np.array(result["T_cam_base"]["t"]))
    P = np.array(result["covariance_cam_base"])
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(np.zeros(6), P, size=100_000)
    R_samples = Rotation.from_rotvec(samples[:, :3]).as_matrix() @ T_cam_base.R  # R_true = Exp(dtheta) R
    t_samples = T_cam_base.t + samples[:, 3:]
    for p in GRASPS:
        moved = np.einsum("nji,nj->ni", R_samples, np.asarray(p) - t_samples)  # T_cam_base^-1 p = R^T (p - t)
        empirical = np.cov(moved.T)
        got = cal.point_error(p)
        np.testing.assert_allclose(got.point_base, T_cam_base.inverse().apply(p), atol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(got.covariance)), np.sqrt(np.diag(empirical)), rtol=0.03)
        # the worst direction too (not only along the axes)
        assert got.largest_sigma3_mm == pytest.approx(3000 * np.sqrt(np.linalg.eigvalsh(empirical)[-1]), rel=0.03)


def test_point_error_is_in_the_result_and_validates(calibration):
    cal, _ = calibration
    cal.at_points = [GRASPS[0], GRASPS[2]]
    try:
        result = validate_result(cal.to_dict(), "test")
    finally:
        cal.at_points = []
    assert [e["point_cam"] for e in result["at"]] == [list(GRASPS[0]), list(GRASPS[2])]
    for entry in result["at"]:
        C = np.array(entry["covariance"])
        assert C.shape == (3, 3)
        np.testing.assert_allclose(entry["sigma3_mm"], 3000 * np.sqrt(np.diag(C)))
    # farther from the camera, a rotation error moves the point more
    assert max(result["at"][1]["sigma3_mm"]) > max(result["at"][0]["sigma3_mm"])


def test_point_at_the_camera_centre_has_the_position_bounds(calibration):
    """At p_cam = 0 the point is the camera centre: its 3-sigma is sigma3_base_cam's position bounds."""
    cal, _ = calibration
    np.testing.assert_allclose(cal.point_error([0, 0, 0]).sigma3_mm, cal.to_dict()["sigma3_base_cam"]["position_mm"],
                               rtol=1e-9)


def test_bad_points_are_refused_in_words():
    with pytest.raises(ValueError, match="X,Y,Z"):
        parse_point("0,0")
    with pytest.raises(ValueError, match="X,Y,Z"):
        parse_point("0,nan,1")
    assert parse_point(" 0.1, -0.2 ,0.6") == (0.1, -0.2, 0.6)
    with pytest.raises(ValueError, match="three finite"):
        point_error(Transform.identity(), np.eye(6), [0, 1])


def _nees(runs: int, images: int) -> np.ndarray:
    """NEES (3 dof) of the point error of each simulated run against the simulator's truth."""
    nees = []
    for seed in range(runs):
        dataset, truth = simulate_base_case(num_images=images, seed=100 + seed)
        cal = calibrate(dataset, diagnose=False)
        T_true = Transform(truth.R_cam_base, truth.t_cam_base).inverse()
        p = GRASPS[seed % len(GRASPS)]
        got = cal.point_error(p)
        e = got.point_base - T_true.apply(p)
        nees.append(float(e @ np.linalg.solve(got.covariance, e)))
    return np.array(nees)


def _assert_in_band(nees: np.ndarray) -> None:
    n = len(nees)
    low, high = chi2.ppf(0.005, 3 * n) / n, chi2.ppf(0.995, 3 * n) / n
    assert low <= np.mean(nees) <= high, f"mean NEES {np.mean(nees):.3f} outside [{low:.3f}, {high:.3f}] over {n} runs"


def test_point_error_nees_against_the_truth_fast():
    _assert_in_band(_nees(8, 30))


@pytest.mark.slow
def test_point_error_nees_against_the_truth_over_100_runs():
    _assert_in_band(_nees(100, 60))
