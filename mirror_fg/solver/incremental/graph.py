"""The iSAM2 side of :class:`~mirror_fg.solver.incremental.calibrator.IncrementalCalibrator`: its graph state, and
how waiting images join the graph (values of new placements and points, their factors, one update).

Frames, keys and units as ``calibrator.py``. :class:`GraphState` is everything a failed start-up rolls
back; :class:`IncrementalGraph` holds one and grows it (the calibrator holds one ``IncrementalGraph``);
the values of new placements come from ``values.py``.

The factors are the one measurement model's (``model/views.py``, built by ``view_factors.py``): each
image a view of the graph's camera, a placement that is an iSAM2 unknown an ``OrientedPlane3`` (its
mirror vector ``v = d n``), a point a ``Point3`` in the base frame.

Eliminated placements (without a robust kernel). The last mirror moves in (nearly) every image,
so one unknown per placement in iSAM2 makes each update cost O(images): every Python factor call gets
a copy of iSAM2's whole ``Values``, and reading the estimate back touches every unknown. Instead each
last-mirror placement is eliminated inside its views' factors (``factors/view_eliminated.py``,
``factors/view_points_eliminated.py``: a Schur complement, as GTSAM's ``SmartProjectionFactor``
eliminates its landmark; the factor's cost is the minimum over the placement, eq. 23, and its
linearisation has the same normal equations as the placement's measurements with the placement
eliminated first). iSAM2 then holds only ``T_cam_base``, the placements of mirrors 1..Nv-1 and the
points. The placements are grouped in :class:`PlacementBlock` s, one stack each (one factor, or a few
with reconstruction points), all under one parent placement: a new image's placement starts a block of
its own, and ``MERGE_FANOUT`` blocks of one level are merged into one (the old factors removed from
iSAM2 in the same update): O(log n) factors for n images, so neither the root clique's re-elimination
nor a relinearisation of the pose grows with the number of Python factors. A merged block, linearised
at iSAM2's linearisation point, is the sum of the blocks it replaces: the same linear system. The
placements' values come from their block (at the estimate when it was made, and for every placement in
``calibration(full=True)``); a placement seen under two parents (or with a robust kernel, every
placement) stays a plane in iSAM2 with the model's stacked factors.
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V

from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.data import Dataset, Image
from mirror_fg.factors.schur import one_blas_thread
from mirror_fg.factors.view_eliminated import collapsed
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.model.graph import Measurement
from mirror_fg.solver.incremental.state import GraphState, PlacementBlock, RelinearizeThresholds, new_isam2
from mirror_fg.solver.incremental.view_factors import eliminated_block, plane_of, stacked_factors, vector_at
from mirror_fg.solver.incremental.values import (
    MIN_PNP_FIDUCIALS,
    REFINE_ITERATIONS,
    PlacementInitialiser,
    initialise_points,
    refine_alone,
)
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.solver.model.residuals import predicted_normalized, residual_statistics
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem
from mirror_fg.solver.result.builder import build_calibration
from mirror_fg.solver.timing import timed

__all__ = [
    "GraphState", "IncrementalGraph", "RelinearizeThresholds", "PlacementBlock", "MIN_PNP_FIDUCIALS", "REFINE_ITERATIONS",
    "POLISH_UPDATES", "ROBUST_POLISH_UPDATES", "POLISH_SIGMAS", "MERGE_FANOUT",
]

#: ``calibration(full=True)`` relinearises every factor at most this many times ...
POLISH_UPDATES = 5
#: ... and with a robust kernel this many: each relinearisation re-weights the measurements too (one
#: step of iteratively reweighted least squares), which converges linearly (a clean 60-image tree with
#: Huber needed 12 to move the pose by < 1e-3 sigma, and stalled at 5).
ROBUST_POLISH_UPDATES = 30
#: ... until a relinearisation moves the pose by less than this (Mahalanobis).
POLISH_SIGMAS = 1e-3
#: Blocks of eliminated placements under one parent are merged this many at a time (a block of level k
#: holds >= MERGE_FANOUT**k placements): at most ``MERGE_FANOUT - 1`` blocks per level and parent, so
#: O(log n) factors in iSAM2 for n images, and each placement is re-blocked O(log n) times in all.
MERGE_FANOUT = 8


class IncrementalGraph:
    """The graph of an :class:`~mirror_fg.solver.incremental.calibrator.IncrementalCalibrator` and how waiting images
    join it: iSAM2, its factors and values (:attr:`state`, what a failed start-up rolls back), one
    ``ISAM2.update`` per batch of new factors.

    ``dataset``: the calibrator's; its ``images`` list is the state's images in the graph. ``robust``:
    ``None``, ``"huber"`` or ``"cauchy"``; ``thresholds``: iSAM2's relinearisation thresholds;
    ``timings``: the calibrator's stage times, added to; ``seed``: of each state's random generator (the
    hypotheses of a node of new placements, eqs. 13-18; :meth:`reset`).
    """

    def __init__(
        self, dataset: Dataset, robust: str | None, thresholds: RelinearizeThresholds, timings: dict[str, float],
        seed: int,
    ) -> None:
        self._ds = dataset
        self._robust = robust
        self._thresholds = thresholds
        self._seed = seed
        self.timings = timings
        self._placements = PlacementInitialiser(dataset)
        #: iSAM2 updates so far (over every state: a start-up's new state continues the count).
        self.updates = 0
        self._state: GraphState
        self.reset([])

    @property
    def dataset(self) -> Dataset:
        """The calibrator's dataset (camera, fiducials, sigma); its ``images``: those in the graph."""
        return self._ds

    @property
    def state(self) -> GraphState:
        """The graph, the estimate, and the images in and waiting for it."""
        return self._state

    @state.setter
    def state(self, state: GraphState) -> None:
        """Make ``state`` the graph's (a new start-up's, or the one a failed start-up rolls back to)."""
        self._state = state
        self._ds.images = state.images

    def reset(self, waiting: Iterable[Image]) -> None:
        """Empty graph and estimate (before a start-up); ``waiting``: the images accepted so far."""
        self.state = GraphState.empty(waiting, self._seed)

    def unconstrained(self, error: Exception) -> str:
        """What GTSAM's indeterminant linear system ``error`` says, naming the unknown of the graph."""
        return unconstrained_message(error, self._state.layout)

    # --- adding images ------------------------------------------------------------------------------

    def collect(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Move every waiting image that can be added into the graph: new values and factors."""
        ready: list[Measurement] = []
        progress = True
        while progress:
            progress = False
            still_waiting = []
            for image in self._state.waiting:
                if all((l + 1, m) in self._state.layout.mirror_keys for l, m in enumerate(image.mirror_configs)):
                    self._add_to_graph(image, ready)
                    progress = True
                else:
                    still_waiting.append(image)
            self._state.waiting = still_waiting
            if self._state.waiting:
                with timed(self.timings, "initialise"):
                    found = self._placements.placements(self._state)
                for config in sorted(found):
                    self.new_mirror(config, found[config], values)
                    progress = True
        ready.extend(initialise_points(self._state, values))
        self._add_factors(ready, factors, values)

    def _add_to_graph(self, image: Image, ready: list[Measurement]) -> None:
        """Put an image in the graph: its measurements go to ``ready``, or wait for their point's value."""
        self._ds.images.append(image)
        normalized = self._ds.normalized(image)
        for name in image.observations:
            meas = Measurement(image.id, name, normalized[name], image.mirror_configs)
            if name in self._ds.fiducials or name in self._state.layout.point_keys:
                ready.append(meas)
            else:
                self._state.point_waiting[name].append(meas)

    def _add_factors(
        self, measurements: list[Measurement], factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> None:
        """The factors of ``measurements`` into ``factors`` (the next update's), and into the graph state.

        Without a robust kernel, measurements whose last placement is eliminated go to placement blocks
        (module docstring, :meth:`_place_in_blocks`); the others get the view model's stacked factors
        (``view_factors.stacked_factors``: a few vectorised factors instead of one Python factor per
        measurement; each view takes only the keys its measurements use).
        """
        if not measurements:
            return
        self._state.measurements.extend(measurements)
        if self._robust is None:
            measurements = self._place_in_blocks(measurements, factors, values)
            if not measurements:
                return
        for factor in stacked_factors(self._ds, self._state.layout, measurements, self._robust):  # point_sigma where given
            factors.add(factor)
            self._state.factors.add(factor)

    def _place_in_blocks(
        self, measurements: list[Measurement], factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> list[Measurement]:
        """Put measurements whose last placement is eliminated into placement blocks; return the others.

        A block holding a placement that gets new measurements (a point's value came, the placement is
        seen again) is dissolved and re-made with them. A placement seen under a second parent becomes an
        iSAM2 unknown (its plane inserted into ``values``; its measurements are returned). Then ``MERGE_FANOUT``
        blocks of one level and parent are merged, until none are. Removed blocks' iSAM2 indices go to
        ``removals``, new blocks' factors into ``factors`` (``pending`` until the update numbers them).
        """
        g = self._state
        Nv = self._ds.num_mirrors
        explicit = [m for m in measurements if (Nv, m.mirror_configs[-1]) in g.kept]
        pool = [m for m in measurements if (Nv, m.mirror_configs[-1]) not in g.kept]
        parents: dict[tuple[int, int], set[tuple[int, ...]]] = defaultdict(set)
        for meas in pool:
            parents[(Nv, meas.mirror_configs[-1])].add(tuple(meas.mirror_configs[:-1]))
        dissolved: dict[int, PlacementBlock] = {}
        for config, seen in parents.items():
            block = g.block_of.get(config)
            if block is not None:
                seen.add(block.parent)
                dissolved[id(block)] = block
        for block in dissolved.values():
            self._drop_block(block)
            pool.extend(block.measurements)
        for config, seen in parents.items():
            if len(seen) > 1:  # one placement under two parents: an iSAM2 unknown of its own
                g.kept[config] = g.layout.mirror_keys[config]
                values.insert(g.layout.mirror_keys[config], plane_of(g.mirrors[config]))
        explicit += [m for m in pool if (Nv, m.mirror_configs[-1]) in g.kept]
        pool = [m for m in pool if (Nv, m.mirror_configs[-1]) not in g.kept]
        by_parent: dict[tuple[int, ...], list[Measurement]] = defaultdict(list)
        for meas in pool:
            by_parent[tuple(meas.mirror_configs[:-1])].append(meas)
        for parent, block_measurements in by_parent.items():
            placements = list(dict.fromkeys((Nv, m.mirror_configs[-1]) for m in block_measurements))
            level = 0
            while MERGE_FANOUT ** (level + 1) <= len(placements):
                level += 1
            while True:  # merge MERGE_FANOUT blocks of the new one's level into it, as long as there are
                same = [b for b in g.blocks if b.parent == parent and b.level == level]
                if len(same) + 1 < MERGE_FANOUT:
                    break
                for block in same:
                    self._drop_block(block)
                    block_measurements = block.measurements + block_measurements
                    placements = block.placements + placements
                level += 1
            self._make_block(parent, level, block_measurements, placements, factors)
        return explicit

    def _make_block(
        self, parent: tuple[int, ...], level: int, measurements: list[Measurement], placements: list[tuple[int, int]],
        factors: gtsam.NonlinearFactorGraph,
    ) -> None:
        """The factors of ``measurements`` with ``placements`` (all under ``parent``) eliminated, into the state
        and ``factors``."""
        g = self._state
        evaluator = eliminated_block(self._ds, g.layout, measurements, {c: g.mirrors[c] for c in placements})
        block_factors, evaluator.factors = evaluator.factors, []  # the block holds the factors, they the evaluator: no cycle
        block = PlacementBlock(parent, level, measurements, placements, evaluator, block_factors)
        g.blocks.append(block)
        for config in placements:
            g.block_of[config] = block
        self._add_block_factors(block, factors)

    def _add_block_factors(self, block: PlacementBlock, factors: gtsam.NonlinearFactorGraph) -> None:
        """A block's factors into ``factors``, pending (their iSAM2 indices come with the update)."""
        self._state.pending.append((block, list(range(factors.size(), factors.size() + len(block.factors)))))
        for factor in block.factors:
            factors.add(factor)

    def _drop_block(self, block: PlacementBlock) -> None:
        """Take a block out of the state; its factor leaves iSAM2 with the next update."""
        g = self._state
        g.blocks.remove(block)
        for config in block.placements:
            if g.block_of.get(config) is block:
                del g.block_of[config]
        if block.indices is not None:
            g.removals.extend(block.indices)
        else:  # made earlier in this same update: not in iSAM2 yet
            g.pending = [(b, position) for b, position in g.pending if b is not block]

    def new_mirror(self, config: tuple[int, int], v: np.ndarray, values: gtsam.Values) -> None:
        """A key and a value for a new placement; into ``values`` (iSAM2's) unless it is eliminated."""
        key = V(len(self._state.layout.mirror_keys))
        self._state.layout.mirror_keys[config] = key
        self._state.mirrors[config] = np.asarray(v, dtype=float)
        if self._robust is not None or config[0] < self._ds.num_mirrors:
            self._state.kept[config] = key
            values.insert(key, plane_of(self._state.mirrors[config]))

    def refine_new(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Each new unknown of ``values`` moved to its optimum on ``factors`` with the rest held at the
        estimate (:func:`~mirror_fg.solver.incremental.values.refine_alone`)."""
        refine_alone(factors, values, self.estimate_values, self._state.layout.pose_key)

    # --- iSAM2 ----------------------------------------------------------------------------------------

    def update(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """One ``ISAM2.update`` with only the new factors and values (and the removal of the blocks merged
        or re-made); refresh the estimate."""
        with one_blas_thread():  # (the factors' small matrices: one limit for the whole update)
            self._update(factors, values)

    def _update(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        g = self._state
        isam = g.require_isam()
        with timed(self.timings, "isam2"):
            pending, g.pending, removals, g.removals = g.pending, [], g.removals, []
            with unconstrained_as_solve_error(self._ds.source, self.unconstrained):
                result = isam.update(factors, values, removals)
                pose_cov = isam.marginalCovariance(g.layout.pose_key)
            indices = result.getNewFactorsIndices()
            for block, positions in pending:
                block.indices = [int(indices[position]) for position in positions]
            self.updates += 1
        with timed(self.timings, "estimate"):
            before = (g.R, g.t, g.pose_cov)
            estimate = isam.calculateEstimate()
            self.set_estimate(estimate, [block for block, _ in pending])
            g.pose_cov = pose_cov
            g.step_sigmas = self.pose_step_sigmas(*before)

    def pose_step_sigmas(self, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> float:
        """Mahalanobis size of the pose step from ``(R, t)`` to the estimate, against ``covariance``
        (GTSAM's tangent; the current covariance when it is undefined, as at a start-up)."""
        step = gtsam.Pose3(gtsam.Rot3(R), t).localCoordinates(gtsam.Pose3(gtsam.Rot3(self._state.R), self._state.t))
        reference = covariance if np.all(np.isfinite(covariance)) else self._state.pose_cov
        quadratic = float(step @ np.linalg.solve(reference, step))
        return float(np.sqrt(max(quadratic, 0.0)))

    def new_isam2(self) -> gtsam.ISAM2:
        return new_isam2(self._thresholds)

    def _all_factors(self) -> gtsam.NonlinearFactorGraph:
        """Every factor of the graph (stacked ones, then the blocks'); the blocks pending as new."""
        g = self._state
        factors = gtsam.NonlinearFactorGraph()
        factors.push_back(g.factors)
        g.pending = []
        for block in g.blocks:
            self._add_block_factors(block, factors)
        return factors

    def polish(self) -> None:
        """Relinearise every factor at the current estimate until the pose stops moving.

        The thresholds leave variables linearised up to a threshold away from the estimate (second-order
        error); a fresh iSAM2 holding the same factors, linearised at the current estimate, is a full
        Gauss-Newton step (one pass over every factor, like one batch iteration).
        """
        for _ in range(POLISH_UPDATES if self._robust is None else ROBUST_POLISH_UPDATES):
            values = self.estimate_values()
            self._state.isam = self.new_isam2()
            self._state.removals = []  # a fresh iSAM2 holds nothing to remove
            self.update(self._all_factors(), values)
            if self._state.step_sigmas < POLISH_SIGMAS:
                break

    def set_estimate(self, values: gtsam.Values, blocks: Iterable[PlacementBlock] = ()) -> None:
        """Read the estimate of iSAM2's unknowns from ``values``, and the placements of ``blocks`` at it
        (every other eliminated placement keeps the value its block last gave)."""
        g = self._state
        pose = values.atPose3(g.layout.pose_key)
        g.R, g.t = pose.rotation().matrix(), np.array(pose.translation())
        for config, key in g.kept.items():
            g.mirrors[config] = vector_at(values, key)
        for name, key in g.layout.point_keys.items():
            g.points[name] = np.array(values.atPoint3(key))
        for block in blocks:
            g.mirrors.update(block.evaluator.mirror_vectors(values))

    def estimate_values(self, keys: Iterable[int] | None = None) -> gtsam.Values:
        """The current estimate of iSAM2's unknowns (not the eliminated placements) as GTSAM values: every
        one, or those of ``keys``."""
        g = self._state
        values = gtsam.Values()
        wanted = None if keys is None else set(keys)
        if wanted is None or g.layout.pose_key in wanted:
            values.insert(g.layout.pose_key, gtsam.Pose3(gtsam.Rot3(g.R), g.t))
        for config, key in g.kept.items():
            if wanted is None or key in wanted:
                values.insert(key, plane_of(g.mirrors[config]))
        for name, key in g.layout.point_keys.items():
            if wanted is None or key in wanted:
                values.insert(key, g.points[name])
        return values

    def explicit_problem(self, refresh: bool = True) -> tuple[ViewProblem, ViewEstimate]:
        """The graph's measurements as a problem of the one model (``model/views.py``: each image restricted
        to its measurements in the graph) and the estimate, every eliminated placement at its optimum there
        (``refresh``; else at the value it has): what ``calibration(full=True)`` takes covariances and
        residuals of, and what a start-up whose placements collapsed solves with every placement an unknown
        (O(images), once)."""
        g = self._state
        values = self.estimate_values()
        for block in g.blocks if refresh else []:
            g.mirrors.update(block.evaluator.mirror_vectors(values))
        names: dict[str, set[str]] = defaultdict(set)
        for meas in g.measurements:
            names[meas.image_id].add(meas.point)
        images = [replace(image, observations={n: z for n, z in image.observations.items() if n in names[image.id]})
                  for image in g.images if image.id in names]
        problem = ViewProblem(replace(self._ds, images=images), self._robust)
        estimate = ViewEstimate({SINGLE_CAMERA: (g.R.copy(), g.t.copy())},
                                {p: g.mirrors[p].copy() for p in problem.placements},
                                {n: g.points[n].copy() for n in problem.point_names})
        return problem, estimate

    def explicit_covariances(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, tuple]:
        """The graph of :meth:`explicit_problem` at the estimate (its own placements eliminated where the
        model allows it), its values and ``ViewProblem.covariances`` there: pose (docs/formats.md
        convention), mirror vectors and points."""
        problem, estimate = self.explicit_problem()
        graph, values, evaluator = problem.solve_graph(estimate)
        with unconstrained_as_solve_error(self._ds.source, lambda error: unconstrained_message(error, problem)):
            poses, _, mirrors, points, _ = problem.covariances(graph, values, estimate, evaluator)
        return graph, values, (poses[SINGLE_CAMERA], mirrors, points)

    def placements_collapsed(self, values: gtsam.Values) -> bool:
        """Whether an eliminated placement at ``values`` has run into the camera centre
        (``factors.view_eliminated.collapsed``)."""
        return collapsed([v for block in self._state.blocks for v in block.evaluator.mirror_vectors(values).values()])

    def remake_blocks(self, solution: ViewEstimate) -> gtsam.NonlinearFactorGraph:
        """Take the estimate from ``solution``, a solve of :meth:`explicit_problem` (every placement an
        unknown), and make every block anew from it. Returns every factor, for a fresh iSAM2."""
        g = self._state
        g.R, g.t = (np.asarray(x, float).copy() for x in solution.poses[SINGLE_CAMERA])
        g.mirrors.update({p: np.asarray(v, float).copy() for p, v in solution.mirror_vectors.items()})
        g.points.update({n: np.asarray(x, float).copy() for n, x in solution.points.items()})
        old, g.blocks, g.block_of, g.pending = g.blocks, [], {}, []
        factors = gtsam.NonlinearFactorGraph()
        factors.push_back(g.factors)
        for block in old:  # their placements start from the solution
            self._make_block(block.parent, block.level, block.measurements, block.placements, factors)
        return factors

    # --- the estimate as a Calibration ----------------------------------------------------------------

    def calibration(
        self, analytic: AnalyticSolution | None, settled: bool, excluded: list[Exclusion], full: bool = False
    ) -> Calibration:
        """The estimate as a ``Calibration`` (``IncrementalCalibrator.calibration`` says what each holds):
        ``full=False`` the pose and its covariance from iSAM2, no residuals; ``full=True`` covariances of
        every unknown and residuals of every measurement, on :meth:`explicit_covariances` at the estimate.
        ``analytic``: the latest start-up's; ``settled``: ``converged`` (with ``full``, also the last
        relinearisation's pose step below ``POLISH_SIGMAS``); ``excluded``: what the calibrator left out."""
        g = self._state
        if not full:
            return self._calibration(
                analytic, settled, excluded, covariance=covariance_from_pose3(g.R, g.pose_cov), mirror_covs={},
                point_covs={}, residuals=np.zeros((0, 2)), whitened=np.zeros(0), labels=[], final_error=math.nan,
                unknowns=None,
            )
        factors, estimate, (covariance, mirror_covs, point_covs) = self.explicit_covariances()
        predicted = predicted_normalized(self._ds, g.measurements, g.R, g.t, g.mirrors, g.points)
        residuals, whitened = residual_statistics(self._ds, g.measurements, predicted)
        # Its cost judged as the batch's (lm.LMRun.expected_final_error): two per measurement less
        # the unknowns (pose, every mirror vector, points).
        calibration = self._calibration(
            analytic, settled, excluded, covariance=covariance, mirror_covs=mirror_covs, point_covs=point_covs,
            residuals=residuals, whitened=whitened, labels=[(m.image_id, m.point) for m in g.measurements],
            final_error=float(factors.error(estimate)), unknowns=6 + 3 * len(g.mirrors) + 3 * len(g.points),
        )
        calibration.converged = settled and g.step_sigmas < POLISH_SIGMAS
        return calibration

    def _calibration(
        self, analytic: AnalyticSolution | None, settled: bool, excluded: list[Exclusion], *, covariance, mirror_covs,
        point_covs, residuals, whitened, labels, final_error, unknowns,
    ) -> Calibration:
        g = self._state
        return build_calibration(
            self._ds, (g.R.copy(), g.t.copy()), covariance, mirror_vectors=dict(g.mirrors),
            mirror_covariances=mirror_covs, points=dict(g.points), point_covariances=point_covs,
            residuals=residuals, whitened=whitened, labels=labels, unknowns=unknowns, iterations=self.updates,
            initial_error=g.initial_error, final_error=final_error, converged=settled, timings=dict(self.timings),
            excluded=excluded, analytic=analytic,
        )
