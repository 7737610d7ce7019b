"""The vectorised paths of the initial estimate give what the one-at-a-time paths give:
batched node solves and P3P, the closed-form eigenvectors, GTSAM's LM loop replayed, and the subtree
refinement that stops at an optimum another hypothesis already reached."""
from itertools import product

import gtsam
import numpy as np
import pytest

import mirror_fg.solver.start.initial as initial
import mirror_fg.solver.start.peeling as peeling
from mirror_fg import calibrate
from mirror_fg.core.geometry import householders
from mirror_fg.solver.start.analytic import TreeWalk
from reference.graph import build_eliminated_graph
from mirror_fg.solver.model.lm import cost_scale, lm_params
from mirror_fg.solver.start.peeling import smallest_eigenvectors, solve_children, solve_children_many, solve_triples
from mirror_fg.solver.start.pnp import pnp_candidates, pnp_candidates_many
from mirror_fg.simulate.tree import simulate_base_case


def _leaf_candidates(**scene):
    dataset, _ = simulate_base_case(**scene)
    return dataset, list(TreeWalk(dataset)._leaf_candidates.values())


@pytest.mark.parametrize("parent_det", [1.0, -1.0])
def test_solve_triples_is_solve_children_of_each_combination(parent_det):
    _, candidates = _leaf_candidates(num_images=60, seed=3, mirror_distance=0.25)
    rng = np.random.default_rng(0)
    combos = []
    for _ in range(10):
        images = rng.choice(len(candidates), 3, replace=False)
        combos.extend(product(*(candidates[i] for i in images)))
    assert any(len(c) > 1 for c in candidates)  # P3P twins present
    A, b, residual = solve_triples(
        np.array([[A for A, _ in c] for c in combos]), np.array([[b for _, b in c] for c in combos]), parent_det
    )
    for k, combo in enumerate(combos):
        one = solve_children([(j, A_j, b_j) for j, (A_j, b_j) in enumerate(combo)], 3, parent_det)
        np.testing.assert_allclose(A[k], one.A_parent, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b[k], one.b_parent, rtol=0, atol=1e-12)
        assert residual[k] == pytest.approx(one.residual, rel=1e-9, abs=1e-15)


def test_solve_children_many_is_solve_children_of_each_choice():
    dataset, candidates = _leaf_candidates(num_images=90, seed=1)
    children = np.array([k % 30 for k in range(90)])  # 30 children seen three times each
    rng = np.random.default_rng(1)
    choices = [[c[rng.integers(len(c))] for c in candidates] for _ in range(3)]
    many = solve_children_many(children, np.array([[A for A, _ in c] for c in choices]),
                               np.array([[b for _, b in c] for c in choices]), 30, -1.0)
    for choice, node in zip(choices, many):
        one = solve_children([(k, A, b) for k, (A, b) in zip(children, choice)], 30, -1.0)
        np.testing.assert_allclose(node.A_parent, one.A_parent, rtol=0, atol=1e-12)
        np.testing.assert_allclose(node.b_parent, one.b_parent, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.array(node.mirror_vectors), np.array(one.mirror_vectors), rtol=0, atol=1e-12)
        assert node.residual == pytest.approx(one.residual, rel=1e-9)


def test_closed_form_eigenvectors_match_eigh():
    rng = np.random.default_rng(2)
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    S = householders(normals, unit=True) + 0.02 * rng.normal(size=(500, 3, 3))
    exact = householders(normals[:20], unit=True)  # eigenvalues -1, 1, 1 exactly
    S = np.concatenate([0.5 * (S + S.transpose(0, 2, 1)), exact, np.eye(3)[None]])
    v = smallest_eigenvectors(S)
    reference = np.linalg.eigh(S)[1][..., 0]
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    alignment = np.abs(np.sum(v[:520] * reference[:520], axis=1))
    assert np.max(1.0 - alignment) < 1e-12
    np.testing.assert_allclose(np.abs(np.sum(v[500:520] * normals[:20], axis=1)), 1.0, atol=1e-12)
    assert np.all(np.isfinite(v[-1]))  # the identity: every vector is an eigenvector


@pytest.mark.parametrize("scene", [
    {"num_images": 120, "seed": 0},
    {"num_images": 120, "seed": 3, "mirror_distance": 0.25, "pixel_sigma": 2.0},
    {"num_images": 60, "seed": 4, "num_mirrors": 1},
    {"num_images": 60, "seed": 5, "num_fiducials": 4},
])
def test_pnp_candidates_many_is_pnp_candidates_of_each_image(scene):
    dataset, _ = simulate_base_case(**scene)
    problems = []
    for image in dataset.images:
        names = [n for n in image.observations if n in dataset.fiducials]
        normalized = dataset.normalized(image)
        problems.append((np.array([dataset.fiducials[n] for n in names]), np.array([normalized[n] for n in names])))
    many = pnp_candidates_many(problems, dataset.num_mirrors)
    counts = []
    for (base_points, observed), candidates in zip(problems, many):
        one = pnp_candidates(base_points, observed, dataset.num_mirrors)
        assert len(candidates) == len(one)
        counts.append(len(one))
        for (A, b), (A_one, b_one) in zip(candidates, one):
            np.testing.assert_array_equal(A, A_one)
            np.testing.assert_array_equal(b, b_one)
    assert min(counts) >= 1


def _level2_nodes(dataset):
    """Every level-2 node of the walk, scored as ``initial_estimate`` scores it."""
    return [node for node in initial.scored_nodes(TreeWalk(dataset)) if node.level > 1]


def test_replayed_lm_loop_is_gtsams():
    dataset, _ = simulate_base_case(num_images=120, seed=3, mirror_distance=0.25)
    for node in _level2_nodes(dataset):
        subtree = node.subtree()
        for proposal in node.proposals:
            params = lm_params(initial.SUBTREE_MAX_ITERATIONS, cost_scale(subtree))
            params.setRelativeErrorTol(initial.SUBTREE_RELATIVE_TOLERANCE)
            first = build_eliminated_graph(subtree, node.subtree_solution(proposal))
            gtsams = gtsam.LevenbergMarquardtOptimizer(first.graph, first.values, params)
            expected = gtsams.optimize()
            second = build_eliminated_graph(subtree, node.subtree_solution(proposal))
            ours = gtsam.LevenbergMarquardtOptimizer(second.graph, second.values, params)
            values = initial._optimize(ours, params, second.layout.pose_key, ())
            assert ours.iterations() == gtsams.iterations()
            np.testing.assert_array_equal(values.atPose3(second.layout.pose_key).matrix(),
                                          expected.atPose3(first.layout.pose_key).matrix())
            assert ours.error() == first.graph.error(expected)


@pytest.mark.parametrize("scene", [
    {"num_images": 200, "seed": 3, "mirror_distance": 0.25},
    {"num_images": 200, "seed": 4, "pixel_sigma": 2.0},
    {"num_images": 300, "num_points": 0, "mirror1_placements": 3, "seed": 0},
])
def test_stopping_at_a_known_optimum_keeps_the_same_hypotheses(scene, monkeypatch):
    """Each node hands up the same optima (P3P twins included) whether or not a refinement that nears an
    optimum already found stops there."""
    tolerance = initial.SAME_OPTIMUM_TOLERANCE
    dataset, _ = simulate_base_case(**scene)
    stopped = [node.kept() for node in _level2_nodes(dataset)]
    monkeypatch.setattr(initial, "SAME_OPTIMUM_TOLERANCE", 0.0)  # never near: every proposal refined in full
    full = [node.kept() for node in _level2_nodes(dataset)]
    assert sum(len(kept) for kept in full) > len(full)  # nodes with more than one optimum
    # "the same optimum" as the module defines it: two LM runs into one optimum end a little apart (its
    # relative cost tolerance; ~1e-4 m in a flat valley), P3P twins are centimetres apart
    for ours, reference in zip(stopped, full):
        assert len(ours) == len(reference)
        for hypothesis, expected in zip(ours, reference):
            np.testing.assert_allclose(hypothesis.A, expected.A, atol=tolerance)
            np.testing.assert_allclose(hypothesis.b, expected.b, atol=tolerance * max(1.0, np.linalg.norm(expected.b)))


def _unbounded(monkeypatch):
    """Every node searched and ranked on all of its placements."""
    monkeypatch.setattr(peeling, "MAX_SEARCH_CHILDREN", 10**9)
    monkeypatch.setattr(initial, "MAX_RANKING_PLACEMENTS", 10**9)


@pytest.mark.parametrize("scene", [
    {"num_images": 600, "num_points": 0, "mirror1_placements": 3, "seed": 0},
    {"num_images": 450, "num_points": 4, "mirror1_placements": 3, "seed": 2, "pixel_sigma": 2.0},
    {"num_images": 400, "num_points": 0, "mirror1_placements": 4, "seed": 5, "mirror_distance": 0.25},
])
def test_bounded_search_and_ranking_reach_the_same_mle(scene, monkeypatch):
    """Nodes with hundreds of placements search (peeling) and rank (LM) on a spread subset of them; the
    MLE and its covariance are those of the search over every placement."""
    dataset, _ = simulate_base_case(**scene)
    assert len(dataset.images) // scene["mirror1_placements"] > max(peeling.MAX_SEARCH_CHILDREN, initial.MAX_RANKING_PLACEMENTS)
    bounded = calibrate(dataset)
    _unbounded(monkeypatch)
    reference = calibrate(dataset)
    assert bounded.final_error == pytest.approx(reference.final_error, rel=1e-9)
    np.testing.assert_allclose(bounded.R_cam_base, reference.R_cam_base, rtol=0, atol=1e-9)
    np.testing.assert_allclose(bounded.t_cam_base, reference.t_cam_base, rtol=0, atol=1e-9 * max(1.0, np.linalg.norm(reference.t_cam_base)))
    np.testing.assert_allclose(bounded.covariance, reference.covariance, rtol=1e-6, atol=0)
    for config, vector in reference.mirror_vectors.items():
        np.testing.assert_allclose(bounded.mirror_vectors[config], vector, rtol=0, atol=1e-9)


def test_bounded_search_fills_in_every_child_from_its_parent():
    """A node with more children than ``MAX_SEARCH_CHILDREN``: the children searched keep the joint
    solve's vectors, every other child's vector is its chosen candidate's reflection from the parent
    (eqs. 6-7), and every observation's candidate is the one most consistent with that parent."""
    dataset, _ = simulate_base_case(num_images=200, num_points=0, mirror1_placements=2, seed=1, mirror_distance=0.25)
    walk = TreeWalk(dataset)
    images = [im for im in dataset.images if im.mirror_configs[0] == 0]
    children = [im.mirror_configs[1] for im in images]
    ids = sorted(set(children))
    index = [ids.index(m) for m in children]
    candidates = [walk._leaf_candidates[im.id] for im in images]
    assert len(ids) > peeling.MAX_SEARCH_CHILDREN and any(len(c) > 1 for c in candidates)
    ranked = peeling.choose_candidates(index, candidates, len(ids), -1.0, np.random.default_rng(0))  # A_1 reflects
    searched = set(peeling.spread_subset(len(ids), peeling.MAX_SEARCH_CHILDREN).tolist())
    for choice, node in ranked:
        misfits = [peeling.reflection_fit(np.array([A for A, _ in c]), np.array([b for _, b in c]), node.A_parent, node.b_parent)[0]
                   for c in candidates]
        assert choice == [int(np.argmin(m)) for m in misfits]
        for k, (c, pick) in enumerate(zip(candidates, choice)):
            if index[k] in searched:
                continue
            A, b = c[pick]
            expected = peeling.reflection_fit(A[None], b[None], node.A_parent, node.b_parent)[1][0]
            np.testing.assert_allclose(node.mirror_vectors[index[k]], expected, rtol=0, atol=1e-12)
    # the best choice is the one the search over every child finds
    full = peeling._search(index, candidates, len(ids), -1.0, np.random.default_rng(0))
    assert ranked[0][0] == full[0][0]
