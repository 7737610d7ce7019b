"""The URDF and the camera_link outputs of mirror_fg.io.ros, read by a URDF library (yourdfpy).

``<stem>.urdf.xml`` is a minimal valid robot (two links and the joint) whose base -> camera transform is
``T_base_cam``; the ``camera_link`` variant (REP 103 body frame, x forward) chains base -> link -> optical
to the same pose; a body-frame name given for the optical frame is refused with one line.
"""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import rotation_to_quaternion_xyzw
from mirror_fg.io.ros import R_LINK_OPTICAL, link_frame_name, ros_outputs, urdf_robot, write_ros_outputs

yourdfpy = pytest.importorskip("yourdfpy")  # test extra: pip install yourdfpy


def _result(seed: int) -> tuple[dict, np.ndarray]:
    """A result@1 with a random T_cam_base; returns it and the 4x4 T_base_cam."""
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.random.default_rng(seed).uniform(-0.5, 0.5, size=3)
    T_base_cam = np.eye(4)
    T_base_cam[:3, :3], T_base_cam[:3, 3] = R.T, -R.T @ t
    entry = lambda R_, t_: {"R": R_.tolist(), "t": t_.tolist(), "q_xyzw": rotation_to_quaternion_xyzw(R_).tolist()}
    return {"format": "mirror-fg/result@1", "T_cam_base": entry(R, t),
            "T_base_cam": entry(R.T, -R.T @ t)}, T_base_cam


@pytest.mark.parametrize("seed", range(4))
def test_urdf_file_is_a_robot_yourdfpy_loads(seed, tmp_path):
    result, T_base_cam = _result(seed)
    _, urdf_path = write_ros_outputs(result, tmp_path / "calib.json", "base_link", "camera_optical_frame")
    robot = yourdfpy.URDF.load(str(urdf_path))
    assert sorted(robot.link_map) == ["base_link", "camera_optical_frame"]
    assert list(robot.joint_map) == ["base_link_to_camera_optical_frame"]
    assert robot.base_link == "base_link"
    T = robot.get_transform("camera_optical_frame", "base_link")
    assert np.max(np.abs(T - T_base_cam)) < 1e-12


@pytest.mark.parametrize("seed", range(4))
def test_camera_link_chain_gives_the_same_optical_pose(seed, tmp_path):
    result, T_base_cam = _result(seed)
    link = ros_outputs(result)["camera_link"]
    assert link["frames"] == {"link": "camera_link", "link_convention": "ROS body (REP 103): x forward, y left, z up",
                              "optical": "camera_optical_frame"}
    text = urdf_robot(link["urdf_joints"], "base_link", "camera_optical_frame").replace(
        "<link name=\"camera_optical_frame\"/>", "<link name=\"camera_optical_frame\"/>\n  <link name=\"camera_link\"/>")
    path = tmp_path / "chain.urdf"
    path.write_text(text)
    robot = yourdfpy.URDF.load(str(path))
    T = robot.get_transform("camera_optical_frame", "base_link")
    assert np.max(np.abs(T - T_base_cam)) < 1e-12
    # The body frame looks where the optical z axis looks: its x axis is the optical axis.
    T_link = robot.get_transform("camera_link", "base_link")
    assert np.allclose(T_link[:3, 0], T_base_cam[:3, 2], atol=1e-12)
    assert np.allclose(T_link[:3, 3], T_base_cam[:3, 3], atol=1e-12)
    assert np.allclose(np.array(link["T_base_link"]["matrix"]), T_link, atol=1e-12)
    # REP 103's fixed optical joint: rpy (-pi/2, 0, -pi/2).
    assert np.allclose(link["T_link_optical"]["rpy"], [-np.pi / 2, 0.0, -np.pi / 2])
    assert np.allclose(robot.get_transform("camera_optical_frame", "camera_link")[:3, :3], R_LINK_OPTICAL)
    assert len(link["static_transform_publisher_commands"]) == 2
    assert "--frame-id camera_link --child-frame-id camera_optical_frame" in link["static_transform_publisher_commands"][1]


@pytest.mark.parametrize("name", ["camera_link", "front_cam_link", "robot/camera_link", "link"])
def test_body_frame_name_for_the_optical_pose_is_refused(name, tmp_path):
    result, _ = _result(0)
    with pytest.raises(DatasetError, match=rf"camera frame '{name}' names a body frame .*optical") as error:
        write_ros_outputs(result, tmp_path / "r.json", "base_link", name)
    assert "\n" not in str(error.value)
    assert list(tmp_path.iterdir()) == []


def test_link_frame_names():
    assert link_frame_name("camera_optical_frame") == "camera_link"
    assert link_frame_name("front_cam_optical") == "front_cam_link"
    assert link_frame_name("cam0") == "cam0_link"
    result, _ = _result(1)
    content = ros_outputs(result, "base", "cam0", link_frame="cam0_body")
    assert content["camera_link"]["frames"]["link"] == "cam0_body"


def test_ros_yaml_holds_both_camera_frames(tmp_path):
    result, _ = _result(2)
    paths = write_ros_outputs(result, tmp_path / "r.json")
    content = yaml.safe_load(paths[0].read_text())
    assert content["frames"]["camera"] == "camera_optical_frame"
    assert content["camera_link"]["frames"]["link"] == "camera_link"
    assert "camera_link" in paths[1].read_text()  # the URDF's comment points at the chain
