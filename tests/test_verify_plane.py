"""``verify`` with one mirror placement the stored result knows (mirror_fg/analysis/verify_plane.py and
solver/fit/placement_covariance.py, docs/formats.md "Has it moved?"): the stored joint covariance of a
placement and the camera against the solver's marginals; the plane's map into {B} and its Jacobians
against finite differences; one stored placement determines the camera (6 of 6 seen), says `not moved`
on unmoved data within alpha and `moved` on a 3-sigma move; a new placement still sees 3 of 6."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mirror_fg.analysis.verify import CANNOT_TELL, MOVED, NOT_MOVED, verify
from mirror_fg.analysis.verify_plane import base_vector
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.geometry import so3_exp
from mirror_fg.data import Image
from mirror_fg.simulate.tree import measure, simulate_base_case
from mirror_fg.solver.calibrate import calibrate

ALPHA = 0.01


def test_the_plane_in_the_base_frame_and_its_jacobians() -> None:
    rng = np.random.default_rng(0)
    R, t = so3_exp(rng.normal(size=3)), rng.normal(size=3)
    v = np.array([0.05, -0.1, 0.6])
    v_B, d_pose, d_v = base_vector(R, t, v)
    # the plane n . x = d (camera frame) through x = R x_B + t: a point on it maps onto the plane in {B}
    n, d = v / np.linalg.norm(v), np.linalg.norm(v)
    x_c = d * n + np.cross(n, [1.0, 0.0, 0.0])  # on the plane
    x_B = R.T @ (x_c - t)
    assert np.dot(v_B / np.linalg.norm(v_B), x_B) == pytest.approx(np.linalg.norm(v_B))
    h = 1e-6
    for k in range(6):
        w, nu = np.zeros(3), np.zeros(3)
        (w if k < 3 else nu)[k % 3] = h
        moved = base_vector(R @ so3_exp(w), t + R @ nu, v)[0]
        assert np.allclose((moved - v_B) / h, d_pose[:, k], atol=1e-5)
    for k in range(3):
        dv = np.zeros(3)
        dv[k] = h
        assert np.allclose((base_vector(R, t, v + dv)[0] - v_B) / h, d_v[:, k], atol=1e-5)


def _stored(seed: int):
    data, truth = simulate_base_case(num_images=20, num_mirrors=1, num_fiducials=4, pixel_sigma=1.0,
                                     mirror1_placements=3, seed=seed)
    return data, truth, calibrate(data)


def test_the_stored_joint_covariance_is_gtsams_joint_marginal() -> None:
    """Each placement's v and its cross-covariance with the pose, as result@1 holds them, against GTSAM's
    joint marginal (its Bayes tree) of the pose and the plane on the same problem."""
    import gtsam

    from mirror_fg.factors.views import vector_of_plane
    from mirror_fg.solver.fit.validation import _problem, estimate_of_calibration

    data, _, cal = _stored(3)
    document = cal.to_dict()
    estimate, estimated = estimate_of_calibration(cal)
    _, problem, values, _ = _problem(data, estimate, [], estimated)
    marginals = gtsam.Marginals(problem.graph(), values)
    pose = problem.pose_keys["camera"]
    T = np.kron(np.eye(2), values.atPose3(pose).rotation().matrix())  # [dtheta, dt] = blkdiag(R, R) [w, nu]
    for entry in document["mirrors"]:
        key = problem.mirror_keys[(entry["mirror"], entry["config"])]
        keys = gtsam.KeyVector([key, pose])
        joint = marginals.jointMarginalCovariance(keys).fullMatrix()  # ordered as the keys: plane, pose
        J = vector_of_plane(values.atOrientedPlane3(key))[1]
        assert np.allclose(entry["covariance"], J @ joint[:3, :3] @ J.T, rtol=1e-5, atol=1e-14)
        assert np.allclose(entry["cross_covariance_cam_base"], J @ joint[:3, 3:] @ T.T, rtol=1e-5, atol=1e-14)


def _at_the_stored_placement(data, truth, move: np.ndarray, images: int, rng, placement=(1, 0)):
    """``images`` new images at ``placement`` (its mirror standing where it stood, fixed in {B}) with the
    camera moved by ``move = [dtheta, dt]`` (the mirror's vector carried into the moved camera's frame)."""
    R, t, v = truth.R_cam_base, truth.t_cam_base, truth.mirror_vectors[placement]
    n, d = v / np.linalg.norm(v), np.linalg.norm(v)
    n_B, d_B = R.T @ n, d - n @ t  # the plane n . x = d with x = R x_B + t
    R_new, t_new = so3_exp(move[:3]) @ R, t + move[3:]
    n_new = R_new @ n_B
    moved = type(truth)(R_new, t_new, {**truth.mirror_vectors, placement: (d_B + n_new @ t_new) * n_new},
                        dict(truth.points))
    configs = [placement[1]]
    sigma = data.pixel_sigma if rng is not None else 0.0
    new_images = [Image(f"new{k}", configs, measure(moved, data.camera, data.fiducials, configs, sigma, rng))
                  for k in range(images)]
    return _with_images(data, new_images)


def _with_images(data, images):
    from dataclasses import replace

    return replace(data, images=images)


def _trials(trials: int, seed: int):
    """Per trial: the unmoved and the 3-sigma-moved verdicts of two new images at one stored placement."""
    rng = np.random.default_rng(seed)
    still, moved, dofs, d2 = [], [], [], []
    for _ in range(trials):
        data, truth, cal = _stored(int(rng.integers(0, 2**31 - 2)))
        exact = verify(cal, _at_the_stored_placement(data, truth, np.zeros(6), 2, None), alpha=ALPHA,
                       tolerance_mm=100.0, tolerance_deg=10.0, standing=True)
        combined = exact.cameras["camera"].covariance
        assert combined is not None
        move = 3.0 * np.sqrt(np.diag(combined)) * rng.choice([-1.0, 1.0], size=6)
        answer = verify(cal, _at_the_stored_placement(data, truth, np.zeros(6), 2, rng), alpha=ALPHA,
                        tolerance_mm=100.0, tolerance_deg=10.0, standing=True).cameras["camera"]
        still.append(answer.verdict)
        dofs.append(answer.dof)
        d2.append(answer.mahalanobis2)
        moved.append(verify(cal, _at_the_stored_placement(data, truth, move, 2, rng), alpha=ALPHA,
                            tolerance_mm=100.0, tolerance_deg=10.0, standing=True).cameras["camera"].verdict)
    return still, moved, dofs, d2


def test_one_stored_placement_determines_the_camera() -> None:
    still, moved, dofs, _ = _trials(6, seed=1)
    assert set(dofs) == {6}
    assert still.count(MOVED) == 0 and still.count(NOT_MOVED) >= 5, still
    assert moved.count(MOVED) >= 5, moved


@pytest.mark.slow
def test_one_stored_placement_power_and_size_over_200_trials() -> None:
    still, moved, _, d2 = _trials(200, seed=2)
    assert still.count(MOVED) / 200 <= ALPHA + 0.02, still.count(MOVED)
    assert moved.count(MOVED) / 200 >= 0.95, moved.count(MOVED)
    assert stats.kstest(d2, "chi2", args=(6,)).pvalue > 0.001


def test_a_new_placement_still_sees_three_of_six() -> None:
    """The same images under a label the result does not know: the plane is new, 3 of 6 seen."""
    data, truth, cal = _stored(5)
    new = _at_the_stored_placement(data, truth, np.zeros(6), 2, np.random.default_rng(0))
    relabelled = _with_images(new, [Image(im.id, [999], im.observations) for im in new.images])
    answer = verify(cal, relabelled, alpha=ALPHA).cameras["camera"]
    assert answer.dof == 3 and answer.verdict == CANNOT_TELL and "--standing-mirror" in answer.advice
    assert verify(cal, new, alpha=ALPHA).cameras["camera"].dof == 3  # not standing: every placement is new
    assert verify(cal, new, alpha=ALPHA, standing=True).cameras["camera"].dof == 6
    with pytest.raises(DatasetError, match="none of its mirror placements"):
        verify(cal, relabelled, alpha=ALPHA, standing=True)


def test_standing_mirror_at_the_cli(tmp_path, capsys) -> None:
    from mirror_fg.cli import main
    from mirror_fg.io.dataset import save_dataset
    from mirror_fg.io.result import write_result

    data, truth, cal = _stored(6)
    write_result(tmp_path / "stored.json", cal.to_dict())
    save_dataset(tmp_path / "new.json", _at_the_stored_placement(data, truth, np.zeros(6), 2, np.random.default_rng(1)))
    code = main(["verify", str(tmp_path / "stored.json"), str(tmp_path / "new.json"), "--standing-mirror",
                 "--tolerance-mm", "100", "--tolerance-deg", "10"])
    assert code == 0 and "6 of 6 degrees of freedom seen" in capsys.readouterr().out
    assert main(["verify", str(tmp_path / "stored.json"), str(tmp_path / "new.json")]) == 5
    assert "3 of 6 degrees of freedom seen" in capsys.readouterr().out
