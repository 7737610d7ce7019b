"""Pixel-predicting reflection factors: the camera intrinsics as one shared unknown.

The one measurement model (``views.py``) predicts pixels through :class:`IntrinsicsModel` and
:func:`pixel_jacobians` of this module, and takes the prior :func:`intrinsics_prior_factor`; the tree's own
stacked pixel factors (:func:`intrinsics_factors`, mirror vectors as ``Point3`` s) are kept as the reference
the model is checked against, like ``batched.py``.

Where ``camera.estimate`` names intrinsics, a measurement is no longer undistorted once with fixed
intrinsics: the factor predicts the *pixel* (Hesch et al. eqs. 2, 3, 5-9 to the normalized point
``h = (x, y)``, then OpenCV's pinhole distortion applied forward and ``K``):

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2),   yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx xd + cx,   v = fy yd + cy

Unknowns (keys): ``Pose3`` ``X(0)`` of ``T_cam_base`` (GTSAM tangent ``[w, nu]``), the intrinsics as
one ``Vector`` ``K(0)`` holding the *estimated* names in :data:`INTRINSIC_NAMES` order (the others
are constants of the factors), mirror-vector ``Point3`` s (camera frame, metres) and landmark
``Point3`` s (base frame, metres). Error: ``[u_1 - u*_1, v_1 - v*_1, ...]`` in pixels, unwhitened.

Speed: one factor per group of images (``stacking.group_measurements``), its measurements run through
the vectorised model of ``model.py`` at once (no per-measurement Python calls). A robust kernel acts per
measurement inside the stacked factor exactly as in ``batched.py`` (rows scaled by ``sqrt(w(r_i))`` when
linearising, by ``sqrt(2 rho(r_i)) / r_i`` for ``error()``), so ``0.5 ||e_i||^2`` is each measurement's
robust loss and the linear system is GTSAM's ``Robust::WhitenSystem`` of one factor per measurement.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import gtsam
import numpy as np

from mirror_fg.core.camera import INTRINSIC_NAMES  # the K(0) order; re-exported here
from mirror_fg.factors.model import measurement_arrays, reflection_model
from mirror_fg.factors.robust import ROBUST_K, check_kernel, robust_row_scales
from mirror_fg.factors.stacking import (
    MAX_POINTS_PER_FACTOR, Fiducials, KeyLayout, Observation, auto_images_per_factor, group_measurements,
)

__all__ = [
    "INTRINSIC_NAMES", "intrinsics_key", "full_intrinsics", "distort_forward", "pixel_jacobians",
    "IntrinsicsModel", "intrinsics_factors", "intrinsics_prior_factor", "predict_pixels",
]


def intrinsics_key() -> int:
    """The GTSAM key of the intrinsics vector, ``K(0)``."""
    return gtsam.symbol_shorthand.K(0)


def full_intrinsics(fixed: np.ndarray, estimated_index: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """All nine intrinsics (INTRINSIC_NAMES order): ``fixed`` (9,) with the ``estimated`` values put
    at ``estimated_index``."""
    theta = np.array(fixed, dtype=float)
    theta[estimated_index] = estimated
    return theta


def distort_forward(theta: np.ndarray, normalized_T: np.ndarray) -> np.ndarray:
    """Pixels (2, M) of normalized points (2, M) through OpenCV's pinhole model (module docstring);
    ``theta`` the nine intrinsics in INTRINSIC_NAMES order."""
    return _project(theta, normalized_T, jacobians=False)[0]


def pixel_jacobians(theta: np.ndarray, normalized_T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(pixels (2, M), d pixel / d (x, y) (2, 2, M), d pixel / d theta (2, 9, M))``."""
    pixels, D, T = _project(theta, normalized_T, jacobians=True)
    assert D is not None and T is not None
    return pixels, D, T


def _project(theta: np.ndarray, h: np.ndarray, jacobians: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = (float(v) for v in theta)
    x, y = h[0], h[1]
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    r4 = r2 * r2
    radial = 1.0 + k1 * r2 + k2 * r4 + k3 * r4 * r2
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    pixels = np.stack([fx * xd + cx, fy * yd + cy])
    if not jacobians:
        return pixels, None, None
    dradial = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4  # d radial / d r2
    D = np.empty((2, 2, h.shape[1]))
    D[0, 0] = fx * (radial + 2.0 * xx * dradial + 2.0 * p1 * y + 6.0 * p2 * x)
    D[0, 1] = fx * (2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[1, 0] = fy * (2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[1, 1] = fy * (radial + 2.0 * yy * dradial + 6.0 * p1 * y + 2.0 * p2 * x)
    zero, one = np.zeros_like(x), np.ones_like(x)
    T = np.stack([
        np.stack([xd, zero, one, zero, fx * x * r2, fx * x * r4, fx * 2.0 * xy, fx * (r2 + 2.0 * xx), fx * x * r4 * r2]),
        np.stack([zero, yd, zero, one, fy * y * r2, fy * y * r4, fy * (r2 + 2.0 * yy), fy * 2.0 * xy, fy * y * r4 * r2]),
    ])  # (2, 9, M)
    return pixels, D, T


class IntrinsicsModel:
    """What every factor shares: the fixed intrinsics and which of them the ``K(0)`` vector holds."""

    def __init__(self, fixed: np.ndarray, estimated: Sequence[str]) -> None:
        unknown = [n for n in estimated if n not in INTRINSIC_NAMES]
        if unknown:
            raise ValueError(f"unknown intrinsics {unknown}: use {', '.join(INTRINSIC_NAMES)}")
        self.fixed = np.asarray(fixed, dtype=float).reshape(9)
        self.estimated = tuple(n for n in INTRINSIC_NAMES if n in estimated)
        self.index = np.array([INTRINSIC_NAMES.index(n) for n in self.estimated], dtype=np.intp)

    def theta(self, vector: np.ndarray) -> np.ndarray:
        """All nine intrinsics from the ``K(0)`` vector."""
        return full_intrinsics(self.fixed, self.index, vector)


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


def _prior_error(index: np.ndarray, given: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values,
                 jacobians: list[np.ndarray] | None) -> np.ndarray:
    """``K(0)[index] - given``: a Gaussian prior on some of the estimated intrinsics."""
    vector = values.atVector(this.keys()[0])
    if jacobians is not None:
        J = np.zeros((len(index), len(vector)))
        J[np.arange(len(index)), index] = 1.0
        jacobians[0] = J
    return vector[index] - given


def intrinsics_prior_factor(model: IntrinsicsModel, sigmas: dict[str, float],
                            key: int | None = None) -> gtsam.CustomFactor | None:
    """Prior factor on ``K(0)``: each estimated name in ``sigmas`` at its value in ``model.fixed`` (the
    given value) with that sigma (pixels or unitless). None when no estimated name has a sigma."""
    names = [n for n in model.estimated if n in sigmas]
    if not names:
        return None
    index = np.array([model.estimated.index(n) for n in names], dtype=np.intp)
    given = model.fixed[[INTRINSIC_NAMES.index(n) for n in names]]
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigmas[n] for n in names], dtype=float))
    return gtsam.CustomFactor(noise, [intrinsics_key() if key is None else key], partial(_prior_error, index, given))


def predict_pixels(theta: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of predicted normalized coordinates (N, 2) through the intrinsics ``theta`` (9,)."""
    return distort_forward(np.asarray(theta, dtype=float), np.asarray(normalized, dtype=float).reshape(-1, 2).T).T
