"""Rigid-transform helpers: quaternions and SPEC's covariance convention (numpy only)."""
from __future__ import annotations

import numpy as np

__all__ = ["rotation_to_quaternion_xyzw", "quaternion_xyzw_to_rotation", "spec_covariance_from_pose3", "rotation_angle"]


def rotation_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Hamilton unit quaternion ``(x, y, z, w)`` of a rotation matrix, ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    trace = float(np.trace(R))
    diag = np.diag(R)
    k = int(np.argmax([trace, *diag]))  # largest of 4w^2-1, 4x^2-1, ... : no cancellation
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] + R[1, 1] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] - R[1, 1] + R[2, 2])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def quaternion_xyzw_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a Hamilton quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def spec_covariance_from_pose3(R_cam_base: np.ndarray, pose3_covariance: np.ndarray) -> np.ndarray:
    """SPEC's ``[dtheta, dt]`` covariance from GTSAM's Pose3 ``[w, nu]`` one: ``dtheta = R w``, ``dt = R nu``."""
    J = np.zeros((6, 6))
    J[:3, :3] = R_cam_base
    J[3:, 3:] = R_cam_base
    return J @ np.asarray(pose3_covariance) @ J.T


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (radians) of the rotation ``R_a R_b^T``."""
    cos = (np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))
