"""The image-level dispersion (``dispersion.py``) of a view problem, every view linearised in one vectorised
pass of the view model (``factors/view_stack.py``'s groups, Hesch et al. eqs. 2, 3, 9) instead of one
GTSAM factor per view: the same ``B`` and ``nu`` to rounding as the dense route and the route through
GTSAM's marginals (``tests/test_view_dispersion.py``).

Frames and units as ``dispersion.py``: each camera pose in GTSAM's Pose3 tangent ``[w, nu]`` (``R Exp(w)``,
``t + R nu``), each placement in its plane's local coordinates (``views.vector_of_plane``), a
reconstruction point in the base frame (metres); rows in normalized image coordinates whitened by their
sigma. ``B`` and ``nu`` do not depend on the unknowns' coordinates (a projection onto each view's column
space, a trace ``tr(Sigma G_i)`` with ``Sigma`` in the same columns), but the information's conditioning
does, hence the view model's own coordinates.

``Sigma`` on a view's columns, as ``dispersion._explained``: the unknowns only this view sees (the last
mirror's placement, a point only it sees) are eliminated from its own information (Schur complement); the
shared ones (the poses, placements several cameras see in one photograph, the first mirrors' placements,
the points) are inverted after every view's elimination. Their information is an arrow: the camera poses
couple with everything, the other shared unknowns only with those a view sees with them. Where it is
large, the other shared unknowns are split into *clusters* (connected through the views that see them
together, poses aside), each cluster eliminated onto the poses and ``Sigma`` built back block by block
(``Sigma_cc = H_cc^-1 + K_c S K_c^T``, ``Sigma_cP = -K_c S``, ``S`` the poses' covariance): a rig's
photographs' placements are hundreds of small clusters, where one dense inverse would be cubic in all of
them. Views of one shape (as many measurements, the same point pattern, the same unknowns seen by
others) are stacked and every step runs over the stack; a reconstruction point's columns meet only its own
measurements' rows, so the information and ``U_i^T J_i`` are summed block by block.

Applies (:func:`view_dispersion_applies`) where every view is a plain Gaussian factor on poses,
placements and points: intrinsics known, no robust kernel, no prior (the scale's) and every measurement
of a counted view used; ``dispersion.py`` otherwise linearises GTSAM's factors.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mirror_fg.factors.view_table import unique_rows
from mirror_fg.factors.views import vectors_of_planes

__all__ = ["CHUNK_ENTRIES", "CLUSTERED_FROM", "view_dispersion", "view_dispersion_applies"]

#: Views are stacked so that their information matrices hold at most this many entries together (8 MB):
#: with many points each view's is dense over all of them (the Schur complement of its own placement
#: couples them), and stacks of hundreds of such matrices cost more in memory traffic than in arithmetic.
CHUNK_ENTRIES = 2**20
#: From this many shared columns, the shared unknowns other than the poses are inverted cluster by cluster
#: (module docstring) rather than in one dense inverse.
CLUSTERED_FROM = 300


def view_dispersion_applies(problem) -> bool:
    """Whether :func:`view_dispersion` computes ``problem``'s dispersion (module docstring; the caller
    vouches that every measurement of its views was used)."""
    from mirror_fg.solver.model.views import scale_prior

    return (not problem.intrinsics and problem.robust is None and problem.table.count > 0
            and scale_prior(problem.dataset, problem.mirror_keys, problem.point_keys).size() == 0)


def view_dispersion(problem, estimate, max_images: int, max_columns: int) -> tuple[float, float, int] | None:
    """``(B, nu, views counted)`` (``dispersion.py``'s module docstring) of the view ``problem``
    (:func:`view_dispersion_applies`) at ``estimate`` (a ``ViewEstimate``), over ``max_images`` views evenly
    spread where there are more (``dispersion.MAX_IMAGES``); None where the shared unknowns need a dense
    inverse of more than ``max_columns`` columns (``dispersion.py`` then asks GTSAM's marginals)."""
    linear = _Linearised(problem, estimate)
    count = problem.table.count
    seen = np.concatenate([keys.reshape(-1) for keys in linear.keys])
    touches = np.bincount(seen[seen >= 0], minlength=len(linear.dims))
    shared_unknowns = np.flatnonzero(touches > 1)
    where = np.full(len(touches), -1)  # each shared unknown's first column among the shared ones
    widths = linear.dims[shared_unknowns]
    where[shared_unknowns] = np.concatenate([[0], np.cumsum(widths)[:-1]]).astype(int) if len(widths) else []
    size = int(widths.sum())
    layout = _Layout(size, *_clusters(linear, touches, where)) if size >= CLUSTERED_FROM else _Layout(size)
    if layout.largest > max_columns:
        return None
    chosen = np.zeros(count, dtype=bool)
    chosen[np.unique(np.linspace(0, count - 1, min(max_images, count)).round().astype(int))] = True
    information = np.zeros(layout.entries)  # the shared columns' information, summed over the views
    stacks = []
    for J, J_point, r, keys, members, slots in zip(linear.J, linear.J_point, linear.r, linear.keys, linear.members,
                                                   linear.slots):
        seen_by_others = np.where(keys >= 0, touches[np.maximum(keys, 0)] > 1, False)
        firsts, which = unique_rows(np.concatenate([slots, keys >= 0, seen_by_others], axis=1).astype(np.intp))
        for k in range(len(firsts)):
            rows = np.flatnonzero(which == k)
            slot = slots[rows[0]]
            unknowns = int(np.sum(keys[rows[0]] >= 0))  # (a view's points last, padding after them)
            shared = seen_by_others[rows[0], :unknowns]
            dims = linear.dims[keys[rows[0], :unknowns]]
            width = J.shape[3] + 3 * (int(slot.max()) + 1 if len(slot) else 0)
            step = max(1, CHUNK_ENTRIES // width**2)
            for start in range(0, len(rows), step):
                part = rows[start:start + step]
                blocks = _Blocks(J[part], J_point[part], slot)
                column_shared = np.repeat(shared, dims)
                s_cols, l_cols = np.flatnonzero(column_shared), np.flatnonzero(~column_shared)
                s_keys = keys[part, :unknowns][:, shared]
                s_at = (np.concatenate([where[s_keys[:, u]][:, None] + np.arange(d)[None]
                                        for u, d in enumerate(dims[shared])], axis=1)
                        if shared.any() else np.zeros((len(part), 0), dtype=int))
                H = blocks.information()
                H_ss = H[:, s_cols[:, None], s_cols[None]]
                if len(l_cols):
                    H_ll_inv = np.linalg.pinv(H[:, l_cols[:, None], l_cols[None]], hermitian=True)
                    K = np.matmul(H_ll_inv, H[:, l_cols[:, None], s_cols[None]])  # H_ll^-1 H_ls
                    H_ss = H_ss - np.matmul(H[:, s_cols[:, None], l_cols[None]], K)  # what only this view sees, eliminated
                else:
                    H_ll_inv, K = np.zeros((len(part), 0, 0)), np.zeros((len(part), 0, len(s_cols)))
                code = layout.code(s_at[:, :, None], s_at[:, None, :]).reshape(-1)
                kept = code >= 0
                information += np.bincount(code[kept], weights=H_ss.reshape(-1)[kept], minlength=layout.entries)
                pick = chosen[members[part]]
                if pick.any():
                    stacks.append((blocks.subset(pick), r[part][pick].reshape(int(pick.sum()), -1), s_at[pick],
                                   s_cols, l_cols, H_ll_inv[pick], K[pick]))
    Sigma_shared = layout.covariance(information)
    cost, rank_sum, explained, views = 0.0, 0, 0.0, 0
    for blocks, e, s_at, s_cols, l_cols, H_ll_inv, K in stacks:
        U, s, _ = np.linalg.svd(blocks.own, full_matrices=False)  # the view's own columns: poses, placements
        rank = np.sum(s > np.maximum(s[:, :1], 1e-300) * 1e-10, axis=1)  # as dispersion._range
        U = U * (np.arange(U.shape[2])[None] < rank[:, None])[:, None, :]  # beyond the rank: zero columns
        W = blocks.projected(U)  # U_i^T J_i
        # tr(Sigma G_i) with Sigma_ll = H_ll^-1 + K S K^T, Sigma_ls = -K S (S: the shared block) is
        # |W_l H_ll^-1/2|^2 + |(W_s - W_l K) S^1/2|^2: two positive terms
        S = Sigma_shared.at(s_at[:, :, None], s_at[:, None, :])
        W_s, W_l = W[:, :, s_cols], W[:, :, l_cols]
        D = W_s - np.matmul(W_l, K)
        explained += float(np.sum(np.matmul(D, S) * D)) + float(np.sum(np.matmul(W_l, H_ll_inv) * W_l))
        rank_sum += int(rank.sum())
        cost += float(np.sum(np.matmul(U.transpose(0, 2, 1), e[:, :, None]) ** 2))
        views += len(e)
    return cost, max(rank_sum - explained, 0.0), views


class _Linearised:
    """Every view of a problem linearised, a list entry per group of one shape (``ViewTable.groups``):
    whitened Jacobians ``J`` (b, N, 2, P) on the view's own columns (its poses, then its placements, as
    ``ViewFactor.slots``), ``J_point`` (b, N, 2, 3) on each measurement's point (zero for a fiducial),
    whitened residuals ``r`` (b, N, 2), the unknowns ``keys`` (b, u) each view sees (indices into ``dims``:
    poses, placements, then its points in order of slot; -1 after a view's last point, where the group's
    views see fewer), the views' positions ``members`` (b,) and each measurement's point ``slots`` (b, N; -1
    a fiducial). ``first_placement``: the index of the first placement in ``dims`` (the poses before)."""

    def __init__(self, problem, estimate):
        table = problem.table
        cameras = list(problem.pose_keys)
        placements = table.placements
        point_index = {key: j for j, key in enumerate(problem.point_keys.values())}
        first_placement, first_point = len(cameras), len(cameras) + len(placements)
        self.dims = np.array([6] * len(cameras) + [3] * (len(placements) + len(point_index)), dtype=int)
        self.first_placement = first_placement
        poses = dict(problem.fixed)
        poses.update({name: estimate.poses[name] for name in cameras})
        vectors = np.array([estimate.mirror_vectors[p] for p in placements], dtype=float).reshape(-1, 3)
        d = np.linalg.norm(vectors, axis=1)
        normals = vectors / d[:, None]
        normals /= np.linalg.norm(normals, axis=1)[:, None]  # as the plane variable's Unit3 (views.plane_of)
        V, JV = vectors_of_planes(np.column_stack([normals, d]))
        row_of = {p: k for k, p in enumerate(placements)}
        point_values = {key: np.asarray(estimate.points[name], dtype=float) for name, key in problem.point_keys.items()}
        self.J, self.J_point, self.r, self.keys, self.members, self.slots = [], [], [], [], [], []
        for template, members, parts in table.groups():
            group = table.group_of(template, parts)
            at = group.placement_index(row_of)  # (b, U)
            z, dz, dzB = group.model(poses, {}, {}, True, base=group.points(point_values), arrays=(V[at], JV[at]))
            whiten = 1.0 / group.sigmas  # (b, 2, N)
            self.r.append(((z - group.observed) * whiten).transpose(0, 2, 1))
            self.J.append((dz * whiten[:, :, None, :]).transpose(0, 3, 1, 2))
            self.J_point.append((dzB * whiten[:, :, None, :]).transpose(0, 3, 1, 2)
                                * (group.landmarks >= 0)[:, :, None, None])
            pose_order = sorted(group.pose_cols, key=group.pose_cols.get)
            pose_ids = np.broadcast_to(np.array([cameras.index(name) for name in pose_order], dtype=int),
                                       (len(members), len(pose_order)))
            slots, point_ids = _point_slots(group.landmarks, point_index)
            point_keys = np.where(point_ids >= 0, first_point + point_ids, -1)
            self.keys.append(np.concatenate([pose_ids, first_placement + at, point_keys], axis=1))
            self.members.append(members)
            self.slots.append(slots)


def _point_slots(landmarks: np.ndarray, point_index: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Each measurement's point slot (b, N: its point's place among the view's points in order first seen,
    -1 a fiducial) and each view's points (b, K; -1 after its last) as indices into the problem's points, from
    the group's
    point keys ``landmarks`` (b, N; -1 a fiducial). A group's views share their points' pattern."""
    b, n = landmarks.shape
    if not (landmarks >= 0).any():
        return np.full((b, n), -1, dtype=np.intp), np.zeros((b, 0), dtype=int)
    slots = np.full((b, n), -1, dtype=np.intp)
    firsts, which = unique_rows(landmarks.astype(np.intp))
    width = max(len({int(k) for k in landmarks[f] if k >= 0}) for f in firsts.tolist())
    ids = np.full((b, width), -1, dtype=int)
    for k, f in enumerate(firsts.tolist()):
        own: dict[int, int] = {}
        slot = [own.setdefault(int(key), len(own)) if key >= 0 else -1 for key in landmarks[f].tolist()]
        rows = which == k
        slots[rows] = slot
        ids[rows, :len(own)] = [point_index[key] for key in own]
    return slots, ids


def _clusters(linear: _Linearised, touches: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The shared columns split (module docstring): the poses' columns (P,) and each cluster's columns, a
    cluster being the shared unknowns other than poses that views see together."""
    parent = np.arange(len(touches))

    def root(u: int) -> int:
        while parent[u] != u:
            parent[u] = parent[parent[u]]
            u = parent[u]
        return u

    first = linear.first_placement  # the poses come first
    for keys in linear.keys:
        shared = np.where((keys >= first) & (touches[np.maximum(keys, 0)] > 1), keys, -1)
        firsts, _ = unique_rows(np.sort(shared, axis=1))
        for row in shared[firsts].tolist():
            row = [u for u in row if u >= 0]
            for u in row[1:]:
                a, b = root(row[0]), root(u)
                if a != b:
                    parent[b] = a
    pose_columns = [where[u] + np.arange(6) for u in range(first) if touches[u] > 1]
    members: dict[int, list[int]] = {}
    for u in np.flatnonzero((touches > 1) & (np.arange(len(touches)) >= first)).tolist():
        members.setdefault(root(u), []).append(u)
    clusters = [np.concatenate([where[u] + np.arange(3) for u in group]) for group in members.values()]
    return np.concatenate(pose_columns).astype(int) if pose_columns else np.zeros(0, dtype=int), clusters


class _Layout:
    """Where each entry of the shared columns' information is summed: a dense ``size`` x ``size`` matrix,
    or with ``clusters`` (module docstring) the poses' block (P x P) and each cluster's rows (c x (c + P):
    its own columns, then the poses'), never a matrix over every shared column (a rig's thousands)."""

    def __init__(self, size: int, pose_columns: np.ndarray | None = None, clusters: Sequence[np.ndarray] = ()):
        self.size, self.clustered = size, pose_columns is not None
        if pose_columns is None:
            self.entries, self.largest = size * size, size
            return
        P = len(pose_columns)
        self.pose_columns, self.clusters = pose_columns, list(clusters)
        self.pose = np.full(size, -1)  # each column's place among the poses' columns
        self.pose[pose_columns] = np.arange(P)
        self.start = np.zeros(size, dtype=int)  # a cluster column's row: where it starts, its width
        self.width = np.zeros(size, dtype=int)
        self.place = np.zeros(size, dtype=int)  # its place in its cluster
        offset = P * P
        self.offsets = []
        for columns in self.clusters:
            c = len(columns)
            self.place[columns] = np.arange(c)
            self.width[columns] = c + P
            self.start[columns] = offset + np.arange(c) * (c + P)
            self.offsets.append(offset)
            offset += c * (c + P)
        self.entries = offset
        self.largest = P + max((len(c) for c in self.clusters), default=0)

    def code(self, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Where the entries at ``rows``, ``columns`` (broadcast together) are summed; -1 for the entries a
        cluster's rows hold already (a pose's row, a cluster's column: its symmetric entry)."""
        if not self.clustered:
            return rows * self.size + columns
        rows, columns = np.broadcast_arrays(rows, columns)
        pose_r, pose_c = self.pose[rows], self.pose[columns]
        in_cluster = pose_r < 0
        # a cluster's row: its cluster's columns first, then the poses' (its width less the poses': c)
        column_in_row = np.where(pose_c >= 0, self.width[rows] - len(self.pose_columns) + pose_c, self.place[columns])
        return np.where(in_cluster, self.start[rows] + column_in_row,
                        np.where(pose_c >= 0, pose_r * len(self.pose_columns) + pose_c, -1))

    def covariance(self, information: np.ndarray):
        """The shared columns' covariance from the information summed here."""
        if not self.clustered:
            H = information.reshape(self.size, self.size)
            return _DenseCovariance(np.linalg.pinv(0.5 * (H + H.T), hermitian=True))
        P = len(self.pose_columns)
        H_PP = information[:P * P].reshape(P, P)
        return _ClusteredCovariance(self, 0.5 * (H_PP + H_PP.T),
                                    [information[o:o + len(c) * (len(c) + P)].reshape(len(c), len(c) + P)
                                     for o, c in zip(self.offsets, self.clusters)])


class _DenseCovariance:
    """The shared columns' covariance, dense (few shared columns)."""

    def __init__(self, Sigma: np.ndarray):
        self.Sigma = Sigma

    def at(self, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """The covariance's entries at ``rows`` and ``columns`` (broadcast together)."""
        return self.Sigma[rows, columns]


class _ClusteredCovariance:
    """The shared columns' covariance on the blocks a view can need (the poses', each cluster's and a
    cluster's with the poses; never between two clusters, which no view sees together): each cluster
    eliminated onto the poses (Schur complement), the poses inverted, the clusters' blocks built back
    (module docstring). Clusters of one size are handled together."""

    def __init__(self, layout: _Layout, H_PP: np.ndarray, cluster_rows: list[np.ndarray]):
        self.layout = layout
        P = len(H_PP)
        S_P = H_PP.copy()
        self.group = np.full(layout.size, -1)  # each cluster column's group (of clusters of one size) ...
        self.cluster = np.zeros(layout.size, dtype=int)  # ... and the cluster's place in it
        by_size: dict[int, list[int]] = {}
        for k, columns in enumerate(layout.clusters):
            by_size.setdefault(len(columns), []).append(k)
        eliminated = []
        for g, ks in enumerate(by_size.values()):
            C = np.array([layout.clusters[k] for k in ks])  # (k, c)
            self.group[C], self.cluster[C] = g, np.arange(len(C))[:, None]
            rows = np.array([cluster_rows[k] for k in ks])  # (k, c, c + P)
            c = C.shape[1]
            H_cc = 0.5 * (rows[:, :, :c] + rows[:, :, :c].transpose(0, 2, 1))
            H_cP = rows[:, :, c:]
            H_cc_inv = np.linalg.pinv(H_cc, hermitian=True)
            K = np.matmul(H_cc_inv, H_cP)  # (k, c, P): H_cc^-1 H_cP
            S_P -= np.einsum("kcp,kcq->pq", H_cP, K)
            eliminated.append((H_cc_inv, K))
        self.Sigma_P = np.linalg.pinv(0.5 * (S_P + S_P.T), hermitian=True) if P else np.zeros((0, 0))
        self.blocks = []  # per group: Sigma_cc (k, c, c), Sigma_cP (k, c, P)
        for H_cc_inv, K in eliminated:
            KS = np.matmul(K, self.Sigma_P)
            self.blocks.append((H_cc_inv + np.matmul(KS, K.transpose(0, 2, 1)), -KS))

    def at(self, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """The covariance's entries at ``rows`` and ``columns`` (broadcast together; a view's columns)."""
        rows, columns = np.broadcast_arrays(rows, columns)
        out = np.zeros(rows.shape)
        pose, place = self.layout.pose, self.layout.place
        pose_r, pose_c = pose[rows], pose[columns]
        both = (pose_r >= 0) & (pose_c >= 0)
        out[both] = self.Sigma_P[pose_r[both], pose_c[both]]
        group_r, group_c = self.group[rows], self.group[columns]
        for g, (Sigma_cc, Sigma_cP) in enumerate(self.blocks):
            m = (group_r == g) & (group_c == g)
            out[m] = Sigma_cc[self.cluster[rows[m]], place[rows[m]], place[columns[m]]]
            m = (group_r == g) & (pose_c >= 0)
            out[m] = Sigma_cP[self.cluster[rows[m]], place[rows[m]], pose_c[m]]
            m = (pose_r >= 0) & (group_c == g)
            out[m] = Sigma_cP[self.cluster[columns[m]], place[columns[m]], pose_r[m]]
        return out


class _Blocks:
    """The whitened Jacobians of a stack of views of one shape: ``own`` (b, 2n, w) on the poses and the
    placements, and each point slot's (b, 2 m_k, 3) on its measurements' rows only."""

    def __init__(self, J: np.ndarray, J_point: np.ndarray, slot: np.ndarray):
        b, n = J.shape[:2]
        self.own = J.reshape(b, 2 * n, -1)
        self.rows = [np.flatnonzero(slot == k) for k in range(int(slot.max()) + 1 if len(slot) else 0)]
        self.by_slot = [J_point[:, rows].reshape(b, 2 * len(rows), 3) for rows in self.rows]
        self.own_by_slot = [J[:, rows].reshape(b, 2 * len(rows), -1) for rows in self.rows]
        self.width = self.own.shape[2] + 3 * len(self.rows)

    def subset(self, pick: np.ndarray) -> _Blocks:
        """The views ``pick`` (a mask over the stack) of this stack."""
        out = object.__new__(_Blocks)
        out.own, out.rows, out.width = self.own[pick], self.rows, self.width
        out.by_slot = [block[pick] for block in self.by_slot]
        out.own_by_slot = [block[pick] for block in self.own_by_slot]
        return out

    def information(self) -> np.ndarray:
        """``J_i^T J_i`` (b, w + 3 points, ...)."""
        b, w = len(self.own), self.own.shape[2]
        H = np.zeros((b, self.width, self.width))
        H[:, :w, :w] = np.matmul(self.own.transpose(0, 2, 1), self.own)
        for k, (point, own) in enumerate(zip(self.by_slot, self.own_by_slot)):
            c = w + 3 * k
            H[:, :w, c:c + 3] = np.matmul(own.transpose(0, 2, 1), point)
            H[:, c:c + 3, :w] = H[:, :w, c:c + 3].transpose(0, 2, 1)
            H[:, c:c + 3, c:c + 3] = np.matmul(point.transpose(0, 2, 1), point)
        return H

    def projected(self, U: np.ndarray) -> np.ndarray:
        """``U^T J_i`` (b, k, w + 3 points) of bases ``U`` (b, 2n, k) of rows."""
        b, _, k = U.shape
        w = self.own.shape[2]
        W = np.zeros((b, k, self.width))
        Ut = U.transpose(0, 2, 1)
        W[:, :, :w] = np.matmul(Ut, self.own)
        U_rows = U.reshape(b, -1, 2, k)
        for slot, (rows, point) in enumerate(zip(self.rows, self.by_slot)):
            W[:, :, w + 3 * slot:w + 3 * slot + 3] = np.matmul(U_rows[:, rows].reshape(b, -1, k).transpose(0, 2, 1), point)
        return W
