"""Inconsistent captures diagnosed: a camera bumped mid-capture is named as a split of the images
in capture order, with how far apart the two groups' ``T_cam_base`` are."""
import numpy as np
import pytest
from scipy.stats import chi2

from conftest import pose_difference
from mirror_fg import calibrate
from mirror_fg.core.transform import rotation_angle
from mirror_fg.data import Dataset
from test_consensus import board_scene

BUMP_AXIS = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
BUMP_DEG = 3.0
BUMP_T = np.array([0.03, -0.02, 0.02])  # metres


def _group(dataset: Dataset, first: int, last: int) -> Dataset:
    return Dataset(dataset.num_mirrors, dataset.camera, dataset.pixel_sigma, dataset.fiducials,
                   dataset.images[first:last], source=f"<images {first}-{last - 1}>")


@pytest.mark.parametrize("bump_at", [8, 16])
def test_camera_bump_split_named(bump_at):
    w = np.radians(BUMP_DEG) * BUMP_AXIS
    dataset, truth = board_scene(1, num_images=24, seed=2, bump=(bump_at, w, BUMP_T))
    calibration = calibrate(dataset, compute_covariance=False)
    assert not calibration.cost_plausible and calibration.excluded == []
    found = calibration.inconsistency
    assert found is not None
    assert found.groups == (tuple(im.id for im in dataset.images[:bump_at]), tuple(im.id for im in dataset.images[bump_at:]))
    assert found.message.startswith(f"images 0–{bump_at - 1} and {bump_at}–23 disagree by ")
    assert found.message.endswith("did the camera or the board move?")
    # The figures are those of the two groups calibrated alone (an independent run of calibrate) ...
    before, after = calibrate(_group(dataset, 0, bump_at)), calibrate(_group(dataset, bump_at, 24))
    assert before.cost_plausible and after.cost_plausible
    assert found.rotation_deg == pytest.approx(np.degrees(rotation_angle(before.R_cam_base, after.R_cam_base)), abs=1e-6)
    assert found.position_mm == pytest.approx(1000 * np.linalg.norm(before.t_base_cam - after.t_base_cam), abs=1e-4)
    # ... and each group's T_cam_base is the one it was simulated with (NEES below chi2(6) at 99.9 %).
    from mirror_fg.core.geometry import so3_exp

    for group, (R, t) in ((before, (truth.R_cam_base, truth.t_cam_base)),
                          (after, (so3_exp(w) @ truth.R_cam_base, truth.t_cam_base + BUMP_T))):
        error = pose_difference(R, t, group.R_cam_base, group.t_cam_base)
        assert error @ np.linalg.solve(group.covariance, error) < chi2.ppf(0.999, 6)


def test_consistent_capture_has_no_split():
    dataset, _ = board_scene(1, num_images=24, seed=2)
    calibration = calibrate(dataset, compute_covariance=False)
    assert calibration.cost_plausible and calibration.inconsistency is None


def test_too_small_sigma_is_not_called_a_split():
    """Every image fits worse than its stated sigma (1 px of noise declared as 0.25 px): no split is
    consistent alone, so none is named."""
    noisy, _ = board_scene(1, num_images=16, seed=3, pixel_sigma=1.0)
    dataset = Dataset(1, noisy.camera, 0.25, noisy.fiducials, noisy.images, source="<sigma too small>")
    calibration = calibrate(dataset, compute_covariance=False)
    assert not calibration.cost_plausible
    assert calibration.inconsistency is None


def test_incremental_camera_bump_split_named():
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

    dataset, _ = board_scene(1, num_images=24, seed=2, bump=(16, np.radians(BUMP_DEG) * BUMP_AXIS, BUMP_T))
    found = calibrate_incremental(dataset).inconsistency
    assert found is not None and found.message.startswith("images 0–15 and 16–23 disagree by ")
    batch = calibrate(dataset, compute_covariance=False).inconsistency
    assert batch is not None and found.groups == batch.groups
    assert found.rotation_deg == pytest.approx(batch.rotation_deg, abs=1e-6)
    assert found.position_mm == pytest.approx(batch.position_mm, abs=1e-4)


def test_incremental_consistent_stream_has_no_split():
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

    dataset, _ = board_scene(1, num_images=24, seed=2)
    assert calibrate_incremental(dataset).inconsistency is None
