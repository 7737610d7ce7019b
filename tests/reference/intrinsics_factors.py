"""The tree's own stacked pixel factors (mirror vectors as ``Point3`` s), the reference the one measurement
model's pixel-predicting view factors (``factors/views.py`` with ``factors/intrinsics.IntrinsicsModel``) are
checked against.

Keys: ``Pose3`` ``X(0)`` of ``T_cam_base`` (GTSAM tangent ``[w, nu]``), the intrinsics vector ``K(0)``
(``factors/intrinsics.py``), mirror-vector ``Point3`` s (camera frame, metres) and landmark ``Point3`` s
(base frame, metres). Error: ``[u_1 - u*_1, v_1 - v*_1, ...]`` in pixels, unwhitened. One factor per group
of images (``stacking.group_measurements``), its measurements run through the vectorised model of
``model.py`` at once. A robust kernel acts per measurement inside the stacked factor exactly as in
``batched.py`` (rows scaled by ``sqrt(w(r_i))`` when linearising, by ``sqrt(2 rho(r_i)) / r_i`` for
``error()``).
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import gtsam
import numpy as np

from mirror_fg.factors.intrinsics import IntrinsicsModel, distort_forward, intrinsics_key, pixel_jacobians
from mirror_fg.factors.robust import ROBUST_K, check_kernel, robust_row_scales
from reference.model import measurement_arrays, reflection_model
from reference.stacking import (
    MAX_POINTS_PER_FACTOR, Fiducials, KeyLayout, Observation, auto_images_per_factor, group_measurements,
)

__all__ = ["intrinsics_factors"]


class _Group:
    """One stacked factor's measurements as arrays, its points renumbered locally; its robust kernel
    (None, ``"huber"``, ``"cauchy"``) with threshold ``robust_k`` sigmas, ``sigma_px`` the noise of each
    measurement (n,), pixels."""

    def __init__(self, point_keys: list[int], mirror_rows: np.ndarray, landmark_rows: np.ndarray,
                 base_points: np.ndarray, pixels: np.ndarray, sigma_px: np.ndarray, robust: str | None = None,
                 robust_k: float = ROBUST_K) -> None:
        self.sigma_px = np.asarray(sigma_px, dtype=float).reshape(-1)
        self.robust = robust
        self.robust_k = float(robust_k)
        rows = np.concatenate([mirror_rows.ravel(), landmark_rows[landmark_rows >= 0]])
        used = list(dict.fromkeys(rows.tolist()))  # first-seen order
        local = {row: i for i, row in enumerate(used)}
        self.keys = [point_keys[row] for row in used]
        self.mirror_rows = np.array([[local[r] for r in level] for level in mirror_rows.T], dtype=np.intp).reshape(
            mirror_rows.shape[1], -1)  # (Nv, n)
        self.landmark_index = np.flatnonzero(landmark_rows >= 0)
        self.landmark_point_rows = np.array([local[r] for r in landmark_rows[self.landmark_index]], dtype=np.intp)
        self.base_T = np.ascontiguousarray(base_points.T)  # (3, n), landmark columns filled per call
        self.pixels_T = np.ascontiguousarray(pixels.T)  # (2, n)
        self.zeros_T = np.zeros_like(self.pixels_T)


def _group_error(model: IntrinsicsModel, group: _Group, this: gtsam.CustomFactor, values: gtsam.Values,
                 jacobians: list[np.ndarray] | None) -> np.ndarray:
    """Pixel error ``[u - u*, v - v*]`` per measurement of ``group``, stacked (eqs. 2, 3, 5-9, then the
    lens); keys ``[X(0), K(0), points...]``."""
    keys = this.keys()
    pose = values.atPose3(keys[0])
    theta = model.theta(values.atVector(keys[1]))
    P = np.array([values.atPoint3(k) for k in keys[2:]]).reshape(-1, 3)
    R, t = pose.rotation().matrix(), np.asarray(pose.translation())
    h, _, blocks = reflection_model(R, t, P, group.base_T, group.landmark_index, group.landmark_point_rows,
                                    group.mirror_rows, group.zeros_T, jacobians is not None)  # eq. (9): h
    if jacobians is None:
        error = (distort_forward(theta, h) - group.pixels_T).T  # (n, 2)
        if group.robust is not None:
            _, loss_scale = robust_row_scales(group.robust, np.linalg.norm(error, axis=1) / group.sigma_px, group.robust_k)
            error = error * loss_scale[:, None]
        return error.reshape(-1)
    assert blocks is not None
    pixels, D, T = pixel_jacobians(theta, h)
    cross, GR, mirror_blocks = blocks
    n = h.shape[1]

    def chain(block: np.ndarray) -> np.ndarray:  # d pixel / d h (2, 2, n) times d h / d . (2, c, n) -> (n, 2, c)
        return np.einsum("ijm,jcm->mic", D, block)

    pose_block = np.concatenate([chain(cross), chain(GR)], axis=2)  # tangent [w, nu]
    jacobians[0] = pose_block.reshape(2 * n, 6)
    jacobians[1] = np.ascontiguousarray(T[:, model.index].transpose(2, 0, 1).reshape(2 * n, len(model.index)))
    J_points = np.zeros((n, 2, len(group.keys), 3))
    every = np.arange(n)
    for level, H in mirror_blocks.items():
        J_points[every, :, group.mirror_rows[level], :] = chain(H)
    if len(group.landmark_index):
        J_points[group.landmark_index, :, group.landmark_point_rows, :] = chain(GR)[group.landmark_index]
    error = (pixels - group.pixels_T).T  # (n, 2)
    if group.robust is not None:
        root, _ = robust_row_scales(group.robust, np.linalg.norm(error, axis=1) / group.sigma_px, group.robust_k)
        error = error * root[:, None]
        pose_block *= root[:, None, None]
        jacobians[0] = pose_block.reshape(2 * n, 6)
        jacobians[1] = np.ascontiguousarray((T[:, model.index].transpose(2, 0, 1) * root[:, None, None]).reshape(
            2 * n, len(model.index)))
        J_points *= root[:, None, None, None]
    for j in range(len(group.keys)):
        jacobians[2 + j] = np.ascontiguousarray(J_points[:, :, j, :].reshape(2 * n, 3))
    return error.reshape(-1)


def intrinsics_factors(
    dataset: Fiducials, layout: KeyLayout, measurements: Sequence[Observation], pixels: np.ndarray,
    model: IntrinsicsModel, sigma_px: float | np.ndarray, robust: str | None = None, robust_k: float = ROBUST_K,
) -> list[gtsam.CustomFactor]:
    """Pixel factors of ``measurements`` (their observed ``pixels`` (M, 2)), keys ``[X(0), K(0),
    mirrors and landmarks of the group]``; noise ``sigma_px`` (pixels: one for all, or one per
    measurement (M,), e.g. a tracked point's ``point_sigma``), stacked by image groups;
    ``robust`` (``"huber"`` / ``"cauchy"``) weights each measurement inside its factor."""
    check_kernel(robust)
    point_keys, mirror_rows, landmark_rows, base_points, _ = measurement_arrays(dataset, layout, measurements)
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    sigmas = np.broadcast_to(np.asarray(sigma_px, dtype=float), (len(pixels),))
    per_image = auto_images_per_factor(measurements, landmark_rows.tolist(), MAX_POINTS_PER_FACTOR)
    groups = group_measurements(measurements, landmark_rows.tolist(), per_image, MAX_POINTS_PER_FACTOR)
    factors = []
    for members in groups:
        index = np.array(members, dtype=np.intp)
        group = _Group(point_keys, mirror_rows[index], landmark_rows[index], base_points[index], pixels[index],
                       sigmas[index], robust, robust_k)
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.repeat(sigmas[index], 2))
        keys = [layout.pose_key, intrinsics_key(), *group.keys]
        factors.append(gtsam.CustomFactor(noise, keys, partial(_group_error, model, group)))
    return factors
