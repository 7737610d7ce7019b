"""The eliminated placements' last reflection in closed form (factors/view_last_reflection.py) against the
general view model it replaces inside the eliminated stack (factors/view_eliminated.py with
``closed_form=False``): the same costs, reduced normal equations and placements at values off the optimum,
on the paper's tree and on a rig where the mirror before the eliminated one is owned by another camera
(its vector transferred between the cameras before the last reflection); views whose eliminated placement
is also an earlier reflection take the general model, next to those that take the closed form."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import V, X

from mirror_fg.factors.view_eliminated import EliminatedViewStack, eliminable
from mirror_fg.factors.views import ViewFactor, plane_of, view_model
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_tree
from mirror_fg.simulate.tree import simulate_base_case
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


def _repeated_placement_views():
    """A photograph's own placement q seen last through q alone, through the fixed mirror m then q, and
    through q, m and q again (q before the last reflection too: the general model's route)."""
    rng = np.random.default_rng(4)
    pose = (gtsam.Rot3.Expmap(np.array([0.02, -0.03, 0.01])).matrix(), np.array([-0.05, -0.04, 0.8]))
    base = np.array([[x, y, 0.0] for x in (0.0, 0.05, 0.1) for y in (0.0, 0.05)]).T
    m = (1, 0)
    vectors = {m: np.array([0.01, 0.3, 0.02])}
    for k in range(6):
        vectors[(2, k)] = np.array([0.3 + 0.01 * k, 0.02 * k - 0.05, 0.03])
    owners = {p: "camera" for p in vectors}
    keys = {p: V(i) for i, p in enumerate(sorted(vectors))}
    views = []
    for k in range(6):
        q = (2, k)
        for reflections in ((q,), (m, q), (q, m, q)):
            z = view_model("camera", reflections, {"camera": pose}, vectors, owners, base)[0]
            observed = z + 1e-3 * rng.normal(size=z.shape)
            views.append(ViewFactor("camera", reflections, {"camera": X(0)}, {}, keys, owners, base,
                                    [-1] * base.shape[1], observed, np.full(z.shape, 1e-3)))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3(pose[0]), pose[1]))
    values.insert(keys[m], plane_of(vectors[m]))
    start = {p: v + 1e-3 * rng.normal(size=3) for p, v in vectors.items()}
    return views, start, values


def test_repeated_placement_falls_back_to_the_general_model():
    views, start, values = _repeated_placement_views()
    graphs, stacks = [], []
    for closed_form in (True, False):
        stack = EliminatedViewStack(views, start, closed_form=closed_form)
        graph = gtsam.NonlinearFactorGraph()
        for factor in stack.factors:
            graph.add(factor)
        graphs.append(graph)
        stacks.append(stack)
    fast = stacks[0]
    assert fast.eliminated == [(2, k) for k in range(6)]
    with_placement = [f for f, u in zip(fast._fast, fast._elim_local) if u is not None]
    assert any(with_placement) and not all(with_placement)  # the (q, m, q) views take the general route
    rng = np.random.default_rng(1)
    for scale in (1e-3, 1e-6):
        at = _perturbed(values, scale, rng)
        assert graphs[0].error(at) == pytest.approx(graphs[1].error(at), rel=1e-12)
        H = graphs[0].linearize(at).augmentedHessian()
        H_ref = graphs[1].linearize(at).augmentedHessian()
        np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-12 * np.abs(H_ref).max())
