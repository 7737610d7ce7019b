"""Reflection factors with the last mirror's placements eliminated (Schur complement), the way GTSAM's
``SmartProjectionFactor`` eliminates its landmark (Hesch et al., eqs. 5, 9, 23).

Why: inside GTSAM's optimizers every Python factor call receives a copy of the whole
``Values``, so a graph with one ``Point3`` per image (the last mirror moves in every image) costs
(factor calls) x (unknowns) = O(n^2). Here the last mirror's placements never enter the ``Values``:

* the factors' keys are ``T_cam_base``, the placements of mirrors 1..Nv-1 and the landmarks only
  (bounded by the mirror schedule and the points, not by the number of images); one factor per parent
  placement ``(c_1, ..., c_{Nv-1})``;
* evaluated at those values, each last-level placement ``v_j`` is first optimised on its own
  measurements (Gauss-Newton to machine precision, vectorised over every placement; variable
  projection), so the factors' cost is ``min_v`` of the cost of eq. (23): the same minimiser;
* linearised, each placement is eliminated from its measurements' whitened system ``[J_x J_v | e]``
  (``J_x <- (I - J_v D^-1 J_v^T) J_x`` with ``D = J_v^T J_v``: the Schur complement) and a factor's
  rows are compressed to ``d + 1`` rows ``[R | r; 0 | rho]`` (:func:`compressed_normal`): the same ``J^T J``,
  ``J^T e`` and ``||e||^2`` as its measurements' system, hence the same LM steps as the joint graph with the
  placements eliminated first.

The placements and their covariances are recovered afterwards (:meth:`EliminatedEvaluator.mirror_vectors`,
:meth:`EliminatedEvaluator.covariances`): ``Sigma_v = D^-1 + D^-1 B^T Sigma_x B D^-1``. Measurement noise
is diagonal, one sigma (x, y) per measurement or one for all (no robust kernel: ``batched.py`` keeps
that case). Not thread-safe (GTSAM
calls Python factors one at a time). ``tests/test_elimination.py`` checks it against the reference
per-measurement factors.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import gtsam
import numpy as np

from mirror_fg.factors.view_eliminated import COLLAPSED_FRACTION, collapsed  # noqa: F401 (public here too)
from reference.model import last_mirror_moments, measurement_arrays, mirror_input, reflection_model
from mirror_fg.factors.schur import (
    compressed_normal, gauss_newton_steps, inverses, one_blas_thread, row_products, segment_sums,
)
from reference.stacking import Fiducials, KeyLayout, Observation, sigma_rows

__all__ = [
    "EliminatedEvaluator", "NotEliminable", "eliminated_evaluator", "collapsed", "COLLAPSED_FRACTION", "INNER_MAX_ITERATIONS",
    "INNER_STEP_TOLERANCE",
]

#: Gauss-Newton iterations allowed per evaluation for the eliminated placements.
INNER_MAX_ITERATIONS = 20
#: A placement is optimal when its Gauss-Newton step is below this (metres); its error then changes
#: the cost by O(step^2) and the Schur-projected gradient not at all (first order).
INNER_STEP_TOLERANCE = 1e-12




class NotEliminable(ValueError):
    """The measurements do not have the structure the elimination needs (use ``batched.py``)."""


class EliminatedEvaluator:
    """The graph's measurements with the last mirror's placements eliminated (module docstring).

    ``factors``: the ``gtsam.CustomFactor`` objects (hand them to a graph, then drop this list or keep
    the evaluator only through them: see :func:`eliminated_evaluator`). ``kept_keys``: the keys the
    factors see; ``eliminated``: the configurations ``(Nv, m)`` solved inside.
    """

    def __init__(
        self,
        dataset: Fiducials,
        layout: KeyLayout,
        measurements: Sequence[Observation],
        noise_sigma: np.ndarray,
        initial_vectors: Mapping[tuple[int, int], np.ndarray],
    ) -> None:
        if not measurements:
            raise ValueError("eliminated_evaluator: no measurements")
        point_keys, mirror_rows, landmark_rows, base_points, observed = measurement_arrays(dataset, layout, measurements)
        self.pose_key = int(layout.pose_key)
        self.point_keys = [int(k) for k in point_keys]
        configs = sorted(layout.mirror_keys)
        num_mirrors = mirror_rows.shape[1]
        self.num_mirrors = num_mirrors
        self.eliminated = [c for c in configs if c[0] == num_mirrors]
        self._elim_rows = np.array([r for r, c in enumerate(configs) if c[0] == num_mirrors], dtype=np.intp)
        eliminated_rows = set(self._elim_rows.tolist())
        kept_rows = [r for r in range(len(point_keys)) if r not in eliminated_rows]
        self._kept_rows = np.array(kept_rows, dtype=np.intp)
        self.kept_keys = [self.pose_key] + [self.point_keys[r] for r in kept_rows]
        self._config_of_row = {r: c for r, c in enumerate(configs)}
        # global columns of the kept unknowns: pose 0..5, then 3 per kept row
        self._column_of_row = {r: 6 + 3 * q for q, r in enumerate(kept_rows)}
        self.dimension_kept = 6 + 3 * len(kept_rows)
        self.dimension = self.dimension_kept + 3 * len(self._elim_rows)
        self.num_measurements = len(measurements)

        placement_of_row = np.full(len(point_keys), -1, dtype=np.intp)
        placement_of_row[self._elim_rows] = np.arange(len(self._elim_rows))
        placement = placement_of_row[mirror_rows[:, -1]]
        if np.any(placement < 0):
            raise KeyError("a measurement's last mirror placement is not a last-level configuration")
        # factor of each measurement: its parent placements, numbered in order of first appearance
        if num_mirrors > 1:
            _, first, inverse = np.unique(mirror_rows[:, :-1], axis=0, return_index=True, return_inverse=True)
            rank = np.empty(len(first), dtype=np.intp)
            rank[np.argsort(first, kind="stable")] = np.arange(len(first))
            group = rank[inverse.reshape(-1)]
        else:
            group = np.zeros(len(placement), dtype=np.intp)
        # Measurements sorted by (factor, placement): every placement and every factor is a contiguous segment.
        self.order = np.lexsort((np.arange(len(placement)), placement, group))
        self.sigma = sigma_rows(noise_sigma, len(measurements))[self.order]  # (M, 2) normalized, sorted order
        self.mirror_rows = np.ascontiguousarray(mirror_rows[self.order].T)  # (Nv, M)
        landmark_rows = landmark_rows[self.order]
        self._base_T = np.ascontiguousarray(base_points[self.order].T)
        self._landmark_index = np.flatnonzero(landmark_rows >= 0)
        self._landmark_point_rows = landmark_rows[self._landmark_index]
        self._observed_T = np.ascontiguousarray(observed[self.order].T)
        placement = placement[self.order]
        group = group[self.order]
        starts = np.flatnonzero(np.r_[True, placement[1:] != placement[:-1]])
        if len(starts) != len(self._elim_rows) or len(np.unique(placement[starts])) != len(starts):
            raise NotEliminable("a last-mirror placement is seen under two parent placements")
        self._placement_starts = starts
        self._placement_of_segment = placement[starts]  # placement index of each segment
        self._segment_of_measurement = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(placement)]))
        self._whiten = np.ascontiguousarray((1.0 / self.sigma).T)  # (2, M)

        # Factors: contiguous measurement ranges, their kept keys and local columns.
        group_starts = np.r_[np.flatnonzero(np.r_[True, group[1:] != group[:-1]]), len(group)]
        self._factors: list[dict] = []
        for f in range(len(group_starts) - 1):
            lo, hi = int(group_starts[f]), int(group_starts[f + 1])
            rows = [int(r) for r in self.mirror_rows[:-1, lo]]  # parents (Nv - 1)
            marks = landmark_rows[lo:hi]
            landmark_unique = list(dict.fromkeys(int(r) for r in marks[marks >= 0]))
            rows += landmark_unique
            local_of_row = {r: 6 + 3 * q for q, r in enumerate(rows)}
            width = 6 + 3 * len(rows)
            global_columns = np.r_[np.arange(6), np.concatenate([np.arange(3) + self._column_of_row[r] for r in rows])
                                   if rows else np.zeros(0, dtype=np.intp)].astype(np.intp)
            local_landmark = np.array([local_of_row[int(r)] for r in marks[marks >= 0]], dtype=np.intp)
            segments = np.flatnonzero((starts >= lo) & (starts < hi))
            # the landmark measurements grouped by landmark: contiguous runs of landmark_order
            landmark_order = np.argsort(local_landmark, kind="stable")
            sorted_columns = local_landmark[landmark_order]
            landmark_starts = np.flatnonzero(np.diff(sorted_columns, prepend=-1))
            self._factors.append({
                "lo": lo, "hi": hi, "keys": [self.pose_key] + [self.point_keys[r] for r in rows], "width": width,
                "columns": global_columns, "landmarks": np.flatnonzero(marks >= 0), "landmark_columns": local_landmark,
                "segments": segments, "local_of_row": local_of_row, "landmark_order": landmark_order,
                "landmark_starts": landmark_starts, "landmark_unique": sorted_columns[landmark_starts],
            })

        self._P = np.zeros((len(point_keys), 3))
        self.restart(initial_vectors)
        self.factors: list[gtsam.CustomFactor] = []

    def restart(self, initial_vectors: Mapping[tuple[int, int], np.ndarray]) -> None:
        """The state of a new evaluator of the same measurements whose last-level placements start at
        ``initial_vectors`` (``(Nv, m) -> v``): one subtree refined from several hypotheses builds its
        arrays and factors once."""
        # State: the full point array (eliminated rows = the placements' current optimum).
        self._P = np.zeros_like(self._P)
        for r in self._elim_rows.tolist():
            self._P[r] = np.asarray(initial_vectors[self._config_of_row[r]], dtype=float)
        self._P_start = self._P[self._elim_rows].copy()  # warm start of the next evaluation
        self._P_initial = self._P_start.copy()  # where a collapsed warm start starts again
        self._state_key: bytes | None = None
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self._cost = np.zeros(len(self._factors))
        self._systems: list[tuple[np.ndarray, list[np.ndarray]]] | None = None
        self._blocks: dict | None = None
        self.evaluations = 0  # for tests and benchmarks
        self.inner_iterations = 0

    # --- reading the values ------------------------------------------------------------------------

    def _read(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, bytes]:
        T = values.atPose3(self.pose_key).matrix()
        P = self._P
        for r in self._kept_rows.tolist():
            P[r] = values.atPoint3(self.point_keys[r])
        key = T.tobytes() + P[self._kept_rows].tobytes()
        return np.ascontiguousarray(T[:3, :3]), T[:3, 3].copy(), key

    def _model(self, P: np.ndarray, jacobians: bool, last_only: bool = False):
        levels = [self.num_mirrors - 1] if last_only else None
        return reflection_model(
            self._R, self._t, P, self._base_T, self._landmark_index, self._landmark_point_rows, self.mirror_rows,
            self._observed_T, jacobians, levels,
        )

    # --- the placements' optimum (variable projection) -------------------------------------------

    def _solve_placements(self) -> None:
        """Each last-level placement's Gauss-Newton optimum on its own measurements at the kept values.

        The points as they reach the last mirror depend on the kept values only: computed once
        (:func:`mirror_input`); each iteration then evaluates the last reflection and sums the moments of
        ``[J_v | e]`` per placement in one pass (:func:`last_mirror_moments`)."""
        P = self._P
        rows = self._elim_rows[self._placement_of_segment]
        starts = self._placement_starts
        last = self.num_mirrors - 1
        P[rows] = self._warm_start()[self._placement_of_segment]
        xb = mirror_input(self._R, self._t, P, self._base_T, self._landmark_index, self._landmark_point_rows,
                          self.mirror_rows, last)
        V = np.ascontiguousarray(P[rows].T)  # (3, S) placements, segment order
        segment_of = self._segment_of_measurement

        def evaluate() -> tuple[np.ndarray, np.ndarray]:
            return last_mirror_moments(xb, np.take(V, segment_of, axis=1), self._observed_T, self._whiten, starts)

        e, moments = evaluate()
        for _ in range(INNER_MAX_ITERATIONS):
            step = gauss_newton_steps(moments)  # (3, S)
            step[~np.isfinite(step)] = 0.0
            active = np.max(np.abs(step), axis=0) > INNER_STEP_TOLERANCE
            if not active.any():
                break
            self.inner_iterations += 1
            step[:, ~active] = 0.0
            # trust region: a step moves a mirror by at most half its distance (v -> 0 is the camera centre)
            length = np.sqrt(np.einsum("is,is->s", step, step))
            limit = 0.5 * np.sqrt(np.einsum("is,is->s", V, V))
            step *= np.minimum(1.0, limit / np.maximum(length, 1e-300))
            base = V.copy()
            cost = moments[9].copy()
            for _halving in range(4):  # keep each placement's cost from rising (damped Gauss-Newton)
                np.add(base, step, out=V)
                e, moments = evaluate()
                worse = moments[9] > cost * (1.0 + 1e-12)
                if not worse.any():
                    break
                step[:, worse] *= 0.5
            else:
                V[:, worse] = base[:, worse]
                e, moments = evaluate()
        P[rows] = V.T
        self._e = np.ascontiguousarray(e.T)  # (M, 2)
        self._moments = moments

    def _warm_start(self) -> np.ndarray:
        """Where each placement's solve starts: its optimum at the last linearisation, or its initial vector
        where that optimum has collapsed into the camera centre (:data:`COLLAPSED_FRACTION`): from there
        the solve, which keeps a placement on its side of the centre, could not come back."""
        start = self._P_start
        distance = np.linalg.norm(start, axis=1)
        low = distance < COLLAPSED_FRACTION * np.median(distance)
        if not low.any():
            return start
        start = start.copy()
        start[low] = self._P_initial[low]
        return start

    # --- the evaluation shared by every factor -----------------------------------------------------

    def _evaluate(self, values: gtsam.Values, jacobians: bool) -> None:
        self._R, self._t, key = self._read(values)
        if key == self._state_key and not (jacobians and self._systems is None):
            return
        with one_blas_thread():
            self._evaluate_at(key, jacobians)

    def _evaluate_at(self, key: bytes, jacobians: bool) -> None:
        if key != self._state_key:
            self.evaluations += 1
            self._solve_placements()
            e = self._e
            total = np.einsum("ma,ma->m", e, e)
            bounds = np.r_[[f["lo"] for f in self._factors], len(total)]
            self._cost = np.add.reduceat(total, bounds[:-1])
            self._state_key = key
            self._systems = None
        if jacobians and self._systems is None:
            self._systems = self._linear_systems()
            self._P_start = self._P[self._elim_rows].copy()  # linearised at an accepted estimate: start there

    def _linear_systems(self) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """Each factor's compressed, eliminated system ``(error (d+1,), Jacobian blocks)``; also the
        pieces the covariances need (``self._blocks``).

        The normal equations of the eliminated system ``[J_x | e]`` projected by ``I - J_v D^-1 J_v^T``
        are ``N - C^T D^-1 C`` with ``N = [J_x | e]^T [J_x | e]`` and ``C = J_v^T [J_x | e]`` per placement
        (the projection is symmetric and idempotent): both sums run over each measurement's nonzero
        columns only (the pose, the parent placements, its landmark and the error: :meth:`_sparse_normal`),
        never over the factor's dense width, which grows with the landmarks."""
        residual, _, (cross, GR, mirror) = self._model(self._P, True)
        w = self._whiten.T[:, :, None]  # (M, 2, 1)
        e = self._e  # (M, 2) whitened, at the placements' optimum
        num_parents = 3 * (self.num_mirrors - 1)
        # per measurement its nonzero columns [pose | parents | landmark | e], whitened (M, 2, 6 + parents + 4)
        A = np.zeros((len(e), 2, 10 + num_parents))
        A[:, :, :3] = cross.transpose(2, 0, 1)
        A[:, :, 3:6] = GR.transpose(2, 0, 1)
        for level in range(self.num_mirrors - 1):
            A[:, :, 6 + 3 * level : 9 + 3 * level] = mirror[level].transpose(2, 0, 1)
        if len(self._landmark_index):
            A[self._landmark_index, :, 6 + num_parents : 9 + num_parents] = A[self._landmark_index, :, 3:6]
        A *= w
        A[:, :, -1] = e
        Jv = mirror[self.num_mirrors - 1].transpose(2, 0, 1) * w  # (M, 2, 3)
        moments = self._moments  # D = J_v^T J_v and J_v^T e per placement, at the placements' optimum
        if not (np.all(np.isfinite(moments)) and np.all(np.isfinite(e))):
            raise RuntimeError("a mirror placement of the last mirror has no finite optimum at these values")
        D_inv = inverses(moments[:6])
        moments_v = row_products(Jv, A)  # (M, 3, k): J_v^T [J_x | e] per measurement, compact
        systems, couplings, informations = [], [], []
        for f in self._factors:
            width, segments = f["width"], f["segments"]
            normal, C = self._sparse_normal(f, A, moments_v)
            K = D_inv[segments] @ C  # D^-1 B^T, (S, 3, d + 1)
            normal -= C.reshape(-1, width + 1).T @ K.reshape(-1, width + 1)  # the Schur complement
            normal = 0.5 * (normal + normal.T)
            information = np.ascontiguousarray(normal[:width, :width])
            R_aug = compressed_normal(information, normal[:width, width], float(normal[width, width]))
            informations.append(information)
            blocks = [np.asfortranarray(R_aug[:, :6])]
            blocks += [np.asfortranarray(R_aug[:, c : c + 3]) for c in range(6, width, 3)]
            systems.append((np.ascontiguousarray(R_aug[:, width]), blocks))
            couplings.append(np.ascontiguousarray(C[:, :, :width]))
        self._blocks = {"D_inv": D_inv, "C": couplings, "information": informations}
        return systems

    def _sparse_normal(self, f: dict, A: np.ndarray, moments_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Factor ``f``'s ``N = [J_x | e]^T [J_x | e]`` ((d+1) x (d+1)) and ``C = J_v^T [J_x | e]`` per
        placement ((S, 3, d+1)) from the measurements' compact rows ``A`` (M, 2, k) (columns: pose, parents,
        landmark (zero for a fiducial), e) and their ``J_v^T A`` (M, 3, k)."""
        lo, hi, width = f["lo"], f["hi"], f["width"]
        k = A.shape[2]
        fixed = np.r_[0 : k - 4, k - 1]  # compact columns every measurement has: pose, parents, e
        fixed_columns = np.r_[0 : k - 4, width]  # ... and the factor's columns of them
        rows = A[lo:hi][:, :, fixed]
        normal = np.zeros((width + 1, width + 1))
        flat = rows.reshape(-1, len(fixed))
        normal[np.ix_(fixed_columns, fixed_columns)] = flat.T @ flat
        segments = f["segments"]
        local_starts = self._placement_starts[segments] - lo
        C = np.zeros((len(segments), 3, width + 1))
        C[:, :, fixed_columns] = segment_sums(moments_v[lo:hi][:, :, fixed], local_starts)
        marks = f["landmarks"]
        if len(marks):
            order, runs = f["landmark_order"], f["landmark_starts"]
            seen = A[lo + marks[order], :, k - 4 : k - 1]  # (n, 2, 3) landmark columns, grouped by landmark
            cross = segment_sums(row_products(rows[marks[order]], seen), runs)  # (u, kF, 3)
            own = segment_sums(row_products(seen, seen), runs)  # (u, 3, 3)
            columns = f["landmark_unique"][:, None] + np.arange(3)  # (u, 3)
            normal[fixed_columns[:, None, None], columns[None]] = cross.transpose(1, 0, 2)
            normal[columns[:, :, None], fixed_columns[None, None, :]] = cross.transpose(0, 2, 1)
            normal[columns[:, :, None], columns[:, None, :]] = own
            # C's landmark columns: each measurement's 3 x 3 added at (its placement, its landmark)
            segment = self._segment_of_measurement[lo + marks] - segments[0]
            at = (segment[:, None, None] * 3 + np.arange(3)[None, :, None]) * (width + 1) + (
                f["landmark_columns"][:, None, None] + np.arange(3)[None, None, :])
            C += np.bincount(at.ravel(), moments_v[lo + marks, :, k - 4 : k - 1].ravel(),
                             minlength=C.size).reshape(C.shape)
        return normal, C

    def _linearized_blocks(self) -> dict:
        """The pieces the covariances need (``self._blocks``), once an evaluation with Jacobians made them."""
        if self._blocks is None:
            raise RuntimeError("eliminated factors: not linearised yet (evaluate with Jacobians first)")
        return self._blocks

    # --- the factors' error function ---------------------------------------------------------------

    def error_function(self, f: int):
        """``error(this, values, jacobians)`` of factor ``f`` for ``gtsam.CustomFactor``."""
        width = self._factors[f]["width"]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            self._evaluate(values, H is not None)
            if H is None:
                out = np.zeros(width + 1)
                out[-1] = np.sqrt(self._cost[f])
                return out
            systems = self._systems
            if systems is None:  # evaluating with Jacobians always leaves them
                raise RuntimeError("eliminated factors: no linear systems after evaluating with Jacobians")
            rhs, blocks = systems[f]
            H.clear()
            H.extend(blocks)
            return rhs

        return error

    # --- after the optimisation -------------------------------------------------------------------

    def mirror_vectors(self, values: gtsam.Values) -> dict[tuple[int, int], np.ndarray]:
        """The eliminated placements' mirror vectors (camera frame, metres) at ``values``' kept unknowns."""
        self._evaluate(values, False)
        return {self._config_of_row[int(r)]: self._P[r].copy() for r in self._elim_rows}

    def information(self, values: gtsam.Values) -> np.ndarray:
        """Information matrix of the kept unknowns (the Schur complement), GTSAM tangents, key order
        ``kept_keys`` (6 for the pose, 3 for each other)."""
        self._evaluate(values, True)
        H = np.zeros((self.dimension_kept, self.dimension_kept))
        for f, information in zip(self._factors, self._linearized_blocks()["information"]):
            cols = f["columns"]
            H[np.ix_(cols, cols)] += information
        return H

    def covariances(self, values: gtsam.Values) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]] | None:
        """``(covariance of the kept unknowns (GTSAM tangents, kept_keys order), {eliminated config: 3x3})``
        at ``values``, or None when the information is singular (the caller names the unknowns)."""
        H = self.information(values)
        with one_blas_thread():
            return self._covariances(H)

    def _covariances(self, H: np.ndarray) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]] | None:
        try:
            if np.min(np.linalg.eigvalsh(H)) <= 1e-12 * np.max(np.diag(H)):
                return None
            covariance = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(covariance)):
            return None
        linearized = self._linearized_blocks()
        D_inv = linearized["D_inv"]
        placements = np.empty((len(D_inv), 3, 3))
        for f, C in zip(self._factors, linearized["C"]):
            cols = f["columns"]
            K = D_inv[f["segments"]] @ C  # D^-1 B^T
            placements[f["segments"]] = D_inv[f["segments"]] + K @ covariance[np.ix_(cols, cols)] @ K.transpose(0, 2, 1)
        by_config = {}
        for segment, j in enumerate(self._placement_of_segment.tolist()):
            by_config[self._config_of_row[int(self._elim_rows[j])]] = placements[segment]
        return covariance, by_config

    def kept_offsets(self) -> dict[int, int]:
        """Column of each kept key in :meth:`information` / :meth:`covariances`."""
        return {self.pose_key: 0, **{self.point_keys[r]: self._column_of_row[r] for r in self._kept_rows.tolist()}}


def eliminated_evaluator(
    dataset: Fiducials,
    layout: KeyLayout,
    measurements: Sequence[Observation],
    noise_sigma: np.ndarray,
    initial_vectors: Mapping[tuple[int, int], np.ndarray],
) -> EliminatedEvaluator:
    """The evaluator and its factors (``evaluator.factors``), one per parent placement.

    dataset: has ``fiducials``; layout: ``pose_key``, ``mirror_keys``, ``point_keys``; measurements:
    ``graph.Measurement`` objects; noise_sigma: (2,) normalized, or (N, 2), one row per measurement in
    the order of ``measurements``; initial_vectors: start of every
    last-level placement ``(Nv, m) -> v`` (camera frame, metres). The factors hold the evaluator;
    clear ``evaluator.factors`` once they are in a graph (else a reference cycle through C++).
    """
    evaluator = EliminatedEvaluator(dataset, layout, measurements, noise_sigma, initial_vectors)
    for f, spec in enumerate(evaluator._factors):
        noise = gtsam.noiseModel.Unit.Create(spec["width"] + 1)
        evaluator.factors.append(gtsam.CustomFactor(noise, spec["keys"], evaluator.error_function(f)))
    return evaluator
