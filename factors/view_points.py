"""Views that see reconstruction points, evaluated together (``view_stack.py``'s groups) and linearised as
their normal equations compressed to ``d + 1`` rows (Hesch et al., eqs. 2, 3, 9, 19-20, 23; the model of
``views.py``).

Why: a view that sees reconstruction points has a Jacobian block per point, and every image sees the
same points: one ``ViewFactor`` per image (a Python call per image, each copying the whole ``Values``)
hands GTSAM an image's rows over the camera pose, its placements and every point, and the points' dense
separator then takes every image's rows (24,600 rows x 195 columns for 200 images of 63 points).
Here, as the paper's tree factors do (``tests/reference/eliminated.py``, ``schur.py``):

* views are grouped by shape and stacked by the set of placements they see (``view_stack.py``), a few
  consecutive sets into one stack (at most :data:`PLACEMENTS_PER_FACTOR` placements) over the camera
  poses, its placements and the points its views see;
* the first factor called at new values evaluates every group (``view_stack._Group.model`` with the
  points at those values) and, when linearising, sums each stack's normal equations
  ``[J | e]^T [J | e]`` from the views' compact blocks (a view's pose and placement columns, each
  measurement's own point: never the factor's dense width);
* a stack's own placements (seen by its views only: the paper's last mirror, a photograph's own) get a
  factor of their own rows ``[R_o | R_c]`` (``R_o^T R_o`` their block, ``R_o^T R_c`` their coupling with the
  rest and ``e``: :func:`_own_rows`), and the rest's Schur complement ``N_rest - R_c^T R_c`` of every stack
  is summed into one shared factor (stacks merged while no wider than the widest stack), compressed to
  ``d + 1`` rows ``[R | r]`` (:func:`_rows_of`): the same ``J^T J``, ``J^T e`` and ``||e||^2`` as the
  views' rows, hence the same Levenberg-Marquardt steps, marginals and cost as one ``ViewFactor`` per
  image. GTSAM then eliminates each stack's own placements from a few rows, and the shared unknowns
  (the poses, the placements several stacks see, the points) from one dense factor, as from the tree's
  factors (``tests/reference/eliminated.py``; one 283 x 282 factor per stack before: 60-80 ms per damped solve of 200
  images and 60 points, 30-40 ms now, the tree's 10 ms: its own placements are not GTSAM's unknowns;
  ``view_points_eliminated.py`` eliminates them inside the factors, as the tree does). Every factor is exact: LAPACK's Cholesky factorisation with complete
  pivoting (``dpstrf``), where a stack alone leaves some unknowns free (a point seen along one ray) too,
  without ``schur.compressed_normal``'s shift, which would move the marginals by 1e-6;
* the other factors check that their own variables are bit for bit those of the batch (a stale result is
  never returned). Not thread-safe (GTSAM calls Python factors one at a time).

Each view's whitening and robust kernel are its ``ViewFactor``'s (per measurement: the square-root
weight in the linear system, the loss where only the cost is asked). ``tests/test_view_points.py``
checks cost, ``J^T J`` and ``J^T e`` against the per-view factors, and whole calibrations;
``tests/test_view_points_rows.py`` the exact factors and the split's steps and marginals.
"""
from __future__ import annotations

from collections import Counter
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
    ``factors``: the ``gtsam.CustomFactor`` objects (hand them to a graph): each stack's own placements'
    rows, then the shared rows of one or a few groups of stacks."""

    def __init__(self, view_factors: Sequence[ViewFactor], placements_per_factor: int = PLACEMENTS_PER_FACTOR):
        self.fixed, self.pose_keys, self.mirror_keys = collected_keys(view_factors)
        self.point_keys = list(dict.fromkeys(k for f in view_factors for k in f.unique_landmarks))
        self._pose_key_set, self._plane_key_set = set(self.pose_keys.values()), set(self.mirror_keys.values())
        stack_of_view = np.zeros(len(view_factors), dtype=np.intp)
        self._stack_keys: list[list[int]] = []
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
                width += self._dim(key)
            self._stack_keys.append(keys)
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
        row = {key: j for j, key in enumerate(self.point_keys)}  # each point's row in the points' array
        self._seen = [group.landmarks >= 0 for group in self.groups]
        self._point_rows = [np.array([row[int(k)] for k in group.landmarks[where]], dtype=np.intp)
                            for group, where in zip(self.groups, self._seen)]
        self._split_stacks(view_factors)
        self.factors = [gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows), keys, self._error_function(f))
                        for f, (keys, rows) in enumerate(zip(self._keys, self._rows))]
        self._valid = False
        self._linearized = False
        self._state: dict[int, bytes] = {}
        self._cost = np.zeros(len(self._keys))
        self._systems: list[tuple[np.ndarray, list[np.ndarray]]] = []
        self.batches = 0

    def _dim(self, key: int) -> int:
        return 6 if key in self._pose_key_set else 3

    #: Whether the own placements' rows are factors of the graph (else kept: ``view_points_eliminated.py``).
    _own_factors = True

    def _is_own(self, key: int, seen: Counter) -> bool:
        """Whether ``key`` is an own placement of its stack (``seen``: stacks that see each placement)."""
        return key in self._plane_key_set and seen[key] == 1

    def _read(self, values: gtsam.Values) -> tuple[dict, dict, dict, dict[int, bytes]]:
        """``view_stack.read_poses_and_planes`` of the stack's poses and placements in ``values``."""
        return read_poses_and_planes(values, self.fixed, self.pose_keys, self.mirror_keys)

    def _split_stacks(self, view_factors: Sequence[ViewFactor]) -> None:
        """Each stack's own placements (seen by its views only, the paper's last mirror) and the rest: one
        factor of the own placements' rows per stack that has both, and the rest's Schur complements summed
        into shared factors, stacks merged while no wider than the widest stack (module docstring)."""
        seen = Counter(k for keys in self._stack_keys for k in keys if k in self._plane_key_set)
        self._rest_keys: list[list[int]] = []  # per stack: the keys of its rest columns
        self._own: list[np.ndarray] = []  # per stack: its own placements' columns
        self._rest: list[np.ndarray] = []  # the other columns and e (last)
        self._keys: list[list[int]] = []  # per factor: its keys
        self._rows: list[int] = []  # per factor: its rows
        self._own_factor: list[int] = []  # per stack: its factor of own rows (-1: none)
        rest_keys = []
        for keys, columns, width in zip(self._stack_keys, self._columns, self._widths):
            own = [k for k in keys if self._is_own(k, seen)]
            rest = [k for k in keys if k not in own]
            if not rest:  # nothing shared: the stack is a factor of its own
                own, rest = [], keys
            self._own.append(np.array([columns[k] + c for k in own for c in range(3)], dtype=np.intp))
            self._rest.append(np.array([columns[k] + c for k in rest for c in range(self._dim(k))] + [width],
                                       dtype=np.intp))
            if own and self._own_factors:
                self._own_factor.append(len(self._keys))
                self._keys.append(own + rest)
                self._rows.append(3 * len(own))
            else:
                self._own_factor.append(-1)
            rest_keys.append(rest)
            self._rest_keys.append(rest)
        limit = max(self._widths, default=0)
        merged: list[tuple[list[int], list[int]]] = []  # (stacks, keys) of each shared factor
        for s, rest in enumerate(rest_keys):
            if merged:
                union = list(dict.fromkeys(merged[-1][1] + rest))
                if sum(map(self._dim, union)) <= limit:
                    merged[-1] = (merged[-1][0] + [s], union)
                    continue
            merged.append(([s], list(rest)))
        kind = {**{k: 0 for k in self._pose_key_set}, **{k: 1 for k in self._plane_key_set}}
        self._shared_factor = np.zeros(len(self._stack_keys), dtype=np.intp)  # per stack: its shared factor
        self._positions: list[np.ndarray] = [np.zeros(0, dtype=np.intp)] * len(self._stack_keys)
        self._shared_widths: list[int] = []
        for stacks, union in merged:
            union.sort(key=lambda k: kind.get(k, 2))  # poses, placements, points
            at, width = {}, 0
            for key in union:
                at[key] = width
                width += self._dim(key)
            for s in stacks:
                self._shared_factor[s] = len(self._shared_widths)
                self._positions[s] = np.array([at[k] + c for k in rest_keys[s] for c in range(self._dim(k))] + [width],
                                              dtype=np.intp)
            self._shared_widths.append(width)
            self._keys.append(union)
            self._rows.append(width + 1)
        self._first_shared = len(self._keys) - len(merged)
        # each stack's blocks as indices into the normal buffer (its upper triangle: min, max of the columns)
        self._take_rest, self._take_own, self._take_cross, self._put = [], [], [], []
        for s, (base, width) in enumerate(zip(self._offsets, self._widths)):
            own_columns, rest_columns = self._own[s], self._rest[s]
            self._take_rest.append(_upper(base, width, rest_columns, rest_columns))
            self._take_own.append(_upper(base, width, own_columns, own_columns))
            self._take_cross.append(_upper(base, width, own_columns, rest_columns))
            position = self._positions[s]
            self._put.append(position[:, None] * (self._shared_widths[self._shared_factor[s]] + 1) + position[None, :])
        # stacks whose own placements share no view: their own block is 3 x 3 blocks on its diagonal
        own_keys = [set(keys) - set(self._keys[self._first_shared + g]) for keys, g in
                    zip(self._stack_keys, self._shared_factor)]
        self._diagonal = [True] * len(self._stack_keys)
        for i, view in enumerate(view_factors):
            s = int(self._stack_of_view[i])
            if sum(k in own_keys[s] for k in view.mirror_keys.values()) > 1:
                self._diagonal[s] = False
        # a stack's cost: its own rows' factor's error, else its shared factor's (their sum is the graph's)
        self._cost_factor = np.array([f if f >= 0 else self._first_shared + g
                                      for f, g in zip(self._own_factor, self._shared_factor)], dtype=np.intp)

    # --- layout -----------------------------------------------------------------------------------

    def _scatter(self, g: int, view_factors: Sequence[ViewFactor]) -> np.ndarray:
        """Group ``g``'s entries of the normal-equation buffer, in the order :func:`_products` gives them:
        ``A^T A`` (b, P, P), ``A^T e`` (b, P), ``e^T e`` (b,), then per point measurement ``A^T L`` (m, P, 3),
        ``L^T L`` (m, 3, 3), ``L^T e`` (m, 3). The upper triangle only where a block's transpose is below the
        diagonal (a point's columns follow the poses' and placements', ``e`` is last): :meth:`_compute`
        reads its mirror image (40% fewer entries to sum)."""
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
            (base + d * stride + d).ravel(),
        ]
        where = group.landmarks >= 0
        lcol = np.array(point_columns, dtype=np.intp).reshape(where.shape)[where][:, None] + np.arange(3)  # (m, 3)
        view_of = np.broadcast_to(np.arange(len(members))[:, None], where.shape)[where]
        cm, dm, bm = colmap[view_of], d[view_of], base[view_of]  # (m, P), (m, 1), (m, 1)
        sm = dm + 1
        parts += [
            (bm[:, :, None] + cm[:, :, None] * sm[:, :, None] + lcol[:, None, :]).ravel(),
            (bm[:, :, None] + lcol[:, :, None] * sm[:, :, None] + lcol[:, None, :]).ravel(),
            (bm + lcol * sm + dm).ravel(),
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
        poses, vectors, plane_jacobians, state = self._read(values)
        points = np.zeros((len(self.point_keys), 3))
        for j, key in enumerate(self.point_keys):
            points[j] = values.atPoint3(key)
            state[key] = points[j].tobytes()
        stack_cost = np.zeros(len(self._stack_keys))
        weights = []
        for group, members, seen, rows in zip(self.groups, self._members, self._seen, self._point_rows):
            base = group.base.transpose(0, 2, 1).copy()  # (b, N, 3): as _Group.points, one gather
            base[seen] = points[rows]
            z, dz, dzB = group.model(poses, vectors, plane_jacobians, jacobians, base.transpose(0, 2, 1))
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
            stack_cost += np.bincount(self._stack_of_view[members], view_cost, minlength=len(stack_cost))
            if jacobians:
                weights += _products(group, lin, dz, dzB, scale)
        self._cost = np.bincount(self._cost_factor, stack_cost, minlength=len(self._keys)).astype(float)
        self._state, self._valid, self._linearized = state, True, jacobians
        if not jacobians:
            return
        normal = np.bincount(self._indices, np.concatenate(weights), minlength=self._size)
        systems: list = [None] * len(self._keys)
        self._own_rows_of: dict[int, np.ndarray] = {}  # per stack with own placements: their rows
        shared = [np.zeros((w + 1, w + 1)) for w in self._shared_widths]
        with one_blas_thread():
            for s in range(len(self._stack_keys)):
                N_rest = normal[self._take_rest[s]]  # (the buffer holds its upper triangle)
                o = len(self._own[s])
                if o:  # eq. (23)'s rows of the own placements, and the rest's Schur complement
                    N_own, N_cross = normal[self._take_own[s]], normal[self._take_cross[s]]
                    diagonal = _diagonal_own_rows(N_own, N_cross) if self._diagonal[s] else None
                    rows = diagonal if diagonal is not None else _own_rows(N_own, N_cross)
                    N_rest -= rows[:, o:].T @ rows[:, o:]
                    self._own_rows_of[s] = rows
                    if self._own_factor[s] >= 0:
                        systems[self._own_factor[s]] = _split(rows, self._keys[self._own_factor[s]], self._dim)
                shared[self._shared_factor[s]].reshape(-1)[self._put[s]] += N_rest
            for g, matrix in enumerate(shared):
                f = self._first_shared + g
                systems[f] = _split(_rows_of(matrix), self._keys[f], self._dim)
        self._systems = systems

    def _error_function(self, f: int):
        rows = self._rows[f]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            if not self._matches(f, values) or (H is not None and not self._linearized):
                self._compute(values, H is not None)
            return compressed_rows(self._cost[f], rows - 1, None if H is None else self._systems[f], H)

        return error


def _split(rows: np.ndarray, keys: list[int], dim) -> tuple[np.ndarray, list[np.ndarray]]:
    """A factor's answer from its rows ``[R | r]``: ``r`` and ``R``'s block of each key, in ``keys``' order."""
    blocks, at = [], 0
    for key in keys:
        d = dim(key)
        blocks.append(np.asfortranarray(rows[:, at:at + d]))
        at += d
    return np.ascontiguousarray(rows[:, at]), blocks


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
    At = A.transpose(0, 2, 1, 3).reshape(len(A), A.shape[2], A.shape[1] * A.shape[3])  # (b, P, 2N); P may be 0
    AA = At @ At.transpose(0, 2, 1)  # (batched matmul: twice einsum's speed here)
    Ae = np.einsum("bkpn,bkn->bp", A, e)
    ee = np.einsum("bkn,bkn->b", e, e)
    out = [AA.ravel(), Ae.ravel(), ee]
    where = group.landmarks >= 0
    if where.any():
        L = (dzB * w[:, :, None, :]).transpose(0, 3, 1, 2)[where]  # (m, 2, 3)
        Am = A.transpose(0, 3, 1, 2)[where]  # (m, 2, P)
        em = e.transpose(0, 2, 1)[where]  # (m, 2)
        AL = Am.transpose(0, 2, 1) @ L  # (m, P, 3): batched matmul, 3x row_products' speed here
        Le = np.einsum("mk,mkq->mq", em, L)
        out += [AL.ravel(), row_products(L, L).ravel(), Le.ravel()]
    return out


def _pivoted(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """LAPACK's Cholesky factorisation with complete pivoting of a positive semidefinite ``normal``:
    ``(U, piv, rank)`` with ``normal[piv][:, piv] = U[:rank]^T U[:rank]`` to rounding (the pivots below
    ``n eps max(diag)`` are the rounding of a singular matrix's zeros, left out)."""
    from scipy.linalg.lapack import dpstrf  # here: importing calibrate loads no scipy (start-up time)

    U, piv, rank, info = dpstrf(normal, lower=0)
    if info < 0:
        raise ValueError(f"dpstrf: argument {-info} invalid")
    return np.triu(U[:rank]), piv - 1, int(rank)


def _rows_of(normal: np.ndarray) -> np.ndarray:
    """``[R | r]`` (d+1, d+1), Fortran-ordered, with ``[R | r]^T [R | r]`` the augmented normal matrix
    ``[J | e]^T [J | e]`` (positive semidefinite): its pivoted Cholesky factor (:func:`_pivoted`), the
    rows past its rank zero: exact where a factor alone leaves some unknowns free (a point seen along one
    ray), without ``schur.compressed_normal``'s shift. Not finite: NaN rows."""
    n = len(normal)
    R = np.zeros((n, n), order="F")
    if not np.all(np.isfinite(normal)):
        R[:] = np.nan
        return R
    if n <= SMALL_EIGEN:  # a few photographs' factor: numpy's eigendecomposition, exact too (no scipy to load)
        eigenvalues, V = np.linalg.eigh(normal, UPLO="U")  # (the buffer fills the upper triangle)
        # eigenvalues below n eps of the largest are a singular matrix's zeros in rounding (as _pivoted drops)
        eigenvalues[eigenvalues <= n * np.finfo(float).eps * max(float(eigenvalues[-1]), 0.0)] = 0.0
        R[:] = np.sqrt(eigenvalues)[:, None] * V.T  # R^T R = V L V^T
        return R
    U, piv, rank = _pivoted(normal)
    R[:rank, piv] = U
    return R


#: Up to this size a stack's rows come from numpy's eigendecomposition instead of LAPACK's pivoted Cholesky
#: (scipy's): as exact, about as fast at this size, and a small capture's command loads no scipy (0.14 s).
SMALL_EIGEN = 64


def _upper(base: int, width: int, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Indices into the normal buffer of the block ``(rows, columns)`` of a stack's augmented matrix
    (``width + 1`` square from ``base``), each entry read from the upper triangle."""
    low, high = np.minimum.outer(rows, columns), np.maximum.outer(rows, columns)
    return (base + low * (width + 1) + high).astype(np.intp)


def _diagonal_own_rows(N_own: np.ndarray, N_cross: np.ndarray) -> np.ndarray | None:
    """:func:`_own_rows` where ``N_own`` is 3 x 3 blocks on its diagonal (no view sees two of the own
    placements): each block's Cholesky factor ``L`` (``R_o`` block ``L^T``, ``R_c`` rows ``L^-1 C``), all
    at once; None where a block is not positive definite (then :func:`_own_rows`)."""
    E = len(N_own) // 3
    at = np.arange(E)
    D = N_own.reshape(E, 3, E, 3)[at, :, at, :]  # (E, 3, 3)
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(N_cross))):
        return None
    try:
        lower = np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        return None
    rows = np.zeros((3 * E, 3 * E + N_cross.shape[1]), order="F")
    first = 3 * at[:, None, None]
    rows[first + np.arange(3)[None, :, None], first + np.arange(3)[None, None, :]] = lower.transpose(0, 2, 1)
    a, b, c, d, e, f = (lower[:, i, j] for i, j in ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2)))
    inverse = np.zeros((E, 3, 3))  # L^-1 of each block in closed form (a batched solve costs 10x more)
    inverse[:, 0, 0], inverse[:, 1, 1], inverse[:, 2, 2] = 1.0 / a, 1.0 / c, 1.0 / f
    inverse[:, 1, 0] = -b / (a * c)
    inverse[:, 2, 1] = -e / (c * f)
    inverse[:, 2, 0] = (b * e - c * d) / (a * c * f)
    rows[:, 3 * E:] = (inverse @ N_cross.reshape(E, 3, -1)).reshape(3 * E, -1)
    return rows


def _own_rows(N_own: np.ndarray, N_cross: np.ndarray) -> np.ndarray:
    """The rows ``[R_o | R_c]`` (o, o + c) of a stack's own placements (``o`` columns) over them and the rest
    (``c`` columns, ``e`` last): ``R_o^T R_o = N_own``, ``R_o^T R_c = N_cross``, so that with the rest's rows
    ``N_rest - R_c^T R_c`` (its Schur complement) the stack's augmented normal matrix is whole. Pivoted
    (:func:`_pivoted`): rows past ``N_own``'s rank are zero (a placement its views leave partly free)."""
    o = len(N_own)
    rows = np.zeros((o, o + N_cross.shape[1]), order="F")  # (its blocks of columns: Fortran-ordered views)
    if not (np.all(np.isfinite(N_own)) and np.all(np.isfinite(N_cross))):
        rows[:] = np.nan
        return rows
    from scipy.linalg import solve_triangular  # here: importing calibrate loads no scipy (start-up time)

    U, piv, rank = _pivoted(N_own)
    rows[:rank, piv] = U
    rows[:rank, o:] = solve_triangular(U[:, :rank], N_cross[piv[:rank]], trans="T")
    return rows
