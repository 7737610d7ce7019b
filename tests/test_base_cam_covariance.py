"""result@1's ``covariance_base_cam``, ``sigma3_base_cam`` and ``covariance_base_cam_ros``.

The bounds of ``T_base_cam`` are checked against two references that share nothing with the code under
test: GTSAM's ``Pose3.AdjointMap`` (the inverse's right-perturbation covariance is ``Ad Sigma Ad^T``) and a
Monte Carlo of the perturbation convention itself (docs/formats.md: ``R_true = Exp(dtheta) R``,
``t_true = t + dt``).
"""
from __future__ import annotations

import copy

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mirror_fg
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.result import base_cam_covariance, ros_pose_covariance, validate_result
from mirror_fg.simulate.tree import simulate_base_case


def _random_pose_and_covariance(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.uniform(-0.5, 0.5, size=3)
    L = np.tril(rng.normal(size=(6, 6))) * np.array([2e-3] * 3 + [3e-3] * 3)[:, None]
    return R, t, L @ L.T + 1e-8 * np.eye(6)


@pytest.mark.parametrize("seed", range(5))
def test_base_cam_covariance_matches_gtsam_adjoint(seed):
    R, t, P = _random_pose_and_covariance(seed)
    # docs/formats.md's [dtheta, dt] (left rotation, additive translation) -> GTSAM's right tangent [w, nu] of T_cam_base.
    J_to = np.zeros((6, 6))
    J_to[:3, :3] = R.T
    J_to[3:, 3:] = R.T
    sigma_cb = J_to @ P @ J_to.T
    # T^-1 Exp(-Ad_T xi) = (T Exp(xi))^-1: the inverse's right tangent is -Ad_T xi.
    T = gtsam.Pose3(gtsam.Rot3(R), t)
    Ad = T.AdjointMap()
    sigma_bc = Ad @ sigma_cb @ Ad.T
    # GTSAM's right tangent of T_base_cam -> docs/formats.md's convention for T_base_cam (rotation about the base axes).
    R_bc = R.T
    J_from = np.zeros((6, 6))
    J_from[:3, :3] = R_bc
    J_from[3:, 3:] = R_bc
    expected = J_from @ sigma_bc @ J_from.T
    got = base_cam_covariance(R, t, P)
    assert np.allclose(got, expected, rtol=1e-10, atol=1e-18)


def test_base_cam_covariance_matches_monte_carlo():
    R, t, P = _random_pose_and_covariance(11)
    rng = np.random.default_rng(0)
    n = 200_000
    d = rng.multivariate_normal(np.zeros(6), P, size=n)
    R_true = Rotation.from_rotvec(d[:, :3]).as_matrix() @ R  # R_true = Exp(dtheta) R
    t_true = t + d[:, 3:]
    R_bc_true = np.transpose(R_true, (0, 2, 1))
    t_bc_true = -np.einsum("nij,nj->ni", R_bc_true, t_true)
    R_bc, t_bc = R.T, -R.T @ t
    dphi = Rotation.from_matrix(R_bc_true @ R_bc.T).as_rotvec()  # R_bc_true = Exp(dphi) R_bc
    samples = np.hstack([dphi, t_bc_true - t_bc])
    empirical = np.cov(samples.T)
    got = base_cam_covariance(R, t, P)
    sd = np.sqrt(np.diag(got))
    # Standard error of a variance from n samples ~ sqrt(2/n) = 0.3 %; first-order terms neglected ~ 0.1 %.
    assert np.allclose(np.sqrt(np.diag(empirical)) / sd, 1.0, atol=0.01)
    assert np.max(np.abs((empirical - got) / np.outer(sd, sd))) < 0.02  # correlations


@pytest.fixture(scope="module")
def result() -> dict:
    ds, _ = simulate_base_case(num_images=30, num_points=1, seed=2)
    return mirror_fg.calibrate(ds).to_dict()


def test_result_holds_the_camera_pose_bounds_in_base_axes(result):
    R = np.array(result["T_cam_base"]["R"])
    t = np.array(result["T_cam_base"]["t"])
    P = np.array(result["covariance_cam_base"])
    P_bc = np.array(result["covariance_base_cam"])
    assert np.allclose(P_bc, base_cam_covariance(R, t, P), rtol=1e-12, atol=0)
    sd3 = 3.0 * np.sqrt(np.diag(P_bc))
    assert np.allclose(result["sigma3_base_cam"]["rotation_deg"], np.rad2deg(sd3[:3]))
    assert np.allclose(result["sigma3_base_cam"]["position_mm"], 1e3 * sd3[3:])
    # The base-frame bounds differ from the camera-frame ones.
    assert not np.allclose(result["sigma3_base_cam"]["position_mm"], result["sigma3_cam_base"]["position_mm"], rtol=0.05)
    ros = np.array(result["covariance_base_cam_ros"])
    assert np.allclose(ros[:3, :3], P_bc[3:, 3:]) and np.allclose(ros[3:, 3:], P_bc[:3, :3])
    assert np.allclose(ros[:3, 3:], P_bc[3:, :3])  # x y z against rot x y z
    assert np.allclose(ros_pose_covariance(P_bc), ros)
    assert validate_result(result, "r.json") == result


@pytest.mark.parametrize(
    "key, edit, words",
    [
        ("covariance_base_cam", lambda P: P * 1.1, "does not match covariance_cam_base"),
        ("covariance_base_cam_ros", lambda P: P.T * 0 + np.eye(6), "does not match covariance_base_cam"),
        ("covariance_base_cam", lambda P: P[:5, :5], "expected 6 rows"),
    ],
)
def test_inconsistent_base_cam_covariance_is_refused(result, key, edit, words):
    bad = copy.deepcopy(result)
    bad[key] = edit(np.array(bad[key])).tolist()
    with pytest.raises(DatasetError, match=f"r.json: {key}: {words}"):
        validate_result(bad, "r.json")


def test_calibration_without_covariance_writes_null_bounds():
    ds, _ = simulate_base_case(num_images=12, seed=4)
    result = mirror_fg.calibrate(ds, compute_covariance=False).to_dict()
    for key in ("covariance_cam_base", "sigma3_cam_base", "covariance_base_cam", "sigma3_base_cam",
                "covariance_base_cam_ros"):
        assert result[key] is None, key
    assert validate_result(result, "r.json") == result
