"""The stacked, compressed factors of views with reconstruction points (factors/view_points.py) against one
ViewFactor per image: the same cost and linear system (J^T J, J^T e) at the analytical start and after a
step, with and without a robust kernel, on the paper's tree with points and a rig with points; the cache;
the Schur marginals (solver/model/schur_marginals.py) against gtsam.Marginals; and a whole calibration
with points equal to the per-view graph's."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.factors.view_points import ViewPointStack
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.simulate.views import simulate_kaleidoscope
from mirror_fg.solver.batch.views_solve import _start
from mirror_fg.solver.model.lm import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params
from mirror_fg.solver.model.schur_marginals import SchurMarginals
from mirror_fg.solver.model.views import ViewProblem, tangent_dimension
from mirror_fg.solver.options import SolveOptions


def _tree(num_images: int = 30, num_points: int = 8, seed: int = 0):
    return simulate_base_case(num_images=num_images, num_points=num_points, mirror1_placements=3, pixel_sigma=1.0,
                              mirror_distance=0.5, tilt_deg=30.0, seed=seed, num_mirrors=2, num_fiducials=3)[0]


def _step(problem: ViewProblem, values: gtsam.Values, size: float = 1e-3) -> gtsam.VectorValues:
    rng = np.random.default_rng(0)
    delta = gtsam.VectorValues()
    for key in problem.keys:
        delta.insert(key, size * rng.normal(size=tangent_dimension(key, values)))
    return delta


def _check(problem: ViewProblem, values: gtsam.Values) -> None:
    per_view, stacked = problem.graph(False), problem.graph(True)
    assert stacked.size() < per_view.size()
    assert stacked.error(values) == pytest.approx(per_view.error(values), rel=1e-12)
    H_ref, g_ref = per_view.linearize(values).hessian()
    H, g = stacked.linearize(values).hessian()
    assert np.abs(H - H_ref).max() <= 1e-10 * np.abs(H_ref).max()  # the compression's shift is 1e-12 of it
    assert np.abs(g - g_ref).max() <= 1e-10 * np.abs(g_ref).max()


@pytest.mark.parametrize("robust", [None, "huber", "cauchy"])
def test_tree_with_points_as_per_view(robust):
    problem = ViewProblem(_tree(), robust)
    values = problem.values(_start(problem, None, SolveOptions()))
    _check(problem, values)
    _check(problem, values.retract(_step(problem, values)))


def test_kaleidoscope_with_points_as_per_view():
    dataset = dataset_from_dict(simulate_kaleidoscope(3, target=True, num_points=4, seed=1)[0])
    problem = ViewProblem(dataset, "huber")
    values = problem.values(_start(problem, None, SolveOptions()))
    _check(problem, values)
    _check(problem, values.retract(_step(problem, values)))


def test_small_stacks_and_cache():
    """Several factors (a few placements each) sharing the points: the same system; a factor called at other
    values than the batch's computes them again (never a stale cost)."""
    problem = ViewProblem(_tree(num_images=12, num_points=4))
    values = problem.values(_start(problem, None, SolveOptions()))
    stack = ViewPointStack(problem.factors, placements_per_factor=4)
    graph = gtsam.NonlinearFactorGraph()
    for factor in stack.factors:
        graph.add(factor)
    assert len(stack.factors) > 2
    per_view = gtsam.NonlinearFactorGraph()
    for factor in problem.factors:
        per_view.add(factor.factor())
    moved = values.retract(_step(problem, values))
    for at in (values, moved, values):
        assert graph.error(at) == pytest.approx(per_view.error(at), rel=1e-12)
        H, g = graph.linearize(at).hessian()
        H_ref, g_ref = per_view.linearize(at).hessian()
        assert np.abs(H - H_ref).max() <= 1e-10 * np.abs(H_ref).max()
        assert np.abs(g - g_ref).max() <= 1e-10 * np.abs(g_ref).max()
    # one factor asked at values other than the batch's: its own cost there
    first = stack.factors[0]
    graph.error(values)
    reference = sum(f.factor().error(moved) for f in problem.factors if set(f.mirror_keys.values()) <= set(first.keys()))
    assert first.error(moved) == pytest.approx(reference, rel=1e-12)


def test_schur_marginals_equal_gtsam():
    problem = ViewProblem(_tree(num_images=60, num_points=6))
    values = problem.values(_start(problem, None, SolveOptions()))
    graph = problem.graph()
    reference, schur = gtsam.Marginals(graph, values), SchurMarginals(graph, values)
    assert schur.covariance.shape[0] > 0  # some unknowns shared between factors
    for key in problem.keys:
        a, b = reference.marginalCovariance(key), schur.marginalCovariance(key)
        assert np.abs(a - b).max() <= 1e-8 * np.abs(a).max()
    keys = [*problem.pose_keys.values(), *list(problem.mirror_keys.values())[:2],
            list(problem.mirror_keys.values())[-1], *list(problem.point_keys.values())[:2]]
    joint = reference.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    assert np.abs(schur.jointMarginalCovariance(keys).fullMatrix() - joint).max() <= 1e-8 * np.abs(joint).max()


def test_calibration_with_points_as_per_view():
    """LM from the same start on the stacked and on the per-view graph: the same optimum and covariances."""
    dataset = _tree(num_images=40, num_points=10, seed=3)
    problem = ViewProblem(dataset)
    start = problem.values(_start(problem, None, SolveOptions()))
    results = []
    for stacked in (True, False):
        graph = problem.graph(stacked)
        params = lm_params(100, cost_scale(dataset), GENERAL_LAMBDA_UPPER_BOUND)
        result = gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize()
        results.append((graph.error(result), problem.read(result), gtsam.Marginals(graph, result)))
    (e, a, ma), (e_ref, b, mb) = results
    assert e == pytest.approx(e_ref, rel=1e-9)
    assert np.allclose(a.poses["camera"][1], b.poses["camera"][1], atol=1e-8)
    for name in a.points:
        assert np.allclose(a.points[name], b.points[name], atol=1e-8)
    for key in problem.keys:
        ca, cb = ma.marginalCovariance(key), mb.marginalCovariance(key)
        assert np.abs(ca - cb).max() <= 1e-6 * np.abs(cb).max()
