"""The general view factors (``views.py``) evaluated together: one vectorised pass over every view of the
same shape, and one factor per set of placements (Hesch et al., eqs. 2, 3, 9; the model of ``views.py``).

Why: a Python factor costs a call per image per LM iteration, and inside GTSAM's optimizers every Python
factor call first copies the whole ``Values`` (``tests/reference/batched.py``'s docstring), so per-image ``ViewFactor``
calls cost O(images x unknowns) per iteration. Here

* views are **grouped by shape**: the same camera, the same owner camera at each reflection, the same
  pattern of repeated placements and as many points. A group's model (``views.view_model`` written with
  a leading axis over its views) is one numpy pass; its placements' vectors and their plane Jacobians
  (``views.vector_of_plane``) are per view, its poses shared;
* views are **stacked** by the set of placements they see (a photograph's views through its own
  placements, by every camera), and a few consecutive sets into one ``gtsam.CustomFactor`` (at most
  :data:`PLACEMENTS_PER_FACTOR` placements): a factor's keys are those placements and the camera poses,
  so elimination treats at most that many planes jointly (a stack over many placements would make it
  dense), while the factor calls, each of which copies the whole ``Values``, are fewer;
* the first factor called at new values evaluates every group (errors, and Jacobians when asked) into
  preallocated buffers; the others check that their own variables are bit for bit those of the batch
  (a stale result is never returned) and return views of them. Not thread-safe (GTSAM calls Python
  factors one at a time).

Each view's rows, whitening and robust kernel are those of its ``ViewFactor`` (per measurement, as
the tree's reference factors do, ``tests/reference/batched.py``): a stack's error is its views' errors one after the other. Views with reconstruction
points are stacked by ``view_points.py`` (these groups, compressed normal equations); views that estimate
intrinsics stay ``ViewFactor`` s. ``tests/test_view_stack.py`` checks errors,
Jacobians and whole calibrations against the per-view factors.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np

from mirror_fg.factors.robust import robust_row_scales
from mirror_fg.factors.view_table import ViewTable, collected_keys, groups_by_shape, stacks_by_placements
from mirror_fg.factors.views import ViewFactor, vectors_of_planes

__all__ = ["stackable", "stacked_view_factors", "ViewStackEvaluator", "read_poses_and_planes", "collected_keys",
           "groups_by_shape", "stacks_by_placements"]

Placement = tuple[int, int]
#: Placements of one stacked factor at most: the views of a few photographs (their own placements) in one
#: factor. Each Python factor call copies the whole ``Values`` (module docstring), so fewer, larger factors
#: cost less per iteration, while a factor's placements are eliminated together (a dense block of this
#: many planes and the camera poses: small).
PLACEMENTS_PER_FACTOR = 16


def stackable(factor: ViewFactor) -> bool:
    """Whether a view's factor can be evaluated in a stack: fiducials only, intrinsics known."""
    return factor.intrinsics is None and not factor.unique_landmarks


def read_poses_and_planes(values: gtsam.Values, fixed: dict, pose_keys: dict[str, int],
                          mirror_keys: dict[Placement, int]) -> tuple[dict, dict, dict, dict[int, bytes]]:
    """The cameras' poses ``{name: (R, t)}`` (the fixed ones too), each placement's mirror vector and its
    plane Jacobian (``views.vector_of_plane``) from ``values``, and each variable's bytes (what a stacked
    factor's cache compares its next values with)."""
    poses = dict(fixed)
    state: dict[int, bytes] = {}
    for name, key in pose_keys.items():
        pose = values.atPose3(key)
        state[key] = pose.matrix().tobytes()
        poses[name] = (pose.rotation().matrix(), np.asarray(pose.translation(), dtype=float))
    placements = list(mirror_keys)
    coefficients = np.array([values.atOrientedPlane3(mirror_keys[p]).planeCoefficients() for p in placements]
                            ).reshape(-1, 4)
    for p, row in zip(placements, coefficients):
        state[mirror_keys[p]] = row.tobytes()
    V, J = vectors_of_planes(coefficients)  # as views.vector_of_plane of each, bit for bit
    return poses, dict(zip(placements, V)), dict(zip(placements, J)), state


def _skew_rows(a: np.ndarray) -> np.ndarray:
    """[a]x of each row of ``a`` (b, 3): (b, 3, 3)."""
    S = np.zeros((len(a), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = a[:, 2], -a[:, 1], a[:, 0]
    return S


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


class _Group:
    """Views of one shape (module docstring): their factors, base points (b, 3, N), observations and
    sigmas (b, 2, N), and where their rows and Jacobian entries go in the evaluator's buffers."""

    def __init__(self, factors: list[ViewFactor]):
        self._arrays(factors[0], np.array([f.base_points for f in factors]), np.array([f.observed for f in factors]),
                     np.array([f.sigmas for f in factors]),
                     np.array([f.landmark_keys for f in factors], dtype=np.int64).reshape(len(factors), -1))
        self.factors = factors
        self.placements = [list(f.mirror_keys) for f in factors]  # (b, U) per view, in order of first reflection

    @classmethod
    def of_arrays(cls, first: ViewFactor, placement_ids: np.ndarray, placements: list[Placement], base: np.ndarray,
                  observed: np.ndarray, sigmas: np.ndarray, landmarks: np.ndarray) -> _Group:
        """The group of views of ``first``'s shape given as arrays (``view_table.ViewTable.groups``): their
        placements (b, U) as indices into ``placements``, base points (b, 3, N), observations and sigmas
        (b, 2, N) and point keys (b, N)."""
        group = cls.__new__(cls)
        group._arrays(first, base, observed, sigmas, landmarks)
        group.placement_ids, group.placement_names = placement_ids, placements
        return group

    def _arrays(self, first: ViewFactor, base: np.ndarray, observed: np.ndarray, sigmas: np.ndarray,
                landmarks: np.ndarray) -> None:
        self.first = first  # its camera, owners, pattern of placements, pose keys and kernel are the group's
        self.camera = first.camera
        placements = list(dict.fromkeys(first.reflections))
        self.steps = [(first.owners[p], placements.index(p)) for p in first.reflections]
        self.slots = first.slots
        self.pose_cols = dict(first.slots.pose_cols)
        self.placement_count = len(placements)
        self.base = base
        self.base_soa = np.ascontiguousarray(self.base.transpose(1, 2, 0))  # (3, N, b)
        self.observed = observed
        self.sigmas = sigmas
        self.robust, self.robust_k = first.robust, first.robust_k
        #: each measurement's reconstruction point key (b, N), -1 for a fiducial (``ViewFactor.landmark_keys``)
        self.landmarks = landmarks
        self.placement_ids: np.ndarray | None = None  # (b, U) indices into placement_names, where built of arrays
        self.placement_names: list[Placement] = []
        self.error_rows: np.ndarray | None = None  # (b, 2N) indices into the error buffers
        self.jacobian_entries: np.ndarray | None = None  # (b, 2N, P) indices into the Jacobian buffer

    @property
    def size(self) -> int:
        """The number of views."""
        return len(self.base)

    def placement_index(self, index: dict[Placement, int]) -> np.ndarray:
        """Each view's placements (b, U) as rows of arrays ordered by ``index`` (:meth:`model`'s ``arrays``)."""
        if self.placement_ids is not None:
            rows = np.array([index.get(p, -1) for p in self.placement_names], dtype=np.intp)
            return rows[self.placement_ids].reshape(self.size, -1)
        return np.array([[index[p] for p in ps] for ps in self.placements], dtype=np.intp).reshape(self.size, -1)

    def points(self, point_values: dict[int, np.ndarray]) -> np.ndarray:
        """The views' points in {B} (b, 3, N): the fiducials as given, each reconstruction point at
        ``point_values`` (``{key: (3,)}``)."""
        if not (self.landmarks >= 0).any():
            return self.base
        B = self.base.transpose(0, 2, 1).copy()
        where = self.landmarks >= 0
        B[where] = np.array([point_values[int(k)] for k in self.landmarks[where]])
        return B.transpose(0, 2, 1)

    def model(self, poses: dict[str, tuple[np.ndarray, np.ndarray]], vectors: dict[Placement, np.ndarray],
              plane_jacobians: dict[Placement, np.ndarray], jacobians: bool, base: np.ndarray | None = None,
              wrt: int | None = None, arrays: tuple | None = None):
        """``views.view_model`` of every view at once: predictions (b, 2, N) and, when asked, ``dz``
        (b, 2, P, N) in the views' local coordinates (the same layout as each ``ViewFactor``'s) and
        ``dz/dBp`` (b, 2, 3, N), the derivative in the point (base frame). ``base``: the points (b, 3, N)
        (:meth:`points`; the fiducials where not given). ``wrt``: ``dz`` in the views' ``wrt``-th placement
        alone (b, 2, 3, N), e.g. to optimise that placement with the rest held. ``arrays``: the views'
        placements' vectors (b, U, 3) and plane Jacobians (b, U, 3, 3) instead of looking each up in
        ``vectors`` and ``plane_jacobians`` (:meth:`placement_arrays`)."""
        x, dx, dB = self.reflected(poses, vectors, plane_jacobians, jacobians, base, wrt, arrays, self.steps)
        z = x[:, :2] / x[:, 2:3]  # eq. (9)
        if not jacobians:
            return z, None, None
        dz = (dx[:, :2] - z[:, :, None, :] * dx[:, 2][:, None]) / x[:, 2][:, None, None, :]
        dzB = (dB[:, :2, :, None] - z[:, :, None, :] * dB[:, 2][:, None, :, None]) / x[:, 2][:, None, None, :]
        return z, dz, dzB

    def reflected(self, poses: dict[str, tuple[np.ndarray, np.ndarray]], vectors: dict[Placement, np.ndarray],
                  plane_jacobians: dict[Placement, np.ndarray], jacobians: bool, base: np.ndarray | None,
                  wrt: int | None, arrays: tuple | None, steps: list[tuple[str, int]]):
        """The views' points in the camera frame after the reflections ``steps`` (a prefix of
        ``self.steps``), ``x`` (b, 3, N), and when asked ``dx`` (b, 3, P, N) (or (b, 3, 3, N) with ``wrt``)
        and ``dx/dBp`` (b, 3, 3): :meth:`model` before its projection (its arguments)."""
        R_c, t_c = poses[self.camera]
        B = self.base if base is None else base
        b, _, n = B.shape
        x = np.matmul(R_c, B) + t_c[None, :, None]  # eq. (2)
        size = self.slots.size if wrt is None else 3
        dx: Any = None
        if jacobians and wrt is not None:
            dx = np.zeros((b, 3, size, n))
        elif jacobians:
            dx = np.zeros((b, 3, size, n))
            if self.camera in self.pose_cols:
                c = self.pose_cols[self.camera]
                S = np.zeros((b, 3, 3, n))
                S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -B[:, 2], B[:, 1], -B[:, 0]
                S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = B[:, 2], -B[:, 1], B[:, 0]
                dx[:, :, c:c + 3, :] = -np.matmul(R_c, S.reshape(b, 3, 3 * n)).reshape(b, 3, 3, n)  # d(R Exp(w) B)/dw = -R [B]x
                dx[:, :, c + 3:c + 6, :] = R_c[None, :, :, None]  # d(t + R nu)/dnu = R
        if arrays is not None:
            v_all, J_all = arrays
        else:
            lists = (self.placements if self.placement_ids is None
                     else [[self.placement_names[u] for u in row] for row in self.placement_ids.tolist()])
            v_all = np.array([[vectors[p] for p in ps] for ps in lists]).reshape(b, -1, 3)  # (b, U, 3)
            J_all = np.array([[plane_jacobians[p] for p in ps] for ps in lists]).reshape(b, -1, 3, 3) if jacobians else None
        offset = 6 * len(self.pose_cols) if wrt is None else 0
        dB: Any = np.broadcast_to(R_c, (b, 3, 3)) if jacobians else None  # dx/dBp, the same for a view's points
        for owner, u in steps:
            v_o = v_all[:, u]
            col = offset + 3 * u if wrt is None else 0
            mine = wrt is None or wrt == u  # this placement's columns are wanted
            dv: Any = None
            if owner == self.camera:
                v = v_o
                if jacobians:
                    dv = np.zeros((b, 3, size))
                    if mine:
                        dv[:, :, col:col + 3] = J_all[:, u]
            else:
                v, parts = self._transfer(v_o, poses[self.camera], poses[owner], jacobians)
                if jacobians:
                    dv_v, dv_wc, dv_nc, dv_wo, dv_no = parts
                    dv = np.zeros((b, 3, size))
                    if mine:
                        dv[:, :, col:col + 3] = dv_v @ J_all[:, u]
                    for who, dw, dn in ((self.camera, dv_wc, dv_nc), (owner, dv_wo, dv_no)) if wrt is None else ():
                        if who in self.pose_cols:
                            c = self.pose_cols[who]
                            dv[:, :, c:c + 3] += dw
                            dv[:, :, c + 3:c + 6] += dn
            vv = np.einsum("bi,bi->b", v, v)
            vx = np.matmul(v[:, None, :], x)[:, 0]
            s = vx / vv[:, None] - 1.0
            if jacobians:
                vdv = np.matmul(v[:, None, :], dv)[:, 0]
                ds = np.matmul(v[:, None, :], dx.reshape(b, 3, size * n)).reshape(b, size, n)  # v . dx
                ds += np.matmul(dv.transpose(0, 2, 1), x)  # x . dv
                ds /= vv[:, None, None]
                ds -= 2.0 * vdv[:, :, None] * vx[:, None, :] / (vv**2)[:, None, None]
                dx -= 2.0 * v[:, :, None, None] * ds[:, None]
                dx -= 2.0 * dv[:, :, :, None] * s[:, None, None, :]
                dB = dB - 2.0 * v[:, :, None] * np.einsum("bi,bij->bj", v, dB)[:, None, :] / vv[:, None, None]  # M dB
            x = x - 2.0 * v[:, :, None] * s[:, None, :]  # eq. (3): M x + 2 v
        return x, dx, dB

    def reflected_soa(self, poses: dict[str, tuple[np.ndarray, np.ndarray]], arrays: tuple, steps: list[tuple[str, int]],
                      jacobians: bool, work: dict | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`reflected` of the fiducials in a structure-of-arrays layout, the views last (no
        reconstruction points, no ``wrt``): ``x`` (3, N, b) and when asked ``dx`` (3, P, N, b), with only
        elementwise operations whose inner loop runs over the views (a batched (3 x 3) product per view, or
        an inner loop over a view's few points, is one step of numpy's outer loop each: far slower at
        thousands of views). ``arrays``: the views' placements' vectors (b, U, 3) and plane Jacobians
        (b, U, 3, 3). ``work``: buffers kept between calls (``dx`` is one of them: valid until the next)."""
        R_c, t_c = poses[self.camera]
        B = self.base_soa
        x = np.tensordot(R_c, B, axes=(1, 0)) + t_c[:, None, None]  # eq. (2)
        v_all, J_all = arrays
        if not jacobians:
            for owner, u in steps:
                v = (v_all[:, u] if owner == self.camera else self._transfer(v_all[:, u], poses[self.camera], poses[owner], False)[0]).T
                vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
                s = (v[0] * x[0] + v[1] * x[1] + v[2] * x[2]) / vv - 1.0
                x -= 2.0 * v[:, None, :] * s[None]  # eq. (3): M x + 2 v
            return x, None
        size, (_, n, b) = self.slots.size, x.shape
        work = {} if work is None else work
        if work.get("shape") != (size, n, b):
            work.update(shape=(size, n, b), dx=np.empty((3, size, n, b)), scratch=np.empty((size, n, b)))
        dx, scratch = work["dx"], work["scratch"]
        dx.fill(0.0)
        if self.camera in self.pose_cols:
            c = self.pose_cols[self.camera]
            for j in range(3):  # d(R Exp(w) B)/dw = -R [B]x: column j is -R (B x e_j) = R (e_j x B)
                e_j_x_B = np.zeros((3, n, b))
                e_j_x_B[(j + 1) % 3], e_j_x_B[(j + 2) % 3] = -B[(j + 2) % 3], B[(j + 1) % 3]
                dx[:, c + j] = np.tensordot(R_c, e_j_x_B, axes=(1, 0))
                dx[:, c + 3 + j] = R_c[:, j, None, None]  # d(t + R nu)/dnu = R
        offset = 6 * len(self.pose_cols)
        for owner, u in steps:
            col = offset + 3 * u
            columns: Any = [col, col + 1, col + 2]  # where dv is not zero: this placement's, and a transfer's poses
            if owner == self.camera:
                v = v_all[:, u].T
                dv = J_all[:, u].transpose(1, 2, 0)  # (3, 3, b)
                columns = slice(col, col + 3)
            else:
                v_rows, parts = self._transfer(v_all[:, u], poses[self.camera], poses[owner], True)
                v = v_rows.T
                dv_v, dv_wc, dv_nc, dv_wo, dv_no = parts
                blocks = [(dv_v @ J_all[:, u]).transpose(1, 2, 0)]
                for who, dw, dn in ((self.camera, dv_wc, dv_nc), (owner, dv_wo, dv_no)):
                    if who in self.pose_cols:
                        c = self.pose_cols[who]
                        columns += range(c, c + 6)
                        blocks.append(np.concatenate([dw, dn], axis=2).transpose(1, 2, 0))
                dv = np.concatenate(blocks, axis=1)  # (3, k, b)
            vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]  # (b,)
            vx = v[0] * x[0] + v[1] * x[1] + v[2] * x[2]  # (N, b)
            s = vx / vv - 1.0
            vdv = v[0] * dv[0] + v[1] * dv[1] + v[2] * dv[2]  # (k, b)
            ds = v[0] * dx[0]  # v . dx (P, N, b)
            ds += np.multiply(v[1], dx[1], out=scratch)
            ds += np.multiply(v[2], dx[2], out=scratch)
            ds[columns] += dv[0][:, None] * x[0] + dv[1][:, None] * x[1] + dv[2][:, None] * x[2]  # x . dv
            ds /= vv
            ds[columns] -= 2.0 * vdv[:, None] * (vx / vv**2)
            for i in range(3):
                dx[i] -= np.multiply(2.0 * v[i], ds, out=scratch)
                dx[i, columns] -= 2.0 * dv[i][:, None] * s
            x -= 2.0 * v[:, None, :] * s[None]  # eq. (3): M x + 2 v
        return x, dx

    @staticmethod
    def _transfer(v_owner: np.ndarray, pose_c, pose_o, jacobians: bool):
        """``views.transfer_mirror_vector`` of many vectors (b, 3) between the same two cameras."""
        (R_c, t_c), (R_o, t_o) = pose_c, pose_o
        a = v_owner @ R_o  # R_o^T v_o, per row
        b_ = R_o.T @ t_o
        u = a @ R_c.T  # R_co v_o
        t_co = t_c - R_c @ b_
        dd = np.einsum("bi,bi->b", v_owner, v_owner)
        ut = u @ t_co
        g = 1.0 + ut / dd
        if not jacobians:
            return u * g[:, None], None
        R_co = R_c @ R_o.T
        Ra = np.einsum("ij,bjk->bik", R_c, _skew_rows(a))
        Rb = R_c @ _skew(b_)
        zero = np.zeros((3, 3))
        du = {"v": R_co, "wc": -Ra, "nc": zero, "wo": Ra, "no": zero}
        dt = {"v": zero, "wc": Rb, "nc": R_c, "wo": -Rb, "no": -R_c}
        out = []
        for name in ("v", "wc", "nc", "wo", "no"):
            d_u = np.broadcast_to(du[name], (len(u), 3, 3))
            dg = (np.einsum("i,bij->bj", t_co, d_u) + np.einsum("bi,ij->bj", u, dt[name])) / dd[:, None]
            if name == "v":
                dg = dg - (ut * 2.0 / dd**2)[:, None] * v_owner
            out.append(g[:, None, None] * d_u + u[:, :, None] * dg[:, None, :])
        return u * g[:, None], out


class ViewStackEvaluator:
    """Every stackable view's factor evaluated together (module docstring), the views given as their
    per-image factors or as a ``view_table.ViewTable``; ``factors``: one ``gtsam.CustomFactor`` per set of
    placements (hand them to a graph)."""

    def __init__(self, view_factors: Sequence[ViewFactor] | ViewTable, placements_per_factor: int = 1):
        table = view_factors if isinstance(view_factors, ViewTable) else ViewTable.of_factors(view_factors)
        first = table.blocks[0].template
        self.fixed, self.pose_keys, self.mirror_keys = table.collected_keys()
        stacks = table.stacks(placements_per_factor)
        shapes = table.groups()
        self.groups = [table.group_of(template, parts) for template, _, parts in shapes]
        rows_of_view = np.zeros(table.count, dtype=np.intp)  # 2 per measurement
        sigmas_of_view: list = [None] * table.count  # each view's sigmas, measurement-major
        for block in table.blocks:
            rows_of_view[block.members] = 2 * block.template.base_points.shape[1]
            whitening = block.template.sigmas.T.reshape(-1)
            for i in block.members.tolist():
                sigmas_of_view[i] = whitening
        # buffers: each stack's rows consecutive; each stack's key blocks (rows, dim) consecutive
        err_size = int(rows_of_view.sum())
        self._err = np.zeros(err_size)
        self._err_lin = np.zeros(err_size) if first.robust is not None else self._err
        self._stack_keys: list[list[int]] = []
        self._stack_rows: list[slice] = []
        self._stack_blocks: list[list[tuple[int, int]]] = []  # (offset, dim) of each key's block
        row_start = np.zeros(table.count, dtype=np.intp)  # each view's first row (error buffer)
        local_start = np.zeros(table.count, dtype=np.intp)  # ... counted from its stack's first row
        block_at: list[dict[int, int]] = []  # per stack: each key's block offset (Jacobian buffer)
        plane_codes: list[int] = []  # (stack, placement) of each stack's planes, and their blocks' offsets
        plane_offsets: list[int] = []
        stack_of = np.zeros(table.count, dtype=np.intp)
        row0, jac0 = 0, 0
        self.factors: list[gtsam.CustomFactor] = []
        for s, (members, pose_keys, placements) in enumerate(
                zip(stacks, *table.stack_keys(stacks, np.zeros(len(table.placements), dtype=bool)))):
            keys = pose_keys + [table.mirror_keys[table.placements[u]] for u in placements]
            dims = [6] * len(pose_keys) + [3] * len(placements)
            sizes = rows_of_view[members]
            rows = int(sizes.sum())
            blocks, offset = [], jac0
            for dim in dims:
                blocks.append((offset, dim))
                offset += rows * dim
            block_at.append(dict(zip(keys, (o for o, _ in blocks))))
            plane_codes.extend(s * len(table.placements) + u for u in placements)
            plane_offsets.extend(o for o, _ in blocks[len(pose_keys):])
            starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
            row_start[members] = row0 + starts
            local_start[members] = starts
            stack_of[members] = s
            self._stack_keys.append(keys)
            self._stack_rows.append(slice(row0, row0 + rows))
            self._stack_blocks.append(blocks)
            sigmas = np.concatenate([sigmas_of_view[i] for i in members.tolist()])
            noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            self.factors.append(gtsam.CustomFactor(noise, keys, self._error_function(len(self.factors))))
            row0, jac0 = row0 + rows, offset
        order = np.argsort(np.array(plane_codes, dtype=np.intp), kind="stable")
        codes, code_offsets = np.array(plane_codes, dtype=np.intp)[order], np.array(plane_offsets, dtype=np.intp)[order]
        # each group's rows and Jacobian entries at once: a view's entry (row j, its column c + k of a key's
        # block) is the block's offset + (its first row in the stack + j) * dim + k
        error_rows, entries = [], []
        for group, (_, members, _) in zip(self.groups, shapes):
            m = 2 * group.base.shape[2]
            error_rows.append(row_start[members][:, None] + np.arange(m)[None, :])
            entry = np.zeros((len(members), m, group.slots.size), dtype=np.intp)
            local = local_start[members][:, None, None] + np.arange(m)[None, :, None]  # (b, m, 1)
            stacks_of = stack_of[members]
            columns: list[tuple[int, int, np.ndarray]] = []  # (first column, dim, each view's block offset)
            for name, c in group.first.slots.pose_cols.items():
                key = group.first.pose_keys[name]
                columns.append((c, 6, np.array([at.get(key, -1) for at in block_at], dtype=np.intp)[stacks_of]))
            ids = group.placement_ids
            assert ids is not None
            offset = 6 * len(group.first.slots.pose_cols)
            for u in range(group.placement_count):  # (views.ViewSlots: in their order of first reflection)
                at = np.searchsorted(codes, stacks_of * len(table.placements) + ids[:, u])
                columns.append((offset + 3 * u, 3, code_offsets[at]))
            for c, dim, offsets in columns:
                entry[:, :, c:c + dim] = offsets[:, None, None] + local * dim + np.arange(dim)[None, None, :]
            entries.append(entry)
        for g, group in enumerate(self.groups):
            group.error_rows, group.jacobian_entries = error_rows[g], entries[g]
        self._jac = np.zeros(jac0)
        self._placement_of_key = {k: p for p, k in self.mirror_keys.items()}
        self._placement_order = list(self.mirror_keys)
        rows_of = {p: i for i, p in enumerate(self._placement_order)}
        self._placement_rows = [group.placement_index(rows_of) for group in self.groups]
        self._camera_of_key = {k: c for c, k in self.pose_keys.items()}
        # cache
        self._valid = False
        self._has_jacobians = False
        self._poses: dict[int, gtsam.Pose3] = {}
        self._planes: dict[int, gtsam.OrientedPlane3] = {}
        self._plane_bytes: dict[int, bytes] = {}
        self.batches = 0

    # --- cache ------------------------------------------------------------------------------------

    def _matches(self, s: int, values: gtsam.Values) -> bool:
        if not self._valid:
            return False
        poses, planes = self._poses, self._plane_bytes
        for key in self._stack_keys[s]:
            if key in poses:
                if not values.atPose3(key).equals(poses[key], 0.0):
                    return False
            elif values.atOrientedPlane3(key).planeCoefficients().tobytes() != planes[key]:
                return False  # (OrientedPlane3.equals at tolerance 0 is false even for itself)
        return True

    def _load(self, values: gtsam.Values) -> None:
        self._poses = {k: values.atPose3(k) for k in self.pose_keys.values()}
        self._planes = {k: values.atOrientedPlane3(k) for k in self.mirror_keys.values()}
        self._plane_bytes = {k: plane.planeCoefficients().tobytes() for k, plane in self._planes.items()}
        self._valid = True
        self._has_jacobians = False

    def _compute(self, jacobians: bool) -> None:
        self.batches += 1
        poses = dict(self.fixed)
        for name, key in self.pose_keys.items():
            pose = self._poses[key]
            poses[name] = (pose.rotation().matrix(), np.asarray(pose.translation(), dtype=float))
        order = self._placement_order
        V, JV = vectors_of_planes(np.array([self._planes[self.mirror_keys[p]].planeCoefficients() for p in order])
                                  .reshape(-1, 4))
        vectors, plane_jacobians = dict(zip(order, V)), dict(zip(order, JV))
        for group, at in zip(self.groups, self._placement_rows):
            z, dz, _ = group.model(poses, vectors, plane_jacobians, jacobians, arrays=(V[at], JV[at] if jacobians else None))
            residual = z - group.observed  # (b, 2, N), h - z
            if group.robust is None:
                self._err[group.error_rows] = residual.transpose(0, 2, 1).reshape(len(residual), -1)
                scale = None
            else:
                norms = np.linalg.norm(residual / group.sigmas, axis=1)
                sqrt_w, loss_scale = robust_row_scales(group.robust, norms.reshape(-1), group.robust_k)
                sqrt_w, loss_scale = sqrt_w.reshape(norms.shape), loss_scale.reshape(norms.shape)
                self._err[group.error_rows] = (residual * loss_scale[:, None]).transpose(0, 2, 1).reshape(len(residual), -1)
                self._err_lin[group.error_rows] = (residual * sqrt_w[:, None]).transpose(0, 2, 1).reshape(len(residual), -1)
                scale = sqrt_w
            if jacobians:
                assert dz is not None
                if scale is not None:
                    dz = dz * scale[:, None, None, :]
                entries = group.jacobian_entries
                assert entries is not None  # set when the stacks were laid out
                self._jac[entries] = np.transpose(dz, (0, 3, 1, 2)).reshape(entries.shape)
        self._has_jacobians = jacobians

    def _error_function(self, s: int):
        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            if not self._matches(s, values):
                self._load(values)
                self._compute(H is not None)
            elif H is not None and not self._has_jacobians:
                self._compute(True)
            rows = self._stack_rows[s]
            if H is None:
                return self._err[rows].copy()
            count = rows.stop - rows.start
            for k, (offset, dim) in enumerate(self._stack_blocks[s]):
                H[k] = self._jac[offset:offset + count * dim].reshape(count, dim).copy()
            return self._err_lin[rows].copy()

        return error


def stacked_view_factors(view_factors: Sequence[ViewFactor] | ViewTable) -> list[gtsam.CustomFactor]:
    """The factors of ``view_factors`` (or of a table's views, ``view_table.py``: the per-image factors made
    only for the views not stacked here): those of fiducials alone stacked (:class:`ViewStackEvaluator`),
    those with reconstruction points stacked and compressed (``view_points.ViewPointStack``), those that
    estimate intrinsics their own ``ViewFactor`` s."""
    from mirror_fg.factors.view_points import ViewPointStack  # it stacks with this module's groups

    if isinstance(view_factors, ViewTable):
        table = view_factors
        stack: Sequence[ViewFactor] | ViewTable = table.subset(lambda block: stackable(block.template))
        others = table.subset(lambda block: not stackable(block.template)).factors()
        with_points = [f for f in others if f.intrinsics is None and f.unique_landmarks]
        factors = [f.factor() for f in others if f.intrinsics is not None]
    else:
        stack = [f for f in view_factors if stackable(f)]
        with_points = [f for f in view_factors if f.intrinsics is None and f.unique_landmarks]
        factors = [f.factor() for f in view_factors if f.intrinsics is not None]
    if (stack.count if isinstance(stack, ViewTable) else stack):
        factors.extend(ViewStackEvaluator(stack, PLACEMENTS_PER_FACTOR).factors)
    if with_points:
        factors.extend(ViewPointStack(with_points).factors)
    return factors
