"""The error at a point fixed on any link of an arm: how far off a grasp will be, from the mounts and the
joint offsets (docs/formats.md, "The answer in the user's units").

Frames and units: {B} the base link; a point ``p`` (metres) fixed on link L (e.g. the grasp point in the
tool flange's frame) at recorded joint values ``q`` (radians, metres for a prismatic joint). The camera's
pose is ``C = FK_c(q + delta) M_c`` (``M_c = T_link_cam``, ``delta`` the joint offsets), the point's
``P = FK_L(q + delta) p``. The camera measures the point at ``x = C^-1 P``; the calibration carries that
measurement into {B} with its estimate ``C_hat``, and the robot places the point at ``P_hat =
FK_L(q + delta_hat) p``. The error is ``e = C_hat C^-1 P - P_hat`` (metres, base axes): the miss between
what the camera sees and where the arm puts the point, zero at the estimate. For the camera on the base
and L the base link it is the camera-frame point error of ``solver/result/point_error.py``.

First order in the estimate's errors ``M_c = M_c_hat Exp(xi)`` (GTSAM's Pose3 tangent ``[w, nu]``) and
``delta = delta_hat + d``, with the frame Jacobians ``FK(q + d) = FK(q) Exp(J d)`` from Pinocchio
(``robot/kinematics.py``): ``C = C_hat Exp(eta)``, ``eta = xi + Ad(M_c^-1) J_c d``, and
``e = R_L (-[p]x w_L + nu_L) + R_C ([x]x w_eta - nu_eta)`` with ``[w_L, nu_L] = J_L d``. Its covariance
(3 x 3, m^2, base axes) is ``J S J^T`` over the joint covariance ``S`` of the camera mount and the joint
offsets (the target mount does not enter). The point itself is taken as exact.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mirror_fg.factors.robot import adjoint, compose, inverse
from mirror_fg.solver.result.point_error import PointError

__all__ = ["LinkErrorModel", "link_point_error", "link_error_jacobian"]

Pose = tuple[np.ndarray, np.ndarray]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@dataclass(frozen=True)
class LinkErrorModel:
    """What a link point's error needs from an arm's calibration: the kinematics, the camera's link and
    mount ``T_link_cam`` (estimate), the estimated joint offsets (``offset_names`` order, radians or metres)
    and the joint covariance ``covariance`` of ``[xi (6, Pose3 tangent of the camera mount; zeros where the
    mount is known), d (len(offset_names))]``."""

    kinematics: object
    camera_link: str
    camera_mount: Pose
    offset_names: tuple[str, ...]
    offsets: np.ndarray
    covariance: np.ndarray

    def corrected(self, joints: Mapping[str, float]) -> dict[str, float]:
        """The recorded ``joints`` with the estimated offsets added (``q_true = q_recorded + delta``)."""
        out = {name: float(value) for name, value in joints.items()}
        for name, value in zip(self.offset_names, self.offsets):
            if name in out:
                out[name] += float(value)
        return out


def _check(model: LinkErrorModel, point: Sequence[float], link: str, joints: Mapping[str, float]) -> np.ndarray:
    kin = model.kinematics
    p = np.asarray(point, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a point is three finite numbers (metres, in link {link!r}'s frame), got {point!r}")
    if link not in kin.links:  # type: ignore[attr-defined]
        raise ValueError(f"point_error: {link!r} is not a link of the robot")
    needed = set(kin.chain(link)) | set(kin.chain(model.camera_link))  # type: ignore[attr-defined]
    missing = sorted(needed - set(joints))
    if missing:
        raise ValueError(f"point_error: joints gives no value for {', '.join(repr(n) for n in missing)}")
    for name, value in joints.items():
        if name not in kin.joints:  # type: ignore[attr-defined]
            raise ValueError(f"point_error: {name!r} is not a joint of the robot")
        if not np.isfinite(value):
            raise ValueError(f"point_error: joint {name!r} is {value} (not a finite number)")
    return p


def link_error_jacobian(model: LinkErrorModel, point: Sequence[float], link: str,
                        joints: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """``(P_hat (3,), J (3, 6 + K))``: the point in {B} at the estimate and d e / d[xi, d] (module docstring)."""
    p = _check(model, point, link, joints)
    kin = model.kinematics
    names = list(model.offset_names)
    F = kin.placements(model.corrected(joints), list(dict.fromkeys([link, model.camera_link])), names)  # type: ignore[attr-defined]
    T_L, J_L = F[link]
    T_c, J_c = F[model.camera_link]
    R_L = T_L[:3, :3]
    P_hat = R_L @ p + T_L[:3, 3]
    C_hat = compose((T_c[:3, :3], T_c[:3, 3]), model.camera_mount)
    x = C_hat[0].T @ (P_hat - C_hat[1])  # the point in the camera frame
    d_eta = C_hat[0] @ np.hstack([_skew(x), -np.eye(3)])  # d e / d eta
    d_offsets = R_L @ np.hstack([-_skew(p), np.eye(3)]) @ J_L + d_eta @ adjoint(inverse(model.camera_mount)) @ J_c
    return P_hat, np.hstack([d_eta, d_offsets])


def link_point_error(model: LinkErrorModel, point: Sequence[float], link: str,
                     joints: Mapping[str, float]) -> PointError:
    """The error at ``point`` (metres, link ``link``'s frame) with the arm at recorded ``joints`` in {B}
    (module docstring): a :class:`~mirror_fg.solver.result.point_error.PointError` whose ``point_cam`` is the
    point in the camera frame, ``point_base`` in {B}, ``covariance`` (3, 3, m^2, base axes) and
    ``sigma3_mm``. ValueError for an unknown link or joint, a missing joint value or a malformed point."""
    P_hat, J = link_error_jacobian(model, point, link, joints)
    C = J @ model.covariance @ J.T
    C = 0.5 * (C + C.T)
    kin = model.kinematics
    T_c = kin.placements(model.corrected(joints), [model.camera_link])[model.camera_link][0]  # type: ignore[attr-defined]
    R, t = compose((T_c[:3, :3], T_c[:3, 3]), model.camera_mount)
    return PointError(R.T @ (P_hat - t), P_hat, C, 3000.0 * np.sqrt(np.clip(np.diag(C), 0.0, None)))
