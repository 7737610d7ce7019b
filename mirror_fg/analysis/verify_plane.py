"""A mirror that still stands, as a prior of ``verify`` (``analysis/verify.py``, docs/formats.md "Has it
moved?"): new images taken at a placement the stored result knows (the same placement label) see a plane
fixed in the base frame {B}, which the result estimated jointly with the camera (result@1's
``mirrors[].covariance`` and ``cross_covariance_cam_base``, ``solver/fit/placement_covariance.py``). Held
there, the plane no longer absorbs a rotation about a line in it, and one placement determines the camera.

Frames and units: ``v`` the mirror vector in the camera frame (``v = d n``, metres, eq. 3), ``T_cam_base
= (R, t)``; the plane in {B} is ``v_B = R^T (v - (v . t) v / |v|^2)`` (``n_B = R^T n``, ``d_B = d - n . t``:
the plane ``n . x = d`` with ``x = R x_B + t``). If the camera moved, the mirror did not: ``v_B`` is the
same before and after, so the prior is on ``v_B`` (a function of the pose and the placement's unknown),
its covariance from the stored joint one by first-order propagation at the stored estimate. As with the
intrinsics (``verify_priors.py``), the plane's marginal ``e = v_B - v_B,stored ~ N(0, P)`` is in every
fit, and the held camera's prior is the pose given the plane: ``xi | e ~ N(B e, A - B P B^T)``,
``B = cov(xi, e) P^-1``, with the marginal the stored joint prior exactly (``xi = Local(T_stored, X)``,
GTSAM's Pose3 tangent ``[w, nu]``, ``[dtheta, dt] = blkdiag(R, R) [w, nu]``).

One stored placement is held (the one with the most new images): result@1 holds no covariance between
placements, so two held at once would count their common error twice; the others are new unknowns.
Not with a result that estimated intrinsics (no plane-intrinsics covariance is stored), nor with several
cameras.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import gtsam
import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.factors.views import vector_of_plane
from mirror_fg.data import Dataset
from mirror_fg.solver.model.views import SINGLE_CAMERA

__all__ = ["StoredPlane", "stored_plane", "standing_plane", "base_vector"]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def base_vector(R: np.ndarray, t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(v_B, d v_B / d[w, nu], d v_B / d v)`` (module docstring): the plane of camera-frame vector ``v`` in
    {B} with ``T_cam_base = (R, t)``, and its Jacobians in the pose's right perturbation
    (``R Exp(w)``, ``t + R nu``) and in ``v``."""
    vv = float(v @ v)
    s = float(v @ t) / vv
    w = v - s * v
    v_B = R.T @ w
    n_B = v_B / np.linalg.norm(v_B)
    d_pose = np.hstack([_skew(v_B), -np.outer(n_B, n_B)])
    d_v = R.T @ ((1.0 - s) * np.eye(3) - np.outer(v, t / vv - 2.0 * float(v @ t) * v / vv ** 2))
    return v_B, d_pose, d_v


@dataclass(frozen=True)
class StoredPlane:
    """A stored placement's plane (module docstring): ``v_B`` and its marginal ``P`` in {B}, ``B`` and the
    pose's conditional covariance ``C`` (tangent) given it."""

    placement: tuple[int, int]
    v_B: np.ndarray
    P: np.ndarray
    B: np.ndarray
    C: np.ndarray

    def marginal_prior(self, pose_key: int, plane_key: int) -> gtsam.CustomFactor:
        """``v_B(X, V) - v_B,stored ~ N(0, P)``, in every fit."""
        return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(self.P), [pose_key, plane_key],
                                  partial(_plane_error, self.v_B))

    def conditional(self, pose_key: int, plane_key: int, stored_pose: gtsam.Pose3) -> gtsam.CustomFactor:
        """The held camera given the plane: ``Local(T_stored, X) - B e ~ N(0, C)``."""
        return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(self.C), [pose_key, plane_key],
                                  partial(_conditional_error, stored_pose, self.v_B, self.B))


def _plane_state(values: gtsam.Values, pose_key: int, plane_key: int):
    pose = values.atPose3(pose_key)
    v, J_plane = vector_of_plane(values.atOrientedPlane3(plane_key))
    v_B, d_pose, d_v = base_vector(pose.rotation().matrix(), np.asarray(pose.translation(), float), v)
    return pose, v_B, d_pose, d_v @ J_plane


def _plane_error(v_B0: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """``v_B(X, V) - v_B,stored`` and its Jacobians (GTSAM's CustomFactor shape)."""
    pose_key, plane_key = this.keys()
    _, v_B, d_pose, d_plane = _plane_state(values, pose_key, plane_key)
    if jacobians is not None:
        jacobians[0], jacobians[1] = d_pose, d_plane
    return v_B - v_B0


def _conditional_error(stored_pose: gtsam.Pose3, v_B0: np.ndarray, B: np.ndarray, this: gtsam.CustomFactor,
                       values: gtsam.Values, jacobians) -> np.ndarray:
    """``Local(T_stored, X) - B (v_B(X, V) - v_B,stored)`` and its Jacobians."""
    pose_key, plane_key = this.keys()
    pose, v_B, d_pose, d_plane = _plane_state(values, pose_key, plane_key)
    H_stored = np.zeros((6, 6), order="F")
    H_pose = np.zeros((6, 6), order="F")
    xi = np.asarray(stored_pose.localCoordinates(pose, H_stored, H_pose), float)
    if jacobians is not None:
        jacobians[0] = np.array(H_pose) - B @ d_pose
        jacobians[1] = -B @ d_plane
    return xi - B @ (v_B - v_B0)


def stored_plane(result: Mapping[str, Any], dataset: Dataset, pose_tangent: np.ndarray, source: str
                 ) -> StoredPlane | None:
    """The stored placement the new images see most (module docstring) as a :class:`StoredPlane`, or None
    (none they see is stored with its joint covariance; several cameras; estimated intrinsics).
    ``pose_tangent``: the camera's stored covariance in GTSAM's tangent at the stored rotation."""
    if result.get("cameras") or (result.get("camera") or {}).get("estimated"):
        return None
    stored = {(e["mirror"], e["config"]): e for e in result.get("mirrors") or []
              if e.get("covariance") is not None and e.get("cross_covariance_cam_base") is not None}
    counts: dict[tuple[int, int], int] = {}
    for image in dataset.images:
        for placement in set(image.reflections):
            if placement in stored:
                counts[placement] = counts.get(placement, 0) + 1
    if not counts:
        return None
    placement = max(sorted(counts), key=lambda p: counts[p])
    entry = stored[placement]
    try:
        v = np.array(entry["v"], dtype=float).reshape(3)
        cov_v = np.array(entry["covariance"], dtype=float).reshape(3, 3)
        cross = np.array(entry["cross_covariance_cam_base"], dtype=float).reshape(3, 6)
    except ValueError:
        raise DatasetError(f"{source}: mirror {placement[0]} config {placement[1]}: covariance must be 3 x 3 and "
                           "cross_covariance_cam_base 3 x 6") from None
    if not (np.all(np.isfinite(cov_v)) and np.all(np.isfinite(cross))):
        raise DatasetError(f"{source}: mirror {placement[0]} config {placement[1]}: a covariance that is not finite")
    R = np.array(result["T_cam_base"]["R"], dtype=float)
    t = np.array(result["T_cam_base"]["t"], dtype=float)
    v_B, K, G = base_vector(R, t, v)
    cross_tangent = np.kron(np.eye(2), R).T @ cross.T  # cov(xi, v), 6 x 3
    A = pose_tangent
    P = G @ cov_v @ G.T + G @ cross_tangent.T @ K.T + K @ cross_tangent @ G.T + K @ A @ K.T  # e = K xi + G dv
    cov_xi_e = cross_tangent @ G.T + A @ K.T
    P = 0.5 * (P + P.T)
    if np.linalg.eigvalsh(P)[0] <= 0:
        raise DatasetError(f"{source}: mirror {placement[0]} config {placement[1]}: its stored covariance is not "
                           "positive definite")
    B = cov_xi_e @ np.linalg.inv(P)
    C = A - B @ cov_xi_e.T
    return StoredPlane(placement, v_B, P, B, 0.5 * (C + C.T))


def standing_plane(result: Mapping[str, Any], dataset: Dataset, refused: bool, stored_tangent: Mapping[str, np.ndarray],
                   source: str) -> StoredPlane:
    """:func:`stored_plane` of the single camera where the user says a mirror stands; DatasetError (one
    line) where it cannot be held (``refused``: several cameras or estimated intrinsics) or none is stored."""
    if refused:
        raise DatasetError(f"{source}: a standing mirror is held for one camera whose intrinsics the result did not "
                           "estimate (no covariance of the plane with the intrinsics is stored)")
    plane = stored_plane(result, dataset, stored_tangent[SINGLE_CAMERA], source)
    if plane is None:
        raise DatasetError(f"{dataset.source}: none of its mirror placements is one {source} holds with its "
                           "covariance (mirrors[].covariance): drop the standing mirror or calibrate again")
    return plane
