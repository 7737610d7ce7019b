"""solver.model.rig: Kalibr's T_cn_cnm1 chain and its covariance propagated from the joint covariance, against
numerical Jacobians of the exact perturbation and a Monte Carlo of the cameras' joint errors."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mirror_fg.solver.model.rig import RigTransform, rig_jacobian, rig_transforms
from rig_calibration import random_poses, random_spd


def _exp(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(w).as_matrix()


def _log(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def _relative(R_a, t_a, R_b, t_b):
    """T_b_base T_a_base^-1 written out independently of Transform."""
    R = R_b @ R_a.T
    return R, t_b - R @ t_a


def _perturbed_error(R_a, t_a, R_b, t_b, delta):
    """[dtheta, dt] of the rig when the cameras' T_cam_base are perturbed by delta = [da, dta, db, dtb]
    in docs/formats.md's convention (R_true = Exp(dtheta) R, t_true = t + dt), exactly."""
    R0, t0 = _relative(R_a, t_a, R_b, t_b)
    R1, t1 = _relative(_exp(delta[0:3]) @ R_a, t_a + delta[3:6], _exp(delta[6:9]) @ R_b, t_b + delta[9:12])
    return np.r_[_log(R1 @ R0.T), t1 - t0]


def _perturbed_errors(R_a, t_a, R_b, t_b, deltas):
    """:func:`_perturbed_error` of many perturbations (N, 12) at once (vectorised rotations)."""
    R0, t0 = _relative(R_a, t_a, R_b, t_b)
    Ra = Rotation.from_rotvec(deltas[:, 0:3]).as_matrix() @ R_a
    Rb = Rotation.from_rotvec(deltas[:, 6:9]).as_matrix() @ R_b
    R1 = Rb @ np.transpose(Ra, (0, 2, 1))
    t1 = (t_b + deltas[:, 9:12]) - np.einsum("nij,nj->ni", R1, t_a + deltas[:, 3:6])
    return np.hstack([Rotation.from_matrix(R1 @ R0.T).as_rotvec(), t1 - t0])


@pytest.mark.parametrize("seed", range(5))
def test_rig_maps_points_of_the_previous_camera_into_the_next(seed):
    rng = np.random.default_rng(seed)
    poses = random_poses(rng, 3)
    rig = rig_transforms(["a", "b", "c"], poses, None)
    assert [(r.from_camera, r.to_camera) for r in rig] == [("a", "b"), ("b", "c")]
    points_base = rng.normal(size=(10, 3))
    in_camera = [points_base @ R.T + t for R, t in poses]
    for n, r in enumerate(rig, start=1):
        assert np.allclose(in_camera[n - 1] @ r.R.T + r.t, in_camera[n], atol=1e-12)  # x_to = R x_from + t
        assert np.allclose(r.T.apply(in_camera[n - 1]), in_camera[n], atol=1e-12)
        assert r.covariance is None and r.sigma3 is None


@pytest.mark.parametrize("seed", range(5))
def test_jacobian_matches_finite_differences_of_the_exact_perturbation(seed):
    rng = np.random.default_rng(10 + seed)
    (R_a, t_a), (R_b, t_b) = random_poses(rng, 2)
    J = rig_jacobian(R_a, t_a, R_b, t_b)
    h = 1e-6
    numeric = np.zeros((6, 12))
    for k in range(12):
        e = np.zeros(12)
        e[k] = h
        numeric[:, k] = (_perturbed_error(R_a, t_a, R_b, t_b, e) - _perturbed_error(R_a, t_a, R_b, t_b, -e)) / (2 * h)
    assert np.allclose(J, numeric, atol=1e-8), np.max(np.abs(J - numeric))


def test_covariance_matches_a_monte_carlo_of_the_joint_errors():
    rng = np.random.default_rng(3)
    poses = random_poses(rng, 3)
    P = random_spd(rng, 18)
    rig = rig_transforms(["a", "b", "c"], poses, P)
    samples = rng.multivariate_normal(np.zeros(18), P, size=40000)
    for n, r in enumerate(rig, start=1):
        (R_a, t_a), (R_b, t_b) = poses[n - 1], poses[n]
        block = samples[:, 6 * (n - 1): 6 * n + 6]
        errors = _perturbed_errors(R_a, t_a, R_b, t_b, block)
        assert np.allclose(errors[:5], [_perturbed_error(R_a, t_a, R_b, t_b, d) for d in block[:5]], atol=1e-15)
        empirical = np.cov(errors.T)
        sd = np.sqrt(np.diag(r.covariance))
        # correlation-scale agreement: 40000 samples give ~0.5 % on a variance, ~1 % on a correlation
        assert np.allclose(np.sqrt(np.diag(empirical)) / sd, 1.0, atol=0.02)
        assert np.max(np.abs((empirical - r.covariance) / np.outer(sd, sd))) < 0.03


def test_cross_covariance_between_the_cameras_is_used():
    """The same marginals with the cross terms dropped give another rig covariance: the propagation
    reads the joint block, not the two marginals."""
    rng = np.random.default_rng(4)
    poses = random_poses(rng, 2)
    P = random_spd(rng, 12)
    dropped = P.copy()
    dropped[:6, 6:] = dropped[6:, :6] = 0.0
    with_cross = rig_transforms(["a", "b"], poses, P)[0].covariance
    without = rig_transforms(["a", "b"], poses, dropped)[0].covariance
    J = rig_jacobian(*poses[0], *poses[1])
    assert np.allclose(with_cross, J @ P @ J.T, rtol=1e-12, atol=1e-20)
    assert np.max(np.abs(with_cross - without)) > 0.1 * np.max(np.abs(without))


def test_a_fully_correlated_rigid_pair_has_no_rig_uncertainty():
    """Two cameras that move together with the body (the base frame's error only) keep their rig exactly."""
    rng = np.random.default_rng(5)
    (R_a, t_a), (R_b, t_b) = random_poses(rng, 2)
    # An error of the base frame: Bp_true = Exp(phi) Bp + rho, seen as each camera's T_cam_base error.
    G = random_spd(rng, 6)
    def camera_error_of_base(R, t):
        # T_cam_base' = T_cam_base * T_base_error^-1 -> dtheta = -R phi, dt = -R rho + [R phi]x t... (linear map)
        h = 1e-7
        cols = []
        for k in range(6):
            e = np.zeros(6)
            e[k] = h
            Rb, tb = _exp(e[:3]), e[3:]
            R1 = R @ Rb.T
            t1 = t - R1 @ tb
            cols.append(np.r_[_log(R1 @ R.T), t1 - t] / h)
        return np.array(cols).T
    A = np.vstack([camera_error_of_base(R_a, t_a), camera_error_of_base(R_b, t_b)])
    P = A @ G @ A.T
    covariance = rig_transforms(["a", "b"], [(R_a, t_a), (R_b, t_b)], P)[0].covariance
    assert np.max(np.abs(covariance)) < 1e-9 * np.max(np.abs(P))


def test_sigma3_and_errors():
    r = RigTransform("a", "b", np.eye(3), np.zeros(3), np.diag([1e-6, 4e-6, 9e-6, 1e-6, 4e-6, 9e-6]))
    assert np.allclose(r.sigma3["rotation_deg"], np.degrees([3e-3, 6e-3, 9e-3]))
    assert np.allclose(r.sigma3["position_mm"], [3.0, 6.0, 9.0])
    with pytest.raises(ValueError, match="12 x 12"):
        rig_transforms(["a", "b"], random_poses(np.random.default_rng(0), 2), np.eye(6))
    with pytest.raises(ValueError, match="2 camera names but 1 poses"):
        rig_transforms(["a", "b"], random_poses(np.random.default_rng(0), 1), None)
    assert rig_transforms(["a"], random_poses(np.random.default_rng(0), 1), np.eye(6)) == []
