"""verify's p-value is the chi-square tail with the degrees of freedom the new images see (docs/formats.md,
"Has it moved?"): with one mirror placement (3 seen) a 6-dof tail would hide a move."""
from __future__ import annotations

import pytest
from scipy import stats
from test_verify import _scene

from mirror_fg.analysis.verify import verify


@pytest.mark.parametrize("placements, dof", [(1, 3), (2, 5)])
def test_the_p_value_uses_the_degrees_of_freedom_seen(placements, dof):
    stored, new, _ = _scene(new_images=placements)
    stored = {k: v for k, v in stored.items() if k != "dispersion"} if isinstance(stored, dict) else stored
    if not isinstance(stored, dict):
        stored.dispersion = None  # without a stored dispersion the test is the chi-square (docs/formats.md)
    answer = verify(stored, new).cameras["camera"]
    assert answer.dof == dof and answer.mahalanobis2 > 0
    assert answer.p_value == pytest.approx(stats.chi2.sf(answer.mahalanobis2, dof), rel=1e-9)


def test_the_statistic_is_the_move_s_mahalanobis_distance():
    """Linearised, ``d2 = 2 (cost_held - cost_free)`` is ``move^T C^-1 move`` with ``C = S + N^-1`` (the
    module docstring of analysis/verify.py): the fits' cost difference against the move and its covariance."""
    import numpy as np

    stored, new, _ = _scene(new_images=3)
    answer = verify(stored, new).cameras["camera"]
    assert answer.dof == 6
    distance = float(answer.move @ np.linalg.solve(answer.covariance, answer.move))
    assert 0.8 < answer.mahalanobis2 / distance < 1.25, (answer.mahalanobis2, distance)


def test_the_update_writes_the_base_camera_covariance_of_the_inverse():
    """``--update``'s covariance_base_cam is the fused covariance_cam_base carried through the inversion
    (uncertainty convention ``R' = Exp(dtheta) R``, ``t' = t + dt``), against central differences."""
    import gtsam
    import numpy as np

    from mirror_fg.io.verification import updated_result

    stored, _, _ = _scene()
    result = stored.to_dict()
    R, t, P = np.array(result["T_cam_base"]["R"]), np.array(result["T_cam_base"]["t"]), 0.5 * np.array(result["covariance_cam_base"])
    out = updated_result(result, (R, t, P), "stored.json", "new.json", 3)
    R_bc, t_bc = R.T, -R.T @ t
    J = np.zeros((6, 6))
    h = 1e-6
    for k in range(6):
        ends = []
        for sign in (1.0, -1.0):
            step = sign * h * np.eye(6)[k]
            R_moved = gtsam.Rot3.Expmap(step[:3]).matrix() @ R
            t_moved = t + step[3:]
            ends.append(np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R_moved.T @ R_bc.T)), -R_moved.T @ t_moved - t_bc]))
        J[:, k] = (ends[0] - ends[1]) / (2 * h)
    np.testing.assert_allclose(out["covariance_cam_base"], P, rtol=1e-12)
    np.testing.assert_allclose(out["covariance_base_cam"], J @ P @ J.T, rtol=1e-5, atol=1e-12 * np.abs(P).max())


def test_the_move_is_new_minus_stored():
    """Noise-free new images of the camera moved by 0.5 deg about x and 4 mm along y: the move (new minus
    stored, ``R_new = Exp(dtheta) R_stored``, ``t_new = t_stored + dt``) is that move within the stored
    estimate's own error."""
    import numpy as np

    from mirror_fg.analysis.verify_study import moved_data

    stored, new, truth = _scene()
    shift = np.array([np.radians(0.5), 0.0, 0.0, 0.0, 0.004, 0.0])
    still = verify(stored, moved_data(new, truth, np.zeros(6), 0.0, None)).cameras["camera"]
    moved = verify(stored, moved_data(new, truth, shift, 0.0, None)).cameras["camera"]
    # the stored estimate's error cancels in the difference of the two moves (first order)
    np.testing.assert_allclose(moved.move - still.move, shift, atol=2e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_held_pose_s_prior_with_the_intrinsics_marginal_is_the_stored_joint_prior(seed):
    """The pose's prior given the intrinsics (analysis/verify_priors.py) with the intrinsics' marginal prior is
    the stored joint Gaussian exactly: GTSAM's joint marginal of the two priors alone equals the stored joint
    covariance of ``[xi (GTSAM's [w, nu]), kappa]``, ``xi = blkdiag(R, R)^T [dtheta, dt]``."""
    import gtsam
    import numpy as np

    from factors.intrinsics import IntrinsicsModel
    from mirror_fg.analysis.verify_priors import StoredIntrinsics, joint_prior

    rng = np.random.default_rng(seed)
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    stored_pose = gtsam.Pose3(gtsam.Rot3(R), rng.normal(size=3))
    root = np.r_[np.full(6, 1e-3), [2.0, 3.0, 0.5, 0.4]][:, None] * rng.normal(size=(10, 10))  # rad / m, px
    joint = root @ root.T  # [dtheta, dt, fx, fy, cx, cy], the convention's order
    J = np.kron(np.eye(2), R)  # [dtheta, dt] = J xi
    expected = joint.copy()
    expected[:6, :6] = J.T @ joint[:6, :6] @ J
    expected[:6, 6:] = J.T @ joint[:6, 6:]
    expected[6:, :6] = expected[:6, 6:].T
    values0 = np.array([800.0, 810.0, 320.0, 240.0])
    model = IntrinsicsModel(np.array([800.0, 810.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0]), ["fx", "fy", "cx", "cy"])
    stored = StoredIntrinsics(model, values0, joint[6:, 6:], joint[6:, :6])
    pose_key, intrinsics_key = 1, 2
    graph = gtsam.NonlinearFactorGraph()
    graph.add(joint_prior(pose_key, intrinsics_key, stored_pose, stored, expected[:6, :6]))
    graph.add(stored.marginal_prior(intrinsics_key))
    values = gtsam.Values()
    values.insert(pose_key, stored_pose)
    values.insert(intrinsics_key, values0)
    found = gtsam.Marginals(graph, values).jointMarginalCovariance(gtsam.KeyVector([pose_key, intrinsics_key])).fullMatrix()
    np.testing.assert_allclose(found, expected, rtol=1e-6, atol=1e-9 * np.abs(expected).max())


def test_the_detectable_move_is_detected_in_every_direction():
    """The detectable move is stated for the worst direction: a pure rotation or translation of that size in
    any direction has a non-centrality at least lambda* (power 0.9 at alpha 0.01, solved here with scipy's
    non-central chi-square), and in the worst direction exactly lambda*."""
    import numpy as np
    from scipy import optimize

    stored, new, _ = _scene(new_images=3)
    stored.dispersion = None  # the chi-square test (docs/formats.md)
    answer = verify(stored, new, alpha=0.01).cameras["camera"]
    assert answer.dof == 6
    critical = stats.chi2.isf(0.01, 6)
    ncp = optimize.brentq(lambda x: stats.ncx2.sf(critical, 6, x) - 0.9, 1e-6, 1e3)
    directions = np.random.default_rng(0).normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    for block, size in ((slice(0, 3), answer.detectable_rad), (slice(3, 6), answer.detectable_m)):
        information = np.linalg.inv(answer.covariance[block, block])  # the block's marginal
        found = size**2 * np.einsum("ni,ij,nj->n", directions, information, directions)
        assert found.min() >= ncp * (1 - 1e-9)
        worst = np.linalg.eigh(answer.covariance[block, block])[1][:, -1]
        assert size**2 * worst @ information @ worst == pytest.approx(ncp, rel=1e-6)


def test_a_rig_is_moved_when_any_camera_moved():
    """docs/formats.md: the verification says `moved` (exit 4) if any camera moved, even where another cannot
    tell; `cannot tell` (exit 5) only where none moved."""
    import math

    from mirror_fg.analysis.verify import CANNOT_TELL, MOVED, NOT_MOVED, CameraVerdict, Verification

    def camera(name, verdict):
        return CameraVerdict(name, verdict, 0.5, 1.0, 6, None, None, math.inf, math.inf, "")

    for verdicts, expected, status in (((MOVED, CANNOT_TELL), MOVED, 4), ((CANNOT_TELL, MOVED, NOT_MOVED), MOVED, 4),
                                       ((NOT_MOVED, CANNOT_TELL), CANNOT_TELL, 5), ((NOT_MOVED, NOT_MOVED), NOT_MOVED, 0)):
        rig = Verification({f"c{k}": camera(f"c{k}", v) for k, v in enumerate(verdicts)}, 0.01, 2.0, 0.2, {})
        assert (rig.verdict, rig.exit_code) == (expected, status), verdicts
