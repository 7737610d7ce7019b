"""mirror_fg.robot.kinematics against independent references on a small hand-written URDF: a continuous
joint's placement is the rotation by its angle (Pinocchio stores it as cos, sin), and every Jacobian column
is the finite difference ``Log(T(q)^-1 T(q + h e_j)) / h`` in GTSAM's Pose3 tangent, also where the chosen
``base_link`` itself moves with a joint (the link's placement relative to it then does not depend on that
joint at all)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.robot.kinematics import Kinematics  # noqa: E402

URDF = """<?xml version="1.0"?>
<robot name="three">
  <link name="root"/><link name="turntable"/><link name="upper"/><link name="tool"/>
  <joint name="spin" type="continuous">
    <parent link="root"/><child link="turntable"/><origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>
  </joint>
  <joint name="shoulder" type="revolute">
    <parent link="turntable"/><child link="upper"/><origin xyz="0.2 0 0.05" rpy="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="wrist" type="revolute">
    <parent link="upper"/><child link="tool"/><origin xyz="0 0.1 0.3" rpy="0 0.2 0"/><axis xyz="1 0 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
</robot>
"""
JOINTS = {"spin": 0.7, "shoulder": -0.4, "wrist": 0.9}
NAMES = ["spin", "shoulder", "wrist"]


@pytest.fixture(scope="module")
def urdf(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("urdf") / "three.urdf"
    path.write_text(URDF)
    return str(path)


def test_a_continuous_joint_turns_its_link_by_its_angle(urdf) -> None:
    kin = Kinematics(urdf, "root")
    T, _ = kin.placements(JOINTS, ["turntable"])["turntable"]
    c, s = np.cos(0.7), np.sin(0.7)
    np.testing.assert_allclose(T[:3, :3], [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, 0.1], atol=1e-12)


@pytest.mark.parametrize("base", ["root", "turntable", "upper"])
def test_every_jacobian_column_is_the_finite_difference(urdf, base) -> None:
    kin = Kinematics(urdf, base)
    h = 1e-6
    for link in ("tool", "upper", "root"):
        T, J = kin.placements(JOINTS, [link], NAMES)[link]
        for j, name in enumerate(NAMES):
            moved = kin.placements({**JOINTS, name: JOINTS[name] + h}, [link])[link][0]
            step = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(T) @ moved)) / h  # [w, nu], right perturbation
            np.testing.assert_allclose(J[:, j], step, atol=1e-5, err_msg=f"base {base}, link {link}, joint {name}")
