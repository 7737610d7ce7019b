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
measurements, the same placements seen by others) are stacked and every step runs over the stack.
Reconstruction points are left to ``dispersion.py`` (an image's rows would be dense over all of them).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mirror_fg.factors.model import reflection_model
from mirror_fg.io.dataset import Dataset
from mirror_fg.io.point_sigma import normalized_sigmas

__all__ = ["tree_dispersion", "tree_dispersion_applies", "plane_jacobians"]


def tree_dispersion_applies(dataset: Dataset, excluded: Sequence[tuple[str, str | None]],
                            estimated_cameras: Mapping[str, Any] | None) -> bool:
    """Whether :func:`tree_dispersion` computes this dispersion: the paper's tree with its intrinsics known,
    no reconstruction point, and no single measurement left out (an image left out is dropped whole)."""
    return (dataset.is_tree and not estimated_cameras and all(point is None for _, point in excluded)
            and not dataset.reconstruction_point_names)


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
                    images_out: set[str], max_images: int, max_columns: int) -> tuple[float, float, int] | None:
    """``(B, nu, images counted)`` (``dispersion.py``'s module docstring) of a tree ``dataset``
    (:func:`tree_dispersion_applies`) at ``R, t`` (``T_cam_base``) and ``mirror_vectors`` (camera frame,
    metres), without the images ``images_out``; over ``max_images`` images evenly spread where there are
    more (``dispersion.MAX_IMAGES``). None where more than ``max_columns`` columns are shared by several
    images (``dispersion.py`` then asks GTSAM's marginals)."""
    used = []  # per image: its placements, its fiducials' names and normalized observations (N, 2)
    for image in dataset.images:
        if image.id in images_out or not all(p in mirror_vectors for p in image.reflections):
            continue
        names = [n for n in image.observations if n in dataset.fiducials]
        if names:
            normalized = dataset.normalized(image)
            used.append((image.reflections, names, np.array([normalized[n] for n in names], dtype=float)))
    if not used:
        return 0.0, 0.0, 0
    placements = sorted({p for reflections, _, _ in used for p in reflections})
    row_of = {p: k for k, p in enumerate(placements)}
    levels = len(used[0][0])
    keys = np.array([[row_of[p] for p in reflections] for reflections, _, _ in used], dtype=np.intp)  # (images, levels)
    touches = np.bincount(keys.reshape(-1), minlength=len(placements))  # images per placement
    counts = np.array([len(names) for _, names, _ in used])
    starts = np.concatenate([[0], np.cumsum(counts)])
    names = [n for _, image_names, _ in used for n in image_names]
    mirror_rows = np.repeat(keys.T, counts, axis=1)  # (levels, M)
    base = np.array([dataset.fiducials[n] for n in names], dtype=float).T  # (3, M)
    observed = np.concatenate([z for _, _, z in used]).T  # (2, M)
    whiten = 1.0 / normalized_sigmas(dataset.camera, dataset.pixel_sigma, dataset.point_sigma, names)  # (M, 2)
    V = np.array([mirror_vectors[p] for p in placements], dtype=float).reshape(-1, 3)
    no_points = np.zeros(0, dtype=np.intp)
    residual, _, blocks = reflection_model(np.asarray(R, float), np.asarray(t, float), V, base, no_points, no_points,
                                           mirror_rows, observed, True)
    assert blocks is not None
    cross, GR, mirror_blocks = blocks
    width = 6 + 3 * levels  # an image's columns: the pose, then its placements
    J = np.empty((starts[-1], 2, width))  # per measurement, whitened
    J[:, :, :3] = cross.transpose(2, 0, 1)
    J[:, :, 3:6] = GR.transpose(2, 0, 1)
    plane = plane_jacobians(V)
    for level in range(levels):  # each placement in its plane's coordinates (module docstring)
        J[:, :, 6 + 3 * level:9 + 3 * level] = np.matmul(mirror_blocks[level].transpose(2, 0, 1), plane[mirror_rows[level]])
    J *= whiten[:, :, None]
    r = residual.T * whiten  # (M, 2), h - z whitened

    shared_rows = np.flatnonzero(touches > 1)
    where = np.full(len(touches), -1)
    where[shared_rows] = 6 + 3 * np.arange(len(shared_rows))  # the pose's columns first, then each shared placement's
    size = 6 + 3 * len(shared_rows)
    if size > max_columns:
        return None
    count = len(used)
    chosen = np.zeros(count, dtype=bool)
    chosen[sorted(set(np.linspace(0, count - 1, min(max_images, count)).round().astype(int).tolist()))] = True
    groups: dict[tuple, list[int]] = {}
    for i, shared in enumerate(map(tuple, touches[keys] > 1)):
        groups.setdefault((int(counts[i]), shared), []).append(i)
    information = np.zeros(size * size)
    stacks = []
    for (n, shared_placements), members in groups.items():
        index = np.array(members)
        rows = starts[index][:, None] + np.arange(n)[None]  # (b, n) measurements
        A = J[rows].reshape(len(members), 2 * n, width)
        e = r[rows].reshape(len(members), 2 * n)
        shared = [count > 1, *shared_placements]  # the pose (whenever another image sees it), each placement
        column_shared = np.repeat(shared, [6] + [3] * levels)
        s_cols, l_cols = np.flatnonzero(column_shared), np.flatnonzero(~column_shared)
        columns = [np.broadcast_to(np.arange(6), (len(members), 6))]  # each unknown's global columns
        columns += [where[keys[index, level]][:, None] + np.arange(3)[None] for level in range(levels)]
        s_at = np.concatenate([c for c, s in zip(columns, shared) if s] or [np.zeros((len(members), 0), int)], axis=1)
        H = np.matmul(A.transpose(0, 2, 1), A)
        H_ss = H[:, s_cols][:, :, s_cols]
        if len(l_cols):
            H_ll_inv = np.linalg.pinv(H[:, l_cols][:, :, l_cols], hermitian=True)
            K = np.matmul(H_ll_inv, H[:, l_cols][:, :, s_cols])  # H_ll^-1 H_ls
            H_ss = H_ss - np.matmul(H[:, s_cols][:, :, l_cols], K)  # the image's own placement eliminated
        else:
            H_ll_inv, K = np.zeros((len(members), 0, 0)), np.zeros((len(members), 0, len(s_cols)))
        flat = (s_at[:, :, None] * size + s_at[:, None, :]).reshape(-1)
        information += np.bincount(flat, weights=H_ss.reshape(-1), minlength=size * size)
        pick = chosen[index]
        if pick.any():
            stacks.append((A[pick], e[pick], s_at[pick], s_cols, l_cols, H_ll_inv[pick], K[pick]))
    information = information.reshape(size, size)
    Sigma_shared = np.linalg.pinv(0.5 * (information + information.T), hermitian=True)
    cost, rank_sum, explained, images = 0.0, 0, 0.0, 0
    for A, e, s_at, s_cols, l_cols, H_ll_inv, K in stacks:
        U, s, _ = np.linalg.svd(A, full_matrices=False)  # every column is the image's own (pose, placements)
        rank = np.sum(s > np.maximum(s[:, :1], 1e-300) * 1e-10, axis=1)  # as dispersion._range
        U = U * (np.arange(U.shape[2])[None] < rank[:, None])[:, None, :]  # beyond the rank: zero columns
        Ut = U.transpose(0, 2, 1)
        W = np.matmul(Ut, A)  # U_i^T J_i
        # tr(Sigma G_i) with Sigma_ll = H_ll^-1 + K S K^T, Sigma_ls = -K S (S: the shared block) is
        # |W_l H_ll^-1/2|^2 + |(W_s - W_l K) S^1/2|^2: two positive terms
        S = Sigma_shared[s_at[:, :, None], s_at[:, None, :]]
        W_s, W_l = W[:, :, s_cols], W[:, :, l_cols]
        D = W_s - np.matmul(W_l, K)
        explained += float(np.sum(np.matmul(D, S) * D)) + float(np.sum(np.matmul(W_l, H_ll_inv) * W_l))
        rank_sum += int(rank.sum())
        cost += float(np.sum(np.matmul(Ut, e[:, :, None]) ** 2))
        images += len(A)
    return cost, max(rank_sum - explained, 0.0), images
