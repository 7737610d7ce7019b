"""The general view factor: one image seen through any sequence of mirror placements, by any camera of a
rig (docs/formats.md, "Views of any reflection order, and several cameras"; Hesch et al., eqs. 2, 3, 9).

A *view* is (camera c, placements p_1..p_k in the order the light meets them). A base point ``Bp`` is
seen at ``z = project(F_k(... F_1(R_c Bp + t_c)))`` (eqs. 2, 9) with ``F_i(x) = M_i x + 2 v_i`` (eq. 3)
the reflection in placement p_i's plane *in camera c's frame*. A placement's unknown is its mirror vector
in its *owner* camera's frame (the first camera that sees it); in another camera's frame it is

    u = R_co v_o,  t_co = t_c - R_co t_o,  R_co = R_c R_o^T,  v_c = u (1 + u . t_co / |v_o|^2)

(the plane ``n . y = d``, ``v_o = d n``, carried into frame c). The variable behind a placement is the
plane itself, a GTSAM ``OrientedPlane3`` ``(n, d)`` with ``v = d n``: unlike ``v``, it has no
singularity where a mirror's plane passes near the camera centre (the side walls of a kaleidoscope, a
mirror held beside the camera), where a small change of ``v`` would turn its normal far (measured: LM
then stalls in another minimum). Its local coordinates ``xi`` give ``dv/dxi = [d B, n]`` (``B`` the
normal's tangent basis). k = 0 is a direct view; the same
placement may appear more than once in a view (a kaleidoscope's third-order chambers), the same mirror
never twice in a row.

Jacobians are carried forward with the point (forward mode): ``dx`` (3, P, N) over the P local
coordinates of the factor's pose and mirror keys (GTSAM's Pose3 tangent ``[w, nu]``, ``R Exp(w)``,
``t + R nu``; a Point3's own coordinates), and ``dx/dBp`` (3, 3, N) for the landmarks. One factor per
image (its N points share the view), error ``[h_1 - z_1; ...]`` unwhitened, normalized coordinates;
robust kernels per measurement as in the tree's reference factors (``tests/reference/batched.py``). The per-measurement reference for tests is this
model at N = 1 checked against numerical differences (``tests/test_view_factor.py``).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.factors.intrinsics import IntrinsicsModel, pixel_jacobians
from mirror_fg.factors.robust import ROBUST_K, check_kernel, robust_row_scales

__all__ = ["ViewSlots", "view_model", "ViewFactor", "transfer_mirror_vector", "plane_of", "vector_of_plane", "vectors_of_planes", "planes_at",
           "points_at", "scaled_error", "landmark_blocks"]


def plane_of(v: np.ndarray) -> gtsam.OrientedPlane3:
    """The plane variable of mirror vector ``v`` (camera frame): normal ``v / |v|``, distance ``|v|``."""
    v = np.asarray(v, dtype=float)
    d = float(np.linalg.norm(v))
    return gtsam.OrientedPlane3(gtsam.Unit3(v / d), d)


def vector_of_plane(plane: gtsam.OrientedPlane3) -> tuple[np.ndarray, np.ndarray]:
    """``(v, dv/dxi)``: the mirror vector ``d n`` of a plane variable and its (3, 3) derivative in the
    plane's local coordinates (two of the normal's tangent, then the distance)."""
    n = np.asarray(plane.normal().point3(), dtype=float)
    d = float(plane.distance())
    return d * n, np.column_stack([d * np.asarray(plane.normal().basis(), dtype=float), n])


def vectors_of_planes(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`vector_of_plane` of many planes at once from their coefficients ``(n, d)`` (P, 4)
    (``OrientedPlane3.planeCoefficients``): vectors (P, 3) and Jacobians (P, 3, 3), the tangent basis
    chosen as GTSAM's ``Unit3::basis`` does (``n x e`` normalised, ``e`` the axis of ``n``'s smallest
    component, ties to the earlier axis; then ``n x b1``)."""
    if not len(coefficients):  # (none kept: every placement eliminated)
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    n, d = coefficients[:, :3], coefficients[:, 3]
    m = np.abs(n)
    axis = np.where((m[:, 0] <= m[:, 1]) & (m[:, 0] <= m[:, 2]), 0,
                    np.where((m[:, 1] <= m[:, 0]) & (m[:, 1] <= m[:, 2]), 1, 2))
    b1 = _cross(n, np.eye(3)[axis])
    b1 = b1 / np.sqrt(np.einsum("pi,pi->p", b1, b1))[:, None]
    b2 = _cross(n, b1)
    return d[:, None] * n, np.stack([d[:, None] * b1, d[:, None] * b2, n], axis=2)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a x b`` of (P, 3) arrays (``np.cross``'s axis handling costs more than the products here:
    an incremental update reads a few planes per factor call)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@dataclass
class ViewSlots:
    """Where a view's unknowns sit among the factor's local coordinates.

    ``pose_cols``: ``{camera: first column}`` of each camera pose that is a variable (6 columns; a fixed
    pose has none); ``mirror_cols``: ``{placement: first column}`` (3 columns each); ``size``: P."""

    pose_cols: dict[str, int]
    mirror_cols: dict[tuple[int, int], int]
    size: int


def transfer_mirror_vector(
    v_owner: np.ndarray, pose_c: tuple[np.ndarray, np.ndarray], pose_o: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mirror vector ``v_owner`` (owner camera o's frame) in camera c's frame, and its derivatives
    (3, 3) in ``v_owner``, c's ``w``, c's ``nu``, o's ``w``, o's ``nu`` (module docstring)."""
    (R_c, t_c), (R_o, t_o) = pose_c, pose_o
    a = R_o.T @ v_owner  # the mirror vector's direction in base-frame axes
    b = R_o.T @ t_o
    u = R_c @ a  # = R_co v_o
    t_co = t_c - R_c @ b
    dd = float(v_owner @ v_owner)
    g = 1.0 + float(u @ t_co) / dd
    R_co = R_c @ R_o.T
    du = {"v": R_co, "wc": -R_c @ _skew(a), "nc": np.zeros((3, 3)), "wo": R_c @ _skew(a), "no": np.zeros((3, 3))}
    dt = {"v": np.zeros((3, 3)), "wc": R_c @ _skew(b), "nc": R_c, "wo": -R_c @ _skew(b), "no": -R_c}
    out = []
    for name in ("v", "wc", "nc", "wo", "no"):
        dg = (t_co @ du[name] + u @ dt[name]) / dd
        if name == "v":
            dg = dg - float(u @ t_co) * 2.0 * v_owner / dd**2
        out.append(g * du[name] + np.outer(u, dg))
    return (u * g, *out)


def view_model(
    camera: str,
    reflections: Sequence[tuple[int, int]],
    poses: dict[str, tuple[np.ndarray, np.ndarray]],
    mirror_vectors: dict[tuple[int, int], np.ndarray],
    owners: dict[tuple[int, int], str],
    base_points: np.ndarray,
    slots: ViewSlots | None = None,
    mirror_jacobians: dict[tuple[int, int], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Predicted normalized coordinates (2, N) of base points (3, N) in this view; with ``slots`` also
    ``dz`` (2, P, N) in the factor's local coordinates and ``dz/dBp`` (2, 3, N). ``mirror_jacobians``:
    each placement's ``dv/dxi`` (3, 3) where its variable is not ``v`` itself (a plane)."""
    identity = np.eye(3)
    R_c, t_c = poses[camera]
    B = np.asarray(base_points, dtype=float)
    x = R_c @ B + t_c[:, None]  # eq. (2)
    n = B.shape[1]
    dx = dB = None
    if slots is not None:
        dx = np.zeros((3, slots.size, n))
        if camera in slots.pose_cols:
            c = slots.pose_cols[camera]
            # d(R Exp(w) B)/dw = -R [B]x ; d(t + R nu)/dnu = R
            dx[:, c:c + 3, :] = -np.einsum("ij,jkn->ikn", R_c, _skew_many(B))
            dx[:, c + 3:c + 6, :] = R_c[:, :, None]
        dB = np.repeat(R_c[:, :, None], n, axis=2)
    for placement in reflections:
        owner = owners[placement]
        v_o = np.asarray(mirror_vectors[placement], dtype=float)
        dv = None
        if owner == camera:
            v = v_o
            if slots is not None:
                dv = np.zeros((3, slots.size))
                col = slots.mirror_cols[placement]
                dv[:, col:col + 3] = identity if mirror_jacobians is None else mirror_jacobians[placement]
        else:
            v, dv_v, dv_wc, dv_nc, dv_wo, dv_no = transfer_mirror_vector(v_o, poses[camera], poses[owner])
            if slots is not None:
                dv = np.zeros((3, slots.size))
                col = slots.mirror_cols[placement]
                dv[:, col:col + 3] = dv_v if mirror_jacobians is None else dv_v @ mirror_jacobians[placement]
                for who, dw, dn in ((camera, dv_wc, dv_nc), (owner, dv_wo, dv_no)):
                    if who in slots.pose_cols:
                        c = slots.pose_cols[who]
                        dv[:, c:c + 3] += dw
                        dv[:, c + 3:c + 6] += dn
        vv = float(v @ v)
        vx = v @ x  # (N,)
        s = vx / vv - 1.0
        if slots is not None:
            assert dx is not None and dB is not None and dv is not None
            # ds = (v^T dx + x^T dv) / vv - 2 (v.x)(v^T dv) / vv^2
            ds = (np.einsum("i,ipn->pn", v, dx) + np.einsum("in,ip->pn", x, dv)) / vv
            ds -= 2.0 * np.outer(v @ dv, vx) / vv**2
            dx = dx - 2.0 * v[:, None, None] * ds[None] - 2.0 * dv[:, :, None] * s[None, None, :]
            dB = dB - 2.0 * np.einsum("i,j,jkn->ikn", v, v, dB) / vv  # M dB
        x = x - 2.0 * v[:, None] * s[None, :]  # eq. (3): M x + 2 v
    z = x[:2] / x[2]  # eq. (9)
    if slots is None:
        return z, None, None
    assert dx is not None and dB is not None
    dz = (dx[:2] - z[:, None, :] * dx[2][None]) / x[2]
    dzB = (dB[:2] - z[:, None, :] * dB[2][None]) / x[2]
    return z, dz, dzB


def _skew_many(B: np.ndarray) -> np.ndarray:
    """[b]x for every column of B (3, N): (3, 3, N)."""
    S = np.zeros((3, 3, B.shape[1]))
    S[0, 1], S[0, 2], S[1, 2] = -B[2], B[1], -B[0]
    S[1, 0], S[2, 0], S[2, 1] = B[2], -B[1], B[0]
    return S


def planes_at(values: gtsam.Values, mirror_keys: dict) -> tuple[dict, dict]:
    """Each placement's mirror vector (its plane variable's, :func:`vector_of_plane`) and that vector's
    3x3 derivative in the plane's local coordinates, at ``values``."""
    mirrors, mirror_jacobians = {}, {}
    for p, key in mirror_keys.items():
        mirrors[p], mirror_jacobians[p] = vector_of_plane(values.atOrientedPlane3(key))
    return mirrors, mirror_jacobians


def points_at(values: gtsam.Values, base_points: np.ndarray, landmark_keys: np.ndarray) -> np.ndarray:
    """The view's points in {B} (3, N): the known ones as given, each unknown one (key >= 0) at ``values``."""
    B = base_points.copy()
    for j, key in enumerate(landmark_keys):
        if key >= 0:
            B[:, j] = values.atPoint3(int(key))
    return B


def scaled_error(residual: np.ndarray, sigmas: np.ndarray, robust: str | None, robust_k: float,
                 linearizing: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(error, scale)``: the residuals (2, N) measurement-major, each measurement scaled for the robust
    kernel (``robust.robust_row_scales``: the square-root weight where the factor is linearised, the
    loss scale where only its cost is asked), and that per-measurement scale (ones without a kernel)."""
    scale = np.ones(residual.shape[1])
    if robust is not None:
        norms = np.linalg.norm(residual / sigmas, axis=0)
        sqrt_w, loss_scale = robust_row_scales(robust, norms, robust_k)
        scale = sqrt_w if linearizing else loss_scale
    return (residual * scale).T.reshape(-1), scale


def landmark_blocks(dzB: np.ndarray, scale: np.ndarray, landmark_keys: np.ndarray, unique_landmarks: list[int]):
    """The Jacobian block (2N, 3) of each unknown point in ``unique_landmarks``' order: its measurements'
    rows of ``dzB`` (2, 3, N), scaled as :func:`scaled_error` scales the residuals (zeros elsewhere)."""
    n = dzB.shape[2]
    slot = {key: u for u, key in enumerate(unique_landmarks)}
    measured = [(j, slot[key]) for j, key in enumerate(landmark_keys.tolist()) if key in slot]
    blocks = np.zeros((len(unique_landmarks), n, 2, 3))  # every block filled at once (a view had hundreds)
    if measured:
        rows, slots = np.array(measured).T
        blocks[slots, rows] = np.transpose(dzB[:, :, rows] * scale[rows], (2, 0, 1))
    yield from blocks.reshape(len(unique_landmarks), 2 * n, 3)


class ViewFactor:
    """The factor of one image (module docstring) as a ``gtsam.CustomFactor``: build with :meth:`factor`.

    ``pose_keys``: ``{camera: key}`` of the poses that are variables; ``fixed_poses``: the others'
    values (the first camera without a known target). ``mirror_keys``: ``{placement: key}`` of the
    ``OrientedPlane3`` variables (module docstring);
    ``owners``: each placement's camera. ``fiducials``: (3, N) base points, NaN columns where
    ``landmark_keys[i]`` (a key, else -1) gives the point. ``observed`` (2, N); ``sigmas`` (2, N).
    ``intrinsics``: ``(model, key)`` where the camera's intrinsics are estimated: then the
    factor predicts pixels through them (``factors/intrinsics.py``), ``observed`` and ``sigmas`` are
    pixels, and the intrinsics vector is the last key.
    """

    def __init__(self, camera: str, reflections: Sequence[tuple[int, int]], pose_keys: dict[str, int],
                 fixed_poses: dict[str, tuple[np.ndarray, np.ndarray]], mirror_keys: dict[tuple[int, int], int],
                 owners: dict[tuple[int, int], str], base_points: np.ndarray, landmark_keys: Sequence[int],
                 observed: np.ndarray, sigmas: np.ndarray, robust: str | None = None, robust_k: float = ROBUST_K,
                 intrinsics: tuple[IntrinsicsModel, int] | None = None):
        check_kernel(robust)
        self.camera, self.reflections = camera, tuple(reflections)
        self.owners = {p: owners[p] for p in self.reflections}
        cameras = [camera] + [o for o in dict.fromkeys(self.owners[p] for p in self.reflections) if o != camera]
        self.fixed = {name: fixed_poses[name] for name in cameras if name in fixed_poses}
        self.pose_keys = {name: pose_keys[name] for name in cameras if name not in self.fixed}
        placements = list(dict.fromkeys(self.reflections))
        pose_cols = {name: 6 * k for k, name in enumerate(self.pose_keys)}
        offset = 6 * len(pose_cols)
        mirror_cols = {p: offset + 3 * k for k, p in enumerate(placements)}
        self.slots = ViewSlots(pose_cols, mirror_cols, offset + 3 * len(placements))
        self.mirror_keys = {p: mirror_keys[p] for p in placements}
        self.base_points = np.array(base_points, dtype=float)
        self.landmark_keys = np.asarray(landmark_keys, dtype=np.int64)
        self.unique_landmarks = list(dict.fromkeys(int(k) for k in self.landmark_keys if k >= 0))
        self.observed = np.asarray(observed, dtype=float)
        self.sigmas = np.asarray(sigmas, dtype=float)
        self.robust, self.robust_k = robust, robust_k
        self.intrinsics = intrinsics
        self.keys = [*self.pose_keys.values(), *self.mirror_keys.values(), *self.unique_landmarks,
                     *([intrinsics[1]] if intrinsics is not None else [])]

    def _state(self, values: gtsam.Values) -> tuple[dict, dict, np.ndarray, dict]:
        poses = dict(self.fixed)
        for name, key in self.pose_keys.items():
            pose = values.atPose3(key)
            poses[name] = (pose.rotation().matrix(), np.asarray(pose.translation(), dtype=float))
        mirrors, mirror_jacobians = planes_at(values, self.mirror_keys)
        return poses, mirrors, points_at(values, self.base_points, self.landmark_keys), mirror_jacobians

    def predict(self, values: gtsam.Values) -> np.ndarray:
        """Predicted normalized coordinates (2, N) at ``values``."""
        poses, mirrors, B, _ = self._state(values)
        return view_model(self.camera, self.reflections, poses, mirrors, self.owners, B)[0]

    def theta(self, values: gtsam.Values) -> np.ndarray:
        """All nine intrinsics at ``values`` (only with ``intrinsics``)."""
        assert self.intrinsics is not None
        model, key = self.intrinsics
        return model.theta(np.asarray(values.atVector(key), dtype=float))

    def error(self, this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        poses, mirrors, B, mirror_jacobians = self._state(values)
        slots = self.slots if jacobians is not None else None
        z, dz, dzB = view_model(self.camera, self.reflections, poses, mirrors, self.owners, B, slots, mirror_jacobians)
        dK = None
        if self.intrinsics is not None:  # pixels through the estimated intrinsics
            pixels, D, T = pixel_jacobians(self.theta(values), z)
            z = pixels
            if slots is not None:
                assert dz is not None and dzB is not None
                dz = np.einsum("ijn,jpn->ipn", D, dz)
                dzB = np.einsum("ijn,jpn->ipn", D, dzB)
                dK = T[:, self.intrinsics[0].index, :]
        residual = z - self.observed  # (2, N), h - z
        error, scale = scaled_error(residual, self.sigmas, self.robust, self.robust_k, jacobians is not None)
        if jacobians is not None:
            assert dz is not None and dzB is not None
            J = np.transpose(dz * scale, (2, 0, 1)).reshape(2 * residual.shape[1], self.slots.size)  # measurement-major
            k = 0
            for name in self.pose_keys:
                c = self.slots.pose_cols[name]
                jacobians[k] = np.ascontiguousarray(J[:, c:c + 6])
                k += 1
            for p in self.mirror_keys:
                c = self.slots.mirror_cols[p]
                jacobians[k] = np.ascontiguousarray(J[:, c:c + 3])
                k += 1
            for block in landmark_blocks(dzB, scale, self.landmark_keys, self.unique_landmarks):
                jacobians[k] = block
                k += 1
            if dK is not None:
                jacobians[k] = np.ascontiguousarray(np.transpose(dK * scale, (2, 0, 1)).reshape(2 * residual.shape[1], -1))
        return error

    def factor(self) -> gtsam.CustomFactor:
        noise = gtsam.noiseModel.Diagonal.Sigmas(self.sigmas.T.reshape(-1))
        return gtsam.CustomFactor(noise, self.keys, self.error)
