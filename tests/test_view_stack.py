"""The stacked view factors (factors/view_stack.py) against one ViewFactor per image: the same cost, the
same linear system (J^T J, J^T e) at the analytical start and after a step, with and without a robust
kernel, on a rig with two hand-held mirrors and on a kaleidoscope with and without reconstruction points."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.model.views import ViewProblem
from mirror_fg.solver.batch.views_solve import _start
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.simulate.views import simulate_kaleidoscope


def _systems(problem: ViewProblem, values: gtsam.Values):
    out = []
    for stacked in (False, True):
        graph = problem.graph(stacked)
        H, g = graph.linearize(values).hessian()
        out.append((graph, graph.error(values), H, g))
    return out


def _check(problem: ViewProblem, values: gtsam.Values, stacks: bool = True) -> None:
    (graph, e_ref, H_ref, g_ref), (stacked, e, H, g) = _systems(problem, values)
    assert (stacked.size() < graph.size()) == stacks
    assert e == pytest.approx(e_ref, rel=1e-12)
    assert np.abs(H - H_ref).max() <= 1e-10 * np.abs(H_ref).max()
    assert np.abs(g - g_ref).max() <= 1e-10 * np.abs(g_ref).max()


@pytest.mark.parametrize("robust", [None, "huber"])
def test_rig_stacked_as_per_view(robust):
    dataset = dataset_from_dict(simulate_rig_mixed(3, own=[3, 3, 3], shared=3, seed=2)[0])
    problem = ViewProblem(dataset, robust)
    values = problem.values(_start(problem, None, SolveOptions()))
    _check(problem, values)
    # the cache: the same graph evaluated at other values gives those values' cost, not the cached one
    stacked, per_view = problem.graph(True), problem.graph(False)
    assert stacked.error(values) == pytest.approx(per_view.error(values), rel=1e-12)
    moved = values.retract(_step(problem, values))
    assert stacked.error(moved) == pytest.approx(per_view.error(moved), rel=1e-12)
    assert stacked.error(moved) != pytest.approx(stacked.error(values), rel=1e-6)


def _step(problem: ViewProblem, values: gtsam.Values) -> gtsam.VectorValues:
    rng = np.random.default_rng(0)
    delta = gtsam.VectorValues()
    for key in problem.pose_keys.values():
        delta.insert(key, 1e-3 * rng.normal(size=6))
    for key in problem.mirror_keys.values():
        delta.insert(key, 1e-3 * rng.normal(size=3))
    for key in problem.point_keys.values():
        delta.insert(key, 1e-3 * rng.normal(size=3))
    return delta


@pytest.mark.parametrize("num_points", [0, 4])
def test_kaleidoscope_stacked_as_per_view(num_points):
    dataset = dataset_from_dict(simulate_kaleidoscope(3, target=True, num_points=num_points, seed=1)[0])
    problem = ViewProblem(dataset)
    values = problem.values(_start(problem, None, SolveOptions()))
    _check(problem, values)  # views with reconstruction points stacked too (factors/view_points.py)
    _check(problem, values.retract(_step(problem, values)))
