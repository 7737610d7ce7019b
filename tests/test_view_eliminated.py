"""The view factors with each photograph's own placements eliminated inside them (factors/view_eliminated.py)
against one ViewFactor per image with every placement an unknown: the same minimum of the cost over the
eliminated placements, the same reduced linear system (the Schur complement of the per-view J^T J) at a
start off the optimum, and whole calibrations with the same estimates and covariances."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

import mirror_fg

from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.simulate.tree import simulate_base_case, simulate_tree
from mirror_fg.solver.batch.views_solve import _start, calibrate_views
from mirror_fg.solver.model.views import ViewProblem, tangent_dimension
from mirror_fg.solver.options import Linearization, SolveOptions
from mirror_fg.solver.start.initial import initial_estimate


def _tree(num_images: int = 24, seed: int = 0):
    return simulate_base_case(num_images=num_images, num_points=0, mirror1_placements=3, pixel_sigma=1.0,
                              mirror_distance=0.5, tilt_deg=30.0, seed=seed, num_mirrors=2, num_fiducials=3)[0]


def _reference(problem: ViewProblem, values: gtsam.Values, kept: gtsam.Values, eliminated: list):
    """The per-view graph's cost minimised over the eliminated placements (Gauss-Newton on them alone, the
    kept unknowns at ``kept``), and its Schur complement onto the kept unknowns there."""
    graph = problem.graph(stacked=False)
    inside = {problem.mirror_keys[p] for p in eliminated}
    values = gtsam.Values(values)
    for key in kept.keys():
        values.update(key, kept.atPose3(key)) if chr(gtsam.Symbol(key).chr()) == "x" else values.update(
            key, kept.atOrientedPlane3(key))
    for _ in range(30):  # the eliminated placements alone: a step on them with the rest held
        ordering = gtsam.Ordering()
        keys = [*problem.pose_keys.values(), *problem.mirror_keys.values()]
        for key in keys:
            ordering.push_back(key)
        A, b = graph.linearize(values).jacobian(ordering)
        columns, at = {}, 0
        for key in keys:
            columns[key] = np.arange(at, at + tangent_dimension(key))
            at += tangent_dimension(key)
        own = np.concatenate([columns[k] for k in keys if k in inside])
        step = np.linalg.lstsq(A[:, own], b, rcond=None)[0]
        delta, at = gtsam.VectorValues(), 0
        for key in keys:
            if key in inside:
                delta.insert(key, step[at:at + 3])
                at += 3
            else:
                delta.insert(key, np.zeros(tangent_dimension(key)))
        values = values.retract(delta)
        if np.abs(step).max() < 1e-13:
            break
    A, _ = graph.linearize(values).jacobian(ordering)
    H = A.T @ A
    rest = np.concatenate([columns[k] for k in keys if k not in inside])
    own = np.concatenate([columns[k] for k in keys if k in inside])
    D_inv = np.linalg.inv(H[np.ix_(own, own)])
    B = H[np.ix_(own, rest)]
    reduced = H[np.ix_(rest, rest)] - B.T @ D_inv @ B
    return graph.error(values), reduced, rest, [k for k in keys if k not in inside]


def test_eliminated_tree_as_per_view():
    dataset = _tree()
    problem = ViewProblem(dataset)
    start = _start(problem, initial_estimate(dataset), SolveOptions())  # the analytical solution: off the optimum
    graph, kept, evaluator = problem.solve_graph(start)
    assert evaluator is not None and len(evaluator.eliminated) == len(dataset.images)  # mirror 2 in every image
    assert graph.size() < len(problem.factors)
    cost, reduced, _, keys = _reference(problem, problem.values(start), kept, evaluator.eliminated)
    assert graph.error(kept) == pytest.approx(cost, rel=1e-9)
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    A, _ = graph.linearize(kept).jacobian(ordering)
    assert np.abs(A.T @ A - reduced).max() <= 1e-7 * np.abs(reduced).max()


@pytest.mark.parametrize("num_mirrors,points", [(1, 0), (2, 0), (3, 0), (2, 3)])
def test_calibration_eliminated_as_the_tree(num_mirrors, points):
    """calibrate_views with the placements eliminated (the default) against the tree's own factors
    (tests/reference/eliminated.py, batched.py through the tree pipeline), and with every placement an
    unknown (linearization="stacked", LM's tolerance: 1e-6): the same estimates and covariances."""
    dataset, _ = simulate_tree(num_mirrors, num_fiducials=4, num_points=points, pixel_sigma=0.5, seed=3)
    eliminated = calibrate_views(dataset)
    for reference, tolerance in ((mirror_fg.calibrate(dataset), 1e-8),
                                 (calibrate_views(dataset, options=SolveOptions(linearization=Linearization.STACKED)), 1e-6)):
        scale = np.abs(reference.covariance).max()
        np.testing.assert_allclose(eliminated.t_cam_base, reference.t_cam_base, atol=tolerance)
        np.testing.assert_allclose(eliminated.R_cam_base, reference.R_cam_base, atol=tolerance)
        np.testing.assert_allclose(eliminated.covariance, reference.covariance, atol=1e-6 * scale)
        for p, v in reference.mirror_vectors.items():
            np.testing.assert_allclose(eliminated.mirror_vectors[p], v, atol=tolerance)
            C = reference.mirror_covariances[p]
            np.testing.assert_allclose(eliminated.mirror_covariances[p], C, atol=1e-6 * np.abs(C).max())
        assert eliminated.final_error == pytest.approx(reference.final_error, rel=1e-9)
        assert eliminated.expected_final_error == reference.expected_final_error


def test_rig_eliminated_as_every_placement_an_unknown():
    """A rig's two-mirror views see each placement first in some and last in others: nothing is eliminated
    there (``view_eliminated.private_placements``), and the solve is the stacked one."""
    dataset = dataset_from_dict(simulate_rig_mixed(3, own=[3, 3, 3], shared=3, seed=2)[0])
    problem = ViewProblem(dataset)
    assert problem.solve_graph(_start(problem, None, SolveOptions()))[2] is None
    eliminated = calibrate_views(dataset)
    unknowns = calibrate_views(dataset, options=SolveOptions(linearization=Linearization.STACKED))
    for name, camera in unknowns.cameras.items():
        np.testing.assert_allclose(eliminated.cameras[name].t_cam_base, camera.t_cam_base, atol=1e-6)
        np.testing.assert_allclose(eliminated.cameras[name].covariance, camera.covariance,
                                   atol=1e-6 * np.abs(camera.covariance).max())
    assert eliminated.final_error == pytest.approx(unknowns.final_error, rel=1e-9)
