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
