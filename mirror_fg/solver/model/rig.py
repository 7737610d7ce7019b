"""The rig of a multi-camera calibration: Kalibr's ``T_cn_cnm1`` chain with its covariance (numpy only).

Every camera ``n`` has ``T_cn_base = (R_n, t_n)`` (``Cp = R_n Bp + t_n``, metres). The rig transform from
camera ``n-1`` (``from``) to camera ``n`` (``to``) is Kalibr's ``T_cn_cnm1`` (its camchain.yaml): it maps
points of the ``from`` camera into the ``to`` camera, ``x_to = R x_from + t``, i.e.
``T_to_from = T_to_base @ T_from_base^-1``: ``R = R_b R_a^T``, ``t = t_b - R t_a`` (``a`` from, ``b`` to).

Covariances follow docs/formats.md: ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) R_est`` (about
the ``to`` camera's axes) and ``t_true = t_est + dt``. With the cameras' errors ``(da, dta)``, ``(db, dtb)``
in the same convention, to first order (``u = R t_a = t_b - t``):
``R' = Exp(db) R Exp(-da) = Exp(db - R da) R``, so ``dtheta = db - R da``;
``t' = t_b + dtb - (I + [dtheta]x) R (t_a + dta)``, so ``dt = dtb - R dta + [u]x dtheta``.
The rig covariance is ``J P_ab J^T`` with ``P_ab`` the (12, 12) joint block of the two cameras, cross
terms included: placements both cameras saw tie them, which is what makes the rig tighter than either pose.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mirror_fg.core.transform import Transform

__all__ = ["RigTransform", "rig_transforms", "rig_jacobian", "pose_sigma3"]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pose_sigma3(covariance: np.ndarray | None) -> dict[str, list[float]] | None:
    """``{"rotation_deg", "position_mm"}``: 3-sigma bounds of a ``[dtheta, dt]`` covariance (3 sqrt(diag),
    degrees and millimetres), or None without a covariance."""
    if covariance is None:
        return None
    sd3 = 3.0 * np.sqrt(np.clip(np.diag(np.asarray(covariance, dtype=float)), 0.0, None))
    return {"rotation_deg": np.rad2deg(sd3[:3]).tolist(), "position_mm": (1e3 * sd3[3:]).tolist()}


@dataclass(frozen=True)
class RigTransform:
    """``T_to_from`` (Kalibr's ``T_cn_cnm1`` with ``from`` = camera n-1, ``to`` = camera n).

    ``R`` (3, 3), ``t`` (3,) metres: ``x_to = R x_from + t``. ``covariance`` (6, 6) ``[dtheta, dt]``
    (rotation error about the ``to`` camera's axes), None without a joint covariance.
    """

    from_camera: str
    to_camera: str
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None = None

    @property
    def T(self) -> Transform:
        """The transform as a :class:`~mirror_fg.core.transform.Transform` (``T_to_from``)."""
        return Transform(self.R, self.t)

    @property
    def sigma3(self) -> dict[str, list[float]] | None:
        """3-sigma bounds ``{"rotation_deg": [3], "position_mm": [3]}`` (the ``to`` camera's axes), or None."""
        return pose_sigma3(self.covariance)


def rig_jacobian(R_from: np.ndarray, t_from: np.ndarray, R_to: np.ndarray, t_to: np.ndarray) -> np.ndarray:
    """(6, 12) Jacobian of the rig error ``[dtheta, dt]`` of ``T_to_from`` with respect to
    ``[da, dta, db, dtb]``: the ``from`` camera's then the ``to`` camera's ``T_cam_base`` errors (module
    docstring)."""
    R = np.asarray(R_to, dtype=float) @ np.asarray(R_from, dtype=float).T
    u = R @ np.asarray(t_from, dtype=float)
    J = np.zeros((6, 12))
    J[:3, 0:3] = -R  # dtheta = db - R da
    J[:3, 6:9] = np.eye(3)
    J[3:, 0:3] = -_skew(u) @ R  # dt = dtb - R dta + [u]x (db - R da)
    J[3:, 3:6] = -R
    J[3:, 6:9] = _skew(u)
    J[3:, 9:12] = np.eye(3)
    return J


def rig_transforms(
    names: Sequence[str],
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    joint_covariance: np.ndarray | None,
) -> list[RigTransform]:
    """Kalibr's chain ``T_cn_cnm1`` of the cameras ``names`` (in that order), one per camera after the first.

    ``poses``: each camera's ``(R_cam_base, t_cam_base)``; ``joint_covariance``: (6C, 6C) of every camera's
    ``T_cam_base`` in ``names`` order, docs/formats.md's ``[dtheta, dt]`` per (6, 6) block, or None (the
    rig then has no covariance). ValueError on mismatched lengths or shapes.
    """
    if len(names) != len(poses):
        raise ValueError(f"rig_transforms: {len(names)} camera names but {len(poses)} poses")
    count = len(names)
    P = None
    if joint_covariance is not None:
        P = np.asarray(joint_covariance, dtype=float)
        if P.shape != (6 * count, 6 * count):
            raise ValueError(f"rig_transforms: joint covariance must be {6 * count} x {6 * count} for {count} "
                             f"cameras, got {P.shape}")
    out = []
    for n in range(1, count):
        (R_a, t_a), (R_b, t_b) = poses[n - 1], poses[n]
        T = Transform(R_b, t_b) @ Transform(R_a, t_a).inverse()  # T_cn_base T_cnm1_base^-1
        covariance = None
        if P is not None:
            index = np.r_[6 * (n - 1): 6 * n + 6]  # the two cameras' blocks, adjacent in P
            J = rig_jacobian(R_a, t_a, R_b, t_b)
            covariance = J @ P[np.ix_(index, index)] @ J.T
            covariance = 0.5 * (covariance + covariance.T)
        out.append(RigTransform(names[n - 1], names[n], T.R, T.t, covariance))
    return out
