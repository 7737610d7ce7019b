"""The image-level dispersion (``dispersion.py``) of the paper's tree, every image linearised in one
vectorised pass of the tree's own model (``factors/model.py``, eqs. 2, 3, 9) instead of one view factor per
image: the same ``B`` and ``nu`` to rounding.

Frames and units as ``dispersion.py``: ``T_cam_base`` perturbed in GTSAM's Pose3 tangent ``[w, nu]``
(``R Exp(w)``, ``t + R nu``), each placement in its plane's local coordinates as the view model has it
(``views.vector_of_plane``; :func:`plane_jacobians`), rows in normalized image coordinates whitened by their
sigma. ``B`` and ``nu`` do not depend on the unknowns' coordinates (a projection onto each image's column
space, a trace ``tr(Sigma G_i)`` with ``Sigma`` in the same columns), but the information's conditioning
does, hence the view model's plane coordinates rather than the mirror vectors themselves.

``Sigma`` on an image's columns, as ``dispersion._explained``: the placements only this image sees (the
last mirror's) are eliminated from its own information (Schur complement); the pose and the placements
several images see are inverted densely after every image's elimination. Images of one shape (as many
measurements, the same points in the same order, the same unknowns seen by others) are stacked and every
step runs over the stack; a reconstruction point's columns meet only its own measurements' rows, so the
information and ``U_i^T J_i`` are summed block by block rather than over rows dense in every point.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mirror_fg.factors.model import reflection_model
from mirror_fg.data import Dataset
from mirror_fg.io.point_sigma import normalized_sigmas

__all__ = ["tree_dispersion", "tree_dispersion_applies", "plane_jacobians", "CHUNK_ENTRIES"]

#: Images are stacked so that their information matrices hold at most this many entries together (8 MB):
#: with many points each image's is dense over all of them (the Schur complement of its own placement
#: couples them), and stacks of hundreds of such matrices cost more in memory traffic than in arithmetic.
CHUNK_ENTRIES = 2**20


def tree_dispersion_applies(dataset: Dataset, excluded: Sequence[tuple[str, str | None]],
                            estimated_cameras: Mapping[str, Any] | None) -> bool:
    """Whether :func:`tree_dispersion` computes this dispersion: the paper's tree with its intrinsics known
    and no single measurement left out (an image left out is dropped whole)."""
    return dataset.is_tree and not estimated_cameras and all(point is None for _, point in excluded)


def plane_jacobians(vectors: np.ndarray) -> np.ndarray:
    """``dv/dxi`` (K, 3, 3) of mirror vectors ``vectors`` (K, 3) in their planes' local coordinates, as
    ``views.vector_of_plane(views.plane_of(v))`` gives them one at a time: ``[d b1, d b2, n]`` with
    ``n = v / d`` and GTSAM's ``Unit3::basis`` ``b1 = n x e / |n x e|`` (``e`` the axis of ``n``'s smallest
    component), ``b2 = n x b1``."""
    d = np.linalg.norm(vectors, axis=1)
    n = vectors / d[:, None]
    n = n / np.linalg.norm(n, axis=1)[:, None]  # Unit3 normalises its point again
    m = np.abs(n)
    axis = np.where((m[:, 0] <= m[:, 1]) & (m[:, 0] <= m[:, 2]), 0,
                    np.where((m[:, 1] <= m[:, 0]) & (m[:, 1] <= m[:, 2]), 1, 2))
    b1 = np.cross(n, np.eye(3)[axis])
    b1 /= np.linalg.norm(b1, axis=1)[:, None]
    b2 = np.cross(n, b1)
    return np.stack([d[:, None] * b1, d[:, None] * b2, n], axis=2)


def tree_dispersion(dataset: Dataset, R: np.ndarray, t: np.ndarray, mirror_vectors: Mapping[tuple[int, int], np.ndarray],
                    points: Mapping[str, np.ndarray], images_out: set[str], max_images: int,
                    max_columns: int) -> tuple[float, float, int] | None:
    """``(B, nu, images counted)`` (``dispersion.py``'s module docstring) of a tree ``dataset``
    (:func:`tree_dispersion_applies`) at ``R, t`` (``T_cam_base``), ``mirror_vectors`` (camera frame,
    metres) and reconstruction ``points`` ({B}, metres; a point not among them is not counted), without the
    images ``images_out``; over ``max_images`` images evenly spread where there are more
    (``dispersion.MAX_IMAGES``). None where more than ``max_columns`` columns are shared by several images
    (``dispersion.py`` then asks GTSAM's marginals)."""
    rows = _Rows(dataset, mirror_vectors, points, images_out)
    if not rows.count:
        return 0.0, 0.0, 0
    J, J_point, r = rows.linearised(R, t, mirror_vectors, points)
    width = J.shape[2]  # an image's own columns: the pose, then its placements
    shared_rows = np.flatnonzero(rows.touches > 1)
    where = np.full(len(rows.touches), -1)
    where[shared_rows] = 6 + 3 * np.arange(len(shared_rows))  # the pose's columns first, then each shared unknown's
    size = 6 + 3 * len(shared_rows)
    if size > max_columns:
        return None
    count = rows.count
    chosen = np.zeros(count, dtype=bool)
    chosen[sorted(set(np.linspace(0, count - 1, min(max_images, count)).round().astype(int).tolist()))] = True
    groups: dict[tuple, list[int]] = {}
    seen_by_others = (rows.touches > 1).tolist()
    for i, (slot, unknowns) in enumerate(zip(rows.slots, rows.keys)):
        groups.setdefault((slot, tuple(seen_by_others[k] for k in unknowns)), []).append(i)
    information_entries = np.zeros(size * size)  # the shared columns' information, summed over the images
    stacks = []
    chunks = []  # each group in stacks of at most CHUNK_ENTRIES entries of their information
    for (slot, shared_keys), members in groups.items():
        step = max(1, CHUNK_ENTRIES // (width + 3 * (len(shared_keys) - rows.levels)) ** 2)
        chunks += [(slot, shared_keys, members[k:k + step]) for k in range(0, len(members), step)]
    for slot, shared_keys, members in chunks:
        index = np.array(members)
        measurements = rows.starts[index][:, None] + np.arange(len(slot))[None]  # (b, n)
        blocks = _Blocks(J[measurements], J_point[measurements], np.array(slot, dtype=np.intp))
        keys = np.array([rows.keys[i] for i in members], dtype=np.intp)  # (b, unknowns): placements, points
        shared = [count > 1, *shared_keys]  # the pose (whenever another image sees it), then each unknown
        column_shared = np.repeat(shared, [6] + [3] * len(shared_keys))
        s_cols, l_cols = np.flatnonzero(column_shared), np.flatnonzero(~column_shared)
        columns = [np.broadcast_to(np.arange(6), (len(members), 6))]  # each unknown's global columns
        columns += [where[keys[:, u]][:, None] + np.arange(3)[None] for u in range(keys.shape[1])]
        s_at = np.concatenate([c for c, s in zip(columns, shared) if s] or [np.zeros((len(members), 0), int)], axis=1)
        H = blocks.information()
        H_ss = H[:, s_cols[:, None], s_cols[None]]
        if len(l_cols):
            H_ll_inv = np.linalg.pinv(H[:, l_cols[:, None], l_cols[None]], hermitian=True)
            K = np.matmul(H_ll_inv, H[:, l_cols[:, None], s_cols[None]])  # H_ll^-1 H_ls
            H_ss = H_ss - np.matmul(H[:, s_cols[:, None], l_cols[None]], K)  # what only this image sees, eliminated
        else:
            H_ll_inv, K = np.zeros((len(members), 0, 0)), np.zeros((len(members), 0, len(s_cols)))
        flat = (s_at[:, :, None] * size + s_at[:, None, :]).reshape(-1)
        information_entries += np.bincount(flat, weights=H_ss.reshape(-1), minlength=size * size)
        pick = chosen[index]
        if pick.any():
            stacks.append((blocks.subset(pick), r[measurements[pick]].reshape(int(pick.sum()), -1), s_at[pick],
                           s_cols, l_cols, H_ll_inv[pick], K[pick]))
    information = information_entries.reshape(size, size)
    Sigma_shared = np.linalg.pinv(0.5 * (information + information.T), hermitian=True)
    cost, rank_sum, explained, images = 0.0, 0, 0.0, 0
    for blocks, e, s_at, s_cols, l_cols, H_ll_inv, K in stacks:
        U, s, _ = np.linalg.svd(blocks.own, full_matrices=False)  # the image's own columns: pose, placements
        rank = np.sum(s > np.maximum(s[:, :1], 1e-300) * 1e-10, axis=1)  # as dispersion._range
        U = U * (np.arange(U.shape[2])[None] < rank[:, None])[:, None, :]  # beyond the rank: zero columns
        W = blocks.projected(U)  # U_i^T J_i
        # tr(Sigma G_i) with Sigma_ll = H_ll^-1 + K S K^T, Sigma_ls = -K S (S: the shared block) is
        # |W_l H_ll^-1/2|^2 + |(W_s - W_l K) S^1/2|^2: two positive terms
        S = Sigma_shared[s_at[:, :, None], s_at[:, None, :]]
        W_s, W_l = W[:, :, s_cols], W[:, :, l_cols]
        D = W_s - np.matmul(W_l, K)
        explained += float(np.sum(np.matmul(D, S) * D)) + float(np.sum(np.matmul(W_l, H_ll_inv) * W_l))
        rank_sum += int(rank.sum())
        cost += float(np.sum(np.matmul(U.transpose(0, 2, 1), e[:, :, None]) ** 2))
        images += len(e)
    return cost, max(rank_sum - explained, 0.0), images


class _Rows:
    """The images counted (not left out, every placement estimated, some known point seen) as the tree
    model's arrays: per image its unknowns ``keys`` (rows of ``touches``: the placements in its order,
    then its points in the order first seen), each measurement's point ``slots`` (-1: a fiducial) and its
    first measurement (``starts``)."""

    def __init__(self, dataset: Dataset, mirror_vectors: Mapping, points: Mapping, images_out: set[str]):
        known = set(dataset.fiducials) | set(points)
        reflections: list[tuple[tuple[int, int], ...]] = []  # per image counted: its placements, its points' names
        names_of: list[tuple[str, ...]] = []
        observed: list[np.ndarray] = []  # each measurement's normalized observation
        for image in dataset.images:
            if image.id in images_out or not all(p in mirror_vectors for p in image.reflections):
                continue
            names = tuple(n for n in image.observations if n in known)
            if names:
                normalized = dataset.normalized(image)
                reflections.append(image.reflections)
                names_of.append(names)
                observed.extend(normalized[n] for n in names)
        self.count = len(reflections)
        if not self.count:
            return
        self.placements = sorted(set().union(*reflections))
        self.point_names = sorted({n for names in set(names_of) for n in names if n not in dataset.fiducials})
        row_of: dict = {p: k for k, p in enumerate(self.placements)}
        row_of.update({n: len(self.placements) + j for j, n in enumerate(self.point_names)})
        self.levels = len(reflections[0])
        shapes: dict[tuple[str, ...], tuple[tuple[int, ...], list[int]]] = {}  # names -> point slots, their rows
        for names in set(names_of):
            own: dict[str, int] = {}  # the image's points, in the order first seen
            slot = tuple(own.setdefault(n, len(own)) if n not in dataset.fiducials else -1 for n in names)
            shapes[names] = slot, [row_of[n] for n in own]
        self.slots = [shapes[names][0] for names in names_of]
        self.keys = [[row_of[p] for p in placements] + shapes[names][1]
                     for placements, names in zip(reflections, names_of)]  # rows of ``touches``
        counts = np.array([len(names) for names in names_of])
        self.starts = np.concatenate([[0], np.cumsum(counts)])
        self.names = [n for names in names_of for n in names]
        self.mirror_rows = np.repeat(np.array([keys[:self.levels] for keys in self.keys], dtype=np.intp).T, counts,
                                     axis=1)  # (levels, M)
        self.landmark_rows = np.array([-1 if n in dataset.fiducials else row_of[n] for n in self.names], dtype=np.intp)
        no_point = np.zeros(3)  # a reconstruction point's column: reflection_model takes it from the points
        self.base = np.array([dataset.fiducials[n] if n in dataset.fiducials else no_point for n in self.names],
                             dtype=np.float64).reshape(-1, 3).T  # (3, M)
        self.observed = np.array(observed, dtype=float).reshape(-1, 2).T  # (2, M)
        self.whiten = 1.0 / normalized_sigmas(dataset.camera, dataset.pixel_sigma, dataset.point_sigma, self.names)
        self.touches = np.bincount([k for keys in self.keys for k in keys], minlength=len(row_of))  # images per unknown

    def linearised(self, R: np.ndarray, t: np.ndarray, mirror_vectors: Mapping, points: Mapping):
        """Each measurement's whitened Jacobian (M, 2, 6 + 3 levels) in the pose and its placements (planes'
        coordinates), in its point (M, 2, 3; zero for a fiducial), and its whitened residual (M, 2)."""
        V = np.array([mirror_vectors[p] for p in self.placements] + [points[n] for n in self.point_names],
                     dtype=float).reshape(-1, 3)
        landmarks = np.flatnonzero(self.landmark_rows >= 0)
        residual, _, blocks = reflection_model(np.asarray(R, float), np.asarray(t, float), V, self.base, landmarks,
                                               self.landmark_rows[landmarks], self.mirror_rows, self.observed, True)
        assert blocks is not None
        cross, GR, mirror_blocks = blocks
        J = np.empty((len(self.names), 2, 6 + 3 * self.levels))
        J[:, :, :3] = cross.transpose(2, 0, 1)
        J[:, :, 3:6] = GR.transpose(2, 0, 1)
        plane = plane_jacobians(V[:len(self.placements)])
        for level in range(self.levels):  # each placement in its plane's coordinates (module docstring)
            J[:, :, 6 + 3 * level:9 + 3 * level] = np.matmul(mirror_blocks[level].transpose(2, 0, 1),
                                                             plane[self.mirror_rows[level]])
        J *= self.whiten[:, :, None]
        J_point = np.zeros((len(self.names), 2, 3))
        J_point[landmarks] = GR.transpose(2, 0, 1)[landmarks] * self.whiten[landmarks, :, None]
        return J, J_point, residual.T * self.whiten


class _Blocks:
    """The whitened Jacobians of a stack of images of one shape: ``own`` (b, 2n, w) on the pose and the
    placements, and each point slot's (b, 2 m_k, 3) on its measurements' rows only."""

    def __init__(self, J: np.ndarray, J_point: np.ndarray, slot: np.ndarray):
        b, n = J.shape[:2]
        self.own = J.reshape(b, 2 * n, -1)
        self.rows = [np.flatnonzero(slot == k) for k in range(int(slot.max()) + 1 if len(slot) else 0)]
        self.by_slot = [J_point[:, rows].reshape(b, 2 * len(rows), 3) for rows in self.rows]
        self.own_by_slot = [J[:, rows].reshape(b, 2 * len(rows), -1) for rows in self.rows]
        self.width = self.own.shape[2] + 3 * len(self.rows)

    def subset(self, pick: np.ndarray) -> _Blocks:
        """The images ``pick`` (a mask over the stack) of this stack."""
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
