"""The stacked arm factor (factors/robot_stack.py) against the per-image factors it stacks
(factors/robot.py): errors and Jacobians at random values, with joint offsets, two reflections, known
mounts and a robust kernel, and a whole calibration."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.factors.robot import RobotViewFactor  # noqa: E402
from mirror_fg.factors.robot_stack import RobotStack, stacked_robot_factors  # noqa: E402
from mirror_fg.factors.views import plane_of  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402

CAM, TGT, OFF = gtsam.symbol("m", 0), gtsam.symbol("m", 1), gtsam.symbol("o", 0)


def _pose(rng, t):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(scale=0.3, size=3)), np.asarray(t) + rng.normal(scale=0.05, size=3))


def _fk(kin, joints, offsets, camera_link, target_link):
    def fk(delta):
        q = dict(joints)
        for n, d in zip(offsets, delta):
            q[n] += float(d)
        out = kin.placements(q, list({camera_link, target_link}), offsets)
        return out[camera_link], out[target_link]
    return fk


@pytest.mark.parametrize("robot,camera_link,target_link,reflections,with_offsets,known,robust", [
    ("arm6", "base_link", "tool0", [(1, 0)], True, None, None),
    ("arm6", "base_link", "tool0", [(1, 0)], False, None, "huber"),
    ("panda", "panda_hand", "base_link", [(1, 0)], True, "target", None),
    ("panda", "panda_link5", "panda_hand", [(1, 0), (2, 0)], True, None, "cauchy"),
])
def test_stack_equals_the_per_image_factors(robot, camera_link, target_link, reflections, with_offsets, known,
                                            robust) -> None:
    rng = np.random.default_rng(11)
    kin = load_kinematics(arm_urdf(robot))
    chain = kin.chain("tool0" if robot == "arm6" else "panda_hand")
    values = gtsam.Values()
    mount_keys = {"camera": CAM, "target": TGT}
    known_mounts = {}
    for role, key, t in (("camera", CAM, (0.3, 0.1, 0.5)), ("target", TGT, (0.05, 0.0, 0.1))):
        pose = _pose(rng, t)
        if role == known:
            known_mounts[role] = (pose.rotation().matrix(), np.asarray(pose.translation()))
            del mount_keys[role]
        else:
            values.insert(key, pose)
    mkeys = {(1, 0): gtsam.symbol("v", 0), (2, 0): gtsam.symbol("v", 1)}
    values.insert(mkeys[(1, 0)], plane_of(np.array([0.9, 0.2, 0.4])))
    values.insert(mkeys[(2, 0)], plane_of(np.array([-0.3, 0.8, 0.2])))
    offsets = list(chain)[1:4] if with_offsets else []
    if offsets:
        values.insert(OFF, rng.normal(scale=0.01, size=3))
    points = rng.normal(scale=0.05, size=(3, 5))
    factors = []
    for _ in range(4):
        joints = {n: 0.3 * rng.normal() for n in chain}
        if robot == "panda":
            joints["panda_joint4"] = -1.5
        observed = rng.normal(scale=0.3, size=(2, 5))
        factors.append(RobotViewFactor(reflections, mount_keys, known_mounts, mkeys,
                                       _fk(kin, joints, offsets, camera_link, target_link), OFF if offsets else None,
                                       len(offsets), points, [-1] * 5, observed,
                                       rng.uniform(1e-3, 3e-3, size=(2, 5)), robust))
    stack = RobotStack(factors)
    assert stack.keys == factors[0].keys
    one = stack.factor().linearize(values)
    A_stack, b_stack = one.jacobian()
    singles = [f.factor().linearize(values).jacobian() for f in factors]
    assert np.allclose(A_stack, np.vstack([A for A, _ in singles]), rtol=1e-10, atol=1e-9)
    assert np.allclose(b_stack, np.concatenate([b for _, b in singles]), rtol=1e-10, atol=1e-12)
    error = stack.factor().error(values)
    assert error == pytest.approx(sum(f.factor().error(values) for f in factors), rel=1e-12)
    assert np.allclose(stack.predict(values), np.array([f.predict(values) for f in factors]), atol=1e-14)
    assert np.abs(A_stack).max() > 1.0  # the stack sees its unknowns


def test_stacked_graph_keeps_images_with_reconstruction_points_alone() -> None:
    rng = np.random.default_rng(3)
    kin = load_kinematics(arm_urdf("arm6"))
    chain = kin.chain("tool0")
    mkeys = {(1, 0): gtsam.symbol("v", 0), (2, 0): gtsam.symbol("v", 1)}
    factors = []
    for k in range(6):
        joints = {n: 0.3 * rng.normal() for n in chain}
        points = rng.normal(scale=0.05, size=(3, 4))
        landmarks = [-1] * 4
        if k == 5:
            points[:, 0] = np.nan
            landmarks[0] = gtsam.symbol("l", 0)
        factors.append(RobotViewFactor([(1 + k % 2, 0)], {"camera": CAM, "target": TGT}, {}, mkeys,
                                       _fk(kin, joints, [], "base_link", "tool0"), None, 0, points, landmarks,
                                       np.zeros((2, 4)), np.full((2, 4), 1e-3)))
    graph = stacked_robot_factors(factors)
    assert len(graph) == 3  # one per placement, and the image with a reconstruction point alone
    assert sorted(g.dim() for g in graph) == [8, 16, 24]


def test_problem_predictions_are_each_images_factors(tmp_path) -> None:
    from mirror_fg.io.dataset import load_dataset
    from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
    from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem

    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=4, seed=1,
                                  joint_offsets_deg={"elbow_joint": 0.3})
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    problem = RobotProblem(load_dataset(path))
    values = problem.values(RobotEstimate({r: p for r, (_, p) in truth.mounts.items()}, dict(truth.mirror_vectors),
                                          {}, np.array([0.004])))
    stacks, alone = problem.stacks
    assert len(stacks) == 3 and not alone  # one per placement
    for z, factor in zip(problem.predictions(values), problem.factors):
        assert np.allclose(z, factor.predict(values), rtol=0, atol=1e-14)
