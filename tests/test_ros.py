"""Tests of mirror_fg.io.ros: URDF joint round trip, quaternions, static_transform_publisher arguments, files."""
from __future__ import annotations

import argparse
import math
import shlex
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from mirror_fg.core.geometry import so3_exp
from mirror_fg.core.transform import quaternion_xyzw_to_rotation, rotation_to_quaternion_xyzw
from mirror_fg.io.ros import ros_outputs, rotation_to_rpy, sigma3_base_cam, write_ros_outputs


def _Rx(a: float) -> np.ndarray:
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _Ry(a: float) -> np.ndarray:
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _Rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def _urdf_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF's fixed-axis convention, written out independently of the module: Rz(yaw) Ry(pitch) Rx(roll)."""
    return _Rz(yaw) @ _Ry(pitch) @ _Rx(roll)


def _result(R_base_cam: np.ndarray, t_base_cam: np.ndarray) -> dict:
    """A minimal result@1 whose camera pose in the base frame is (R_base_cam, t_base_cam)."""
    R = R_base_cam.T
    t = -R @ t_base_cam
    return {
        "format": "mirror-fg/result@1",
        "T_cam_base": {"R": R.tolist(), "t": t.tolist()},
        "T_base_cam": {"R": R_base_cam.tolist(), "t": t_base_cam.tolist()},
        "sigma3_cam_base": {"rotation_deg": [0.1, 0.2, 0.3], "position_mm": [1.0, 2.0, 3.0]},
        "residuals": {"rms_px": 0.51, "max_px": 2.2},
    }


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quaternion_xyzw_to_rotation(q / np.linalg.norm(q))


def _rotations() -> list[np.ndarray]:
    """Random rotations, near and at gimbal lock, identity and half turns."""
    rng = np.random.default_rng(7)
    rotations = [_random_rotation(rng) for _ in range(100)]
    for sign in (1.0, -1.0):
        for offset in (0.0, 1e-15, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, -1e-9, -1e-5):
            roll, yaw = rng.uniform(-math.pi, math.pi, size=2)
            rotations.append(_urdf_rotation(roll, sign * (math.pi / 2 - offset), yaw))
    rotations.append(np.eye(3))
    rotations += [np.diag(d) for d in ([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0])]
    rotations.append(so3_exp(math.pi * np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)))
    return rotations


def _parse_joint(text: str) -> tuple[np.ndarray, np.ndarray, ET.Element]:
    joint = ET.fromstring(text)
    origin = joint.find("origin")
    xyz = np.array([float(x) for x in origin.get("xyz").split()])
    rpy = [float(x) for x in origin.get("rpy").split()]
    return xyz, _urdf_rotation(*rpy), joint


@pytest.mark.parametrize("index", range(len(_rotations())))
def test_urdf_round_trip(index):
    R = _rotations()[index]
    t = np.random.default_rng(index).uniform(-2.0, 2.0, size=3)
    result = _result(R, t)
    if index % 2:
        del result["T_base_cam"]  # computed as the inverse of T_cam_base then
    out = ros_outputs(result)
    xyz, R_back, joint = _parse_joint(out["urdf_joint"])
    assert joint.tag == "joint" and joint.get("type") == "fixed"
    assert joint.find("parent").get("link") == "base_link"
    assert joint.find("child").get("link") == "camera_optical_frame"
    assert np.max(np.abs(xyz - t)) <= 1e-9
    assert np.max(np.abs(R_back - R)) <= 1e-9
    roll, pitch, yaw = rotation_to_rpy(R)
    assert -math.pi / 2 <= pitch <= math.pi / 2 and -math.pi <= roll <= math.pi and -math.pi <= yaw <= math.pi


def test_rpy_matches_known_angles():
    roll, pitch, yaw = 0.3, -0.4, 1.2
    assert np.allclose(rotation_to_rpy(_urdf_rotation(roll, pitch, yaw)), (roll, pitch, yaw), atol=1e-12)
    # Exact gimbal lock: yaw is set to 0 and roll carries the rest.
    r, p, y = rotation_to_rpy(_urdf_rotation(0.5, math.pi / 2, 0.2))
    assert y == 0.0 and p == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("index", range(0, len(_rotations()), 5))
def test_quaternions_match_rotations(index):
    R = _rotations()[index]
    out = ros_outputs(_result(R, np.array([0.1, 0.2, 0.3])))
    for key, expected in (("T_base_cam", R), ("T_cam_base", R.T)):
        x, y, z, w = out[key]["quaternion_xyzw"]
        assert math.isclose(x * x + y * y + z * z + w * w, 1.0, abs_tol=1e-12)
        # Hamilton, scalar last, written out here (not the module's converter).
        Q = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        assert np.max(np.abs(Q - expected)) < 1e-12
        T = np.array(out[key]["matrix"])
        assert np.allclose(T[:3, :3], expected, atol=1e-15) and np.array_equal(T[3], [0, 0, 0, 1])
        assert np.array_equal(T[:3, 3], out[key]["translation"])
    T_bc, T_cb = np.array(out["T_base_cam"]["matrix"]), np.array(out["T_cam_base"]["matrix"])
    assert np.allclose(T_bc @ T_cb, np.eye(4), atol=1e-12)


def test_quaternion_sign_follows_result_file():
    R = so3_exp(np.array([0.3, -0.2, 0.5]))
    result = _result(R, np.zeros(3))
    q = rotation_to_quaternion_xyzw(R)
    result["T_base_cam"]["q_xyzw"] = (-q).tolist()
    assert np.allclose(ros_outputs(result)["T_base_cam"]["quaternion_xyzw"], -q)
    del result["T_base_cam"]["q_xyzw"]
    assert ros_outputs(result)["T_base_cam"]["quaternion_xyzw"][3] >= 0.0


def _parse_publisher(args: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    for name in ("x", "y", "z", "qx", "qy", "qz", "qw"):
        parser.add_argument(f"--{name}", type=float, required=True)
    parser.add_argument("--frame-id", required=True)
    parser.add_argument("--child-frame-id", required=True)
    return parser.parse_args(shlex.split(args))


@pytest.mark.parametrize("index", range(0, len(_rotations()), 3))
def test_static_transform_publisher_parses_back(index):
    R = _rotations()[index]
    t = np.array([-0.065, 1e-17, 12.5])
    out = ros_outputs(_result(R, t), base_frame="robot/base", camera_frame="front_cam_optical")
    ns = _parse_publisher(out["static_transform_publisher"])
    assert ns.frame_id == "robot/base" and ns.child_frame_id == "front_cam_optical"
    assert np.array_equal([ns.x, ns.y, ns.z], t)
    assert np.max(np.abs(quaternion_xyzw_to_rotation([ns.qx, ns.qy, ns.qz, ns.qw]) - R)) < 1e-12
    assert out["static_transform_publisher_command"].startswith("ros2 run tf2_ros static_transform_publisher --x ")


def test_sigma3_base_cam_matches_numerical_jacobian():
    rng = np.random.default_rng(3)
    R_cb, t_cb = _random_rotation(rng), rng.uniform(-1, 1, size=3)
    L = rng.normal(size=(6, 6)) * 1e-3
    cov = L @ L.T
    result = _result(R_cb.T, -R_cb.T @ t_cb)
    result["covariance_cam_base"] = cov.tolist()
    # Numerical Jacobian of the base-frame pose [dphi (base axes), dp] w.r.t. docs/formats.md's [dtheta, dt].
    J = np.zeros((6, 6))
    eps = 1e-7
    R_bc, t_bc = R_cb.T, -R_cb.T @ t_cb
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        R2, t2 = so3_exp(d[:3]) @ R_cb, t_cb + d[3:]
        R2_bc, t2_bc = R2.T, -R2.T @ t2
        W = R2_bc @ R_bc.T
        J[:3, k] = np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]]) / (2 * eps)
        J[3:, k] = (t2_bc - t_bc) / eps
    sd3 = 3.0 * np.sqrt(np.diag(J @ cov @ J.T))
    got = sigma3_base_cam(result)
    assert np.allclose(got["rotation_deg"], np.rad2deg(sd3[:3]), rtol=1e-5)
    assert np.allclose(got["position_mm"], 1e3 * sd3[3:], rtol=1e-5)
    assert ros_outputs(result)["sigma3_base_cam"] == got


def test_write_ros_outputs(tmp_path):
    R = so3_exp(np.array([0.1, -0.7, 0.2]))
    t = np.array([0.12, -0.03, 0.45])
    result = _result(R, t)
    (tmp_path / "calib.ros.yaml").write_text("old")
    paths = write_ros_outputs(result, tmp_path / "calib.json", "base", "cam_optical")
    assert [p.name for p in paths] == ["calib.ros.yaml", "calib.urdf.xml"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.ros.yaml", "calib.urdf.xml"]  # no temp files
    content = yaml.safe_load(paths[0].read_text())
    assert content["frames"]["base"] == "base" and content["frames"]["camera"] == "cam_optical"
    assert np.allclose(np.array(content["T_base_cam"]["matrix"])[:3, :3], R, atol=1e-15)
    assert content["T_base_cam"]["translation"] == t.tolist()  # repr floats: exact
    assert content["sigma3"]["rotation_deg"] == [0.1, 0.2, 0.3]
    assert content["sigma3"]["position_mm"] == [1.0, 2.0, 3.0]
    assert content["rms_px"] == 0.51
    xyz, R_back, _ = _parse_joint(content["urdf_joint"])
    assert np.max(np.abs(R_back - R)) < 1e-9 and np.max(np.abs(xyz - t)) < 1e-9
    assert "\n" not in content["static_transform_publisher"]
    assert _parse_publisher(content["static_transform_publisher"]).frame_id == "base"
    # The URDF file is a well-formed URDF robot (two links) holding the same joint.
    robot = ET.parse(paths[1]).getroot()
    assert robot.tag == "robot" and [link.get("name") for link in robot.findall("link")] == ["base", "cam_optical"]
    (joint,) = robot.findall("joint")
    assert joint.find("parent").get("link") == "base"
    joint.tail = None
    assert ET.tostring(joint) == ET.tostring(ET.fromstring(content["urdf_joint"]))


def test_bad_input_raises_and_writes_nothing(tmp_path):
    good = _result(np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="frame name"):
        write_ros_outputs(good, tmp_path / "r.json", "base link", "cam")
    with pytest.raises(ValueError, match="frame name"):
        ros_outputs(good, camera_frame='cam"><evil')
    bad = dict(good)
    del bad["T_cam_base"]
    with pytest.raises(ValueError, match="T_cam_base"):
        write_ros_outputs(bad, tmp_path / "r.json")
    bad = _result(np.eye(3), np.zeros(3))
    bad["T_cam_base"]["R"] = (2.0 * np.eye(3)).tolist()
    with pytest.raises(ValueError, match="not a rotation"):
        ros_outputs(bad)
    bad = _result(np.eye(3), np.zeros(3))
    bad["T_base_cam"]["t"] = [1.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="not the inverse"):
        ros_outputs(bad)
    assert list(tmp_path.iterdir()) == []
