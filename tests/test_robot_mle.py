"""The arm's MLE (solver/batch/robot_solve.py) against an independent reference (tests/robot_reference.py:
scipy least_squares, yourdfpy kinematics): estimates within 0.05 sigma, covariances within 15 %; its
analytical start needs no truth; the truth within 3 sigma."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pinocchio")
pytest.importorskip("yourdfpy")

from robot_reference import reference_mle  # noqa: E402

from mirror_fg.io.dataset import load_dataset  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.calibrate import calibrate  # noqa: E402

OFFSET = {"arm6": "shoulder_lift_joint", "panda": "panda_joint2"}


def _pose(entry):
    return np.array(entry["R"], float), np.array(entry["t"], float)


def _rotation_error(R_est, R_ref):
    """dtheta with R_ref = Exp(dtheta) R_est (the uncertainty convention)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R_ref @ R_est.T).as_rotvec()


def _solve(tmp_path, robot, eye_in_hand, seed, sigma=0.5, poses=8):
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=3, arm_poses=poses, pixel_sigma=sigma,
                                  joint_offsets_deg={OFFSET[robot]: 0.5}, seed=seed)
    path = tmp_path / f"{robot}.json"
    write_arm_simulation(str(path), dataset, truth)
    return dataset, truth, calibrate(load_dataset(path))


@pytest.mark.parametrize("robot,eye_in_hand", [("arm6", False), ("panda", True), ("panda", False), ("arm6", True)])
def test_mle_equals_the_independent_reference(tmp_path, robot, eye_in_hand) -> None:
    dataset, truth, result = _solve(tmp_path, robot, eye_in_hand, seed=11)
    mounts_truth = {role: pose for role, (_, pose) in truth.mounts.items()}
    ref = reference_mle(dataset, arm_urdf(robot), mounts_truth, {m: v for (_, m), v in truth.mirror_vectors.items()})
    assert result.final_error == pytest.approx(ref.cost, rel=1e-6)
    ours = result.robot
    for role in ("camera", "target"):
        entry = ours["mounts"][role]
        R, t = _pose(entry["T_link_cam" if role == "camera" else "T_link_target"])
        R_ref, t_ref = ref.mounts[role]
        delta = np.concatenate([_rotation_error(R, R_ref), t_ref - t])
        C_ref = ref.covariance[ref.layout[role], ref.layout[role]]
        assert np.all(np.abs(delta) < 0.05 * np.sqrt(np.diag(C_ref))), (role, delta / np.sqrt(np.diag(C_ref)))
        C = np.array(entry["covariance"])
        assert np.allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(C_ref)), rtol=0.15)
        assert np.linalg.norm(C - C_ref) < 0.15 * np.linalg.norm(C_ref)
    for (l, m), v in result.mirror_vectors.items():
        C_ref = ref.covariance[ref.layout[m], ref.layout[m]]
        assert np.all(np.abs(v - ref.planes[m]) < 0.05 * np.sqrt(np.diag(C_ref)))
        assert np.allclose(np.sqrt(np.diag(result.mirror_covariances[(l, m)])), np.sqrt(np.diag(C_ref)), rtol=0.15)
    offset = ours["joint_offsets"][OFFSET[robot]]
    sigma_ref = math.degrees(math.sqrt(ref.covariance[ref.layout["offsets"], ref.layout["offsets"]][0, 0]))
    assert abs(offset["offset_deg"] - math.degrees(ref.offsets[0])) < 0.05 * sigma_ref
    assert offset["sigma3_deg"] / 3.0 == pytest.approx(sigma_ref, rel=0.15)
