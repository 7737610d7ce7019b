"""The arm's view factor (factors/robot.py) against numerical differences: mounts, planes in {B},
reconstruction points and joint offsets, the offsets' Jacobians from Pinocchio's frame Jacobians."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.factors.robot import RobotViewFactor  # noqa: E402
from mirror_fg.factors.views import plane_of  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402

CAM, TGT, OFF = gtsam.symbol("m", 0), gtsam.symbol("m", 1), gtsam.symbol("o", 0)


def _pose(rng, scale=0.3, t=(0.0, 0.0, 0.0)):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(scale=scale, size=3)), np.asarray(t) + rng.normal(scale=0.05, size=3))


@pytest.mark.parametrize("robot,camera_link,target_link,reflections", [
    ("arm6", "base_link", "tool0", [(1, 0)]),
    ("panda", "panda_hand", "base_link", [(1, 0)]),
    ("panda", "panda_link5", "panda_hand", [(1, 0), (2, 0)]),
    ("arm6", "base_link", "tool0", []),
])
def test_jacobians_match_numerical_differences(robot, camera_link, target_link, reflections) -> None:
    rng = np.random.default_rng(7)
    kin = load_kinematics(arm_urdf(robot))
    joints = {n: 0.3 * rng.normal() for n in kin.chain("tool0" if robot == "arm6" else "panda_hand")}
    if robot == "panda":
        joints["panda_joint4"] = -1.5
    offsets = list(joints)[1:4]

    def fk(delta):
        q = dict(joints)
        for n, d in zip(offsets, delta):
            q[n] += float(d)
        out = kin.placements(q, list({camera_link, target_link}), offsets)
        return out[camera_link], out[target_link]

    values = gtsam.Values()
    values.insert(CAM, _pose(rng, t=(0.3, 0.1, 0.5)))
    values.insert(TGT, _pose(rng, t=(0.05, 0.0, 0.1)))
    mkeys = {(1, 0): gtsam.symbol("v", 0), (2, 0): gtsam.symbol("v", 1)}
    values.insert(mkeys[(1, 0)], plane_of(np.array([0.9, 0.2, 0.4])))
    values.insert(mkeys[(2, 0)], plane_of(np.array([-0.3, 0.8, 0.2])))
    values.insert(gtsam.symbol("l", 0), rng.normal(scale=0.05, size=3))
    values.insert(OFF, rng.normal(scale=0.01, size=3))
    points = rng.normal(scale=0.05, size=(3, 4))
    points[:, 2] = np.nan
    landmarks = [-1, -1, gtsam.symbol("l", 0), -1]
    factor = RobotViewFactor(reflections, {"camera": CAM, "target": TGT}, {}, mkeys, fk, OFF, 3, points, landmarks,
                             np.zeros((2, 4)), np.full((2, 4), 1e-3))
    A = factor.factor().linearize(values).jacobian()[0]
    columns = []
    for key in factor.keys:
        symbol = chr(gtsam.Symbol(key).chr())
        dim = {"m": 6, "v": 3, "l": 3, "o": 3}[symbol]
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = 1e-6
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            for sign, vals in ((1.0, plus), (-1.0, minus)):
                if symbol == "m":
                    vals.update(key, values.atPose3(key).retract(sign * d))
                elif symbol == "v":
                    vals.update(key, values.atOrientedPlane3(key).retract(sign * d))
                elif symbol == "l":
                    vals.update(key, values.atPoint3(key) + sign * d)
                else:
                    vals.update(key, values.atVector(key) + sign * d)
            columns.append((factor.predict(plus) - factor.predict(minus)).T.reshape(-1) / 2e-6 / 1e-3)
    numerical = np.column_stack(columns)
    assert A.shape == numerical.shape
    assert np.allclose(A, numerical, atol=1e-4 * max(1.0, np.abs(numerical).max()), rtol=1e-5)
    assert np.abs(A).max() > 1.0  # the factor sees its unknowns
