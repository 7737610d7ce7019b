"""The error at a point on any link of an arm (docs/formats.md, "The answer in the user's units"):
``cal.point_error(p, link=NAME, joints=q)`` against a Monte Carlo of the result's own covariance (camera
mount and joint offsets) through Pinocchio's forward kinematics, within 3 %; on the base link of an
eye-to-hand arm it is the camera-frame point error."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.factors.robot import compose, inverse  # noqa: E402
from mirror_fg.io.dataset import dataset_from_dict  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm  # noqa: E402
from mirror_fg.solver.batch.robot_solve import calibrate_robot  # noqa: E402


def _calibrate(robot: str, eye_in_hand: bool, offsets: dict | None = None):
    data, _ = simulate_arm(robot, eye_in_hand, placements=3, arm_poses=6, pixel_sigma=0.5, seed=3,
                           joint_offsets_deg=offsets)
    data["robot"]["urdf"] = arm_urdf(robot)
    dataset = dataset_from_dict(data, source=f"{robot}.json")
    return dataset, calibrate_robot(dataset)


def _monte_carlo(model, point, link, joints, samples: int = 40000, seed: int = 0) -> np.ndarray:
    """Covariance of the exact miss ``C_hat C^-1 P - P_hat`` over draws of the result's own covariance."""
    kin = model.kinematics
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(np.zeros(len(model.covariance)), model.covariance, size=samples)
    q_hat = model.corrected(joints)

    def poses(q):
        F = kin.placements(q, list(dict.fromkeys([link, model.camera_link])))
        T_L, T_c = F[link][0], F[model.camera_link][0]
        return (T_L[:3, :3], T_L[:3, 3]), (T_c[:3, :3], T_c[:3, 3])

    (R_L, t_L), F_c = poses(q_hat)
    P_hat = R_L @ point + t_L
    C_hat = compose(F_c, model.camera_mount)
    misses = np.empty((samples, 3))
    for k, z in enumerate(draws):
        q = dict(q_hat)
        for name, d in zip(model.offset_names, z[6:]):
            q[name] += d
        (R, t), F = poses(q) if len(z) > 6 else ((R_L, t_L), F_c)
        X = gtsam.Pose3.Expmap(z[:6]).matrix()
        C = compose(compose(F, model.camera_mount), (X[:3, :3], X[:3, 3]))
        x = inverse(C)[0] @ (R @ point + t) + inverse(C)[1]
        misses[k] = C_hat[0] @ x + C_hat[1] - P_hat
    return np.cov(misses.T)


@pytest.mark.parametrize("robot,eye_in_hand,link,offsets", [
    ("panda", True, "panda_hand", {"panda_joint2": 0.5, "panda_joint4": -0.5}),
    ("arm6", False, "tool0", {"shoulder_lift_joint": 0.5}),
])
def test_a_grasp_points_error_equals_a_monte_carlo_of_the_results_covariance(robot, eye_in_hand, link, offsets) -> None:
    dataset, cal = _calibrate(robot, eye_in_hand, offsets)
    model = cal.robot["link_error"]
    joints = dataset.images[4].joints
    grasp = np.array([0.0, 0.0, 0.10])  # 10 cm along the flange's axis
    error = cal.point_error(grasp, link=link, joints=joints)
    reference = _monte_carlo(model, grasp, link, joints)
    assert np.allclose(np.sqrt(np.diag(error.covariance)), np.sqrt(np.diag(reference)), rtol=0.03), (
        error.covariance, reference)
    largest = 3000.0 * np.sqrt(np.linalg.eigvalsh(reference)[-1])
    assert abs(error.largest_sigma3_mm - largest) < 0.03 * largest
    assert np.all(model.covariance[6:, 6:].diagonal() > 0)  # the offsets enter
    # the point is where the arm's kinematics put it
    T = model.kinematics.placements(model.corrected(joints), [link])[link][0]
    assert np.allclose(error.point_base, T[:3, :3] @ grasp + T[:3, 3])


def test_on_the_base_link_of_an_eye_to_hand_arm_it_is_the_camera_frame_point_error() -> None:
    _, cal = _calibrate("arm6", False)
    p_base = np.array([0.4, 0.1, 0.3])
    p_cam = cal.T_cam_base.apply(p_base)
    on_link = cal.point_error(p_base, link="base_link", joints={})
    in_camera = cal.point_error(p_cam)
    assert np.allclose(on_link.point_base, in_camera.point_base)
    assert np.allclose(on_link.covariance, in_camera.covariance, rtol=1e-6, atol=1e-15)


def test_bad_link_or_joints_are_said_in_words() -> None:
    dataset, cal = _calibrate("arm6", False)
    joints = dataset.images[0].joints
    with pytest.raises(ValueError, match="'gripper' is not a link"):
        cal.point_error([0, 0, 0.1], link="gripper", joints=joints)
    with pytest.raises(ValueError, match="no value for 'wrist_3_joint'"):
        cal.point_error([0, 0, 0.1], link="tool0", joints={k: v for k, v in joints.items() if k != "wrist_3_joint"})
    with pytest.raises(ValueError, match="give both link"):
        cal.point_error([0, 0, 0.1], link="tool0")
