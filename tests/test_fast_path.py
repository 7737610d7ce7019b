"""The tree's batched factors (tests/reference/batched.py) against its per-measurement reference (tests/reference/reflection.py).

Errors and every Jacobian block to 1e-9, robust linear systems and losses, the evaluation cache, and
whole calibrations (LM + Marginals) that must give the same estimates either way.
"""
from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from mirror_fg.solver.model import lm as lm_module
import reference.lm as reference_lm
from reference.lm import use_tree_factors
from reference.batched import ROBUST_K, batched_evaluator, batched_factors, robust_weight_and_loss
from reference.reflection import noise_model, reflection_error
from mirror_fg.solver.calibrate import calibrate
from reference.graph import build_graph, measurement_factor
from mirror_fg.simulate.tree import simulate_base_case

RTOL = 1e-9


def _scene(num_mirrors: int, num_points: int, num_images: int = 12, seed: int = 1, pixel_sigma: float = 1.0):
    """Simulated dataset, its graph layout and measurements, and values perturbed from the truth."""
    placements = 2 if num_mirrors == 3 else 3
    dataset, truth = simulate_base_case(
        num_images=num_images, num_points=num_points, num_mirrors=num_mirrors,
        mirror1_placements=placements, pixel_sigma=pixel_sigma, seed=seed,
    )
    _, values, layout, measurements = build_graph(dataset, _perturbed(truth, seed))
    return dataset, layout, measurements, values


def _perturbed(truth, seed: int, scale: float = 1.0):
    """The ground truth moved by a few mm / mrad (an initial estimate that is not the optimum)."""
    rng = np.random.default_rng(seed)
    w = 0.01 * scale * rng.normal(size=3)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    R = truth.R_cam_base @ (np.eye(3) + K + 0.5 * K @ K)
    U, _, Vt = np.linalg.svd(R)
    return dataclasses.replace(
        truth,
        R_cam_base=U @ Vt,
        t_cam_base=truth.t_cam_base + 0.005 * scale * rng.normal(size=3),
        mirror_vectors={c: v + 0.005 * scale * rng.normal(size=3) for c, v in truth.mirror_vectors.items()},
        points={n: p + 0.005 * scale * rng.normal(size=3) for n, p in truth.points.items()},
    )


def _reference_blocks(dataset, layout, meas, values):
    """Unwhitened error (2,) and ``{key: (2, dim) Jacobian}`` of one measurement's reference factor."""
    factor = measurement_factor(dataset, layout, meas, noise_model(dataset.normalized_sigma))
    fiducial = dataset.fiducials.get(meas.point)
    keys = list(factor.keys())
    jacobians = [None] * len(keys)
    error = reflection_error(np.asarray(meas.normalized), fiducial, len(meas.mirror_configs), factor, values, jacobians)
    return error, dict(zip(keys, jacobians))


def _assert_close(actual, expected, what):
    scale = max(float(np.max(np.abs(expected))), 1e-12)
    assert np.max(np.abs(np.asarray(actual) - expected)) <= RTOL * scale, what


@pytest.mark.parametrize("num_mirrors", [1, 2, 3])
@pytest.mark.parametrize(
    "num_points, images_per_factor, max_points_per_factor",
    [(0, 1, None), (4, 1, None), (4, 3, None), (4, 4, 2), (0, 5, None)],
)
def test_error_and_jacobian_blocks_match_reference(num_mirrors, num_points, images_per_factor, max_points_per_factor):
    dataset, layout, measurements, values = _scene(num_mirrors, num_points)
    evaluator = batched_evaluator(
        dataset, layout, measurements, dataset.normalized_sigma,
        images_per_factor=images_per_factor, max_points_per_factor=max_points_per_factor,
    )
    covered = []
    for f, factor in enumerate(evaluator.factors):
        keys, indices = evaluator.factor_layout(f)
        assert list(factor.keys()) == keys and keys[0] == layout.pose_key
        covered.extend(indices.tolist())
        jacobians: list = []
        error = evaluator.error_function(f)(factor, values, jacobians)
        assert error.shape == (2 * len(indices),) and len(jacobians) == len(keys)
        for r, i in enumerate(indices):
            ref_error, ref_jacobians = _reference_blocks(dataset, layout, measurements[i], values)
            _assert_close(error[2 * r : 2 * r + 2], ref_error, "error")
            for key, block in zip(keys, jacobians):
                expected = ref_jacobians.get(key, np.zeros((2, block.shape[1])))
                _assert_close(block[2 * r : 2 * r + 2], expected, f"Jacobian of {gtsam.DefaultKeyFormatter(key)}")
        # Through GTSAM: unwhitened error, and the whitened system of the Diagonal noise model.
        _assert_close(factor.unwhitenedError(values), error, "unwhitenedError")
        A, b = factor.linearize(values).jacobian()
        sigmas = np.tile(dataset.normalized_sigma, len(indices))
        _assert_close(A, np.hstack(jacobians) / sigmas[:, None], "whitened A")
        _assert_close(b, -error / sigmas, "whitened b")
    assert sorted(covered) == list(range(len(measurements)))  # every measurement exactly once


def _reference_graph(dataset, layout, measurements, robust):
    noise = noise_model(dataset.normalized_sigma, robust)
    graph = gtsam.NonlinearFactorGraph()
    for meas in measurements:
        graph.add(measurement_factor(dataset, layout, meas, noise))
    return graph


@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_robust_kernels_per_measurement_match_reference(kind):
    """Rows reweighted per measurement give GTSAM Robust's linear system and loss (not the stack's)."""
    dataset, layout, measurements, values = _scene(2, 3, pixel_sigma=1.0)
    rng = np.random.default_rng(3)
    for i in rng.choice(len(measurements), size=8, replace=False):  # outliers: kernels active
        measurements[i].normalized = measurements[i].normalized + 30.0 * dataset.normalized_sigma * rng.normal(size=2)
    reference = _reference_graph(dataset, layout, measurements, kind)
    evaluator = batched_evaluator(dataset, layout, measurements, dataset.normalized_sigma, kind, images_per_factor=3)
    for f, factor in enumerate(evaluator.factors):
        _, indices = evaluator.factor_layout(f)
        keys = list(factor.keys())
        assert np.isclose(factor.error(values), sum(reference.at(int(i)).error(values) for i in indices), rtol=RTOL)
        A, b = factor.linearize(values).jacobian()
        for r, i in enumerate(indices):
            ref = reference.at(int(i)).linearize(values)
            ref_A, ref_b = ref.jacobian()
            _assert_close(b[2 * r : 2 * r + 2], ref_b, "robust b")
            offsets = np.cumsum([0] + [6 if k == layout.pose_key else 3 for k in keys])
            ref_offsets = np.cumsum([0] + [6 if k == layout.pose_key else 3 for k in ref.keys()])
            for j, key in enumerate(ref.keys()):
                p = keys.index(key)
                _assert_close(
                    A[2 * r : 2 * r + 2, offsets[p] : offsets[p + 1]],
                    ref_A[:, ref_offsets[j] : ref_offsets[j + 1]],
                    "robust A",
                )
    batched = gtsam.NonlinearFactorGraph()
    for factor in evaluator.factors:
        batched.add(factor)
    assert np.isclose(batched.error(values), reference.error(values), rtol=RTOL)


def test_robust_weight_and_loss_are_gtsams():
    residuals = np.array([0.0, 0.3, ROBUST_K, 2.0, 7.5, 40.0])
    for kind, estimator in [
        ("huber", gtsam.noiseModel.mEstimator.Huber.Create(ROBUST_K)),
        ("cauchy", gtsam.noiseModel.mEstimator.Cauchy.Create(ROBUST_K)),
    ]:
        weight, loss = robust_weight_and_loss(kind, residuals)
        np.testing.assert_allclose(weight, [estimator.weight(e) for e in residuals], rtol=1e-14)
        np.testing.assert_allclose(loss, [estimator.loss(e) for e in residuals], rtol=1e-14)
    with pytest.raises(ValueError, match="unknown robust kernel"):
        batched_factors(*_scene(1, 0)[:3], np.ones(2), "tukey-ish")


@pytest.mark.parametrize("check", ["per key", "whole values"])
def test_cache_never_returns_stale_results(monkeypatch, check):
    """Factors sharing the batch recompute whenever any of their own variables differ."""
    import reference.batched as batched

    monkeypatch.setattr(batched, "_VALUES_CHECK_US_PER_ENTRY", 1e9 if check == "per key" else 0.0)
    dataset, layout, measurements, values = _scene(2, 4)
    evaluator = batched_evaluator(dataset, layout, measurements, dataset.normalized_sigma, images_per_factor=2)
    assert all(layout.check_whole_values == (check == "whole values") for layout in evaluator._layouts)
    graph = gtsam.NonlinearFactorGraph()
    for factor in evaluator.factors:
        graph.add(factor)
    reference = _reference_graph(dataset, layout, measurements, None)
    moved_point = gtsam.Values(values)
    name, key = next(iter(layout.point_keys.items()))
    moved_point.update(key, values.atPoint3(key) + 1e-3)  # only one landmark differs
    moved_mirror = gtsam.Values(values)
    config, mkey = sorted(layout.mirror_keys.items())[-1]
    moved_mirror.update(mkey, values.atPoint3(mkey) * (1.0 + 1e-12))  # a last-bit change of one mirror
    moved_pose = gtsam.Values(values)
    moved_pose.update(layout.pose_key, values.atPose3(layout.pose_key).retract(1e-9 * np.ones(6)))
    for current in [values, moved_point, values, moved_mirror, moved_mirror, moved_pose, values]:
        for with_jacobians in (False, True, False):
            if with_jacobians:
                A, b = graph.linearize(current).jacobian()
                ref_A, ref_b = reference.linearize(current).jacobian()
                _assert_close(A.T @ A, ref_A.T @ ref_A, "Hessian")
                _assert_close(A.T @ b, ref_A.T @ ref_b, "gradient")
            else:
                assert np.isclose(graph.error(current), reference.error(current), rtol=RTOL)
    assert evaluator.batches < 4 * 7 * 3  # the cache did serve most calls


def _fast_build_graph(**options):
    """``graph.build_graph`` with the batched factors and the given grouping options."""
    reference_build = build_graph

    def fast(dataset, initial, robust=None, fast=True):
        _, values, layout, measurements = reference_build(dataset, initial, robust, fast=False)
        graph = gtsam.NonlinearFactorGraph()
        for factor in batched_factors(dataset, layout, measurements, dataset.normalized_sigma, robust, **options):
            graph.add(factor)
        return graph, values, layout, measurements

    return fast


def _assert_same_calibration(fast, ref):
    _assert_close(fast.R_cam_base, ref.R_cam_base, "R")
    _assert_close(fast.t_cam_base, ref.t_cam_base, "t")
    for config, v in ref.mirror_vectors.items():
        _assert_close(fast.mirror_vectors[config], v, f"mirror {config}")
    for name, p in ref.points.items():
        _assert_close(fast.points[name], p, f"point {name}")
    _assert_close(fast.covariance, ref.covariance, "pose covariance")
    for config, c in ref.mirror_covariances.items():
        _assert_close(fast.mirror_covariances[config], c, f"mirror {config} covariance")
    for name, c in ref.point_covariances.items():
        _assert_close(fast.point_covariances[name], c, f"point {name} covariance")
    assert fast.iterations == ref.iterations
    assert np.isclose(fast.final_error, ref.final_error, rtol=RTOL)
    np.testing.assert_allclose(fast.residuals, ref.residuals, atol=1e-9)


@pytest.mark.parametrize(
    "robust, options",
    [(None, {}), (None, {"images_per_factor": 1, "max_points_per_factor": 2}), ("huber", {"images_per_factor": 4})],
)
def test_calibrate_fast_and_reference_paths_agree(monkeypatch, robust, options):
    use_tree_factors(monkeypatch)  # the tree's own factors (tests/reference/batched.py) and their options
    dataset, truth = simulate_base_case(num_images=36, num_points=4, seed=5)
    initial = _perturbed(truth, 7, scale=2.0)
    reference = calibrate(dataset, initial=initial, robust=robust, fast=False)
    monkeypatch.setattr(lm_module, "ELIMINATE", False)  # the stacked factors (tests/test_elimination.py: the default)
    monkeypatch.setattr(reference_lm, "build_graph", _fast_build_graph(**options))
    fast = calibrate(dataset, initial=initial, robust=robust)
    assert fast.converged and reference.converged
    _assert_same_calibration(fast, reference)


def test_rejects_bad_options():
    dataset, layout, measurements, _ = _scene(1, 0)
    with pytest.raises(ValueError, match="images_per_factor"):
        batched_factors(dataset, layout, measurements, np.ones(2), images_per_factor=0)
    with pytest.raises(ValueError, match="max_points_per_factor"):
        batched_factors(dataset, layout, measurements, np.ones(2), max_points_per_factor=0)
    with pytest.raises(ValueError, match="no measurements"):
        batched_factors(dataset, layout, [], np.ones(2))


def test_predicted_matches_graph_predictions():
    from reference.graph import extract_values
    from mirror_fg.solver.model.residuals import predicted_normalized

    dataset, layout, measurements, values = _scene(2, 4)
    evaluator = batched_evaluator(dataset, layout, measurements, dataset.normalized_sigma, "huber")
    R, t, mirror_vectors, points = extract_values(values, layout)
    expected = predicted_normalized(dataset, measurements, R, t, mirror_vectors, points)
    _assert_close(evaluator.predicted(values), expected, "predicted")


def test_factor_of_a_subgraph_with_only_its_own_values():
    """Values holding only one factor's keys (a subgraph): the others' unknowns are simply absent."""
    dataset, layout, measurements, values = _scene(2, 4)
    evaluator = batched_evaluator(dataset, layout, measurements, dataset.normalized_sigma)
    factor = evaluator.factors[1]
    own = gtsam.Values()
    own.insert(layout.pose_key, values.atPose3(layout.pose_key))
    for key in list(factor.keys())[1:]:
        own.insert(key, values.atPoint3(key))
    _, indices = evaluator.factor_layout(1)
    expected = np.concatenate([_reference_blocks(dataset, layout, measurements[i], values)[0] for i in indices])
    _assert_close(factor.unwhitenedError(own), expected, "error on own values")


def test_stacked_calibrate_uses_the_fast_path_and_matches_reference(monkeypatch):
    monkeypatch.setattr(lm_module, "ELIMINATE", False)  # the default eliminates: tests/test_elimination.py
    use_tree_factors(monkeypatch)  # the tree's own stacked factors (tests/reference/batched.py)
    dataset, truth = simulate_base_case(num_images=60, num_points=3, seed=9)
    graph, *_ = build_graph(dataset, truth)
    assert graph.size() < sum(len(im.observations) for im in dataset.images)  # stacked factors
    fast = calibrate(dataset)
    reference = calibrate(dataset, fast=False)
    _assert_same_calibration(fast, reference)


def test_calibrations_do_not_leak_their_graphs():
    """The factors' closures hold the evaluator; nothing may hold them back (a cycle through C++)."""
    import gc

    from reference.batched import BatchEvaluator

    from reference.eliminated import EliminatedEvaluator

    dataset, _ = simulate_base_case(num_images=12, seed=3)
    gc.collect()
    kinds = (BatchEvaluator, EliminatedEvaluator)
    before = sum(isinstance(o, kinds) for o in gc.get_objects())
    for robust in (None, "huber", None):
        calibrate(dataset, robust=robust)
    gc.collect()
    assert sum(isinstance(o, kinds) for o in gc.get_objects()) == before
