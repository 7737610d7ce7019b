"""Rigid transforms as typed values, and the covariance convention of docs/formats.md (numpy only).

:class:`Transform` ``T_a_b`` maps points of frame b into frame a, ``p_a = R @ p_b + t`` (metres), as
jaxlie/Sophus do: ``T_a_b @ T_b_c`` is ``T_a_c``, ``T_a_b.inverse()`` is ``T_b_a``, ``T_a_b.apply(p_b)``
is ``p_a``. Names state the frames (``T_cam_base``, ``T_base_cam``).

Covariances of a transform are ``[dtheta (3, rad), dt (3, m)]`` with ``R_true = Exp(dtheta) @ R_est``
(rotation error about the axes of frame a) and ``t_true = t_est + dt``. GTSAM's Pose3 covariance is
in its right-perturbation tangent ``[w, nu]`` (``R Exp(w)``, ``t + R nu``): ``dtheta = R w``,
``dt = R nu`` (:func:`covariance_from_pose3`, :func:`covariance_to_pose3`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Transform",
    "rotation_to_quaternion_xyzw",
    "quaternion_xyzw_to_rotation",
    "rpy_to_rotation",
    "rotation_to_rpy",
    "covariance_from_pose3",
    "covariance_to_pose3",
    "spec_covariance_from_pose3",
    "rotation_angle",
]


@dataclass(frozen=True, eq=False)
class Transform:
    """A rigid transform ``T_a_b``: ``p_a = R @ p_b + t``. ``R`` (3, 3) rotation, ``t`` (3,) metres."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.array(self.R, dtype=float).reshape(3, 3))
        object.__setattr__(self, "t", np.array(self.t, dtype=float).reshape(3))

    @classmethod
    def identity(cls) -> Transform:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Transform:
        """From a 4x4 homogeneous matrix."""
        m = np.asarray(matrix, dtype=float)
        return cls(m[:3, :3], m[:3, 3])

    @classmethod
    def from_quaternion_xyzw(cls, q_xyzw: np.ndarray, t: np.ndarray) -> Transform:
        return cls(quaternion_xyzw_to_rotation(q_xyzw), t)

    def inverse(self) -> Transform:
        """``T_b_a`` of ``T_a_b``: ``(R^T, -R^T t)``."""
        return Transform(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Transform) -> Transform:
        """Composition ``T_a_b @ T_b_c = T_a_c``."""
        return Transform(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``R @ p + t`` of points (3,) or (N, 3)."""
        return np.asarray(points, dtype=float) @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    def quaternion_xyzw(self) -> np.ndarray:
        """Hamilton unit quaternion ``(x, y, z, w)``, ``w >= 0``."""
        return rotation_to_quaternion_xyzw(self.R)

    def rpy(self) -> tuple[float, float, float]:
        """URDF ``(roll, pitch, yaw)``, radians: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
        return rotation_to_rpy(self.R)

    def inverse_covariance(self, covariance: np.ndarray) -> np.ndarray:
        """Covariance (6, 6) of ``T_b_a = T_a_b.inverse()`` from that of ``T_a_b``, both in the
        ``[dtheta, dt]`` convention (rotation error about frame b's axes for the inverse). First order:
        ``dtheta' = -R^T dtheta``, ``dt' = -R^T [t]x dtheta - R^T dt``."""
        R, t = self.R, self.t
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        J = np.zeros((6, 6))
        J[:3, :3] = -R.T
        J[3:, :3] = -R.T @ tx
        J[3:, 3:] = -R.T
        return J @ np.asarray(covariance, dtype=float) @ J.T

    def __repr__(self) -> str:
        return f"Transform(R={np.array2string(self.R, precision=6)}, t={np.array2string(self.t, precision=6)})"


def _pose3_jacobian(R: np.ndarray) -> np.ndarray:
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    return J


def covariance_from_pose3(R: np.ndarray, pose3_covariance: np.ndarray) -> np.ndarray:
    """``[dtheta, dt]`` covariance from GTSAM's Pose3 ``[w, nu]`` one: ``dtheta = R w``, ``dt = R nu``."""
    J = _pose3_jacobian(np.asarray(R, dtype=float))
    return J @ np.asarray(pose3_covariance) @ J.T


def covariance_to_pose3(R: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 ``[w, nu]`` covariance from a ``[dtheta, dt]`` one: ``w = R^T dtheta``, ``nu = R^T dt``."""
    J = _pose3_jacobian(np.asarray(R, dtype=float).T)
    return J @ np.asarray(covariance) @ J.T


#: Former name of :func:`covariance_from_pose3`.
spec_covariance_from_pose3 = covariance_from_pose3


def rotation_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Hamilton unit quaternion ``(x, y, z, w)`` of a rotation matrix, ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    trace = float(np.trace(R))
    diag = np.diag(R)
    k = int(np.argmax([trace, *diag]))  # largest of 4w^2-1, 4x^2-1, ... : no cancellation
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        terms = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        terms = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] + R[1, 1] - R[2, 2])
        terms = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] - R[1, 1] + R[2, 2])
        terms = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(terms, dtype=float)
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


#: Below this cos(pitch) the URDF yaw is not defined by the matrix (gimbal lock).
_GIMBAL_LOCK_COS = 1e-12


def rpy_to_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF fixed-axis rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (radians)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def rotation_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF ``(roll, pitch, yaw)`` in radians of a rotation, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    pitch in [-pi/2, pi/2], roll and yaw in (-pi, pi]. Near gimbal lock (pitch = +/-pi/2) yaw is taken
    from the matrix where it is still defined (0 at exact lock) and roll is solved from what remains,
    ``Rx(roll) = Ry(pitch)^T Rz(yaw)^T R``, so that an imprecise yaw is absorbed by roll and
    :func:`rpy_to_rotation` gives ``R`` back to rounding error at any pitch.
    """
    R = np.asarray(R, dtype=float)
    cos_pitch = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cos_pitch)
    yaw = math.atan2(R[1, 0], R[0, 0]) if cos_pitch > _GIMBAL_LOCK_COS else 0.0
    X = rpy_to_rotation(0.0, pitch, yaw).T @ R  # = Rx(roll) up to rounding
    roll = math.atan2(X[2, 1] - X[1, 2], X[1, 1] + X[2, 2])
    return _clean(roll), _clean(pitch), _clean(yaw)


def _clean(x: float) -> float:
    """``x`` as a plain float without a negative zero (``-0.0`` reads oddly in a URDF)."""
    x = float(x)
    return 0.0 if x == 0.0 else x


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (radians) of the rotation ``R_a R_b^T``."""
    cos = (np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))
