"""``--incremental`` on general data: iSAM2 on the view factors (``solver/incremental/views.py``)
against the batch ``mirror_fg.calibrate`` (``views_solve.calibrate_views``, Levenberg-Marquardt and
``gtsam.Marginals``) on the same dataset: every pose, mirror vector and point within 0.1 of the batch's
standard deviation, covariances within 5 %, whatever order the images come in."""
from __future__ import annotations

import json
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from incremental_scenes import SCENES, board, images_of, mixed, rig

import mirror_fg
from mirror_fg.cli import main
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator, calibrate_incremental
from mirror_fg.solver.incremental.tree import TreeIncrementalCalibrator
from mirror_fg.solver.incremental.views import ViewsIncrementalCalibrator
from mirror_fg.solver.incremental.views_start import determines_new_unknowns
from mirror_fg.solver.model.views import ViewEstimate, ViewProblem

#: Largest difference from the batch, in the batch's standard deviations.
MAX_SIGMAS = 0.1
#: Largest relative difference of a covariance from the batch's.
MAX_COVARIANCE_REL = 0.05


def _late(raw: dict) -> dict:
    """The images reordered so that the start comes late: most reflections first, direct views last."""
    images = sorted(raw["images"], key=lambda im: -len(im["reflections"]))
    return dict(raw, images=images)


def _dataset(raw: dict, name: str):
    return dataset_from_dict(raw, source=name)


def _pose_sigmas(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
                 covariance: np.ndarray) -> np.ndarray:
    """|a - b| per component in the standard deviations of ``covariance`` (docs/formats.md: ``R_a = Exp(dtheta) R_b``)."""
    dtheta = gtsam.Rot3.Logmap(gtsam.Rot3(a[0] @ b[0].T))
    return np.abs(np.concatenate([dtheta, a[1] - b[1]])) / np.sqrt(np.diag(covariance))


def _close_covariance(a: np.ndarray, b: np.ndarray) -> bool:
    return (np.linalg.norm(a - b) <= MAX_COVARIANCE_REL * np.linalg.norm(b)
            and bool(np.all(np.abs(np.diag(a) / np.diag(b) - 1.0) <= MAX_COVARIANCE_REL)))


def _poses(calibration) -> dict:
    """``{camera: ((R, t), covariance)}`` of a calibration (its cameras, else the one pose)."""
    if calibration.cameras is not None:
        return {n: ((c.R_cam_base, c.t_cam_base), c.covariance) for n, c in calibration.cameras.items()}
    return {"camera": ((calibration.R_cam_base, calibration.t_cam_base), calibration.covariance)}


def assert_matches_batch(incremental, batch) -> None:
    poses, batch_poses = _poses(incremental), _poses(batch)
    assert set(poses) == set(batch_poses)
    for name, (pose, covariance) in batch_poses.items():
        if not np.any(covariance):  # the first camera without a known target: the base frame itself
            np.testing.assert_array_equal(poses[name][0][1], pose[1])
            assert not np.any(poses[name][1])
            continue
        assert np.max(_pose_sigmas(poses[name][0], pose, covariance)) < MAX_SIGMAS, name
        assert _close_covariance(poses[name][1], covariance), name
    assert set(incremental.mirror_vectors) == set(batch.mirror_vectors)
    for p, v in batch.mirror_vectors.items():
        sigma = np.sqrt(np.diag(batch.mirror_covariances[p]))
        assert np.max(np.abs(incremental.mirror_vectors[p] - v) / sigma) < MAX_SIGMAS, p
        assert _close_covariance(incremental.mirror_covariances[p], batch.mirror_covariances[p]), p
    assert set(incremental.points) == set(batch.points)
    for name, x in batch.points.items():
        sigma = np.sqrt(np.diag(batch.point_covariances[name]))
        assert np.max(np.abs(incremental.points[name] - x) / sigma) < MAX_SIGMAS, name
        assert _close_covariance(incremental.point_covariances[name], batch.point_covariances[name]), name
    if batch.camera_pose_covariance is not None:
        assert _close_covariance(incremental.camera_pose_covariance, batch.camera_pose_covariance)
    assert incremental.mirror_frames == batch.mirror_frames
    assert incremental.final_error == pytest.approx(batch.final_error, rel=1e-6)
    assert incremental.expected_final_error == batch.expected_final_error
    assert incremental.residual_labels == batch.residual_labels
    np.testing.assert_allclose(incremental.residuals, batch.residuals, atol=1e-3)


@pytest.mark.parametrize("order", ["file", "late"])
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_incremental_equals_batch(scene: str, order: str) -> None:
    raw = SCENES[scene]()
    dataset = _dataset(raw if order == "file" else _late(raw), scene)
    assert not dataset.is_tree
    batch = mirror_fg.calibrate(dataset)
    assert not batch.excluded  # the batch's final check left nothing out: the same measurements
    estimates, waits = [], []
    incremental = calibrate_incremental(dataset, on_estimate=lambda i, c: estimates.append(i),
                                        on_wait=lambda i, s: waits.append((i, s)))
    assert_matches_batch(incremental, batch)
    assert incremental.converged
    assert estimates and estimates == list(range(estimates[0], len(dataset.images) + 1))
    assert [i for i, _ in waits] == list(range(1, estimates[0]))
    assert all(s.startswith("waiting") for _, s in waits)


def test_calibrator_waits_for_the_start_and_takes_the_rest_later() -> None:
    """Double views first: add_image is None until mirror 1 has three placements seen alone (rule 2's
    minimum), then every buffered double view joins at once."""
    raw = _late(mixed())
    dataset = _dataset(raw, "mixed")
    calibrator = IncrementalCalibrator(dataset)
    assert isinstance(calibrator.backend, ViewsIncrementalCalibrator)
    results = [calibrator.add_image(image) for image in dataset.images]
    singles = [k for k, im in enumerate(dataset.images) if len(im.reflections) == 1]
    start = singles[2]
    assert all(r is None for r in results[:start])
    assert all(r is not None for r in results[start:])
    assert calibrator.started and calibrator.waiting_images == []
    assert calibrator.num_images == len(dataset.images)
    cheap = results[-1]
    full = calibrator.calibration(full=True)
    batch = mirror_fg.calibrate(dataset)
    assert_matches_batch(full, batch)
    # the cheap estimate is iSAM2's, before the final relinearisation: close already
    assert np.max(_pose_sigmas((cheap.R_cam_base, cheap.t_cam_base), (batch.R_cam_base, batch.t_cam_base),
                               batch.covariance)) < 1.0
    assert _close_covariance(calibrator.marginal_covariance((2, 1)), batch.mirror_covariances[(2, 1)])
    assert _close_covariance(calibrator.marginal_covariance("P0"), batch.point_covariances["P0"])
    assert _close_covariance(calibrator.marginal_covariance(), batch.covariance)


def test_tree_data_still_take_the_tree_calibrator() -> None:
    raw = mixed()
    tree = dict(raw, images=[im for im in raw["images"] if len(im["reflections"]) == 1])
    dataset = _dataset(dict(tree, num_mirrors=1), "tree")
    assert dataset.is_tree
    assert type(IncrementalCalibrator(dataset).backend) is TreeIncrementalCalibrator


def test_an_image_nothing_else_completes_keeps_waiting() -> None:
    """A point seen by one image only: the image cannot join (two measurements do not fix a point), the
    others are solved; calibrate_incremental refuses the file naming it, as the batch refuses it."""
    raw = mixed()
    fid = board()
    poses = {"camera": (np.eye(3), np.array([-0.08, -0.06, 0.8]))}
    lonely = images_of([("camera", (), [*fid, "Q"])], poses, {}, {}, fid, {"Q": [0.05, 0.05, 0.1]},
                       {"camera": raw["camera"]})[0]
    lonely["id"] = "lonely"
    dataset = _dataset(dict(raw, images=[lonely, *raw["images"]]), "lonely")
    calibrator = IncrementalCalibrator(dataset)
    for image in dataset.images:
        calibrator.add_image(image)
    assert calibrator.started and calibrator.waiting_images == ["lonely"]
    assert "Q" not in calibrator.calibration(full=True).points
    with pytest.raises(SolveError, match="lonely"):
        calibrate_incremental(dataset)
    with pytest.raises(SolveError, match="'Q'"):
        mirror_fg.calibrate(dataset)


@pytest.mark.parametrize("scene", ["mixed", "rig"])
def test_cli_calibrate_incremental(tmp_path, scene: str) -> None:
    path = tmp_path / f"{scene}.json"
    path.write_text(json.dumps(_late(SCENES[scene]())))
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "--incremental", "-q", "--no-ros"]) == 0
    result = json.loads(out.read_text())
    batch = mirror_fg.calibrate(_dataset(json.loads(path.read_text()), scene))
    pose = (np.array(result["T_cam_base"]["R"]), np.array(result["T_cam_base"]["t"]))
    assert np.max(_pose_sigmas(pose, (batch.R_cam_base, batch.t_cam_base), batch.covariance)) < MAX_SIGMAS
    assert result["optimizer"]["converged"]


def test_determines_new_unknowns_counts_what_a_factor_fixes() -> None:
    """A point seen by one image is not determined by it (2 rows, 3 unknowns), by two it is; the first
    camera's pose by one image of 20 fiducials is, a mirror vector through it too, but not with the points."""
    from gtsam.symbol_shorthand import L, X

    dataset = _dataset(mixed(), "mixed")
    batch = mirror_fg.calibrate(dataset)
    problem = ViewProblem(dataset)
    values = problem.values(ViewEstimate({"camera": (batch.R_cam_base, batch.t_cam_base)}, batch.mirror_vectors,
                                         batch.points))
    one, two = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    one.add(problem.factors[0].factor())
    two.add(problem.factors[0].factor())
    two.add(problem.factors[1].factor())
    point = problem.point_keys["P0"]
    assert point == L(0)
    assert not determines_new_unknowns(one, values, [point])
    assert determines_new_unknowns(two, values, [point])
    assert determines_new_unknowns(one, values, [X(0)])
    mirror = problem.mirror_keys[dataset.images[0].reflections[0]]
    assert determines_new_unknowns(one, values, [mirror])
    assert not determines_new_unknowns(one, values, [mirror, point, problem.point_keys["P1"]])


@pytest.mark.parametrize("robust", ["huber", "cauchy"])
@pytest.mark.parametrize("scene", ["no_target", "mixed"])
def test_robust_kernels_equal_the_batch(scene: str, robust: str) -> None:
    """With a robust kernel the final Gauss-Newton steps may not settle: Levenberg-Marquardt finishes."""
    dataset = _dataset(_late(SCENES[scene]()), scene)
    assert_matches_batch(calibrate_incremental(dataset, robust=robust), mirror_fg.calibrate(dataset, robust=robust))


@pytest.mark.parametrize("scene", ["mixed", "rig"])
def test_a_gross_measurement_is_left_out_as_the_batch_does(scene: str) -> None:
    """One observation 15 px off: the final check (``consensus.final_check``) leaves it out, as the batch's
    does, and the rest is solved again: the same exclusion, the same solution."""
    raw = _late(SCENES[scene]())
    image = raw["images"][-2]
    name = list(image["observations"])[1]
    u, v = image["observations"][name]
    image["observations"][name] = [u + 15.0, v]
    dataset = _dataset(raw, scene)
    batch = mirror_fg.calibrate(dataset)
    incremental = calibrate_incremental(dataset)
    assert [(e.image, e.point) for e in batch.excluded] == [(image["id"], name)]
    assert [(e.image, e.point) for e in incremental.excluded] == [(image["id"], name)]
    assert_matches_batch(incremental, batch)


def test_a_calibrator_built_without_images_turns_to_the_view_model_at_the_first_image_off_the_tree() -> None:
    """A dataset without images looks like the tree (one camera, a target): the tree calibrator takes the
    first double view in tree order, and becomes the view model's at the next one, fed both."""
    raw = _late(mixed())
    dataset = _dataset(raw, "mixed")
    calibrator = IncrementalCalibrator(replace(dataset, images=[]))
    assert type(calibrator.backend) is TreeIncrementalCalibrator
    assert calibrator.add_image(raw["images"][0]) is None  # ((1, 0), (2, 0)): the tree's order
    results = [calibrator.add_image(image) for image in raw["images"][1:]]
    assert isinstance(calibrator.backend, ViewsIncrementalCalibrator)
    assert results[-1] is not None and calibrator.num_images == len(raw["images"])
    assert_matches_batch(calibrator.calibration(full=True), mirror_fg.calibrate(dataset))


def test_bad_images_are_refused_before_anything_changes() -> None:
    dataset = _dataset(rig(), "rig")
    calibrator = IncrementalCalibrator(dataset)
    first = rig()["images"][0]
    calibrator.add_image(first)
    given = calibrator.num_images, list(calibrator.waiting_images)
    with pytest.raises(DatasetError, match="duplicate image id"):
        calibrator.add_image(first)
    with pytest.raises(DatasetError, match="middle"):
        calibrator.add_image(dict(first, id="other", camera="middle"))
    with pytest.raises(DatasetError, match="mirror 3"):
        calibrator.add_image(dict(first, id="third", reflections=[[3, 0]]))
    assert (calibrator.num_images, calibrator.waiting_images) == given


def test_the_start_fit_is_judged_by_the_median_measurement() -> None:
    """About 1 at the batch's solution whatever one gross measurement does; far above the refusal
    threshold (``POOR_FIT_RATIO``) at a pose 2 cm off."""
    from mirror_fg.solver.result.calibration import POOR_FIT_RATIO
    from mirror_fg.solver.incremental.views import _median_fit

    raw = mixed()
    batch = mirror_fg.calibrate(_dataset(raw, "mixed"))  # before the gross measurement
    raw["images"][0]["observations"]["F0_0"][0] += 40.0
    problem = ViewProblem(_dataset(raw, "mixed"))
    estimate = ViewEstimate({"camera": (batch.R_cam_base, batch.t_cam_base)}, batch.mirror_vectors, batch.points)
    assert 0.7 < _median_fit(problem.factors, problem.values(estimate)) < 1.3
    off = ViewEstimate({"camera": (batch.R_cam_base, batch.t_cam_base + [0.02, 0, 0])}, batch.mirror_vectors,
                       batch.points)
    assert _median_fit(problem.factors, problem.values(off)) > 5 * POOR_FIT_RATIO


@pytest.mark.parametrize("scene", ["kaleidoscope", "rig", "mixed"])
def test_a_gross_measurement_in_the_first_image(scene: str) -> None:
    """15 px off in the image the start is made of: the start still fits by its median, the final check
    leaves the measurement out, and the result is the batch's on the rest. (The batch on the whole file
    is no reference here: its Levenberg-Marquardt stops before its first step, see lm_settings.)"""
    from mirror_fg.solver.screen.consensus import without

    raw = SCENES[scene]()
    image = raw["images"][0]
    name = list(image["observations"])[-1]
    image["observations"][name][0] += 15.0
    dataset = _dataset(raw, scene)
    incremental = calibrate_incremental(dataset)
    assert [(e.image, e.point) for e in incremental.excluded] == [(image["id"], name)]
    rest = without(dataset, incremental.excluded)
    assert_matches_batch(incremental, mirror_fg.calibrate(rest))
