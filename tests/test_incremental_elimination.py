"""The incremental graph with the last mirror's placements eliminated (mirror_fg/solver/incremental/graph.py)
against the per-measurement reference graph (the one model's view factor of each measurement alone,
factors/views.py, keyed as the graph is), as tests/test_elimination.py does for the batch graph.

After a stream, the factors iSAM2 holds (placement blocks, merged and re-made along the way, and the
stacked factors of the placements kept as unknowns) must have the reference's cost and, at iSAM2's
unknowns, the Schur complement of the reference's linear system with the eliminated placements
eliminated; the placements recovered from the blocks must be the reference's optimum given the rest.
"""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.data import Dataset, Image
from mirror_fg.factors.views import plane_of
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator
from mirror_fg.solver.incremental.graph import MERGE_FANOUT
from mirror_fg.solver.incremental.view_factors import view_factors_of
from mirror_fg.simulate.tree import measure, simulate_base_case
from test_fast_path import _assert_close

RTOL = 1e-9


def _stream(ds: Dataset) -> IncrementalCalibrator:
    calibrator = IncrementalCalibrator(ds)
    for image in ds.images:
        calibrator.add_image(image)
    assert calibrator.settled and calibrator.waiting_images == []
    return calibrator


def _reference(calibrator: IncrementalCalibrator, values: gtsam.Values):
    """The per-measurement graph of every measurement in the calibrator's graph (its own keys) and its
    values: ``values`` plus every eliminated placement's plane at its block's optimum there."""
    g = calibrator.backend.state
    ds = calibrator.dataset
    full = gtsam.Values(values)
    for block in g.blocks:
        for config, v in block.evaluator.mirror_vectors(values).items():
            full.insert(g.layout.mirror_keys[config], plane_of(v))
    graph = gtsam.NonlinearFactorGraph()
    for meas in g.measurements:
        (view,) = view_factors_of(ds, g.layout, [meas])
        graph.add(view.factor())
    return graph, full


def _ordering(keys) -> gtsam.Ordering:
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    return ordering


def _check_against_reference(calibrator: IncrementalCalibrator) -> None:
    g = calibrator.backend.state
    isam = g.isam
    values = isam.getLinearizationPoint()  # what iSAM2's linear factors were made at
    kept = [g.layout.pose_key, *g.kept.values(), *g.layout.point_keys.values()]
    assert values.size() == len(kept)  # no eliminated placement among iSAM2's unknowns
    held = isam.getFactorsUnsafe()  # removed (merged, re-made) blocks are gone from it
    assert held.nrFactors() == g.factors.size() + sum(len(block.factors) for block in g.blocks)
    reference, full = _reference(calibrator, values)
    assert np.isclose(held.error(values), reference.error(full), rtol=RTOL)

    gone = [k for c, k in g.layout.mirror_keys.items() if c not in g.kept]
    H, eta = reference.linearize(full).hessian(_ordering(kept + gone))
    k = 6 + 3 * (len(kept) - 1)
    # the recovered placements are the reference's optimum given the rest: zero gradient there
    scale = np.max(np.abs(eta[:k])) + np.max(np.abs(np.diag(H)))
    assert np.max(np.abs(eta[k:])) <= 1e-7 * scale
    schur = H[:k, :k] - H[:k, k:] @ np.linalg.solve(H[k:, k:], H[k:, :k])
    gradient = eta[:k] - H[:k, k:] @ np.linalg.solve(H[k:, k:], eta[k:])
    H_held, eta_held = held.linearize(values).hessian(_ordering(kept))
    _assert_close(H_held, schur, "information")
    _assert_close(eta_held, gradient, "gradient")


@pytest.mark.parametrize("num_mirrors, num_points, num_images", [(1, 0, 60), (2, 0, 150), (2, 3, 90), (3, 2, 162)])
def test_isam2_graph_is_the_schur_complement_of_the_reference(num_mirrors, num_points, num_images):
    ds, _ = simulate_base_case(num_images=num_images, num_points=num_points, num_mirrors=num_mirrors,
                               mirror1_placements=3, seed=2)
    calibrator = _stream(ds)
    g = calibrator.backend.state
    assert len(g.kept) == sum(1 for l, _ in g.layout.mirror_keys if l < num_mirrors)
    # merged along the way: far fewer factors than images, and every placement in exactly one block
    parents = {block.parent for block in g.blocks}
    assert len(g.blocks) <= len(parents) * (MERGE_FANOUT - 1) * 4
    assert len(g.blocks) < num_images / 4
    assert sorted(c for block in g.blocks for c in block.placements) == sorted(
        c for c in g.layout.mirror_keys if c[0] == num_mirrors)
    assert sum(len(block.measurements) for block in g.blocks) == len(g.measurements)
    _check_against_reference(calibrator)


def test_full_calibration_recovers_the_batch_placements_and_covariances():
    ds, _ = simulate_base_case(num_images=120, num_points=2, pixel_sigma=1.0, seed=5)
    calibrator = _stream(ds)
    full = calibrator.calibration(full=True)
    batch = calibrate(ds)
    assert full.converged
    assert set(full.mirror_vectors) == set(batch.mirror_vectors)
    for config, v in batch.mirror_vectors.items():
        sigma = np.sqrt(np.diag(batch.mirror_covariances[config]))
        assert np.max(np.abs(full.mirror_vectors[config] - v) / sigma) < 0.05, config
        np.testing.assert_allclose(full.mirror_covariances[config], batch.mirror_covariances[config], rtol=0.02,
                                   atol=1e-3 * np.max(np.abs(batch.mirror_covariances[config])))
    # an eliminated placement's covariance on demand: the full graph's marginal
    last = max(c for c in full.mirror_vectors if c[0] == 2)
    np.testing.assert_allclose(calibrator.marginal_covariance(last), full.mirror_covariances[last], rtol=1e-6)
    # and the cheap estimate after every image reports every placement
    assert set(calibrator.calibration().mirror_vectors) == set(batch.mirror_vectors)


def test_placement_under_a_second_parent_becomes_an_unknown():
    """A mirror-2 placement seen again with mirror 1 elsewhere cannot be eliminated inside one factor: its
    block is dissolved and it joins iSAM2 as a plane, with the stacked factors; the estimate stays the
    batch MLE (whose graph then keeps every placement, ``build_eliminated_graph`` returning None)."""
    ds, truth = simulate_base_case(num_images=60, num_points=0, pixel_sigma=1.0, seed=3)
    rng = np.random.default_rng(0)
    shared = ds.images[5].mirror_configs[1]  # a placement of mirror 2 under mirror 1's placement 0 ...
    configs = (2, shared)  # ... seen again under placement 2
    again = Image("again", configs, measure(truth, ds.camera, ds.fiducials, configs, 1.0, rng))
    ds.images.append(again)
    calibrator = _stream(ds)
    g = calibrator.backend.state
    assert (2, shared) in g.kept and (2, shared) not in g.block_of
    assert all((2, shared) not in block.placements for block in g.blocks)
    _check_against_reference(calibrator)
    batch = calibrate(ds)
    full = calibrator.calibration(full=True)
    difference = np.r_[full.t_cam_base - batch.t_cam_base]
    assert np.max(np.abs(difference) / np.sqrt(np.diag(batch.covariance))[3:]) < 0.05


def test_start_up_whose_placements_collapse_is_solved_with_every_placement():
    """test_point_sigma's scene: at its 21-image start-up, LM on the eliminated graph ran six placements
    into the camera centre (|v| ~ 1e-8 m, cost 130 against 77). Now a collapsed warm start starts again
    from its initial vector (factors.eliminated), a start-up still collapsed is solved again with every
    placement an unknown, and no placement is ever reported collapsed; the stream ends at the batch MLE."""
    from test_point_sigma import noisy_dataset

    ds, truth = noisy_dataset(2, 27, {"P0": 3.0, "P1": 0.4}, 1.0, seed=1, num_points=3)
    calibrator = IncrementalCalibrator(ds)
    for image in ds.images:
        calibrator.add_image(image)
        if calibrator.started:
            distances = [np.linalg.norm(v) for c, v in calibrator.calibration().mirror_vectors.items() if c[0] == 2]
            assert min(distances) > 0.5 * np.median(distances)
    _check_against_reference(calibrator)
    batch = calibrate(ds)
    full = calibrator.calibration(full=True)
    sigma = np.sqrt(np.diag(batch.covariance))[3:]
    assert np.max(np.abs(full.t_cam_base - batch.t_cam_base) / sigma) < 0.05
