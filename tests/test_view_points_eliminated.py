"""Views with reconstruction points, their own placements eliminated inside the factors
(factors/view_points_eliminated.py), against one ViewFactor per image: LM from the same start reaches the
same optimum, and the estimates (the eliminated placements too) and covariances (poses, every placement,
points) read through ViewProblem.read / ViewProblem.covariances are the per-view graph's."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.factors.view_points_eliminated import EliminatedViewPointStack
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.batch.views_solve import _start
from mirror_fg.solver.model.lm import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params, polished
from mirror_fg.solver.model.views import ViewProblem
from mirror_fg.solver.options import SolveOptions


def _relative(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max())


@pytest.mark.parametrize("closed_form", [True, False])
def test_eliminated_points_as_per_view(closed_form):
    """``closed_form``: the inner solve's last reflection in closed form (view_last_reflection.py), else the
    general model."""
    dataset = simulate_base_case(num_images=30, num_points=8, mirror1_placements=3, pixel_sigma=1.0,
                                 mirror_distance=0.5, tilt_deg=30.0, seed=4, num_mirrors=2, num_fiducials=3)[0]
    problem = ViewProblem(dataset)
    start = _start(problem, None, SolveOptions())
    evaluator = EliminatedViewPointStack(problem.factors, start.mirror_vectors)
    assert len(evaluator.eliminated) == len(dataset.images)  # each photograph's own placement
    assert all(evaluator._fast)
    if not closed_form:
        evaluator._fast = [False] * len(evaluator._fast)
    graph = gtsam.NonlinearFactorGraph()
    for factor in evaluator.factors:
        graph.add(factor)
    reference = problem.graph(stacked=False)
    params = lm_params(100, cost_scale(dataset), GENERAL_LAMBDA_UPPER_BOUND)
    results = []
    for g, values, inside in ((graph, problem.values(start, skip=set(evaluator.eliminated)), evaluator),
                              (reference, problem.values(start), None)):
        result = polished(g, gtsam.LevenbergMarquardtOptimizer(g, values, params).optimize())
        estimate = problem.read(result, inside)
        results.append((g.error(result), estimate, problem.covariances(g, result, estimate, inside)))
    (cost, estimate, covariances), (cost_ref, estimate_ref, covariances_ref) = results
    assert cost == pytest.approx(cost_ref, rel=1e-10)
    assert _relative(estimate.poses["camera"][1], estimate_ref.poses["camera"][1]) <= 1e-8
    for p, v in estimate_ref.mirror_vectors.items():
        assert _relative(estimate.mirror_vectors[p], v) <= 1e-8
    for name, x in estimate_ref.points.items():
        assert _relative(estimate.points[name], x) <= 1e-8
    poses, _, mirrors, points, _ = covariances
    poses_ref, _, mirrors_ref, points_ref, _ = covariances_ref
    assert _relative(poses["camera"], poses_ref["camera"]) <= 1e-6
    for p, c in mirrors_ref.items():
        assert _relative(mirrors[p], c) <= 1e-6
    for name, c in points_ref.items():
        assert _relative(points[name], c) <= 1e-6


def test_eliminated_points_refuses_a_robust_kernel():
    dataset = simulate_base_case(num_images=6, num_points=3, mirror1_placements=2, pixel_sigma=1.0,
                                 mirror_distance=0.5, tilt_deg=30.0, seed=1, num_mirrors=2, num_fiducials=3)[0]
    problem = ViewProblem(dataset, "huber")
    with pytest.raises(ValueError):
        EliminatedViewPointStack(problem.factors, {})
