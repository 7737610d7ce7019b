"""Planning an arm's calibration through mirrors (docs/formats.md, "Robot arms: joint states and mounts"):
the Cramer-Rao bounds of a described set-up, and which arm pose to try next.

- :func:`arm_bounds`: the mounts' 3-sigma at the simulated truth of a set-up (``simulate.simulate_arm``),
  the inverse Fisher information of the view model with forward kinematics, averaged over draws.
- :func:`rank_joint_candidates`: the data calibrated, each candidate joint configuration (a CSV of
  reachable ones) imagined as one more image through the mirror where it stands now (the data's last
  placement), its noise-free measurements' information added; ranked by the norm of the camera mount's predicted
  position 3-sigma (the moving mount's where the camera mount is known). Candidates whose target would not
  be seen (outside the image, behind the camera or the mirror) are left out.
Units: millimetres and degrees in what is printed, radians and metres inside.
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.factors.robot import RobotViewFactor

if TYPE_CHECKING:
    import gtsam

__all__ = ["arm_bounds", "rank_joint_candidates", "load_joint_candidates", "Candidate", "candidate_jacobian",
           "mount_bounds"]


def _sigma3(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = 3.0 * np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return np.degrees(s[:3]), 1000.0 * s[3:]


def arm_bounds(robot: str, eye_in_hand: bool, placements: int, arm_poses: int, pixel_sigma: float,
               draws: int = 3, seed: int = 0, folder: str | None = None, cameras: int = 1) -> dict:
    """``{mount: {"rotation_deg": [3], "position_mm": [3]}}``: each unknown mount's 3-sigma (Cramer-Rao, at
    the truth) of a simulated set-up, averaged over ``draws`` scenes; ``cameras`` > 1: that many cameras
    (``simulate_arm``'s), their mounts ``camera:cam0``, ``camera:cam1``, ..."""
    import tempfile

    from mirror_fg.io.dataset import load_dataset
    from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
    from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem, camera_role

    sums: dict[str, np.ndarray] = {}
    with tempfile.TemporaryDirectory(dir=folder) as where:
        for draw in range(draws):
            dataset, truth = simulate_arm(robot, eye_in_hand, placements, arm_poses, pixel_sigma, seed=seed + draw,
                                          cameras=cameras)
            path = os.path.join(where, f"plan{draw}.json")
            write_arm_simulation(path, dataset, truth)
            problem = RobotProblem(load_dataset(path))
            mounts = {r: pose for r, (_, pose) in truth.mounts.items()}
            mounts.update({camera_role(n): pose for n, (_, pose) in truth.cameras.items()})
            at_truth = RobotEstimate(mounts, dict(truth.mirror_vectors))
            information, columns = problem.information(problem.graph(), problem.values(at_truth))
            covariance = problem.covariances(np.linalg.inv(information), columns, at_truth)
            for role, C in covariance["mounts"].items():
                rotation, position = _sigma3(C)
                sums[role] = sums.get(role, 0.0) + np.concatenate([rotation, position]) / draws
    return {role: {"rotation_deg": v[:3].tolist(), "position_mm": v[3:].tolist()} for role, v in sums.items()}


@dataclass
class Candidate:
    """A candidate arm pose: its row in the file (1 = the first after the header), joint values, the
    predicted 3-sigma of the ranked mount after adding it (position mm, rotation deg)."""

    row: int
    joints: dict[str, float]
    position_mm: np.ndarray
    rotation_deg: np.ndarray


def load_joint_candidates(path: str, needed: list[str]) -> list[dict[str, float]]:
    """Rows of a CSV whose header names joints (every joint in ``needed``; other columns ignored)."""
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as error:
        raise DatasetError(f"{path}: cannot read the joint candidates: {error.strerror or error}") from None
    if not rows:
        raise DatasetError(f"{path}: no joint candidates (a header of joint names, then one row per arm pose)")
    missing = [n for n in needed if n not in rows[0]]
    if missing:
        raise DatasetError(f"{path}: no column for joint {missing[0]!r} (the header names every joint: "
                           f"{', '.join(needed)})")
    out = []
    for k, row in enumerate(rows, start=1):
        values = {}
        for n in needed:
            try:
                values[n] = float(row[n])
            except (TypeError, ValueError):
                raise DatasetError(f"{path}: row {k}: joint {n!r} is {row[n]!r}, not a number") from None
            if not math.isfinite(values[n]):
                raise DatasetError(f"{path}: row {k}: joint {n!r} is {row[n]!r}, not a finite number")
        out.append(values)
    return out


def _seen(factor: RobotViewFactor, values: gtsam.Values, placement, mirror: np.ndarray, camera) -> bool:
    """Whether the candidate's target would be seen through the mirror: the camera and every target point on
    one side of the plane, the points ahead of the camera and inside the image."""
    state = factor.poses(values)
    C, D = state["C"], state["D"]
    x_B = D[0] @ factor.target_points + D[1][:, None]
    n, d = mirror / np.linalg.norm(mirror), float(np.linalg.norm(mirror))
    side_camera = float(n @ C[1]) - d
    if np.any((n @ x_B - d) * side_camera <= 0):
        return False
    reflected = x_B - 2.0 * np.outer(n, n @ x_B - d)  # eq. (3)
    x_cam = C[0].T @ (reflected - C[1][:, None])
    if np.any(x_cam[2] <= 0.05):
        return False
    if camera is None:
        return True
    return bool(camera.contains(camera.distort((x_cam[:2] / x_cam[2]).T)).all())


def candidate_jacobian(solution, dataset, joints: dict[str, float], placement) -> np.ndarray | None:
    """The whitened Jacobian (2N, unknowns; ``solution.columns``) of one more image at ``joints`` through
    ``placement`` at the solution, or None where its target would not be seen (:func:`_seen`)."""
    from mirror_fg.io.point_sigma import normalized_sigmas

    problem, values = solution.problem, solution.values
    names = list(dataset.fiducials)
    points = np.array([dataset.fiducials[n] for n in names]).T
    sigmas = normalized_sigmas(dataset.camera, dataset.pixel_sigma, dataset.point_sigma, names).T
    factor = RobotViewFactor((placement,), problem.mount_keys, problem.known, problem.mirror_keys,
                             problem.forward(joints), problem.offset_key, len(problem.offsets), points,
                             [-1] * len(names), np.zeros((2, len(names))), sigmas)
    if not _seen(factor, values, placement, solution.estimate.mirror_vectors[placement], dataset.camera):
        return None
    A = factor.factor().linearize(values).jacobian()[0]  # whitened by the noise model, as the information
    J = np.zeros((A.shape[0], solution.information.shape[0]))
    start = 0
    for key in factor.keys:
        c = solution.columns[key]
        J[:, c] = A[:, start:start + (c.stop - c.start)]
        start += c.stop - c.start
    return J


def mount_bounds(solution, information: np.ndarray, role: str) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation 3-sigma deg, position 3-sigma mm)`` of a mount under ``information``."""
    from mirror_fg.core.transform import covariance_from_pose3

    c = solution.columns[solution.problem.mount_keys[role]]
    return _sigma3(covariance_from_pose3(solution.estimate.mounts[role][0], np.linalg.inv(information)[c, c]))


def rank_joint_candidates(dataset, candidates: list[dict[str, float]], solution=None) -> tuple[list[Candidate], dict]:
    """The candidates ranked (module docstring), best first, and the ranked mount's current 3-sigma
    ``{"mount", "placement", "position_mm", "rotation_deg"}``. ``solution``: a ``robot_solve.RobotSolution``
    of ``dataset`` (solved here when None)."""
    from mirror_fg.solver.batch.robot_solve import solve_robot

    solution = solution if solution is not None else solve_robot(dataset)
    problem = solution.problem
    role = "camera" if "camera" in problem.mount_keys else next(iter(problem.mount_keys))
    placement = dataset.images[-1].reflections[-1] if dataset.images[-1].reflections else problem.placements[-1]
    now_rotation, now_position = mount_bounds(solution, solution.information, role)
    ranked = []
    for row, joints in enumerate(candidates, start=1):
        J = candidate_jacobian(solution, dataset, joints, placement)
        if J is None:
            continue
        rotation, position = mount_bounds(solution, solution.information + J.T @ J, role)
        ranked.append(Candidate(row, joints, position, rotation))
    ranked.sort(key=lambda c: float(np.linalg.norm(c.position_mm)))
    return ranked, {"mount": role, "placement": placement, "position_mm": now_position, "rotation_deg": now_rotation}
