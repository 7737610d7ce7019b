"""The eliminated placements' last reflection in closed form (factors/view_last_reflection.py) against the
general view model it replaces inside the eliminated stack (factors/view_eliminated.py with
``closed_form=False``): the same costs, reduced normal equations and placements at values off the optimum,
on the paper's tree and on a rig where the mirror before the eliminated one is owned by another camera
(its vector transferred between the cameras before the last reflection)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_tree
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.factors.view_eliminated import EliminatedViewStack, eliminable
from mirror_fg.solver.batch.views_solve import _start
from mirror_fg.solver.model.views import ViewProblem
from mirror_fg.solver.options import SolveOptions


def _tree():
    return simulate_base_case(num_images=40, num_points=0, mirror1_placements=3, pixel_sigma=1.0,
                              mirror_distance=0.5, tilt_deg=30.0, seed=1, num_mirrors=2, num_fiducials=3)[0]


def _rig():
    """Shared photographs that only the second camera's image keeps: their own placement is that camera's
    (eliminated), the mirror-1 placement before it the first camera's."""
    data = simulate_rig_tree(2, own=[9, 9], shared=6, num_fiducials=4, seed=3)[0]
    data["images"] = [image for image in data["images"] if image["id"] not in ("cam0_0003", "cam0_0004", "cam0_0005")]
    return dataset_from_dict(data)


def _stacks(dataset, closed_form: bool):
    problem = ViewProblem(dataset)
    start = _start(problem, None, SolveOptions())
    views = [f for f in problem.factors if eliminable(f)]
    stack = EliminatedViewStack(views, start.mirror_vectors, closed_form=closed_form)
    graph = gtsam.NonlinearFactorGraph()
    for factor in stack.factors:
        graph.add(factor)
    return problem, stack, graph, problem.values(start, skip=set(stack.eliminated))


def _perturbed(values: gtsam.Values, scale: float, rng: np.random.Generator) -> gtsam.Values:
    delta = gtsam.VectorValues()
    for key in values.keys():
        delta.insert(key, scale * rng.normal(size=6 if chr(gtsam.Symbol(key).chr()) == "x" else 3))
    return values.retract(delta)


@pytest.mark.parametrize("make", [_tree, _rig], ids=["tree", "rig"])
def test_closed_form_as_the_general_model(make):
    dataset = make()
    problem, fast, fast_graph, values = _stacks(dataset, True)
    _, general, general_graph, _ = _stacks(dataset, False)
    assert any(fast._fast) and not any(general._fast)
    if make is _rig:  # a kept placement owned by the other camera before an eliminated one
        assert any(f and any(owner != g.camera for owner, _ in g.steps[:-1]) for f, g in zip(fast._fast, fast.groups))
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1e-6):
        at = _perturbed(values, scale, rng)
        assert fast_graph.error(at) == pytest.approx(general_graph.error(at), rel=1e-12)
        ours, theirs = fast.vectors_at(at), general.vectors_at(at)
        for p in fast.eliminated:
            np.testing.assert_allclose(ours[p], theirs[p], rtol=0, atol=1e-12 * np.linalg.norm(theirs[p]))
        H = fast_graph.linearize(at).augmentedHessian()
        H_ref = general_graph.linearize(at).augmentedHessian()
        np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-12 * np.abs(H_ref).max())
