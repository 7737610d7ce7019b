"""A camera that moved between groups of placements: the paper's two-mirror scene with six
placements of mirror 1 and ten fiducials, the camera moved after the first three. A mirror placement
absorbs most of the move, so the cost stays plausible; the split at the boundary between placements of
mirror 1 is tested anyway, by a chi-square test on the two sides' poses with their covariances."""
import numpy as np
import pytest
from scipy.stats import chi2

from conftest import pose_difference
from mirror_fg import calibrate
from mirror_fg.core.geometry import so3_exp
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.screen import consistency
from mirror_fg.solver.screen.consistency import MAX_MOVE_SPLITS, MOVE_SIGNIFICANCE
from mirror_fg.simulate.tree import GroundTruth, default_camera, default_fiducials, measure, simulate_base_case

MOVE_AXIS = np.array([0.2, 1.0, -0.3]) / np.linalg.norm([0.2, 1.0, -0.3])
MOVE_DIRECTION = np.array([1.0, -0.5, 0.4]) / np.linalg.norm([1.0, -0.5, 0.4])


def moved_scene(num_images: int = 240, degrees: float = 5.0, mm: float = 80.0, seed: int = 0,
                sigma: float = 1.0) -> tuple[Dataset, GroundTruth]:
    """Six placements of mirror 1 (images in order), ten non-coplanar fiducials; images of placements 3-5
    see ``T_cam_base`` moved by ``degrees`` about MOVE_AXIS and ``mm`` along MOVE_DIRECTION."""
    layout, truth = simulate_base_case(num_images=num_images, mirror1_placements=6, num_fiducials=4,
                                       pixel_sigma=sigma, seed=seed)
    rng = np.random.default_rng(seed + 7)
    fiducials = dict(default_fiducials(4))
    centre = np.mean(list(fiducials.values()), axis=0)
    fiducials.update({f"Q{k}": centre + rng.uniform(-0.08, 0.08, 3) for k in range(6)})
    moved = GroundTruth(so3_exp(np.radians(degrees) * MOVE_AXIS) @ truth.R_cam_base,
                        truth.t_cam_base + mm / 1000 * MOVE_DIRECTION, truth.mirror_vectors)
    camera, images = default_camera(), []
    for im in layout.images:
        seen = measure(moved if im.mirror_configs[0] >= 3 else truth, camera, fiducials, im.mirror_configs, sigma, rng)
        inside = camera.contains(np.array(list(seen.values())))  # the move takes a few out of the picture
        images.append(Image(im.id, im.mirror_configs, {n: z for (n, z), keep in zip(seen.items(), inside) if keep}))
    return Dataset(2, camera, sigma, fiducials, images, source="<moved camera>"), truth


def _half(dataset: Dataset, first: int, last: int) -> Dataset:
    return Dataset(dataset.num_mirrors, dataset.camera, dataset.pixel_sigma, dataset.fiducials,
                   dataset.images[first:last], source=f"<images {first}-{last - 1}>")


def test_moved_camera_is_named_although_the_cost_is_plausible():
    dataset, truth = moved_scene()
    boundary = next(k for k, im in enumerate(dataset.images) if im.mirror_configs[0] == 3)
    calibration = calibrate(dataset)
    assert calibration.cost_plausible  # the move hides in the mirror placements ...
    error = pose_difference(truth.R_cam_base, truth.t_cam_base, calibration.R_cam_base, calibration.t_cam_base)
    assert error @ np.linalg.solve(calibration.covariance, error) > chi2.ppf(0.999, 6)  # ... but the answer is off
    found = calibration.inconsistency
    assert found is not None
    ids = [im.id for im in dataset.images]
    assert found.groups == (tuple(ids[:boundary]), tuple(ids[boundary:]))
    assert found.message.startswith(f"images 0–{boundary - 1} and {boundary}–{len(ids) - 1} disagree by ")
    assert found.message.endswith("did the camera or the board move?")
    # The evidence is that of the two sides calibrated apart (independent runs of calibrate): their
    # difference, each rotation taken from the whole's, against the sum of their covariances.
    before, after = calibrate(_half(dataset, 0, boundary)), calibrate(_half(dataset, boundary, len(ids)))
    assert before.cost_plausible and after.cost_plausible
    e0, e1 = (pose_difference(calibration.R_cam_base, calibration.t_cam_base, side.R_cam_base, side.t_cam_base)
              for side in (before, after))
    d2 = (e1 - e0) @ np.linalg.solve(before.covariance + after.covariance, e1 - e0)
    assert d2 > chi2.isf(MOVE_SIGNIFICANCE, 6)
    reported = float(found.message.split("Mahalanobis distance ")[1].split(" ")[0])
    assert reported == pytest.approx(np.sqrt(d2), rel=0.05)  # the sides' covariances scaled by their cost (~1)
    assert found.position_mm == pytest.approx(1000 * np.linalg.norm(before.t_base_cam - after.t_base_cam), abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1])
def test_consistent_capture_is_not_split(seed):
    dataset, _ = moved_scene(num_images=120, degrees=0.0, mm=0.0, seed=seed)
    assert calibrate(dataset).inconsistency is None


def test_incremental_names_the_same_split():
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

    dataset, _ = moved_scene()
    found = calibrate_incremental(dataset).inconsistency
    batch = calibrate(dataset, compute_covariance=False).inconsistency
    assert found is not None and batch is not None and found.groups == batch.groups


def test_the_split_test_is_bounded(monkeypatch):
    """A capture where every image is a placement of mirror 1: at most MAX_MOVE_SPLITS boundaries,
    two solves each."""
    from test_consensus import board_scene

    dataset, _ = board_scene(1, num_images=24, seed=2)
    calls = []
    fit_group = consistency.fit_group
    monkeypatch.setattr(consistency, "fit_group", lambda *args, **kwargs: calls.append(1) or fit_group(*args, **kwargs))
    calibration = calibrate(dataset, compute_covariance=False)
    assert calibration.cost_plausible and calibration.inconsistency is None
    assert 0 < len(calls) <= 2 * MAX_MOVE_SPLITS


def test_solvable_boundaries_are_those_a_test_per_boundary_finds():
    """The bisections of ``_solvable_boundaries`` against the plain definition, boundary by boundary."""
    from test_consensus import board_scene

    from mirror_fg.solver.start.placement_tree import complete_tree

    def every_boundary(dataset: Dataset) -> list[int]:
        images, Nv = dataset.images, dataset.num_mirrors
        return [k for k in range(1, len(images)) if images[k].mirror_configs[0] != images[k - 1].mirror_configs[0]
                and complete_tree(images[:k], Nv) and complete_tree(images[k:], Nv)]

    for dataset in (moved_scene(120, 0.0, 0.0)[0], board_scene(1, num_images=24, seed=2)[0],
                    board_scene(2, num_images=28, seed=2)[0], board_scene(1, num_images=5, seed=2)[0]):
        assert consistency._solvable_boundaries(dataset) == every_boundary(dataset)
