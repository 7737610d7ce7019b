"""An arm's view factors (``robot.py``) evaluated together: the images that see the same placements in the
same order, with as many target points and no reconstruction points, in one ``gtsam.CustomFactor`` whose
model is one numpy pass over its images (Hesch et al., eqs. 2, 3, 9; the model of ``robot.py``).

Why: a Python factor costs a call per image per LM iteration (each call reads the mounts and planes from
the ``Values``, runs the kinematics' composition and the view model on a handful of points), which made
the arm's LM several times the cost of a tree's. An arm's images of one placement share every unknown
(the mounts, the placement's plane, the joint offsets), so stacking them changes nothing but the number of
calls: a stack's error is its images' errors one after the other, each with its own whitening and robust
kernel, and its Jacobians are theirs stacked (``tests/test_robot_stack.py`` checks both against the
per-image factors, and a whole calibration).

Frames as in ``robot.py``: {B} the base link, ``C_i = F_c(q_i) M_c``, ``D_i = F_t(q_i) M_t``,
``T_i = C_i^-1 D_i``; each plane ``n . x = d`` in {B} carried into camera i's frame as
``v_c = (d - n . t_C) R_C^T n``. Normalized image coordinates; a leading axis ``b`` over the images.
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mirror_fg.factors.robot import RobotViewFactor, adjoint, inverse
from mirror_fg.factors.robust import robust_row_scales
from mirror_fg.factors.views import vector_of_plane

__all__ = ["stackable", "RobotStack", "robot_stacks", "stacked_robot_factors"]


def stackable(factor: RobotViewFactor) -> bool:
    """Whether an image's factor can join a stack: target points only (no reconstruction points)."""
    return not factor.unique_landmarks


def _skew_rows(a: np.ndarray) -> np.ndarray:
    """[a]x of each row of ``a`` (..., 3): (..., 3, 3)."""
    S = np.zeros((*a.shape[:-1], 3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -a[..., 2], a[..., 1], -a[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = a[..., 2], -a[..., 1], a[..., 0]
    return S


def _adjoint_rows(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``robot.adjoint`` of each pose ``(R[k], t[k])``: (b, 6, 6)."""
    A = np.zeros((len(R), 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    A[:, 3:, :3] = _skew_rows(t) @ R
    return A


class RobotStack:
    """The factors of images of one shape (module docstring) as one ``gtsam.CustomFactor``: build with
    :meth:`factor`. ``factors``: the images' :class:`RobotViewFactor` s, all with the same reflections,
    keys, known mounts, number of points and robust kernel."""

    def __init__(self, factors: Sequence[RobotViewFactor]):
        first = factors[0]
        self.members = list(factors)
        self.reflections = first.reflections
        self.mount_keys, self.known, self.mirror_keys = first.mount_keys, first.known, first.mirror_keys
        self.offset_key, self.num_offsets = first.offset_key, first.num_offsets
        self.slots = first.slots
        self.robust, self.robust_k = first.robust, first.robust_k
        self.keys = list(first.keys)
        self.points = np.array([f.target_points for f in factors])  # (b, 3, N)
        self.observed = np.array([f.observed for f in factors])  # (b, 2, N)
        self.sigmas = np.array([f.sigmas for f in factors])
        self._fk_at: bytes | None = None
        self._fk: tuple[np.ndarray, ...] | None = None

    def _kinematics(self, delta: np.ndarray) -> tuple[np.ndarray, ...]:
        """Every image's link placements and offset Jacobians at ``delta``: ``F_c, J_c, F_t, J_t`` stacked
        (computed once per ``delta``; without estimated offsets, once)."""
        at = delta.tobytes()
        if self._fk is None or at != self._fk_at:
            out = [f.fk(delta) for f in self.members]
            self._fk = (np.array([c[0] for c, _ in out]), np.array([c[1] for c, _ in out]),
                        np.array([t[0] for _, t in out]), np.array([t[1] for _, t in out]))
            self._fk_at = at
        return self._fk

    def _state(self, values: gtsam.Values):
        mounts, delta = self.members[0].mounts_and_offsets(values)  # the same mount and offset keys in every member
        F_c, J_c, F_t, J_t = self._kinematics(delta)
        (R_mc, t_mc), (R_mt, t_mt) = mounts["camera"], mounts["target"]
        R_C = F_c[:, :3, :3] @ R_mc  # C = F_c M_c
        t_C = F_c[:, :3, :3] @ t_mc + F_c[:, :3, 3]
        R_D = F_t[:, :3, :3] @ R_mt
        t_D = F_t[:, :3, :3] @ t_mt + F_t[:, :3, 3]
        R_T = np.transpose(R_C, (0, 2, 1)) @ R_D  # T = C^-1 D
        t_T = np.einsum("bji,bj->bi", R_C, t_D - t_C)
        planes = {p: vector_of_plane(values.atOrientedPlane3(key)) for p, key in self.mirror_keys.items()}
        return mounts, (J_c, J_t), (R_C, t_C), (R_T, t_T), planes

    def _model(self, R_C, t_C, R_T, t_T, planes, jacobians: bool):
        """``robot.RobotViewFactor._model`` of every image: predictions (b, 2, N) and, when asked, ``dz``
        (b, 2, P, N) in the images' local coordinates, and each plane's ``d v_c / d u`` and ``d v_c / d a``
        (``a`` C's perturbation)."""
        in_camera, d_u, d_a = {}, {}, {}
        for p, (u, _) in planes.items():
            d = float(np.linalg.norm(u))
            n = u / d
            n_c = n @ R_C  # R_C^T n, per image
            d_c = d - t_C @ n
            in_camera[p] = d_c[:, None] * n_c
            if jacobians:
                along = np.eye(3) - np.outer(n, n)  # dn/du = along / d
                inner = (d_c / d)[:, None, None] * along + n[None, :, None] * (n[None, :] - t_C @ along.T / d)[:, None, :]
                d_u[p] = np.transpose(R_C, (0, 2, 1)) @ inner
                d_a[p] = np.concatenate([d_c[:, None, None] * _skew_rows(n_c), -n_c[:, :, None] * n_c[:, None, :]], axis=2)
        B = self.points
        b, _, count = B.shape
        x = R_T @ B + t_T[:, :, None]  # eq. (2)
        size = self.slots.size
        dx = None
        if jacobians:
            dx = np.zeros((b, 3, size, count))
            S = np.zeros((b, 3, 3, count))
            S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -B[:, 2], B[:, 1], -B[:, 0]
            S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = B[:, 2], -B[:, 1], B[:, 0]
            dx[:, :, 0:3, :] = -np.einsum("bij,bjkn->bikn", R_T, S)  # d(R Exp(w) B)/dw = -R [B]x
            dx[:, :, 3:6, :] = R_T[:, :, :, None]  # d(t + R nu)/dnu = R
        for placement in self.reflections:
            v = in_camera[placement]
            vv = np.einsum("bi,bi->b", v, v)
            vx = np.einsum("bi,bin->bn", v, x)
            s = vx / vv[:, None] - 1.0
            if jacobians:
                assert dx is not None
                col = self.slots.mirror_cols[placement]
                # ds = (v^T dx + x^T dv) / vv - 2 (v.x)(v^T dv) / vv^2, dv the identity at the placement's columns
                ds = np.einsum("bi,bipn->bpn", v, dx) / vv[:, None, None]
                ds[:, col:col + 3, :] += x / vv[:, None, None]
                ds[:, col:col + 3, :] -= 2.0 * v[:, :, None] * vx[:, None, :] / (vv**2)[:, None, None]
                dx = dx - 2.0 * v[:, :, None, None] * ds[:, None]
                dx[:, :, col:col + 3, :] -= 2.0 * np.eye(3)[None, :, :, None] * s[:, None, None, :]
            x = x - 2.0 * v[:, :, None] * s[:, None, :]  # eq. (3): M x + 2 v
        z = x[:, :2] / x[:, 2:3]  # eq. (9)
        if not jacobians:
            return z, None, d_u, d_a
        assert dx is not None
        dz = (dx[:, :2] - z[:, :, None, :] * dx[:, 2][:, None]) / x[:, 2][:, None, None, :]
        return z, dz, d_u, d_a

    def predict(self, values: gtsam.Values) -> np.ndarray:
        """Predicted normalized coordinates (b, 2, N) at ``values``."""
        _, _, (R_C, t_C), (R_T, t_T), planes = self._state(values)
        return self._model(R_C, t_C, R_T, t_T, planes, False)[0]

    def error(self, this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        mounts, (J_c, J_t), (R_C, t_C), (R_T, t_T), planes = self._state(values)
        z, dz, d_u, d_a = self._model(R_C, t_C, R_T, t_T, planes, jacobians is not None)
        residual = z - self.observed  # (b, 2, N), h - z
        b, _, count = residual.shape
        scale = np.ones((b, count))
        if self.robust is not None:
            norms = np.linalg.norm(residual / self.sigmas, axis=1)
            sqrt_w, loss_scale = robust_row_scales(self.robust, norms.reshape(-1), self.robust_k)
            scale = (sqrt_w if jacobians is not None else loss_scale).reshape(b, count)
        error = (residual * scale[:, None, :]).transpose(0, 2, 1).reshape(-1)
        if jacobians is None:
            return error
        assert dz is not None
        rows = 2 * count
        J = np.transpose(dz * scale[:, None, None, :], (0, 3, 1, 2)).reshape(b, rows, self.slots.size)
        dT = J[:, :, 0:6]
        R_i, t_i = np.transpose(R_T, (0, 2, 1)), -np.einsum("bji,bj->bi", R_T, t_T)  # T^-1
        dC = dT @ -_adjoint_rows(R_i, t_i)  # in C's perturbation: through T, and the planes' transfer
        for p in self.mirror_keys:
            c = self.slots.mirror_cols[p]
            dC = dC + J[:, :, c:c + 3] @ d_a[p]
        k = 0
        for role in self.mount_keys:
            jacobians[k] = (dC if role == "camera" else dT).reshape(b * rows, 6)
            k += 1
        for p in self.mirror_keys:
            c = self.slots.mirror_cols[p]
            jacobians[k] = (J[:, :, c:c + 3] @ (d_u[p] @ planes[p][1])).reshape(b * rows, 3)
            k += 1
        if self.offset_key is not None:
            a = adjoint(inverse(mounts["camera"])) @ J_c  # C's perturbation per offset, (b, 6, K)
            t = adjoint(inverse(mounts["target"])) @ J_t  # D's
            jacobians[k] = (dC @ a + dT @ t).reshape(b * rows, -1)
        return error

    def factor(self) -> gtsam.CustomFactor:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.transpose(self.sigmas, (0, 2, 1)).reshape(-1))
        return gtsam.CustomFactor(noise, self.keys, self.error)


def robot_stacks(factors: Sequence[RobotViewFactor]) -> tuple[list[tuple[list[int], RobotStack]], list[int]]:
    """The stacks of ``factors`` (module docstring), each with its images' indices in ``factors``, and the
    indices of the images that stay alone (reconstruction points)."""
    shapes: dict[tuple, list[int]] = {}
    alone = []
    for i, f in enumerate(factors):
        if not stackable(f):
            alone.append(i)
            continue
        shape = (f.reflections, tuple(f.keys), f.target_points.shape[1], f.robust, f.robust_k,
                 tuple((role, R.tobytes(), np.asarray(t).tobytes()) for role, (R, t) in sorted(f.known.items())))
        shapes.setdefault(shape, []).append(i)
    return [(members, RobotStack([factors[i] for i in members])) for members in shapes.values()], alone


def stacked_robot_factors(factors: Sequence[RobotViewFactor]) -> list[gtsam.CustomFactor]:
    """The factors of an arm's images: the stackable ones of one shape (module docstring) in one
    :class:`RobotStack` each, the others (reconstruction points) their own :class:`RobotViewFactor` s."""
    stacks, alone = robot_stacks(factors)
    return [factors[i].factor() for i in alone] + [stack.factor() for _, stack in stacks]
