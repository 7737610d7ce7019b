"""What the incremental calibrator's settings and rules are there for, each against an independent
reference: the hand-over to the general backend keeps every image given (the batch on the whole file), a
start that fits several times worse than the noise model is not taken (the noise factor put into the
data), an optimizer that runs out of iterations is not converged (its own iteration count), and iSAM2's
estimate is the full back-substitution of its linear system (GTSAM's ``calculateBestEstimate``)."""
from __future__ import annotations

import re
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from incremental_scenes import kaleidoscope, mixed

import mirror_fg
from mirror_fg.core.errors import SolveError
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.solver.incremental import views as incremental_views
from mirror_fg.solver.result.calibration import POOR_FIT_RATIO
from mirror_fg.solver.incremental import IncrementalCalibrator, calibrate_incremental
from mirror_fg.solver.incremental.state import new_isam2
from mirror_fg.solver.incremental.tree import TreeIncrementalCalibrator
from mirror_fg.solver.incremental.views import ViewsIncrementalCalibrator


def test_the_hand_over_feeds_every_image_the_tree_took():
    """Two double views in the tree's order (mirror 1 then 2) go to the tree backend; the next image (a single
    reflection) leaves the tree, and the general backend is fed both before it: the end is the batch's."""
    raw = mixed()
    images = raw["images"]
    order = [images[4], images[6], *images[:4], images[5], images[7], images[8]]
    assert [len(im["reflections"]) for im in order[:3]] == [2, 2, 1]
    dataset = dataset_from_dict(dict(raw, images=order), source="mixed")
    calibrator = IncrementalCalibrator(replace(dataset, images=[]))
    calibrator.add_image(order[0])
    calibrator.add_image(order[1])
    assert type(calibrator.backend) is TreeIncrementalCalibrator
    calibrator.add_image(order[2])
    assert type(calibrator.backend) is ViewsIncrementalCalibrator
    assert sorted(calibrator.waiting_images) == sorted(im["id"] for im in order[:3])
    for image in order[3:]:
        calibrator.add_image(image)
    assert calibrator.num_images == len(order) and calibrator.waiting_images == []
    full, batch = calibrator.calibration(full=True), mirror_fg.calibrate(dataset)
    assert full.final_error == pytest.approx(batch.final_error, rel=1e-6)
    assert set(full.mirror_vectors) == set(batch.mirror_vectors)


@pytest.mark.parametrize("noise_factor", [2.0, 5.0])
def test_a_start_that_fits_worse_than_the_noise_model_allows_is_not_taken(noise_factor):
    """The kaleidoscope's 0.5 px of noise under a pixel_sigma ``noise_factor`` times smaller: the start's
    measurements fit about ``noise_factor`` times worse than the noise model says. Below
    ``POOR_FIT_RATIO`` (3) the calibrator starts; at 5 it never does, says how badly the start fits, and
    ``calibrate_incremental`` refuses the file."""
    raw = kaleidoscope()
    raw["pixel_sigma"] = 0.5 / noise_factor
    dataset = dataset_from_dict(raw, source="data.json")
    calibrator = ViewsIncrementalCalibrator(dataset)
    for image in dataset.images:
        calibrator.add_image(image)
    assert calibrator.started == (noise_factor < POOR_FIT_RATIO)
    if noise_factor > POOR_FIT_RATIO:
        found = re.search(r"fit the start ([0-9.]+) times worse", str(calibrator.startup_error))
        assert found is not None and abs(float(found.group(1)) / noise_factor - 1.0) < 0.2, calibrator.startup_error
        with pytest.raises(SolveError, match="never allowed a start"):
            calibrate_incremental(dataset)


def test_an_optimizer_that_runs_out_of_iterations_is_not_converged(monkeypatch):
    """From iSAM2's estimate the final Levenberg-Marquardt needs a few iterations (counted here with the
    default limit); allowed one, it runs out: the calibration is not converged and the stream refused."""
    dataset = dataset_from_dict(kaleidoscope(), source="data.json")

    def streamed() -> ViewsIncrementalCalibrator:
        calibrator = ViewsIncrementalCalibrator(dataset)
        for image in dataset.images:
            calibrator.add_image(image)
        return calibrator

    calibrator = streamed()
    before = calibrator.calibration().iterations  # iSAM2's updates so far
    free = calibrator.calibration(full=True)
    needed = free.iterations - before  # the final LM's own iterations
    assert free.converged and needed > 1
    monkeypatch.setattr(incremental_views, "FINAL_LM_ITERATIONS", 1)
    short = streamed().calibration(full=True)
    assert short.final_error > free.final_error  # one iteration did not reach the minimum
    assert not short.converged
    with pytest.raises(SolveError, match="converge"):
        calibrate_incremental(dataset)


def test_the_estimate_is_the_full_back_substitution_after_every_update():
    """A chain of 25 poses with loop closures, one pose per update through the calibrators' iSAM2 settings:
    after every update the estimate equals GTSAM's full back-substitution of the same linear system."""
    rng = np.random.default_rng(0)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    truth = [gtsam.Pose3(gtsam.Rot3.Rz(0.3 * k), np.array([np.cos(0.3 * k), np.sin(0.3 * k), 0.0])) for k in range(25)]
    isam = new_isam2()
    for k, pose in enumerate(truth):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", 0), pose, noise))
        else:
            step = truth[k - 1].between(pose).retract(rng.normal(0, 0.002, 6))
            graph.add(gtsam.BetweenFactorPose3(gtsam.symbol("x", k - 1), gtsam.symbol("x", k), step, noise))
        if k >= 10 and k % 5 == 0:
            loop = truth[0].between(pose).retract(rng.normal(0, 0.002, 6))
            graph.add(gtsam.BetweenFactorPose3(gtsam.symbol("x", 0), gtsam.symbol("x", k), loop, noise))
        values.insert(gtsam.symbol("x", k), pose.retract(rng.normal(0, 0.001, 6)))
        isam.update(graph, values)
        estimate, best = isam.calculateEstimate(), isam.calculateBestEstimate()
        for j in range(k + 1):
            key = gtsam.symbol("x", j)
            np.testing.assert_allclose(estimate.atPose3(key).localCoordinates(best.atPose3(key)), 0.0, atol=1e-9)


def test_an_update_that_brings_new_unknowns_ends_at_the_optimum_of_the_images_so_far():
    """No known target, in file order: each of mirrors 2 and 3 joins with its single view. After the update
    that brings it (and the settling update that relinearises what it moved), the estimate's cost on every
    image in the graph is within 0.01 of the minimum Levenberg-Marquardt finds from it (GTSAM's defaults):
    the estimate is that minimum, not one Gauss-Newton step at stale linearisation points."""
    from incremental_scenes import no_target

    from mirror_fg.solver.model.views import ViewEstimate, ViewProblem

    dataset = dataset_from_dict(no_target(), source="no_target")
    calibrator = ViewsIncrementalCalibrator(dataset)
    seen: set = set()
    checked = 0
    for image in dataset.images:
        estimate = calibrator.add_image(image)
        if estimate is None:
            continue
        new, seen = set(estimate.mirror_vectors) - seen, set(estimate.mirror_vectors)
        if not new or len(seen) == len(new):  # nothing new, or the start (refined by LM as a whole)
            continue
        problem = ViewProblem(calibrator.dataset)
        graph = problem.graph()
        values = problem.values(ViewEstimate({"camera": (estimate.R_cam_base, estimate.t_cam_base)},
                                             estimate.mirror_vectors, estimate.points))
        minimum = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        assert graph.error(values) - graph.error(minimum) < 0.01, (image.id, new)
        checked += 1
    assert checked == 2
