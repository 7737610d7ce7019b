"""The view factor of an image taken by or of a robot arm (docs/formats.md, "Robot arms: joint states and
mounts"): ``factors/views.py``'s model with each image's camera and target poses given by forward
kinematics.

Frames: {B} the robot's base link; the camera's pose in {B} is ``C = F_c(q) M_c`` and the target's
``D = F_t(q) M_t`` (``F`` a link's placement by forward kinematics at the joint values ``q + delta``,
``M`` the mount ``T_link_cam`` / ``T_link_target``); target points ``Tp`` (metres, target frame) are seen
through mirror planes fixed in {B}. The view model (eqs. 2, 3, 9) takes the pose of the target in the
camera, ``T = C^-1 D``, and each plane ``n . x = d`` carried into the camera's frame:
``n_c = R_C^T n``, ``d_c = d - n . t_C``, ``v_c = d_c n_c``.

Jacobians, chained from the view model's (GTSAM's right perturbation ``T Exp(xi)``, ``xi = [w, nu]``):
``C Exp(a)`` gives ``T Exp(-Ad(T^-1) a)`` and moves ``v_c`` by ``d_c [n_c]x w - n_c n_c^T nu``;
``D Exp(b)`` gives ``T Exp(b)``; a joint
offset ``delta`` moves ``F(q) Exp(J delta)`` (``J`` the link's frame Jacobian from the kinematics, never
written here), so ``a = Ad(M_c^-1) J_c delta`` and ``b = Ad(M_t^-1) J_t delta``. Unknowns: the unknown
mounts (Pose3), the planes (OrientedPlane3 in {B}), reconstruction points (Point3, target frame) and the
estimated joint offsets (one Vector, radians or metres). Nothing here imports the solver: the kinematics
arrive as a callable.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gtsam
import numpy as np

from mirror_fg.factors.robust import ROBUST_K, check_kernel
from mirror_fg.factors.views import ViewSlots, landmark_blocks, planes_at, points_at, scaled_error, view_model

__all__ = ["RobotViewFactor", "adjoint", "compose", "inverse", "CAMERA"]

#: The name of the pose handed to ``view_model``: the target in the camera (target -> camera).
CAMERA = "camera"

Pose = tuple[np.ndarray, np.ndarray]
#: ``fk(delta) -> ((T_B_camlink 4x4, J_c 6xK), (T_B_targetlink 4x4, J_t 6xK))`` at ``q + delta``.
ForwardKinematics = Callable[[np.ndarray], tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def adjoint(pose: Pose) -> np.ndarray:
    """GTSAM's Pose3 adjoint (6, 6) in ``[w, nu]`` order: ``T Exp(xi) = Exp(Ad(T) xi) T``."""
    R, t = pose
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = _skew(t) @ R
    return A


def compose(a: Pose, b: Pose) -> Pose:
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def inverse(a: Pose) -> Pose:
    return a[0].T, -a[0].T @ a[1]


def _pose_of(T: np.ndarray) -> Pose:
    return np.asarray(T[:3, :3], float), np.asarray(T[:3, 3], float)


class RobotViewFactor:
    """One image of an arm as a ``gtsam.CustomFactor`` (module docstring); build with :meth:`factor`.

    ``reflections``: the placements the light meets; ``mount_keys``: ``{"camera"|"target": key}`` of the
    unknown mounts; ``known_mounts``: the others' ``(R, t)``; ``mirror_keys``: ``{placement: key}`` of
    the planes in {B}; ``fk``: the image's forward kinematics (``ForwardKinematics``); ``offset_key``:
    the Vector of joint offsets (None: none estimated); ``target_points`` (3, N) in the target frame,
    NaN where ``landmark_keys[i]`` (else -1) gives the point; ``observed``, ``sigmas`` (2, N) normalized.
    """

    def __init__(self, reflections: Sequence[tuple[int, int]], mount_keys: dict[str, int],
                 known_mounts: dict[str, Pose], mirror_keys: dict[tuple[int, int], int], fk: ForwardKinematics,
                 offset_key: int | None, num_offsets: int, target_points: np.ndarray, landmark_keys: Sequence[int],
                 observed: np.ndarray, sigmas: np.ndarray, robust: str | None = None, robust_k: float = ROBUST_K):
        check_kernel(robust)
        self.reflections = tuple(reflections)
        self.mount_keys = dict(mount_keys)
        self.known = dict(known_mounts)
        placements = list(dict.fromkeys(self.reflections))
        self.mirror_keys = {p: mirror_keys[p] for p in placements}
        self.slots = ViewSlots({CAMERA: 0}, {p: 6 + 3 * k for k, p in enumerate(placements)}, 6 + 3 * len(placements))
        self.fk, self.offset_key, self.num_offsets = fk, offset_key, num_offsets
        self.target_points = np.array(target_points, dtype=float)
        self.landmark_keys = np.asarray(landmark_keys, dtype=np.int64)
        self.unique_landmarks = list(dict.fromkeys(int(k) for k in self.landmark_keys if k >= 0))
        self.observed = np.asarray(observed, dtype=float)
        self.sigmas = np.asarray(sigmas, dtype=float)
        self.robust, self.robust_k = robust, robust_k
        self.keys = [*self.mount_keys.values(), *self.mirror_keys.values(), *self.unique_landmarks,
                     *([offset_key] if offset_key is not None else [])]

    def mounts_and_offsets(self, values: gtsam.Values) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """Both mounts ``(R, t)`` (the known ones as given, the unknown ones at ``values``) and the joint
        offsets at ``values`` (zeros where they are not estimated)."""
        mounts = dict(self.known)
        for role, key in self.mount_keys.items():
            pose = values.atPose3(key)
            mounts[role] = (pose.rotation().matrix(), np.asarray(pose.translation(), float))
        delta = (np.asarray(values.atVector(self.offset_key), float) if self.offset_key is not None
                 else np.zeros(self.num_offsets))
        return mounts, delta

    def poses(self, values: gtsam.Values) -> dict[str, Any]:
        """The image's state at ``values``: mounts, link placements and Jacobians, C, D, T (module docstring)."""
        mounts, delta = self.mounts_and_offsets(values)
        (F_c, J_c), (F_t, J_t) = self.fk(delta)
        C = compose(_pose_of(F_c), mounts["camera"])
        D = compose(_pose_of(F_t), mounts["target"])
        return {"mounts": mounts, "J_c": J_c, "J_t": J_t, "C": C, "D": D, "T": compose(inverse(C), D)}

    def _state(self, values: gtsam.Values):
        state = self.poses(values)
        mirrors, mirror_jacobians = planes_at(values, self.mirror_keys)
        return state, mirrors, points_at(values, self.target_points, self.landmark_keys), mirror_jacobians

    def predict(self, values: gtsam.Values) -> np.ndarray:
        """Predicted normalized coordinates (2, N) at ``values``."""
        state, mirrors, B, _ = self._state(values)
        return self._model(state, mirrors, B)[0]

    def _model(self, state, mirrors, B, slots=None):
        """The view model with the planes in the camera's frame (module docstring); with ``slots`` also each
        camera-frame vector's derivatives in the {B} vector and in C's perturbation."""
        R_C, t_C = state["C"]
        in_camera, d_u, d_a = {}, {}, {}
        for p, u in mirrors.items():
            d = float(np.linalg.norm(u))
            n = u / d
            n_c = R_C.T @ n
            d_c = d - float(n @ t_C)
            in_camera[p] = d_c * n_c
            if slots is not None:
                along = np.eye(3) - np.outer(n, n)  # dn/du = along / d
                d_u[p] = R_C.T @ ((d_c / d) * along + np.outer(n, n - along @ t_C / d))
                d_a[p] = np.hstack([d_c * _skew(n_c), -np.outer(n_c, n_c)])
        owners = {p: CAMERA for p in self.mirror_keys}
        z, dz, dzB = view_model(CAMERA, self.reflections, {CAMERA: state["T"]}, in_camera, owners, B, slots)
        return z, dz, dzB, d_u, d_a

    def error(self, this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        state, mirrors, B, mirror_jacobians = self._state(values)
        slots = self.slots if jacobians is not None else None
        z, dz, dzB, d_u, d_a = self._model(state, mirrors, B, slots)
        residual = z - self.observed
        error, scale = scaled_error(residual, self.sigmas, self.robust, self.robust_k, jacobians is not None)
        if jacobians is None:
            return error
        assert dz is not None and dzB is not None
        rows = 2 * residual.shape[1]
        J = np.transpose(dz * scale, (2, 0, 1)).reshape(rows, self.slots.size)  # measurement-major
        dT = J[:, 0:6]
        dC = dT @ -adjoint(inverse(state["T"]))  # in C's perturbation: through T, and the planes' transfer
        for p in self.mirror_keys:
            c = self.slots.mirror_cols[p]
            dC = dC + J[:, c:c + 3] @ d_a[p]
        mounts = state["mounts"]
        k = 0
        for role in self.mount_keys:
            jacobians[k] = dC if role == "camera" else dT
            k += 1
        for p in self.mirror_keys:
            c = self.slots.mirror_cols[p]
            jacobians[k] = J[:, c:c + 3] @ d_u[p] @ mirror_jacobians[p]
            k += 1
        for block in landmark_blocks(dzB, scale, self.landmark_keys, self.unique_landmarks):
            jacobians[k] = block
            k += 1
        if self.offset_key is not None:
            a = adjoint(inverse(mounts["camera"])) @ state["J_c"]  # C's perturbation per offset
            b = adjoint(inverse(mounts["target"])) @ state["J_t"]  # D's
            jacobians[k] = dC @ a + dT @ b
        return error

    def factor(self) -> gtsam.CustomFactor:
        noise = gtsam.noiseModel.Diagonal.Sigmas(self.sigmas.T.reshape(-1))
        return gtsam.CustomFactor(noise, self.keys, self.error)
