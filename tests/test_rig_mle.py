"""mirror_fg's MLE for several cameras on one body (docs/formats.md "Several cameras on one body") against the
independent reference (views_reference.py): every camera's pose, the shared and own placements (each in
its owner camera's frame), the rig chain and its covariance; and the bad input of a rig dataset.

``vr.compare`` reads ``cameras[name].R_cam_base / .t_cam_base / .covariance``; the rig is
``calibration.rig`` (``.from_camera``, ``.to_camera``, ``.R``, ``.t``, ``.covariance``) and
``calibration.camera_pose_covariance`` (6C x 6C, ``cameras`` order). Run one case by name:
``pytest tests/test_rig_mle.py -k rig_three_cameras``.
"""
import copy

import numpy as np
import pytest

import mirror_fg
import views_reference as vr
from test_views_mle import ESTIMATE_SIGMAS, SIGMA_RATIO, check_against_reference

#: cal.rig's covariance is the first-order propagation of cal.camera_pose_covariance (same formula).
RIG_PROPAGATION_RTOL = 1e-6

RIG_CASES = ["rig_two_cameras", "rig_three_cameras"]


@pytest.mark.parametrize("name", RIG_CASES)
def test_rig_mle_equals_reference(name):
    dataset, truth = vr.CASES[name](0)
    calibration, reference, _ = check_against_reference(dataset, truth)
    names = list(dataset["cameras"])
    assert list(calibration.cameras) == names
    assert calibration.mirror_frames == reference.owners  # v of each placement in its owner camera's frame
    # the top level is the first camera (single-camera readers keep working)
    np.testing.assert_array_equal(calibration.R_cam_base, calibration.cameras[names[0]].R_cam_base)
    np.testing.assert_array_equal(calibration.t_cam_base, calibration.cameras[names[0]].t_cam_base)

    joint = np.asarray(calibration.camera_pose_covariance)
    assert joint.shape == (6 * len(names), 6 * len(names))
    for i, c in enumerate(names):  # the per-camera covariance is the joint's block
        np.testing.assert_allclose(joint[6 * i:6 * i + 6, 6 * i:6 * i + 6], calibration.cameras[c].covariance,
                                   rtol=1e-9, atol=1e-300)
    ratio = np.sqrt(np.diag(joint) / np.diag(reference.joint_pose_cov))
    assert SIGMA_RATIO[0] < ratio.min() and ratio.max() < SIGMA_RATIO[1], ratio
    # correlations across cameras (shared placements, common target) as the reference has them
    ref_corr = reference.joint_pose_cov / np.sqrt(np.outer(np.diag(reference.joint_pose_cov),
                                                           np.diag(reference.joint_pose_cov)))
    corr = joint / np.sqrt(np.outer(np.diag(joint), np.diag(joint)))
    assert np.abs(corr - ref_corr).max() < 0.05

    # Kalibr's chain: one entry per camera after the first, from the camera before it
    assert [(e.from_camera, e.to_camera) for e in calibration.rig] == list(zip(names, names[1:]))
    poses = {c: (calibration.cameras[c].R_cam_base, calibration.cameras[c].t_cam_base) for c in names}
    for entry in calibration.rig:
        R_ref, t_ref, cov_ref = reference.rig(entry.from_camera, entry.to_camera)
        error = vr.pose_error(R_ref, t_ref, entry.R, entry.t) / np.sqrt(np.diag(cov_ref))
        assert np.abs(error).max() < ESTIMATE_SIGMAS, (entry.from_camera, entry.to_camera, error)
        ratio = np.sqrt(np.diag(entry.covariance) / np.diag(cov_ref))
        assert SIGMA_RATIO[0] < ratio.min() and ratio.max() < SIGMA_RATIO[1], ratio
        R, t, cov = vr.rig_transform(poses, joint, names, entry.from_camera, entry.to_camera)
        np.testing.assert_allclose(entry.R, R, atol=1e-12)
        np.testing.assert_allclose(entry.t, t, atol=1e-12)
        np.testing.assert_allclose(entry.covariance, cov, rtol=RIG_PROPAGATION_RTOL,
                                   atol=RIG_PROPAGATION_RTOL * np.abs(cov).max())


def test_rig_top_camera_sees_only_shared_placements():
    """Camera 'top' owns no placement: both of its placements are in the frame of 'left'."""
    dataset, truth = vr.rig_three_cameras(0)
    calibration = mirror_fg.calibrate(copy.deepcopy(dataset))
    assert "top" not in set(calibration.mirror_frames.values())
    assert calibration.mirror_frames[(1, 0)] == "left" and calibration.mirror_frames[(1, 5)] == "right"


# --- bad input of a rig dataset ---

def _raises(dataset, match):
    with pytest.raises(mirror_fg.DatasetError, match=match) as err:
        mirror_fg.calibrate(dataset)
    assert "\n" not in str(err.value)


def test_bad_input_image_names_an_undeclared_camera():
    dataset, _ = vr.rig_two_cameras(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    next(im for im in dataset["images"] if im["id"] == "right_5")["camera"] = "middle"
    _raises(dataset, "image 'right_5'.*middle")


def test_bad_input_camera_and_cameras_together():
    dataset, _ = vr.rig_two_cameras(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    dataset["camera"] = dict(dataset["cameras"]["left"])
    _raises(dataset, "'?camera'? and '?cameras'?|'?cameras'? and '?camera'?")


def test_bad_input_image_without_camera_in_a_rig():
    dataset, _ = vr.rig_two_cameras(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    del next(im for im in dataset["images"] if im["id"] == "left_3")["camera"]
    _raises(dataset, "image 'left_3'")
