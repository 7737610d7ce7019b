"""The error at a point the camera measures, in the base frame: how far off a grasp will be.

Frames and units (docs/formats.md, "The answer in the user's units"): a point ``p_cam`` (metres, camera
frame {C}, OpenCV axes) maps into the base frame {B} as ``p_base = T_base_cam p_cam = R p_cam + t``
(eq. 2 inverted). ``T_base_cam``'s covariance is ``[dtheta (rad), dt (m)]`` about and along the *base*
axes with ``R_true = Exp(dtheta) R``, ``t_true = t + dt`` (docs/formats.md "Uncertainty convention"), so to
first order ``p_true = p_base + dtheta x (R p_cam) + dt``: the Jacobian is ``[-[R p_cam]x, I]`` and the
point's covariance (3 x 3, m^2, base axes) ``J P J^T``. Only the pose's uncertainty enters: the point is
taken as measured exactly (its own measurement error is the user's to add).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.transform import Transform

__all__ = ["PointError", "point_error", "point_jacobian", "at_entries", "calibration_poses", "parse_point"]


@dataclass(frozen=True)
class PointError:
    """A point's position error in {B}: ``point_cam`` / ``point_base`` (metres), ``covariance`` (3, 3, m^2,
    base axes) and ``sigma3_mm`` (3,), the 3-sigma along the base axes in millimetres."""

    point_cam: np.ndarray
    point_base: np.ndarray
    covariance: np.ndarray
    sigma3_mm: np.ndarray

    @property
    def largest_sigma3_mm(self) -> float:
        """The 3-sigma along the worst direction (the covariance's largest eigenvalue), millimetres."""
        return float(3000.0 * np.sqrt(max(float(np.linalg.eigvalsh(self.covariance)[-1]), 0.0)))

    def to_dict(self) -> dict[str, Any]:
        """The result@1 ``at`` entry (docs/formats.md)."""
        return {"point_cam": self.point_cam.tolist(), "point_base": self.point_base.tolist(),
                "covariance": self.covariance.tolist(), "sigma3_mm": self.sigma3_mm.tolist()}


def point_jacobian(R_base_cam: np.ndarray, point_cam: np.ndarray) -> np.ndarray:
    """d p_base / d[dtheta, dt] (3, 6) of ``p_base = R p_cam + t`` under the perturbation of the module
    docstring: ``[-[R p_cam]x, I]``."""
    a = np.asarray(R_base_cam, float) @ np.asarray(point_cam, float)
    skew = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.hstack([-skew, np.eye(3)])


def point_error(T_base_cam: Transform, covariance_base_cam: np.ndarray, point_cam: Sequence[float]) -> PointError:
    """The error at ``point_cam`` (metres, camera frame) in {B} from ``T_base_cam``'s covariance (6, 6, base
    axes, the module docstring's convention). ValueError where the point is not three finite numbers."""
    p = np.asarray(point_cam, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a point is three finite numbers (metres, camera frame), got {point_cam!r}")
    J = point_jacobian(T_base_cam.R, p)
    C = J @ np.asarray(covariance_base_cam, dtype=float) @ J.T
    C = 0.5 * (C + C.T)
    return PointError(p, T_base_cam.apply(p), C, 3000.0 * np.sqrt(np.clip(np.diag(C), 0.0, None)))


def parse_point(text: str) -> tuple[float, float, float]:
    """``X,Y,Z`` (metres) as three finite numbers; ValueError in words otherwise (``calibrate --at``)."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise ValueError(f"expected a point X,Y,Z in metres (camera frame), e.g. 0,0,0.6; got {str(text)[:40]!r}")
    return values  # type: ignore[return-value]


def at_entries(poses: Mapping[str | None, tuple[Transform, np.ndarray | None]],
               points_cam: Sequence[Sequence[float]]) -> list[dict[str, Any]]:
    """result@1's ``at`` list: for each point (camera frame) and each camera ``{name: (T_base_cam, its
    covariance)}`` (name None for a single camera: no ``camera`` key), the :class:`PointError` entry. A
    camera without a covariance gives ``covariance`` and ``sigma3_mm`` null."""
    entries = []
    for p in points_cam:
        for name, (T, covariance) in poses.items():
            if covariance is None:
                p_cam = np.asarray(p, float)
                entry = {"point_cam": p_cam.tolist(), "point_base": T.apply(p_cam).tolist(), "covariance": None,
                         "sigma3_mm": None}
            else:
                entry = point_error(T, covariance, p).to_dict()
            entries.append(entry if name is None else {"camera": name, **entry})
    return entries


def calibration_poses(calibration: Any) -> dict[str | None, tuple[Transform, np.ndarray | None]]:
    """``{camera name: (T_base_cam, its covariance)}`` of a calibration for :func:`at_entries`: every camera
    of a rig by name, else ``{None: ...}`` for the one camera."""
    cameras = getattr(calibration, "cameras", None)
    if cameras:
        return {name: (pose.T_base_cam, pose.covariance_base_cam) for name, pose in cameras.items()}
    return {None: (calibration.T_base_cam, calibration.covariance_base_cam)}
