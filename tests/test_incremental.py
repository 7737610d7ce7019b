"""Tests of mirror_fg.solver.incremental.calibrator: iSAM2 image by image against the batch MLE (graph.calibrate).

Deviations are per axis of the 6-DoF pose in docs/formats.md's convention, ``|incremental - batch| / sigma`` with
the batch's marginal standard deviations.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import pose_difference

from mirror_fg.core.errors import SolveError
from mirror_fg.solver.start.analytic import solve_analytic
from mirror_fg.io.dataset import dataset_to_dict
from mirror_fg.data import Dataset, Image
from mirror_fg.core.errors import DatasetError
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator, complete_tree
from mirror_fg.simulate.tree import simulate_base_case

#: Largest allowed deviation from the batch MLE, in batch standard deviations (the issue's figure).
MAX_SIGMAS = 0.1


def _prefix(ds: Dataset, n: int) -> Dataset:
    return Dataset(ds.num_mirrors, ds.camera, ds.pixel_sigma, ds.fiducials, ds.images[:n], ds.source)


def _earliest_two_mirror_solution(ds: Dataset) -> int:
    """First image count at which every placement of mirror 1 seen so far has >= 3 placements of mirror 2
    under it and there are >= 3 placements of mirror 1 (docs/formats.md, the paper's tree), counted directly."""
    children: dict[int, set[int]] = {}
    for n, image in enumerate(ds.images, start=1):
        children.setdefault(image.mirror_configs[0], set()).add(image.mirror_configs[1])
        if len(children) >= 3 and all(len(c) >= 3 for c in children.values()):
            return n
    raise AssertionError("the stream never allows the analytical solution")


def _sigmas_from(batch, estimate) -> np.ndarray:
    difference = pose_difference(batch.R_cam_base, batch.t_cam_base, estimate.R_cam_base, estimate.t_cam_base)
    return np.abs(difference) / np.sqrt(np.diag(batch.covariance))


def _stream(ds: Dataset, calibrator: IncrementalCalibrator | None = None):
    calibrator = calibrator or IncrementalCalibrator(ds)
    estimates = [calibrator.add_image(image) for image in ds.images]
    return calibrator, estimates


def _check_stream_against_batch(ds: Dataset) -> tuple[int, float, float]:
    """Stream ``ds``; check the first estimate's image, and the last per-image and the full estimate
    against the batch MLE. Returns (first image, their largest deviations in sigma)."""
    earliest = _earliest_two_mirror_solution(ds)
    # The direct count agrees with the analytical solution itself on the prefixes around it.
    with pytest.raises((DatasetError, SolveError)):
        solve_analytic(_prefix(ds, earliest - 1))
    solve_analytic(_prefix(ds, earliest))

    calibrator, estimates = _stream(ds)
    first = next(n for n, estimate in enumerate(estimates, start=1) if estimate is not None)
    assert first == earliest
    assert all(estimate is not None and np.all(np.isfinite(estimate.covariance)) for estimate in estimates[first - 1 :])
    assert calibrator.waiting_images == [] and calibrator.num_images == len(ds.images)

    batch = calibrate(ds)
    last = _sigmas_from(batch, estimates[-1])
    full = calibrator.calibration(full=True)
    final = _sigmas_from(batch, full)
    assert last.max() <= MAX_SIGMAS, last
    assert final.max() <= MAX_SIGMAS, final
    # The uncertainty is the batch's too.
    np.testing.assert_allclose(np.sqrt(np.diag(full.covariance)), np.sqrt(np.diag(batch.covariance)), rtol=0.01)
    np.testing.assert_allclose(
        np.sqrt(np.diag(estimates[-1].covariance)), np.sqrt(np.diag(batch.covariance)), rtol=0.05
    )
    return first, float(last.max()), float(final.max())


# --- the issue's stream ---------------------------------------------------------------------------


def test_small_stream_first_estimate_and_batch_agreement() -> None:
    """Mirror 1 in three placements of 15 images each, mirror 2 new in every image, 4 points, 1 px."""
    ds, _ = simulate_base_case(num_images=45, num_points=4, pixel_sigma=1.0, seed=1)
    _check_stream_against_batch(ds)


def test_300_image_stream_matches_batch_mle() -> None:
    """Mirror 1 in three placements of 100 images each, mirror 2 new in every image, 10 points, 1 px."""
    ds, _ = simulate_base_case(num_images=300, num_points=10, pixel_sigma=1.0, seed=0)
    _check_stream_against_batch(ds)


# --- refusing bad images --------------------------------------------------------------------------


def _bad_images(ds: Dataset, good: Image) -> list:
    as_dict = {"id": "bad", "mirror_configs": list(good.mirror_configs),
               "observations": {n: z.tolist() for n, z in good.observations.items()}}
    unknown = json.loads(json.dumps(as_dict))
    unknown["observations"]["Q9"] = [500.0, 400.0]
    not_finite = json.loads(json.dumps(as_dict))
    not_finite["observations"]["F0"] = [float("nan"), 400.0]
    infinite = Image("bad-inf", good.mirror_configs, {**good.observations, "F1": np.array([np.inf, 1.0])})
    too_long = json.loads(json.dumps(as_dict))
    too_long["mirror_configs"] = list(good.mirror_configs) + [0]
    negative = json.loads(json.dumps(as_dict))
    negative["mirror_configs"] = [-1, 0]
    duplicate = Image(good.id, good.mirror_configs, dict(good.observations))
    no_id = {"mirror_configs": list(good.mirror_configs), "observations": as_dict["observations"]}
    empty = {"id": "bad-empty", "mirror_configs": list(good.mirror_configs), "observations": {}}
    return [unknown, not_finite, infinite, too_long, negative, duplicate, no_id, empty, "not an image"]


def test_bad_images_are_refused_and_change_nothing() -> None:
    ds, _ = simulate_base_case(num_images=45, num_points=4, pixel_sigma=1.0, seed=1)
    _, reference = _stream(ds)
    calibrator = IncrementalCalibrator(ds)
    got = []
    for n, image in enumerate(ds.images):
        got.append(calibrator.add_image(image))
        if n in (10, 32, 40):  # before start-up, at it, after it
            for bad in _bad_images(ds, image):
                with pytest.raises(DatasetError) as error:
                    calibrator.add_image(bad)
                assert "\n" not in str(error.value)
    for expected, estimate in zip(reference, got):
        assert (expected is None) == (estimate is None)
        if estimate is not None:
            np.testing.assert_array_equal(estimate.R_cam_base, expected.R_cam_base)
            np.testing.assert_array_equal(estimate.t_cam_base, expected.t_cam_base)
            np.testing.assert_array_equal(estimate.covariance, expected.covariance)
    assert calibrator.num_images == len(ds.images)


def test_refusal_messages_name_the_image_and_problem() -> None:
    ds, _ = simulate_base_case(num_images=12, num_points=1, pixel_sigma=1.0, seed=1)
    calibrator = IncrementalCalibrator(ds)
    first = ds.images[0]
    calibrator.add_image(first)
    with pytest.raises(DatasetError, match=r"image 'img00000'.*duplicate image id"):
        calibrator.add_image(first)
    with pytest.raises(DatasetError, match=r"image 'x'.*unknown point 'Q'"):
        calibrator.add_image({"id": "x", "mirror_configs": [0, 0], "observations": {"Q": [1.0, 2.0]}})
    with pytest.raises(DatasetError, match=r"image 'y'.*mirror_configs has 1 entries, expected 2"):
        calibrator.add_image({"id": "y", "mirror_configs": [0], "observations": {"F0": [1.0, 2.0]}})
    with pytest.raises(DatasetError, match=r"image 'z'.*point 'F0'.*not finite"):
        calibrator.add_image({"id": "z", "mirror_configs": [0, 0], "observations": {"F0": [float("inf"), 2.0]}})


def test_point_names_policy() -> None:
    ds, _ = simulate_base_case(num_images=12, num_points=1, pixel_sigma=1.0, seed=1)
    image = {"id": "a", "mirror_configs": [0, 0], "observations": {"F0": [500.0, 400.0], "NEW": [510.0, 410.0]}}
    with pytest.raises(DatasetError, match="unknown point 'NEW'"):
        IncrementalCalibrator(ds).add_image(image)  # names from the dataset's images
    assert IncrementalCalibrator(ds, points={"NEW"}).add_image(image) is None
    no_images = Dataset(ds.num_mirrors, ds.camera, ds.pixel_sigma, ds.fiducials, [], "<live>")
    assert IncrementalCalibrator(no_images).add_image(image) is None  # any name is a new point


# --- what the calibrator returns --------------------------------------------------------------------


def test_dict_images_give_the_same_estimates() -> None:
    ds, _ = simulate_base_case(num_images=45, num_points=2, pixel_sigma=1.0, seed=3)
    _, from_images = _stream(ds)
    calibrator = IncrementalCalibrator(ds)
    from_dicts = [calibrator.add_image(entry) for entry in dataset_to_dict(ds)["images"]]
    np.testing.assert_array_equal(from_dicts[-1].t_cam_base, from_images[-1].t_cam_base)
    np.testing.assert_array_equal(from_dicts[-1].covariance, from_images[-1].covariance)


def test_calibration_shapes_and_covariances() -> None:
    ds, _ = simulate_base_case(num_images=45, num_points=3, pixel_sigma=1.0, seed=1)
    calibrator = IncrementalCalibrator(ds)
    with pytest.raises(SolveError, match="no estimate yet"):
        calibrator.calibration()
    calibrator, estimates = _stream(ds, calibrator)
    batch = calibrate(ds).to_dict()
    cheap = estimates[-1].to_dict()
    full = calibrator.calibration(full=True).to_dict()
    assert set(cheap) == set(batch) - {"dispersion"} == set(full)  # the batch alone stores the image-level dispersion (verify)
    assert cheap["sigma3_cam_base"] is not None and cheap["residuals"]["rms_px"] == 0.0
    assert all(m["sigma3_mm"] is None for m in cheap["mirrors"])
    assert len(full["mirrors"]) == len(batch["mirrors"]) and set(full["points"]) == set(batch["points"])
    assert all(m["sigma3_mm"] is not None for m in full["mirrors"])
    assert 0.8 < full["residuals"]["rms_px"] / batch["residuals"]["rms_px"] < 1.2
    assert full["optimizer"]["converged"]
    # docs/formats.md's covariance on demand, and the covariances of other unknowns.
    np.testing.assert_allclose(calibrator.marginal_covariance(), calibrator.calibration().covariance)
    assert calibrator.marginal_covariance((1, 0)).shape == (3, 3)
    assert calibrator.marginal_covariance("P0").shape == (3, 3)
    with pytest.raises(KeyError):
        calibrator.marginal_covariance("nope")


def test_robust_kernel_matches_batch() -> None:
    ds, _ = simulate_base_case(num_images=45, num_points=2, pixel_sigma=1.0, seed=1)
    calibrator, _ = _stream(ds, IncrementalCalibrator(ds, robust="huber"))
    batch = calibrate(ds, robust="huber")
    assert _sigmas_from(batch, calibrator.calibration(full=True)).max() <= MAX_SIGMAS


# --- waiting images and points --------------------------------------------------------------------


def test_new_placement_of_mirror_1_after_start_up_waits_for_its_subtree() -> None:
    """Mirror 1 in four placements: the fourth brings two unknown placements per image, which wait
    until three children of it let its subtree be solved (eqs. 13-18 under the known pose)."""
    ds, _ = simulate_base_case(num_images=48, num_points=2, pixel_sigma=1.0, mirror1_placements=4, seed=0)
    calibrator = IncrementalCalibrator(ds)
    waiting_after = {}
    for n, image in enumerate(ds.images, start=1):
        calibrator.add_image(image)
        waiting_after[n] = len(calibrator.waiting_images)
    assert calibrator.started
    assert waiting_after[37] == 1 and waiting_after[38] == 2  # first two images of placement (1, 3)
    assert waiting_after[39] == 0  # the third solves the node
    assert calibrator.num_images == 48
    batch = calibrate(ds)
    assert _sigmas_from(batch, calibrator.calibration(full=True)).max() <= MAX_SIGMAS


def test_points_seen_once_wait_and_images_without_pnp_join() -> None:
    ds, _ = simulate_base_case(num_images=36, num_points=2, pixel_sigma=1.0, seed=1)
    calibrator, _ = _stream(ds, IncrementalCalibrator(ds, points={"P0", "P1", "LATE"}))
    assert calibrator.started
    # A point seen once waits; the second image that sees it gives it a value (eq. 20).
    late = ds.images[-1]
    seen_once = Image("seen-once", late.mirror_configs, {**late.observations, "LATE": late.observations["P0"] + 3.0})
    calibrator.add_image(seen_once)
    assert "LATE" not in calibrator.calibration().points
    seen_twice = Image("seen-twice", ds.images[-2].mirror_configs,
                       {**ds.images[-2].observations, "LATE": ds.images[-2].observations["P0"] + 3.0})
    calibrator.add_image(seen_twice)
    assert "LATE" in calibrator.calibration().points
    # Fewer than three fiducials: no PnP, but its placements are known, so it joins the graph.
    before = calibrator.num_images
    calibrator.add_image(Image("two-fiducials", late.mirror_configs, {n: late.observations[n] for n in ("F0", "P0")}))
    assert calibrator.num_images == before + 1 and calibrator.waiting_images == []


def test_image_with_unknown_placement_and_no_pnp_waits() -> None:
    ds, _ = simulate_base_case(num_images=36, num_points=1, pixel_sigma=1.0, seed=1)
    calibrator, _ = _stream(ds)
    last = ds.images[-1]
    lonely = Image("lonely", (last.mirror_configs[0], 999), {"F0": last.observations["F0"], "F1": last.observations["F1"]})
    calibrator.add_image(lonely)
    assert calibrator.waiting_images == ["lonely"]
    assert calibrator.num_images == len(ds.images)


# --- the start-up tree --------------------------------------------------------------------------------


def _images(configs: list[tuple[int, ...]]) -> list[Image]:
    return [Image(f"i{k}", c, {}) for k, c in enumerate(configs)]


def test_complete_tree_prunes_incomplete_placements() -> None:
    full_node = [(0, 0), (0, 1), (0, 2), (1, 3), (1, 4), (1, 5)]
    assert complete_tree(_images(full_node + [(2, 6), (2, 7)]), 2) == []  # (1, 2) has two children
    kept = complete_tree(_images(full_node + [(2, 6), (2, 7), (2, 8), (3, 9)]), 2)
    assert [im.mirror_configs for im in kept] == full_node + [(2, 6), (2, 7), (2, 8)]  # (1, 3) pruned
    assert len(complete_tree(_images([(0,), (1,), (2,)]), 1)) == 3
    assert complete_tree(_images([(0,), (1,), (1,)]), 1) == []
    three = [(a, b, c) for a in range(3) for b in range(3 * a, 3 * a + 3) for c in range(3 * b, 3 * b + 3)]
    assert len(complete_tree(_images(three), 3)) == 27
    assert complete_tree(_images(three[:-1]), 3) == []  # one leaf short: its node, then the root, fall
