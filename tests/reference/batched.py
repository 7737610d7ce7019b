"""Fast, batched reflection factors (Hesch et al., eqs. 5, 9, 23): the model of ``reflection.py``.

Why (measured here, scripts/benchmark.py): GTSAM's native projection factor linearises in ~0.3-0.5 us;
our per-measurement Python ``CustomFactor`` takes ~55 us, and a Python factor call costs ~3-4 us even
when it does nothing. Worse, inside GTSAM's optimizers (and ``Marginals``) every Python factor call
first *copies the whole* ``Values`` (pybind11 copies a ``const Values&`` argument that has no Python
object; ~75 us with 900 mirror nodes), so the per-measurement graph costs O(measurements x unknowns)
per iteration. Hence this module

1. **stacks** measurements into few factors: consecutive images under the same parent placements (about
   ``TARGET_MEASUREMENTS_PER_FACTOR`` measurements, at most ``MAX_IMAGES_PER_FACTOR`` images) with at
   most ``MAX_POINTS_PER_FACTOR`` landmarks per factor -- bigger factors cut calls, but their
   zero-padded dense Jacobians slow elimination and ``Marginals``; error ``[h_1 - z_1; h_2 - z_2; ...]``
   (2 rows per measurement, unwhitened, normalized coordinates), ``Diagonal`` noise with each
   measurement's sigmas (one sigma (2,) for all, or one row per measurement: ``point_sigma``);
2. **vectorises** the model over *all* measurements of the graph at once (numpy structure of arrays;
   the Jacobians of ``geometry.measurement_jacobians`` written out in closed form);
3. **caches** that batch: the first factor evaluated at new values computes every factor's error (and
   Jacobians when asked); the others check that their own variables are bit-for-bit those of the batch
   and return views of preallocated buffers (no per-call allocation or numpy work). The check is exact,
   so a stale result is never returned. Not thread-safe (GTSAM runs Python factors one at a time).

Keys of one factor, in order: the ``Pose3`` of ``T_cam_base``, its mirror-vector ``Point3`` keys (mirror
1 first; first-seen order within a level), then its landmark ``Point3`` keys (first-seen order).

Robust kernels (``"huber"``, ``"cauchy"``) act **per measurement inside the stacked factor** (a Robust
noise model around the stack would weight all its measurements by their joint norm, which is wrong),
reproducing what GTSAM's ``noiseModel.Robust`` does for one per-measurement factor:

* with Jacobians (linearisation) measurement i's error and Jacobian rows are scaled by ``sqrt(w(r_i))``,
  ``r_i`` its whitened residual norm, so after the Diagonal whitening GTSAM builds the same ``A, b`` as
  ``Robust::WhitenSystem`` (block reweighting ``b <- sqrt(w) b``, ``A <- sqrt(w) A``);
* without Jacobians (``error()``) rows are scaled by ``sqrt(2 rho(r_i)) / r_i`` so that
  ``0.5 ||e_i||^2 = rho(r_i)``, the per-measurement factor's robust loss.

So with a kernel ``unwhitenedError`` is the scaled residual, without one exactly ``h - z``.
``tests/test_fast_path.py`` checks errors, Jacobian blocks, robust systems and losses, the cache and
whole calibrations against the per-measurement reference.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.core.geometry import nested_transforms, predict_camera_points, project
from reference.model import measurement_arrays, reflection_model
from reference.stacking import (
    MAX_POINTS_PER_FACTOR,
    Fiducials,
    KeyLayout,
    Observation,
    auto_images_per_factor,
    group_measurements,
    sigma_rows,
)
from mirror_fg.factors.robust import ROBUST_K, check_kernel, robust_row_scales, robust_weight_and_loss

__all__ = [  # robust_weight_and_loss and ROBUST_K are robust.py's, kept importable from here
    "BatchEvaluator", "batched_factors", "batched_evaluator", "robust_weight_and_loss", "ROBUST_K",
]


#: Measured costs (us) to choose how a factor checks that the cache holds its variables: reading and
#: comparing each of its keys, or comparing the whole ``Values`` with the cached copy (C++).
_KEY_CHECK_US = 0.5
_VALUES_CHECK_US_PER_ENTRY = 0.014


@dataclass
class _FactorLayout:
    """Static description of one stacked factor: rows, keys and where its Jacobian blocks live."""

    start: int  # first measurement (batch order)
    stop: int
    keys: list[int]
    point_slots: list[int]  # rows of the evaluator's point array checked by this factor (its keys)
    check_whole_values: bool


class BatchEvaluator:
    """Vectorised model of every measurement of a graph, shared by its stacked factors.

    Built by :func:`batched_factors`; ``factors`` holds the ``gtsam.CustomFactor`` objects.
    ``order[i]`` is the index (in the ``measurements`` argument) of batch measurement ``i``; ``sigma``
    (M, 2) its noise in normalized coordinates (the constructor's ``sigma``: (2,), or (M, 2) in the
    ``measurements`` order).
    """

    def __init__(
        self,
        pose_key: int,
        point_keys: Sequence[int],
        mirror_rows: np.ndarray,
        landmark_rows: np.ndarray,
        base_points: np.ndarray,
        observed: np.ndarray,
        groups: list[list[int]],
        sigma: np.ndarray,
        robust: str | None,
        robust_k: float,
    ) -> None:
        self.pose_key = int(pose_key)
        self.point_keys = [int(k) for k in point_keys]  # row r of the point array <-> key
        num_mirrors = mirror_rows.shape[1]
        self.num_mirrors = num_mirrors
        self.robust = robust
        self.robust_k = float(robust_k)
        check_kernel(robust)

        # Batch order: the factors' measurements, contiguous.
        self.order = np.array([i for group in groups for i in group], dtype=np.intp)
        self.sigma = sigma_rows(sigma, len(observed))[self.order]  # (M, 2) normalized, batch order
        self.mirror_rows = np.ascontiguousarray(mirror_rows[self.order].T)  # (Nv, M)
        self.landmark_rows = landmark_rows[self.order]  # (M,), -1 for fiducials
        self.base_points = base_points[self.order].copy()  # (M, 3); fiducials filled, landmarks 0
        self.observed = observed[self.order].copy()  # (M, 2)
        self.is_landmark = self.landmark_rows >= 0
        self.landmark_index = np.flatnonzero(self.is_landmark)
        self._landmark_point_rows = self.landmark_rows[self.landmark_index]
        self._base_T = np.ascontiguousarray(self.base_points.T)  # (3, M)
        self._observed_T = np.ascontiguousarray(self.observed.T)  # (2, M)
        self._inv_sigma2 = np.ascontiguousarray((1.0 / self.sigma**2).T)  # (2, M)
        M = len(self.order)
        self.num_measurements = M

        # Preallocated outputs: views of these are what the factors hand to GTSAM.
        self._err = np.zeros((M, 2))  # h - z (scaled for error() with a robust kernel)
        self._err_lin = self._err if robust is None else np.zeros((M, 2))  # rows for linearisation
        self._H_pose = np.zeros((M, 2, 6))
        self._H_mirror = np.zeros((num_mirrors, M, 2, 3))

        # Factors: keys and Jacobian views. The pose block and a mirror shared by all of a factor's rows
        # are views of the dense buffers; other keys (landmarks, and the last mirror when a factor
        # spans images) get a zero-padded (2n, 3) block in ``_pad`` where each of their measurements'
        # 2x3 block is scattered at its rows.
        self._layouts: list[_FactorLayout] = []
        self._err_views: list[np.ndarray] = []
        self._err_lin_views: list[np.ndarray] = []
        views_of: list[list[np.ndarray | tuple[int, int]]] = []
        scatter_meas: list[list[np.ndarray]] = [[] for _ in range(num_mirrors + 1)]
        scatter_offset: list[list[np.ndarray]] = [[] for _ in range(num_mirrors + 1)]
        num_values = 1 + len(self.point_keys)
        pad_size = 0
        start = 0
        for group in groups:
            n = len(group)
            stop = start + n
            local = np.arange(n)
            keys = [self.pose_key]
            slots: list[int] = []
            views: list[np.ndarray | tuple[int, int]] = [self._H_pose[start:stop].reshape(2 * n, 6)]
            for slot in range(num_mirrors + 1):  # mirror levels, then landmarks
                if slot < num_mirrors:
                    members, rows = local, self.mirror_rows[slot, start:stop]
                else:
                    members = np.flatnonzero(self.landmark_rows[start:stop] >= 0)
                    rows = self.landmark_rows[start:stop][members]
                if len(rows) == 0:
                    continue
                unique, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
                by_first = np.argsort(first)  # keys in first-seen order
                rank = np.empty(len(unique), dtype=np.intp)
                rank[by_first] = np.arange(len(unique))
                ordered = unique[by_first].tolist()
                keys.extend(self.point_keys[row] for row in ordered)
                slots.extend(ordered)
                if slot < num_mirrors and len(unique) == 1:
                    views.append(self._H_mirror[slot, start:stop].reshape(2 * n, 3))
                    continue
                views.extend((pad_size + 6 * n * q, n) for q in range(len(unique)))  # filled in below
                scatter_meas[slot].append(start + members)
                scatter_offset[slot].append(pad_size + 6 * n * rank[inverse.reshape(-1)] + 6 * members)
                pad_size += 6 * n * len(unique)
            check_whole = _VALUES_CHECK_US_PER_ENTRY * num_values < _KEY_CHECK_US * len(slots)
            self._layouts.append(_FactorLayout(start, stop, keys, slots, check_whole))
            views_of.append(views)
            self._err_views.append(self._err[start:stop].reshape(-1))
            self._err_lin_views.append(self._err_lin[start:stop].reshape(-1))
            start = stop
        self._pad = np.zeros(pad_size)
        self._jacobian_views: list[list[np.ndarray]] = [
            [v if isinstance(v, np.ndarray) else self._pad[v[0] : v[0] + 6 * v[1]].reshape(2 * v[1], 3) for v in views]
            for views in views_of
        ]
        # Scatter plan per slot: measurements, and the flat index in ``_pad`` of component (row r,
        # column c) of each one's 2x3 block: block offset + 3 r + c, shaped (2, 3, count).
        components = (3 * np.arange(2)[:, None] + np.arange(3)[None, :])[:, :, None]
        self._scatter = [
            (slot, np.concatenate(scatter_meas[slot]), np.concatenate(scatter_offset[slot])[None, None, :] + components)
            for slot in range(num_mirrors + 1)
            if scatter_meas[slot]
        ]

        self._any_whole_check = any(layout.check_whole_values for layout in self._layouts)
        self._all_keys_sorted = sorted([self.pose_key, *self.point_keys])
        self._extract_rows: np.ndarray | None = None
        # Cache state.
        self._valid = False
        self._has_jacobians = False
        self._pose: gtsam.Pose3 | None = None
        self._point_bytes: list[bytes] = []
        self._values_copy: gtsam.Values | None = None
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self._P = np.zeros((len(self.point_keys), 3))
        self.batches = 0  # number of batch evaluations (for tests and benchmarks)
        self.factors: list[gtsam.CustomFactor] = []

    # --- cache ------------------------------------------------------------------------------------

    def _matches(self, f: int, values: gtsam.Values) -> bool:
        """Whether the cached batch was computed at exactly this factor's variables in ``values``."""
        if not self._valid:
            return False
        layout = self._layouts[f]
        if layout.check_whole_values:
            return self._values_copy is not None and values.equals(self._values_copy, 0.0)
        if self._pose is None or not values.atPose3(self.pose_key).equals(self._pose, 0.0):
            return False
        cached = self._point_bytes
        keys = self.point_keys
        for row in layout.point_slots:
            if values.atPoint3(keys[row]).tobytes() != cached[row]:
                return False
        return True

    def _read(self, values: gtsam.Values) -> tuple[gtsam.Pose3, np.ndarray, np.ndarray, np.ndarray]:
        """The pose, its ``R`` and ``t``, and every point row (K, 3) of ``values`` (one C++ call for the
        points when possible)."""
        pose = values.atPose3(self.pose_key)
        T = pose.matrix()
        R = np.ascontiguousarray(T[:3, :3])
        t = T[:3, 3].copy()
        P = None
        if values.size() == len(self._all_keys_sorted) and values.keys() == self._all_keys_sorted:
            extracted = gtsam.utilities.extractPoint3(values)
            if extracted.shape[0] == len(self.point_keys):  # every other value is a Point3: ours, in key order
                if self._extract_rows is None:
                    order = sorted(range(len(self.point_keys)), key=lambda r: self.point_keys[r])
                    rows = np.empty(len(order), dtype=np.intp)
                    rows[order] = np.arange(len(order))
                    self._extract_rows = rows
                P = np.ascontiguousarray(extracted[self._extract_rows], dtype=float)
        if P is None:  # other keys in ``values``, or a subgraph's values without some of ours (NaN)
            P = np.full((len(self.point_keys), 3), np.nan)
            for row, key in enumerate(self.point_keys):
                if values.exists(key):
                    P[row] = values.atPoint3(key)
        return pose, R, t, P

    def _load(self, values: gtsam.Values) -> None:
        """Read ``values`` into the cache (:meth:`_read`)."""
        pose, self._R, self._t, P = self._read(values)
        self._P = P
        self._pose = gtsam.Pose3(pose)
        flat = P.tobytes()
        self._point_bytes = [flat[24 * r : 24 * r + 24] for r in range(len(P))]
        if self._any_whole_check:
            self._values_copy = gtsam.Values(values)
        self._valid = True
        self._has_jacobians = False

    def evaluate(self, values: gtsam.Values, jacobians: bool) -> None:
        """Recompute the batch at ``values`` (errors, and Jacobians when asked)."""
        self._load(values)
        self._compute(jacobians)

    # --- vectorised model (eqs. 2, 3, 5-9): reflection_model() ------------------------------------

    def _compute(self, jacobians: bool) -> None:
        self.batches += 1
        R, t = self._R, self._t
        residual, B, blocks = reflection_model(
            R, t, self._P, self._base_T, self.landmark_index, self._landmark_point_rows, self.mirror_rows,
            self._observed_T, jacobians,
        )
        if self.robust is None:
            self._err.T[...] = residual
        else:
            r = np.sqrt(np.einsum("im,im->m", residual, residual * self._inv_sigma2))
            sqrt_w, loss_scale = robust_row_scales(self.robust, r, self.robust_k)
            self._err.T[...] = residual * loss_scale
            self._err_lin.T[...] = residual * sqrt_w
        self._has_jacobians = jacobians
        if not jacobians:
            return
        if blocks is None:  # reflection_model returns the blocks whenever asked for Jacobians
            raise RuntimeError("batched factors: reflection model returned no Jacobian blocks")
        cross, GR, mirror_blocks = blocks
        if self.robust is not None:
            GR *= sqrt_w
            cross *= sqrt_w
            for H in mirror_blocks.values():
                H *= sqrt_w
        H_pose = self._H_pose  # (M, 2, 6), tangent [w, nu]: R <- R Exp(w), t <- t + R nu
        H_pose[:, :, :3] = cross.transpose(2, 0, 1)
        H_pose[:, :, 3:] = GR.transpose(2, 0, 1)
        for level, H in mirror_blocks.items():
            self._H_mirror[level] = H.transpose(2, 0, 1)
        for slot, measurements, destination in self._scatter:
            source = GR if slot == self.num_mirrors else mirror_blocks[slot]
            self._pad[destination] = np.take(source, measurements, axis=2)

    # --- the factors' error function ---------------------------------------------------------------

    def error_function(self, f: int):
        """``error(this, values, jacobians)`` of factor ``f`` for ``gtsam.CustomFactor``."""
        matches = self._matches
        err_views = self._err_views[f]
        err_lin_views = self._err_lin_views[f]
        jacobian_views = self._jacobian_views[f]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            if not matches(f, values):
                self.evaluate(values, H is not None)
            elif H is not None and not self._has_jacobians:
                self._compute(True)
            if H is None:
                return err_views
            H.clear()
            H.extend(jacobian_views)
            return err_lin_views

        return error

    def predicted(self, values: gtsam.Values) -> np.ndarray:
        """Predicted normalized coordinates ``h`` (N, 2) of every measurement at ``values`` (eqs. 5, 9),
        in the order of the ``measurements`` the factors were built from (no robust scaling). The core's
        batched primitives, one composite ``(A, b)`` per measurement; the cache is left as it is."""
        _, R, t, P = self._read(values)
        base_points = self.base_points.copy()
        base_points[self.landmark_index] = P[self._landmark_point_rows]
        A, b = nested_transforms(R, t, [P[rows] for rows in self.mirror_rows])  # eqs. (5)-(8)
        out = np.empty_like(self.observed)
        out[self.order] = project(predict_camera_points(A, b, np.arange(self.num_measurements), base_points))  # eq. (9)
        return out

    def factor_layout(self, f: int) -> tuple[list[int], np.ndarray]:
        """Keys of factor ``f`` and the indices (``measurements`` order) of its measurements."""
        layout = self._layouts[f]
        return list(layout.keys), self.order[layout.start : layout.stop].copy()


def batched_factors(
    dataset: Fiducials,
    layout: KeyLayout,
    measurements: Sequence[Observation],
    noise_sigma: np.ndarray,
    robust: str | None = None,
    *,
    robust_k: float = ROBUST_K,
    images_per_factor: int | None = None,
    max_points_per_factor: int | None = MAX_POINTS_PER_FACTOR,
) -> list[gtsam.CustomFactor]:
    """Stacked reflection factors for ``measurements``: a drop-in for one ``ReflectionFactor`` each.

    dataset: has ``fiducials`` ``{name: (3,) metres, base frame}``. layout: ``graph.GraphLayout``
    (``pose_key``, ``mirror_keys[(l, m)]``, ``point_keys[name]``). measurements: ``graph.Measurement``
    objects (``image_id``, ``point``, ``normalized`` (2,), ``mirror_configs``). noise_sigma: (2,)
    standard deviation in normalized coordinates, or (N, 2), one row per measurement in the order of
    ``measurements`` (``graph.measurement_sigmas``). robust: ``None``, ``"huber"`` or ``"cauchy"`` per
    measurement, threshold ``robust_k`` sigmas (module docstring). images_per_factor: consecutive
    images sharing their parent placements stacked in one factor (``None``: about 72 measurements per
    factor, at most 12 images). max_points_per_factor: at most this many landmarks per factor (an
    image's landmarks split over several factors; ``None``: no limit).

    The factors share one :class:`BatchEvaluator`; :func:`batched_evaluator` returns it (its
    ``factors``, and ``predicted(values)`` for every measurement's prediction in one vectorised pass;
    its ``factors`` list makes a reference cycle through C++ that only ``evaluator.factors.clear()``
    breaks).
    """
    evaluator = batched_evaluator(
        dataset, layout, measurements, noise_sigma, robust,
        robust_k=robust_k, images_per_factor=images_per_factor, max_points_per_factor=max_points_per_factor,
    )
    # The factors' error functions hold the evaluator; the evaluator must not hold the factors, or the
    # C++ factors and the Python evaluator form a cycle Python's garbage collector cannot see (each
    # calibration would leak its graph).
    factors, evaluator.factors = evaluator.factors, []
    return factors


def batched_evaluator(
    dataset: Fiducials,
    layout: KeyLayout,
    measurements: Sequence[Observation],
    noise_sigma: np.ndarray,
    robust: str | None = None,
    *,
    robust_k: float = ROBUST_K,
    images_per_factor: int | None = None,
    max_points_per_factor: int | None = MAX_POINTS_PER_FACTOR,
) -> BatchEvaluator:
    """Like :func:`batched_factors`, returning the evaluator (its ``factors`` are the graph's factors)."""
    if images_per_factor is not None and images_per_factor < 1:
        raise ValueError(f"images_per_factor must be >= 1, got {images_per_factor}")
    if max_points_per_factor is not None and max_points_per_factor < 1:
        raise ValueError(f"max_points_per_factor must be >= 1 or None, got {max_points_per_factor}")
    if not measurements:
        raise ValueError("batched_factors: no measurements")
    point_keys, mirror_rows, landmark_rows, base_points, observed = measurement_arrays(dataset, layout, measurements)
    landmark_of = landmark_rows.tolist()
    if images_per_factor is None:
        images_per_factor = auto_images_per_factor(measurements, landmark_of, max_points_per_factor)
    groups = group_measurements(measurements, landmark_of, images_per_factor, max_points_per_factor)
    sigma = sigma_rows(noise_sigma, len(measurements))
    evaluator = BatchEvaluator(
        layout.pose_key, point_keys, mirror_rows, landmark_rows, base_points, observed, groups, sigma, robust, robust_k
    )
    noise_by_sigmas: dict[bytes, gtsam.noiseModel.Base] = {}
    for f, group in enumerate(groups):
        keys, indices = evaluator.factor_layout(f)
        sigmas = sigma[indices].reshape(-1)  # each measurement's (x, y), the factor's row order
        noise = noise_by_sigmas.get(sigmas.tobytes())
        if noise is None:
            noise = noise_by_sigmas[sigmas.tobytes()] = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        evaluator.factors.append(gtsam.CustomFactor(noise, keys, evaluator.error_function(f)))
    return evaluator
