"""Views that see reconstruction points, evaluated together (``view_stack.py``'s groups) and linearised as
their normal equations compressed to ``d + 1`` rows (Hesch et al., eqs. 2, 3, 9, 19-20, 23; the model of
``views.py``).

Why: a view that sees reconstruction points has a Jacobian block per point, and every image sees the
same points: one ``ViewFactor`` per image (a Python call per image, each copying the whole ``Values``)
hands GTSAM an image's rows over the camera pose, its placements and every point, and the points' dense
separator then takes every image's rows (24,600 rows x 195 columns for 200 images of 63 points).
Here, as the paper's tree factors do (``eliminated.py``, ``schur.py``):

* views are grouped by shape and stacked by the set of placements they see (``view_stack.py``), a few
  consecutive sets into one ``gtsam.CustomFactor`` (at most :data:`PLACEMENTS_PER_FACTOR` placements);
  a factor's keys are the camera poses, its placements and the points its views see;
* the first factor called at new values evaluates every group (``view_stack._Group.model`` with the
  points at those values) and, when linearising, sums each factor's normal equations
  ``[J | e]^T [J | e]`` from the views' compact blocks (a view's pose and placement columns, each
  measurement's own point: never the factor's dense width) and compresses them to
  ``d + 1`` rows ``[R | r]`` with ``[R | r]^T [R | r]`` that matrix (:func:`_rows_of`: its Cholesky factor,
  or an eigendecomposition's root where a factor alone leaves some unknowns free, e.g. a point seen along
  one ray; without ``schur.compressed_normal``'s shift, which would move the marginals by 1e-6): the same ``J^T J``,
  ``J^T e`` and ``||e||^2`` as the views' rows, hence the same Levenberg-Marquardt steps, marginals and cost as one ``ViewFactor`` per
  image, in a factor of ``d + 1`` rows;
* the other factors check that their own variables are bit for bit those of the batch (a stale result is
  never returned). Not thread-safe (GTSAM calls Python factors one at a time).

Each view's whitening and robust kernel are its ``ViewFactor``'s (per measurement: the square-root
weight in the linear system, the loss where only the cost is asked). ``tests/test_view_points.py``
checks cost, ``J^T J`` and ``J^T e`` against the per-view factors, and whole calibrations.
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mirror_fg.factors.robust import robust_row_scales
from mirror_fg.factors.schur import one_blas_thread, row_products
from mirror_fg.factors.view_stack import (_Group, collected_keys, groups_by_shape, read_poses_and_planes,
                                          stacks_by_placements)
from mirror_fg.factors.views import ViewFactor

__all__ = ["ViewPointStack", "PLACEMENTS_PER_FACTOR"]

Placement = tuple[int, int]
#: Placements of one factor at most. A factor's width is its poses, its placements and every point its
#: views see (the points are shared by all views): wider factors than ``view_stack``'s, so more placements
#: each (fewer factors, fewer Python calls, fewer dense separators for GTSAM to add up).
PLACEMENTS_PER_FACTOR = 32


class ViewPointStack:
    """Views with reconstruction points (intrinsics known) in a few compressed factors (module docstring);
    ``factors``: one ``gtsam.CustomFactor`` per set of placements (hand them to a graph)."""

    def __init__(self, view_factors: Sequence[ViewFactor], placements_per_factor: int = PLACEMENTS_PER_FACTOR):
        self.fixed, self.pose_keys, self.mirror_keys = collected_keys(view_factors)
        self.point_keys = list(dict.fromkeys(k for f in view_factors for k in f.unique_landmarks))
        self._pose_key_set, self._plane_key_set = set(self.pose_keys.values()), set(self.mirror_keys.values())
        stack_of_view = np.zeros(len(view_factors), dtype=np.intp)
        self._keys: list[list[int]] = []
        self._widths: list[int] = []
        self._offsets: list[int] = []  # where each stack's augmented normal (d+1)^2 starts in the buffer
        self._columns: list[dict[int, int]] = []  # key -> first column, per stack
        size = 0
        for s, members in enumerate(stacks_by_placements(view_factors, placements_per_factor)):
            views = [view_factors[i] for i in members]
            keys = list(dict.fromkeys(k for f in views for k in f.pose_keys.values()))
            keys += list(dict.fromkeys(k for f in views for k in f.mirror_keys.values()))
            keys += list(dict.fromkeys(k for f in views for k in f.unique_landmarks))
            columns, width = {}, 0
            for key in keys:
                columns[key] = width
                width += 6 if key in self.pose_keys.values() else 3
            self._keys.append(keys)
            self._columns.append(columns)
            self._widths.append(width)
            self._offsets.append(size)
            size += (width + 1) ** 2
            stack_of_view[members] = s
        self._size = size
        self._stack_of_view = stack_of_view
        shapes = groups_by_shape(view_factors)
        self.groups = [_Group([view_factors[i] for i in members]) for members in shapes]
        self._members = [np.asarray(members, dtype=np.intp) for members in shapes]
        self._indices = np.concatenate([self._scatter(g, view_factors) for g in range(len(self.groups))])
        self.factors = [gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(width + 1), keys, self._error_function(s))
                        for s, (keys, width) in enumerate(zip(self._keys, self._widths))]
        self._valid = False
        self._linearized = False
        self._state: dict[int, bytes] = {}
        self._cost = np.zeros(len(self._keys))
        self._systems: list[tuple[np.ndarray, list[np.ndarray]]] = []
        self.batches = 0

    # --- layout -----------------------------------------------------------------------------------

    def _scatter(self, g: int, view_factors: Sequence[ViewFactor]) -> np.ndarray:
        """Group ``g``'s entries of the normal-equation buffer, in the order :meth:`_weights` gives its
        products: ``A^T A`` (b, P, P), ``A^T e`` and ``e^T A`` (b, P), ``e^T e`` (b,), then per point
        measurement ``A^T L``, ``L^T A`` (m, P, 3), ``L^T L`` (m, 3, 3), ``L^T e``, ``e^T L`` (m, 3)."""
        group, members = self.groups[g], self._members[g]
        P = group.slots.size
        colmaps, ends, bases = [], [], []
        point_columns = []
        for view, i in zip(group.factors, members):
            s = self._stack_of_view[i]
            columns, width, base = self._columns[s], self._widths[s], self._offsets[s]
            colmap = np.zeros(P, dtype=np.intp)
            for name, key in view.pose_keys.items():
                colmap[view.slots.pose_cols[name]:view.slots.pose_cols[name] + 6] = columns[key] + np.arange(6)
            for p, key in view.mirror_keys.items():
                colmap[view.slots.mirror_cols[p]:view.slots.mirror_cols[p] + 3] = columns[key] + np.arange(3)
            colmaps.append(colmap)
            ends.append(width)
            bases.append(base)
            point_columns.append([columns[int(k)] if k >= 0 else -1 for k in view.landmark_keys])
        colmap = np.array(colmaps)  # (b, P)
        d = np.array(ends)[:, None]  # (b, 1)
        base = np.array(bases)[:, None]
        stride = d + 1
        parts = [
            (base[:, :, None] + colmap[:, :, None] * stride[:, :, None] + colmap[:, None, :]).ravel(),
            (base + colmap * stride + d).ravel(),
            (base + d * stride + colmap).ravel(),
            (base + d * stride + d).ravel(),
        ]
        where = group.landmarks >= 0
        lcol = np.array(point_columns, dtype=np.intp).reshape(where.shape)[where][:, None] + np.arange(3)  # (m, 3)
        view_of = np.broadcast_to(np.arange(len(members))[:, None], where.shape)[where]
        cm, dm, bm = colmap[view_of], d[view_of], base[view_of]  # (m, P), (m, 1), (m, 1)
        sm = dm + 1
        parts += [
            (bm[:, :, None] + cm[:, :, None] * sm[:, :, None] + lcol[:, None, :]).ravel(),
            (bm[:, :, None] + lcol[:, None, :] * sm[:, :, None] + cm[:, :, None]).ravel(),  # L^T A, as A^T L's layout
            (bm[:, :, None] + lcol[:, :, None] * sm[:, :, None] + lcol[:, None, :]).ravel(),
            (bm + lcol * sm + dm).ravel(),
            (bm + dm * sm + lcol).ravel(),
        ]
        return np.concatenate(parts)

    # --- evaluation -------------------------------------------------------------------------------

    def _matches(self, s: int, values: gtsam.Values) -> bool:
        if not self._valid:
            return False
        return all(self._bytes(key, values) == self._state[key] for key in self._keys[s])

    def _bytes(self, key: int, values: gtsam.Values) -> bytes:
        if key in self._pose_key_set:
            return values.atPose3(key).matrix().tobytes()
        if key in self._plane_key_set:
            return values.atOrientedPlane3(key).planeCoefficients().tobytes()
        return np.asarray(values.atPoint3(key), dtype=float).tobytes()

    def _compute(self, values: gtsam.Values, jacobians: bool) -> None:
        self.batches += 1
        poses, vectors, plane_jacobians, state = read_poses_and_planes(values, self.fixed, self.pose_keys,
                                                                       self.mirror_keys)
        points = {}
        for key in self.point_keys:
            points[key] = np.asarray(values.atPoint3(key), dtype=float)
            state[key] = points[key].tobytes()
        cost = np.zeros(len(self._keys))
        weights = []
        for group, members in zip(self.groups, self._members):
            z, dz, dzB = group.model(poses, vectors, plane_jacobians, jacobians, group.points(points))
            residual = (z - group.observed) / group.sigmas  # (b, 2, N) whitened, h - z
            if group.robust is None:
                lin = residual
                view_cost = np.einsum("bkn,bkn->b", residual, residual)
                scale = None
            else:
                norms = np.linalg.norm(residual, axis=1)
                sqrt_w, loss_scale = robust_row_scales(group.robust, norms.reshape(-1), group.robust_k)
                sqrt_w, loss_scale = sqrt_w.reshape(norms.shape), loss_scale.reshape(norms.shape)
                view_cost = np.einsum("bn,bn->b", norms * loss_scale, norms * loss_scale)
                lin = residual * sqrt_w[:, None]
                scale = sqrt_w
            cost += np.bincount(self._stack_of_view[members], view_cost, minlength=len(cost))
            if jacobians:
                weights += _products(group, lin, dz, dzB, scale)
        self._cost = cost
        self._state, self._valid, self._linearized = state, True, jacobians
        if not jacobians:
            return
        normal = np.bincount(self._indices, np.concatenate(weights), minlength=self._size)
        systems = []
        with one_blas_thread():
            for base, width, keys in zip(self._offsets, self._widths, self._keys):
                R = _rows_of(normal[base:base + (width + 1) ** 2].reshape(width + 1, width + 1))
                blocks, at = [], 0
                for key in keys:
                    dim = 6 if key in self._pose_key_set else 3
                    blocks.append(np.asfortranarray(R[:, at:at + dim]))
                    at += dim
                systems.append((np.ascontiguousarray(R[:, width]), blocks))
        self._systems = systems

    def _error_function(self, s: int):
        width = self._widths[s]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            if not self._matches(s, values) or (H is not None and not self._linearized):
                self._compute(values, H is not None)
            return compressed_rows(self._cost[s], width, None if H is None else self._systems[s], H)

        return error


def compressed_rows(cost: float, width: int, system: tuple | None, H: list[np.ndarray] | None) -> np.ndarray:
    """A compressed factor's answer to GTSAM: without Jacobians, ``width + 1`` rows whose squared norm is the
    factor's ``cost`` (its error); with them, the compressed right-hand side, its blocks put in ``H``."""
    if H is None:
        out = np.zeros(width + 1)
        out[-1] = np.sqrt(cost)
        return out
    assert system is not None
    rhs, blocks = system
    H.clear()
    H.extend(blocks)
    return rhs


def _products(group: _Group, e: np.ndarray, dz: np.ndarray, dzB: np.ndarray, scale: np.ndarray | None) -> list:
    """Group's products for the normal equations in :meth:`ViewPointStack._scatter`'s order, from the
    whitened residuals ``e`` (b, 2, N) and the model's ``dz`` (b, 2, P, N), ``dzB`` (b, 2, 3, N)."""
    w = 1.0 / group.sigmas if scale is None else scale[:, None] / group.sigmas  # (b, 2, N)
    A = dz * w[:, :, None, :]
    AA = np.einsum("bkpn,bkqn->bpq", A, A)
    Ae = np.einsum("bkpn,bkn->bp", A, e)
    ee = np.einsum("bkn,bkn->b", e, e)
    out = [AA.ravel(), Ae.ravel(), Ae.ravel(), ee]
    where = group.landmarks >= 0
    if where.any():
        L = (dzB * w[:, :, None, :]).transpose(0, 3, 1, 2)[where]  # (m, 2, 3)
        Am = A.transpose(0, 3, 1, 2)[where]  # (m, 2, P)
        em = e.transpose(0, 2, 1)[where]  # (m, 2)
        AL = row_products(Am, L)  # (m, P, 3)
        Le = np.einsum("mk,mkq->mq", em, L)
        out += [AL.ravel(), AL.ravel(), row_products(L, L).ravel(), Le.ravel(), Le.ravel()]
    return out


def _rows_of(normal: np.ndarray) -> np.ndarray:
    """``[R | r]`` (d+1, d+1), Fortran-ordered, with ``[R | r]^T [R | r]`` the augmented normal matrix
    ``[J | e]^T [J | e]`` (positive semidefinite): its Cholesky factor where it is positive definite, else
    ``sqrt(L) V^T`` of its eigendecomposition (negative rounding clipped): exact either way, without
    ``schur.compressed_normal``'s shift."""
    try:
        lower = np.linalg.cholesky(normal)
    except np.linalg.LinAlgError:
        lower = None
    if lower is not None and np.all(np.isfinite(lower)):
        return np.asfortranarray(lower.T)
    eigenvalues, V = np.linalg.eigh(normal)
    return np.asfortranarray(np.sqrt(np.clip(eigenvalues, 0.0, None))[:, None] * V.T)
