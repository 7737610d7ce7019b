"""An eliminated evaluator restarted from other placements (tests/reference/eliminated.py, ``restart``) behaves bit for
bit as a new one built from them: the same LM iterates, cost and recovered placements (initial.py refines
each hypothesis of a subtree on one graph)."""
import gtsam
import numpy as np

from mirror_fg.simulate.tree import simulate_base_case
from reference.graph import build_eliminated_graph, extract_values, initial_values
from mirror_fg.solver.model.lm import lm_params
from test_fast_path import _perturbed


def _solved(eliminated, values):
    optimizer = gtsam.LevenbergMarquardtOptimizer(eliminated.graph, values, lm_params(20, 1.0))
    result = optimizer.optimize()
    return optimizer.error(), optimizer.iterations(), extract_values(result, eliminated.layout, eliminated.evaluator)


def test_restarted_equals_new():
    dataset, truth = simulate_base_case(num_images=30, num_mirrors=2, mirror1_placements=3, seed=3)
    first, second = _perturbed(truth, 1), _perturbed(truth, 2)
    reused = build_eliminated_graph(dataset, first)
    _solved(reused, reused.values)  # leaves its state at the first start's optimum
    reused.evaluator.restart(second.mirror_vectors)
    again = _solved(reused, initial_values(reused.layout, second, frozenset(reused.evaluator.eliminated)))
    fresh = build_eliminated_graph(dataset, second)
    expected = _solved(fresh, fresh.values)
    assert again[:2] == expected[:2]
    R, t, mirrors, _ = again[2]
    R_new, t_new, mirrors_new, _ = expected[2]
    assert np.array_equal(R, R_new) and np.array_equal(t, t_new)
    assert all(np.array_equal(mirrors[c], mirrors_new[c]) for c in mirrors_new)
