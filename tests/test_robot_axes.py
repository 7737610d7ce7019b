"""The one-rotation-axis check before an arm's solve (solver/batch/robot_solve.py ``check_rotation_axes``) on given
link rotations: turns about one axis (within about a degree per radian) are refused with exit 3, turns
about two clearly different axes are enough (hand-eye needs two, not three), a mount on the base link is
never checked; and the camera mount's covariance carried to ``T_cam_link``."""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from mirror_fg.core.errors import SolveError
from mirror_fg.solver.batch.robot_solve import check_rotation_axes


def _rotation(rotation_vector) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotation_vector, float))[0]


def _problem(rotations: list[np.ndarray], link: str = "tool0") -> SimpleNamespace:
    """The parts of a RobotProblem the check reads: image i puts ``link`` at ``rotations[i]``."""
    class Kinematics:
        base_link = "base_link"

        def placements(self, joints, links):
            T = np.eye(4)
            T[:3, :3] = rotations[joints["i"]]
            return {links[0]: (T, None)}

    images = [SimpleNamespace(joints={"i": i}) for i in range(len(rotations))]
    return SimpleNamespace(kinematics=Kinematics(), mount_keys={"target": 1}, links={"target": link},
                           dataset=SimpleNamespace(images=images, source="arm.json"))


def test_turns_about_nearly_one_axis_are_refused():
    # the axis tilts by +-0.3 degrees from pose to pose: still one axis (ratio ~0.005 < 0.02)
    tilt = np.radians(0.3)
    rotations = [_rotation(angle * np.array([tilt * (-1) ** k, 0.0, 1.0]))
                 for k, angle in enumerate(np.linspace(0.0, 1.2, 7))]
    with pytest.raises(SolveError, match=r"along the axis \[0\.00, 0\.00, 1\.00\] of link 'tool0' is not determined"):
        check_rotation_axes(_problem(rotations))


def test_turns_about_two_axes_are_enough():
    rotations = [np.eye(3)] + [_rotation(v) for v in ([0.6, 0, 0], [0, 0.6, 0], [0.4, -0.5, 0], [-0.3, 0.2, 0])]
    check_rotation_axes(_problem(rotations))  # no third axis needed


def test_a_mount_on_the_base_link_is_not_checked():
    check_rotation_axes(_problem([np.eye(3)] * 4, link="base_link"))


def test_the_camera_mount_s_covariance_inverts_as_the_first_order_propagation():
    """``camera_base_pose``: the covariance of ``T_cam_link`` (uncertainty convention ``R' = Exp(dtheta) R``,
    ``t' = t + dt``) from the mount's Pose3 tangent one, against central differences of the inversion."""
    import gtsam

    from mirror_fg.solver.model.robot_views import camera_base_pose

    R, t = _rotation([0.3, -1.1, 0.5]), np.array([0.05, -0.12, 0.3])
    A = np.random.default_rng(4).normal(size=(6, 6))
    P = A @ A.T * 1e-4
    (R_inv, t_inv), covariance = camera_base_pose((R, t), P)
    mount = gtsam.Pose3(gtsam.Rot3(R), t)
    J = np.zeros((6, 6))
    h = 1e-6
    for k in range(6):
        ends = []
        for sign in (1.0, -1.0):
            moved = mount.compose(gtsam.Pose3.Expmap(sign * h * np.eye(6)[k])).inverse()
            ends.append(np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(moved.rotation().matrix() @ R_inv.T)),
                                        moved.translation() - t_inv]))
        J[:, k] = (ends[0] - ends[1]) / (2 * h)
    np.testing.assert_allclose(covariance, J @ P @ J.T, atol=1e-9)
