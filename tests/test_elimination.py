"""The tree's eliminated factors (tests/reference/eliminated.py) against its per-measurement reference (tests/reference/reflection.py).

The reduced system of the eliminated graph must be the Schur complement of the reference graph's
system with the last mirror's placements eliminated (same cost, information and gradient), and whole
calibrations must reach the reference's MLE and covariances to 1e-9 once both are converged.
"""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.solver.model import lm as lm_module
from mirror_fg.solver.calibrate import calibrate
from reference.graph import build_eliminated_graph, build_graph, extract_values, initial_values
from mirror_fg.simulate.tree import simulate_base_case
from test_fast_path import _assert_close, _perturbed

RTOL = 1e-9


def _scene(num_mirrors: int, num_points: int, num_images: int = 24, seed: int = 2, placements: int = 3):
    dataset, truth = simulate_base_case(
        num_images=num_images, num_points=num_points, num_mirrors=num_mirrors, mirror1_placements=placements, seed=seed,
    )
    return dataset, truth


@pytest.mark.parametrize("num_mirrors, num_points", [(1, 0), (2, 0), (2, 5), (3, 3)])
def test_reduced_system_is_the_schur_complement_of_the_reference(num_mirrors, num_points):
    dataset, truth = _scene(num_mirrors, num_points, num_images=36 if num_mirrors == 3 else 24, placements=2 if num_mirrors == 3 else 3)
    start = _perturbed(truth, 3)
    eliminated = build_eliminated_graph(dataset, start)
    evaluator, values = eliminated.evaluator, eliminated.values
    assert values.size() == 1 + len(dataset.reconstruction_point_names) + sum(
        1 for l, _ in dataset.configurations if l < num_mirrors)
    R, t, mirrors, points = extract_values(values, eliminated.layout, evaluator)  # placements at their optimum
    full_estimate = type(start)(**{**start.__dict__, "R_cam_base": R, "t_cam_base": t, "mirror_vectors": mirrors,
                                   "points": points})
    reference, full_values, layout, _ = build_graph(dataset, full_estimate, fast=False)
    assert np.isclose(eliminated.graph.error(values), reference.error(full_values), rtol=RTOL)

    kept = list(evaluator.kept_keys)
    gone = [layout.mirror_keys[c] for c in evaluator.eliminated]
    ordering = gtsam.Ordering()
    for key in kept + gone:
        ordering.push_back(key)
    H, eta = reference.linearize(full_values).hessian(ordering)
    k = evaluator.dimension_kept
    schur = H[:k, :k] - H[:k, k:] @ np.linalg.solve(H[k:, k:], H[k:, :k])
    gradient = eta[:k] - H[:k, k:] @ np.linalg.solve(H[k:, k:], eta[k:])
    kept_ordering = gtsam.Ordering()
    for key in kept:
        kept_ordering.push_back(key)
    H_reduced, eta_reduced = eliminated.graph.linearize(values).hessian(kept_ordering)
    _assert_close(H_reduced, schur, "information")
    _assert_close(eta_reduced, gradient, "gradient")
    _assert_close(evaluator.information(values), schur, "evaluator information")


def _converged_reference(dataset, initial):
    """The reference per-measurement graph solved to the last digit: LM, then Gauss-Newton steps."""
    reference = calibrate(dataset, initial=initial, fast=False)
    graph, values, layout, _ = build_graph(dataset, reference, fast=False)
    values = lm_module._polished(graph, values)
    R, t, mirrors, points = extract_values(values, layout)
    polished = type(reference)(**{**reference.__dict__, "R_cam_base": R, "t_cam_base": t, "mirror_vectors": mirrors,
                                  "points": points})
    return calibrate(dataset, initial=polished, fast=False, max_iterations=100)


@pytest.mark.parametrize("num_mirrors, num_points, num_images", [(1, 0, 30), (2, 0, 36), (2, 4, 36), (3, 2, 81)])
def test_calibration_reaches_the_reference_mle_and_covariances(num_mirrors, num_points, num_images):
    dataset, truth = _scene(num_mirrors, num_points, num_images=num_images)
    initial = _perturbed(truth, 7, scale=2.0)
    ours = calibrate(dataset, initial=initial)
    reference = _converged_reference(dataset, initial)
    assert ours.converged and reference.converged
    _assert_close(ours.R_cam_base, reference.R_cam_base, "R")
    _assert_close(ours.t_cam_base, reference.t_cam_base, "t")
    for config, v in reference.mirror_vectors.items():
        _assert_close(ours.mirror_vectors[config], v, f"mirror {config}")
    for name, p in reference.points.items():
        _assert_close(ours.points[name], p, f"point {name}")
    # three mirrors with two placements each: an ill-conditioned information matrix, where the two ways
    # of forming the Schur complement round differently (measured 1.2e-9 relative)
    covariance_rtol = 1e-8 if num_mirrors == 3 else RTOL

    def assert_covariance(actual, expected, what):
        assert np.max(np.abs(actual - expected)) <= covariance_rtol * np.max(np.abs(expected)), what

    assert_covariance(ours.covariance, reference.covariance, "pose covariance")
    for config, c in reference.mirror_covariances.items():
        assert_covariance(ours.mirror_covariances[config], c, f"mirror {config} covariance")
    for name, c in reference.point_covariances.items():
        assert_covariance(ours.point_covariances[name], c, f"point {name} covariance")
    assert np.isclose(ours.final_error, reference.final_error, rtol=RTOL)
    assert ours.expected_final_error == reference.expected_final_error


def test_default_path_eliminates_and_keeps_few_values():
    dataset, truth = simulate_base_case(num_images=300, seed=4)
    eliminated = build_eliminated_graph(dataset, truth)
    assert eliminated.values.size() == 4  # T_cam_base and mirror 1's three placements; 300 placements inside
    assert eliminated.graph.size() == 3  # one factor per mirror 1 placement
    full = initial_values(eliminated.layout, truth)
    assert full.size() == 304


def test_robust_kernels_keep_the_stacked_factors():
    dataset, _ = simulate_base_case(num_images=12, seed=3)
    calibration = calibrate(dataset, robust="huber")
    assert calibration.converged


def test_calibration_without_covariance_repr_and_progress(caplog):
    """No covariance gives None bounds; a bounded repr and an HTML table; per-stage progress."""
    import logging

    dataset, _ = simulate_base_case(num_images=200, num_points=20, seed=1)
    calls = []
    with caplog.at_level(logging.INFO, logger="mirror_fg"):
        calibration = calibrate(dataset, compute_covariance=False, progress=lambda *call: calls.append(call))
    assert calibration.sigma3_position_mm is None and calibration.sigma3_rotation_deg is None
    text = repr(calibration)
    assert len(text) < 2000
    assert "t_cam_base" in text and "iterations" in text and "3-sigma position (mm): n/a" in text
    assert calibration._repr_html_().startswith("<table>")
    stages = [stage for stage, _, _ in calls]
    assert stages[0] == "initial estimate" and "Levenberg-Marquardt" in stages and "marginals" not in stages
    assert any("Levenberg-Marquardt" in r.getMessage() for r in caplog.records)
    with_covariance = calibrate(dataset, progress=lambda *call: calls.append(call))
    assert len(repr(with_covariance)) < 2000 and with_covariance.sigma3_position_mm.shape == (3,)
    assert calls[-1] == ("marginals", 1, 1)


def _collapsing_scene():
    """test_point_sigma's 27-image scene cut to 21 images: LM on the eliminated graph ran six placements
    into the camera centre there (|v| ~ 1e-8 m) and reported convergence at cost 129.6, 200 mm from the
    MLE (77.28) that every placement as an unknown reaches."""
    import dataclasses

    from test_point_sigma import noisy_dataset

    dataset, _ = noisy_dataset(2, 27, {"P0": 3.0, "P1": 0.4}, 1.0, seed=1, num_points=3)
    return dataclasses.replace(dataset, images=dataset.images[:21])


def test_a_collapsed_placement_starts_again_from_its_initial_vector(monkeypatch, caplog):
    """The eliminated solve itself reaches the MLE: a placement whose warm start collapsed into the camera
    centre starts again from its initial vector (no fallback needed)."""
    from reference.eliminated import collapsed

    dataset = _collapsing_scene()
    with caplog.at_level("INFO", logger="mirror_fg"):
        ours = calibrate(dataset)
    assert "collapsed" not in caplog.text
    assert not collapsed(list(ours.mirror_vectors.values()))
    monkeypatch.setattr(lm_module, "ELIMINATE", False)
    reference = calibrate(dataset)
    assert ours.final_error == pytest.approx(reference.final_error, rel=1e-9)
    # the explicit graph's LM stops ~1e-7 relative from the optimum (no Gauss-Newton polish there)
    np.testing.assert_allclose(ours.t_cam_base, reference.t_cam_base, atol=1e-6)
    assert collapsed([np.array([0.0, 0.0, 1e-8])] + [np.array([0.0, 0.0, 0.4])] * 5)


def test_a_collapsed_solution_is_solved_again_with_every_placement(monkeypatch, caplog):
    """Where an eliminated solution still has a collapsed placement, LM runs again with every placement an
    unknown: the answer is that run's."""
    dataset = _collapsing_scene()
    monkeypatch.setattr(lm_module, "collapsed", lambda vectors: True)
    with caplog.at_level("INFO", logger="mirror_fg"):
        ours = calibrate(dataset)
    assert "collapsed into the camera centre" in caplog.text
    monkeypatch.setattr(lm_module, "ELIMINATE", False)
    reference = calibrate(dataset)
    assert ours.final_error == reference.final_error
    np.testing.assert_array_equal(ours.t_cam_base, reference.t_cam_base)
