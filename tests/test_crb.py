"""Fisher information / Cramér-Rao bound (mirror_fg.solver.information.crb) against finite differences, GTSAM and chi-square."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.core.errors import SolveError
from mirror_fg.solver.information.crb import (
    UnknownIndex, chi2_quantile, cramer_rao_bound, fisher_information, linearize, nees, nees_band, pose_error,
    weakest_direction,
)
from mirror_fg.data import Dataset, Image
from mirror_fg.core.geometry import measurement, so3_exp
from mirror_fg import calibrate
from reference.graph import build_graph
from mirror_fg.simulate.tree import GroundTruth, simulate_base_case
from mirror_fg.core.transform import covariance_from_pose3 as spec_covariance_from_pose3


@pytest.fixture(scope="module")
def small_case():
    """9 images (3 placements of mirror 1, mirror 2 moving), 3 fiducials, 2 reconstruction points."""
    return simulate_base_case(num_images=9, num_points=2, pixel_sigma=0.5, seed=5)


def _unknown_vector_functions(dataset: Dataset, truth: GroundTruth):
    """``h(delta)``: every predicted measurement (stacked) after perturbing the truth by ``delta``
    (pose on GTSAM's retraction ``R Exp(w)``, ``t + R nu``; mirrors and points additively)."""
    index = UnknownIndex.for_dataset(dataset)

    def predict(delta: np.ndarray) -> np.ndarray:
        R = truth.R_cam_base @ so3_exp(delta[:3])
        t = truth.t_cam_base + truth.R_cam_base @ delta[3:6]
        mirrors = {c: truth.mirror_vectors[c] + delta[s : s + 3] for c, s in index.mirrors.items()}
        points = {p: truth.points[p] + delta[s : s + 3] for p, s in index.points.items()}
        out = []
        for image in dataset.images:
            vectors = [mirrors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)]
            for name in image.observations:
                base = dataset.fiducials[name] if name in dataset.fiducials else points[name]
                out.append(measurement(R, t, vectors, base))  # eqs. (5), (9)
        return np.concatenate(out)

    return index, predict


def test_fisher_information_matches_finite_differences(small_case):
    dataset, truth = small_case
    index, predict = _unknown_vector_functions(dataset, truth)
    step = 1e-6
    columns = []
    for i in range(index.size):
        delta = np.zeros(index.size)
        delta[i] = step
        columns.append((predict(delta) - predict(-delta)) / (2 * step))
    J = np.stack(columns, axis=1)
    sigma = dataset.normalized_sigma
    W = np.tile(1.0 / sigma**2, len(J) // 2)
    numeric = J.T @ (W[:, None] * J)
    analytic = fisher_information(dataset, truth)
    assert analytic.shape == (index.size, index.size)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6 * np.max(np.abs(numeric)))
    # The score J^T W (z - h) uses the same Jacobian and the observations.
    observed = np.concatenate([np.array(list(dataset.normalized(im).values())).ravel() for im in dataset.images])
    score = linearize(dataset, truth, with_score=True).score
    np.testing.assert_allclose(score, J.T @ (W * (observed - predict(np.zeros(index.size)))), rtol=1e-5,
                               atol=1e-6 * np.max(np.abs(score)))


def test_bound_equals_gtsam_marginals_at_the_truth(small_case):
    dataset, truth = small_case
    bound = cramer_rao_bound(dataset, truth)
    graph, values, layout, _ = build_graph(dataset, truth)
    marginals = gtsam.Marginals(graph, values)
    pose = spec_covariance_from_pose3(truth.R_cam_base, marginals.marginalCovariance(layout.pose_key))
    np.testing.assert_allclose(bound.pose_covariance, pose, rtol=1e-6, atol=1e-14)
    for config, key in layout.mirror_keys.items():
        np.testing.assert_allclose(bound.mirror_covariances[config], marginals.marginalCovariance(key), rtol=1e-6)
    for name, key in layout.point_keys.items():
        np.testing.assert_allclose(bound.point_covariances[name], marginals.marginalCovariance(key), rtol=1e-6)
    np.testing.assert_allclose(bound.sigma3_position_mm, 3000 * np.sqrt(np.diag(pose)[3:]), rtol=1e-6)
    np.testing.assert_allclose(bound.sigma3_rotation_deg, np.degrees(3 * np.sqrt(np.diag(pose)[:3])), rtol=1e-6)


def test_bound_scales_with_the_noise(small_case):
    dataset, truth = small_case
    one = cramer_rao_bound(dataset, truth, sigma_normalized=1e-3)
    two = cramer_rao_bound(dataset, truth, sigma_normalized=2e-3)
    np.testing.assert_allclose(two.pose_covariance, 4.0 * one.pose_covariance, rtol=1e-9)


def test_first_order_estimator_predicts_the_mle_at_low_noise():
    dataset, truth = simulate_base_case(num_images=30, num_points=4, pixel_sigma=0.05, seed=2)
    bound = cramer_rao_bound(dataset, truth, with_score=True)
    cal = calibrate(dataset, initial=truth, compute_covariance=False)
    mle = pose_error(truth.R_cam_base, truth.t_cam_base, cal.R_cam_base, cal.t_cam_base)
    first_order, points = bound.first_order_errors()
    sigma = np.sqrt(np.diag(bound.pose_covariance))
    # The two differ by second-order terms, a small fraction of a standard deviation at 0.05 px.
    assert np.max(np.abs(mle - first_order) / sigma) < 0.02
    for name, error in points.items():
        np.testing.assert_allclose(truth.points[name] - cal.points[name], error, atol=0.02 * np.max(
            np.sqrt(np.diag(bound.point_covariances[name]))))


def test_first_order_errors_need_the_score(small_case):
    dataset, truth = small_case
    with pytest.raises(ValueError, match="with_score"):
        cramer_rao_bound(dataset, truth).first_order_errors()


def test_unconstrained_point_is_named():
    dataset, truth = simulate_base_case(num_images=9, num_points=1, pixel_sigma=0.0, seed=1)
    # P0 seen in one image only: its depth along the ray is unconstrained.
    images = [Image(im.id, im.mirror_configs, dict(im.observations)) for im in dataset.images]
    for image in images[1:]:
        image.observations.pop("P0")
    lonely = Dataset(dataset.num_mirrors, dataset.camera, 1.0, dataset.fiducials, images, source="lonely.json")
    with pytest.raises(SolveError, match=r"lonely.json: .*point 'P0'"):
        cramer_rao_bound(lonely, truth)


def test_pose_error_follows_spec_convention():
    rng = np.random.default_rng(0)
    R_est = so3_exp(rng.normal(size=3))
    dtheta = np.array([0.01, -0.02, 0.005])
    R_true = so3_exp(dtheta) @ R_est  # docs/formats.md: R_true = Exp(dtheta) R_est
    t_est = rng.normal(size=3)
    error = pose_error(R_true, t_est + [0.1, 0.2, 0.3], R_est, t_est)
    np.testing.assert_allclose(error, [*dtheta, 0.1, 0.2, 0.3], atol=1e-12)


def test_nees_and_its_band():
    P = np.diag([1.0, 4.0, 9.0, 1.0, 1.0, 1.0])
    e = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(nees(e, P), [3.0])
    np.testing.assert_allclose(nees(np.stack([e, 2 * e]), np.stack([P, P])), [3.0, 12.0])
    # Consistent Gaussian errors: the mean NEES of many runs lands in the band.
    rng = np.random.default_rng(1)
    L = np.linalg.cholesky(P)
    samples = rng.normal(size=(2000, 6)) @ L.T
    lo, hi = nees_band(2000)
    assert lo < np.mean(nees(samples, P)) < hi
    assert lo < 6.0 < hi


def test_chi2_quantile_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for dof in (1, 2, 6, 7.5, 60, 600, 6000):
        for p in (0.0005, 0.025, 0.5, 0.975, 0.9995):
            assert chi2_quantile(p, dof) == pytest.approx(stats.chi2.ppf(p, dof), rel=1e-9)
    assert nees_band(10) == pytest.approx((stats.chi2.ppf(0.025, 60) / 10, stats.chi2.ppf(0.975, 60) / 10))


def test_weakest_direction_names_the_axis():
    covariance = np.diag([1e-6, 4e-4, 1e-6, 1e-6, 1e-6, 1e-6])
    weakest = weakest_direction(covariance)
    assert weakest.text.startswith("rotation about camera y is the weakest")
    assert weakest.shares[1] == pytest.approx(1.0)
    # At a 1 mm lever arm the same rotation weighs less than a 1 mm translation along z.
    covariance[5, 5] = 4e-6
    assert weakest_direction(covariance, lever_arm_m=1e-3).text.startswith("translation along camera z")
    # A correlated pair is reported as a coupling.
    coupled = np.diag([1e-8] * 6)
    coupled[np.ix_([0, 4], [0, 4])] = [[1e-4, 0.9e-4], [0.9e-4, 1e-4]]
    text = weakest_direction(coupled).text
    assert "coupled with" in text and "translation along camera y" in text
