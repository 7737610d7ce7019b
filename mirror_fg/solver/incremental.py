"""Incremental calibration with iSAM2: the estimate and its 3-sigma bounds firm up image by image.

Same unknowns, measurement model and noise as the batch pipeline (``graph.py``): ``X(0)`` is
``T_cam_base`` (camera <- base, ``Cp = R Bp + t``, metres), ``V(i)`` one mirror vector per configuration
``(l, m)`` (camera frame, metres), ``L(j)`` one reconstruction point (base frame, metres); keys are
numbered in the order the unknowns get a value. The factors are the batch fast path's stacked ones
(``factors.batched``: one Python call per image instead of one per measurement), built for each
update's new measurements only.

Life of an image (``IncrementalCalibrator.add_image``):

1. It is validated (``dataset.validate_image``) and refused with ``DatasetError`` on bad input, leaving
   the calibrator as it was.
2. Until start-up every image waits. Start-up happens at the first image where the images with >= 3
   fiducials contain a complete configuration tree (:func:`complete_tree`: every kept placement of
   mirror l has >= 3 kept placements of mirror l+1 under it, the root >= 3 placements of mirror 1;
   Sect. 4.2, Fig. 3). The analytical solution is solved on that tree, every image whose placements
   it determines goes into one graph, Levenberg-Marquardt refines it (as the batch does) and a fresh
   iSAM2 gets that whole graph at the refined values.
3. Afterwards an image whose placements all have values only adds its factors (one ``ISAM2.update``
   with the new factors and values, nothing re-added). A new placement gets its value from the image's
   PnP ``(A, b)`` (eqs. 10-12) and the current estimate: the known mirrors after it are peeled off
   ``(A, b)`` and those before it applied to ``T_cam_base``, which leaves one reflection (eqs. 6-7): its
   normal is the -1 eigenvector of ``A_l A_{l-1}^T``, its offset the part of ``b_l - M_l b_{l-1}`` along
   it. Several new placements in one image (a new placement of mirror 1 with a new one of mirror 2)
   wait until their subtree can be solved like a node of the analytical solution (eqs. 13-18) under
   the known parent. A reconstruction point gets its value by eq. (20) from the current estimate once
   two images in the graph see it; until then its observations wait. Each new unknown is then moved
   to its optimum with everything else held (a few Gauss-Newton steps on its own factors) so that
   iSAM2 does not keep it linearised at a rough initial value.

Settling. On the smallest tree (a placement seen with only three children) the analytical solution
can be far off: on the issue's 300-image stream (seed 0) it is 1.5 m off at image 203, where the
likelihood has a long curved valley; Levenberg-Marquardt stalls in it and undamped Gauss-Newton, what
iSAM2 does, diverged from there (65 deg off after two steps, then an indeterminant system). So a
start-up counts as *settled* only when iSAM2's Gauss-Newton step at the LM solution moves the pose by
less than ``SETTLED_SIGMAS`` of its own standard deviation. Until then the estimate reported is the LM
one and the start-up is re-run on every image so far (on that stream it settles five images later,
when the analytical solution is 0.3 m off). A settled calibrator whose pose jumps by more than
``DIVERGENCE_SIGMAS`` in one update, or meets an indeterminant system, restarts the same way.
"""
from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from mirror_fg.solver.analytic import (
    MIN_NORMAL_SPREAD,
    AnalyticSolution,
    solve_node,
    pnp_candidates,
    reflection_fit,
    triangulate_point,
)
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import Dataset, Image, validate_image
from mirror_fg.factors.batched import batched_factors
from mirror_fg.core.geometry import householder, nested_transform
from mirror_fg.solver.graph import (
    OUTLIER_SIGMAS,
    Calibration,
    GraphLayout,
    Measurement,
    extract_values,
    initial_estimate,
    as_dataset,
    cost_scale,
    lm_params,
    require_converged,
    marginal_covariances,
    predicted_normalized,
    residual_statistics,
    unconstrained_message,
)
from mirror_fg.core.transform import spec_covariance_from_pose3

__all__ = ["IncrementalCalibrator", "RelinearizeThresholds", "complete_tree"]

#: Minimum number of fiducials in an image for its own PnP (eq. 10; 3 gives up to four candidates).
MIN_PNP_FIDUCIALS = 3
#: Levenberg-Marquardt iterations at most per start-up (a stalled start-up is retried with more images).
STARTUP_LM_ITERATIONS = 30
#: ... and for ``calibration(full=True)`` of an unsettled calibrator (as ``graph.calibrate``).
FINAL_LM_ITERATIONS = 100
#: A start-up is settled when iSAM2's Gauss-Newton step at the LM solution moves the pose by less than
#: this many of its own standard deviations (Mahalanobis distance).
SETTLED_SIGMAS = 0.5
#: A settled calibrator restarts when one update moves the pose by more than this (Mahalanobis).
DIVERGENCE_SIGMAS = 5.0
#: Unsettled: re-run the start-up on every image for this many tries, then on every 2nd, 4th, ... image.
UNSETTLED_EVERY_IMAGE = 8
#: ... but at least every this many images.
UNSETTLED_MAX_INTERVAL = 32
#: Gauss-Newton iterations on a new unknown alone before it goes to iSAM2.
REFINE_ITERATIONS = 3
#: ``calibration(full=True)`` relinearises every factor at most this many times ...
POLISH_UPDATES = 5
#: ... until a relinearisation moves the pose by less than this (Mahalanobis).
POLISH_SIGMAS = 1e-3


@dataclass(frozen=True)
class RelinearizeThresholds:
    """iSAM2 relinearisation thresholds per kind of unknown (absolute tangent components).

    A variable is relinearised (each of its factors re-evaluated in Python: the expensive part) when a
    component of its iSAM2 delta exceeds the threshold. ``pose``: ``[w (rad) x3, nu (m) x3]``, GTSAM's
    Pose3 tangent of ``T_cam_base``; ``mirror`` and ``point``: metres. Every factor touches the pose, so
    its threshold sets how often an update costs a pass over the whole graph; what a linearisation
    point that far from the estimate costs in accuracy is second order (one Gauss-Newton step).
    """

    pose: tuple[float, float, float, float, float, float] = (0.005, 0.005, 0.005, 0.01, 0.01, 0.01)
    mirror: float = 0.003
    point: float = 0.003

    def threshold_map(self) -> gtsam.ISAM2ThresholdMap:
        thresholds = gtsam.ISAM2ThresholdMap()
        thresholds.insert(("x", np.asarray(self.pose, dtype=float)))
        thresholds.insert(("v", np.full(3, float(self.mirror))))
        thresholds.insert(("l", np.full(3, float(self.point))))
        return thresholds


def complete_tree(images: Iterable[Image], num_mirrors: int) -> list[Image]:
    """The images that form a complete configuration tree (Fig. 3), or ``[]`` if there is none.

    Bottom-up, a placement of mirror l is kept when >= 3 kept placements of mirror l+1 were seen under
    it (a leaf, a placement of mirror Nv, is kept when seen); the tree exists when >= 3 placements of
    mirror 1 are kept. Returns the images whose every placement is kept, in their order.
    """
    images = list(images)
    kept: set[tuple[int, ...]] = {im.mirror_configs for im in images}  # level Nv: every leaf seen
    kept_by_level = {num_mirrors: kept}
    for level in range(num_mirrors, 0, -1):
        children: dict[tuple[int, ...], set[int]] = defaultdict(set)
        for prefix in kept:
            children[prefix[:-1]].add(prefix[-1])
        kept = {parent for parent, c in children.items() if len(c) >= 3}
        kept_by_level[level - 1] = kept
    if () not in kept_by_level[0]:
        return []
    return [
        im for im in images if all(im.mirror_configs[:level] in kept_by_level[level] for level in range(num_mirrors + 1))
    ]


@dataclass
class _Candidate:
    """One hypothesis for a node's ``(A_k, b_k)`` and the new mirror vectors it implies below it."""

    A: np.ndarray
    b: np.ndarray
    mirrors: dict[tuple[int, int], list[np.ndarray]] = field(default_factory=dict)


class IncrementalCalibrator:
    """Camera-to-base calibration that takes images one at a time (iSAM2 on the batch factors).

    ``dataset`` gives the camera, fiducials, number of mirrors and pixel sigma; its images are not
    calibrated. ``points``: the reconstruction point names images may use; ``None`` takes the names in
    ``dataset.images`` when it has images (any other non-fiducial name is then refused as unknown) and
    accepts any non-fiducial name when it has none. ``robust``: ``None``, ``"huber"`` or ``"cauchy"``
    kernel as in ``graph.calibrate``. ``thresholds``: iSAM2 relinearisation thresholds. ``seed``: for the
    analytical solution's P3P hypotheses.

    ``add_image(image)`` returns ``None`` until the analytical solution exists, then a cheap
    ``Calibration`` after every image; ``calibration(full=True)`` adds mirror and point covariances and
    residuals over every image in the graph; ``marginal_covariance()`` gives covariances on demand.
    """

    def __init__(
        self,
        dataset: Dataset,
        *,
        points: Iterable[str] | None = None,
        robust: str | None = None,
        thresholds: RelinearizeThresholds | None = None,
        seed: int = 0,
    ) -> None:
        dataset = as_dataset(dataset, "IncrementalCalibrator()")
        # Our own Dataset holds the images in the graph: normalisation cache, residuals, messages.
        self._ds = Dataset(
            num_mirrors=dataset.num_mirrors,
            camera=dataset.camera,
            pixel_sigma=dataset.pixel_sigma,
            fiducials={name: np.array(p, dtype=float) for name, p in dataset.fiducials.items()},
            images=[],
            source=dataset.source,
        )
        if points is not None:
            self._known_points: set[str] | None = set(points)
        elif dataset.images:
            self._known_points = set(dataset.reconstruction_point_names)
        else:
            self._known_points = None
        if robust not in (None, "huber", "cauchy"):
            raise ValueError(f"unknown robust kernel {robust!r}: use 'huber' or 'cauchy'")
        self._robust = robust
        self._thresholds = thresholds or RelinearizeThresholds()
        self._seed = seed
        self._ids: set[str] = set()
        self._accepted: list[Image] = []  # every accepted image, in order
        self._pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        # Start-up / restart bookkeeping.
        self._analytic: AnalyticSolution | None = None
        self._settled = False
        self._unsettled_tries = 0
        self._accepted_at_restart = 0
        self._failed_tree: frozenset | None = None  # placements of the last failed analytical solution
        #: Why the latest start-up attempt failed (``None`` after a successful one).
        self.startup_error: Exception | None = None
        self.restarts = 0
        self._lm_iterations: list[int] = []  # LM iterations of each start-up
        self.timings: dict[str, float] = defaultdict(float)
        self._updates = 0
        self._reset_graph()

    def _reset_graph(self) -> None:
        """Empty graph and estimate (before a start-up)."""
        self._isam: gtsam.ISAM2 | None = None
        self._factors = gtsam.NonlinearFactorGraph()  # every factor in the graph (iSAM2 holds the same)
        self._layout = GraphLayout(pose_key=X(0), mirror_keys={}, point_keys={})
        self._ds.images = []
        self._waiting: list[Image] = list(self._accepted)  # accepted, not in the graph
        self._measurements: list[Measurement] = []  # in the graph, in the order added
        self._point_waiting: dict[str, list[Measurement]] = defaultdict(list)  # points without a value
        self._rng = np.random.default_rng(self._seed)
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self._mirrors: dict[tuple[int, int], np.ndarray] = {}
        self._points: dict[str, np.ndarray] = {}
        self._pose_cov = np.full((6, 6), np.nan)  # GTSAM's [w, nu]
        self._initial_error = math.nan
        self._step_sigmas = math.inf  # Mahalanobis size of the last pose step

    # --- public -------------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """Whether the analytical solution has been formed and there is an estimate."""
        return self._analytic is not None

    @property
    def settled(self) -> bool:
        """Whether iSAM2 runs on its own (the start-up's Levenberg-Marquardt solution was a clean minimum)."""
        return self._settled

    @property
    def num_images(self) -> int:
        """Images whose factors are in the graph."""
        return len(self._ds.images)

    @property
    def waiting_images(self) -> list[str]:
        """Ids of accepted images not in the graph: before start-up, or their placements still unknown."""
        return [im.id for im in self._waiting]

    @property
    def analytic(self) -> AnalyticSolution | None:
        """The analytical solution of the latest start-up (``None`` before start-up)."""
        return self._analytic

    def add_image(self, image: Image | Mapping[str, Any]) -> Calibration | None:
        """Take one image's observations (a ``mirror_fg.Image`` or its dataset@1 dict).

        Returns ``None`` while the analytical solution cannot be formed, else the current ``Calibration``
        (the cheap one, see :meth:`calibration`). Raises ``DatasetError`` on bad input (unknown point
        name, non-finite value, wrong ``mirror_configs`` length, an id already given) before anything
        changes. Trouble solving never raises here: the calibrator keeps its estimate, unsettled, retries
        with later images and keeps the reason in ``startup_error``.
        """
        checked = validate_image(image, self._ds, known_points=self._known_points)
        if checked.id in self._ids:
            raise DatasetError(f"{self._ds.source}: image {checked.id!r}: duplicate image id (already given)")
        # Accepted: nothing below is input validation.
        self._ids.add(checked.id)
        self._accepted.append(checked)
        self._waiting.append(checked)
        if not self._settled:
            if self._restart_due():
                self._restart()
            if not self.started:
                return None
        else:
            self._process_waiting()
        return self.calibration()

    def marginal_covariance(self, unknown: tuple[int, int] | str | None = None) -> np.ndarray:
        """Marginal covariance from iSAM2's Bayes tree, on demand (at the linearisation point).

        ``None``: ``T_cam_base``, 6x6 in SPEC's convention ``[dtheta (rad), dt (m)]`` with ``R_true =
        Exp(dtheta) R_est``, ``t_true = t_est + dt``. ``(l, m)``: the mirror vector of that configuration,
        3x3, m^2, camera frame. A point name: that reconstruction point, 3x3, m^2, base frame.
        """
        self._require_started()
        if unknown is None:
            return spec_covariance_from_pose3(self._R, self._pose_cov)
        key = self._layout.point_keys.get(unknown) if isinstance(unknown, str) else self._layout.mirror_keys.get(tuple(unknown))
        if key is None:
            raise KeyError(f"{unknown!r} has no value in the graph yet")
        if self._settled:
            return self._isam.marginalCovariance(key)
        # Unsettled, iSAM2 may not hold the reported (LM) estimate: marginals of the whole graph there.
        _, mirrors, points = marginal_covariances(self._factors, self._values(), self._layout, self._ds.source)
        return points[unknown] if isinstance(unknown, str) else mirrors[tuple(unknown)]

    def calibration(self, full: bool = False) -> Calibration:
        """The current estimate as a ``Calibration`` (same shape as the batch one).

        ``full=False`` (what ``add_image`` returns, about a millisecond): pose and its covariance from
        iSAM2; mirror vectors and points without covariances; no residuals (empty, so ``to_dict()``
        reports 0) and NaN ``initial_error``/``final_error`` (each would cost a pass over every factor).
        ``full=True`` (about a second for 300 images): first every factor is relinearised at the current
        estimate until the pose moves less than 1e-3 of its standard deviation (an unsettled calibrator
        first re-runs the start-up on every image with the batch's LM budget); then covariances of every
        unknown by ``gtsam.Marginals`` on the whole graph, the residual of every measurement in the graph,
        ``final_error`` of the whole graph and ``initial_error`` of the latest start-up graph at its
        analytical solution.

        Both: ``iterations`` counts iSAM2 updates so far; ``converged`` is whether the calibrator is
        settled (and, with ``full=True``, the relinearisation converged). Raises ``SolveError`` before
        start-up.
        """
        self._require_started()
        if not full:
            return self._make_calibration(
                covariance=spec_covariance_from_pose3(self._R, self._pose_cov),
                mirror_covs={},
                point_covs={},
                residuals=np.zeros((0, 2)),
                labels=[],
                outliers=[],
                final_error=math.nan,
            )
        start = time.perf_counter()
        if not self._settled:
            # Every image, and the batch's iteration budget, for the Levenberg-Marquardt solution.
            self._restart(lm_iterations=FINAL_LM_ITERATIONS)
        if self._settled:
            try:
                self._polish()
            except SolveError:  # relinearised, the system turned indeterminant: fall back to LM
                self._settled = False
                self._restart(lm_iterations=FINAL_LM_ITERATIONS)
        # Unsettled, the estimate is the start-up's Levenberg-Marquardt solution: no Gauss-Newton step.
        graph = self._factors
        estimate = self._values()
        covariance, mirror_covs, point_covs = marginal_covariances(graph, estimate, self._layout, self._ds.source)
        predicted = predicted_normalized(self._ds, self._measurements, self._R, self._t, self._mirrors, self._points)
        residuals, whitened = residual_statistics(self._ds, self._measurements, predicted)
        outliers = [(m.image_id, m.point, float(w)) for m, w in zip(self._measurements, whitened) if w > OUTLIER_SIGMAS]
        calibration = self._make_calibration(
            covariance=covariance,
            mirror_covs=mirror_covs,
            point_covs=point_covs,
            residuals=residuals,
            labels=[(m.image_id, m.point) for m in self._measurements],
            outliers=outliers,
            final_error=float(graph.error(estimate)),
        )
        calibration.converged = self._settled and self._step_sigmas < POLISH_SIGMAS
        calibration.timings["full"] = time.perf_counter() - start
        return calibration

    # --- start-up and restarts (Sects. 4-5) ------------------------------------------------------------

    def _restart_due(self) -> bool:
        """Unsettled: retry the start-up on every image at first, then less and less often."""
        if not self.started:
            return True
        tries = self._unsettled_tries - UNSETTLED_EVERY_IMAGE
        interval = 1 if tries < 0 else min(2 ** (tries // 4 + 1), UNSETTLED_MAX_INTERVAL)
        return len(self._accepted) - self._accepted_at_restart >= interval

    def _restart(self, lm_iterations: int = STARTUP_LM_ITERATIONS) -> bool:
        """Analytical solution on the complete tree of every image so far, LM, then a fresh iSAM2.

        Returns whether there is a new estimate. On failure (no complete tree yet, degenerate geometry)
        the calibrator keeps what it had, unsettled, and the reason in ``startup_error``.
        """
        start = time.perf_counter()
        saved, saved_images = dict(self.__dict__), self._ds.images
        try:
            self._start(lm_iterations)
            self.startup_error = None
            return True
        except (SolveError, DatasetError) as error:
            failed_tree = self._failed_tree
            self.__dict__.clear()
            self.__dict__.update(saved)
            self._ds.images = saved_images
            self._failed_tree = failed_tree
            self.startup_error = error
            self._settled = False
            return False
        finally:
            self.timings["startup"] += time.perf_counter() - start

    def _start(self, lm_iterations: int) -> None:
        Nv = self._ds.num_mirrors
        tree = complete_tree([im for im in self._accepted if self._num_fiducials(im) >= MIN_PNP_FIDUCIALS], Nv)
        if not tree:
            raise SolveError(
                f"{self._ds.source}: no complete tree of placements yet (each placement needs >= 3 child "
                "placements seen with >= 3 fiducials)"
            )
        placements = frozenset(im.mirror_configs for im in tree)
        if placements == self._failed_tree:
            # More views of the placements that failed will not make the analytical solution work.
            raise self.startup_error or SolveError(f"{self._ds.source}: the analytical solution failed")
        # Fiducials only: points are triangulated below from every image the start-up admits.
        fiducial_only = Dataset(
            num_mirrors=Nv,
            camera=self._ds.camera,
            pixel_sigma=self._ds.pixel_sigma,
            fiducials=self._ds.fiducials,
            images=[
                Image(im.id, im.mirror_configs, {n: z for n, z in im.observations.items() if n in self._ds.fiducials})
                for im in tree
            ],
            source=self._ds.source,
        )
        try:
            analytic = initial_estimate(fiducial_only, seed=self._seed)
        except (SolveError, DatasetError):
            self._failed_tree = placements
            raise
        was_started = self.started
        self._reset_graph()
        self._R = analytic.R_cam_base.copy()
        self._t = np.asarray(analytic.t_cam_base, dtype=float).copy()
        values = gtsam.Values()
        values.insert(self._layout.pose_key, gtsam.Pose3(gtsam.Rot3(self._R), self._t))
        for config in sorted(analytic.mirror_vectors):
            self._new_mirror(config, analytic.mirror_vectors[config], values)
        factors = gtsam.NonlinearFactorGraph()
        self._collect(factors, values)
        analytic.points = dict(self._points)  # eq. (20) at the analytical solution
        initial_error = float(factors.error(values))
        lm_start = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(factors, values, lm_params(lm_iterations, cost_scale(self._ds)))
        try:
            optimized = optimizer.optimize()
        except RuntimeError as error:  # IndeterminantLinearSystemException
            raise SolveError(f"{self._ds.source}: {unconstrained_message(error, self._layout)}") from None
        self.timings["startup_lm"] += time.perf_counter() - lm_start
        self._factors = factors
        self._isam = self._new_isam2()
        self._set_estimate(optimized)
        try:
            self._update(factors, optimized)
            # Settled when iSAM2's own Gauss-Newton step from the LM solution is small: the linear
            # model there can be trusted. Otherwise report the LM solution (iSAM2's covariance is the
            # one there: its linearisation point) and retry with later images.
            self._settled = self._step_sigmas < SETTLED_SIGMAS
        except SolveError:  # iSAM2's Cholesky gave up near the LM solution (nearly indeterminant)
            self._settled = False
            self._set_estimate(optimized)
            covariance, _, _ = marginal_covariances(factors, optimized, self._layout, self._ds.source)
            J = np.kron(np.eye(2), self._R.T)  # SPEC's [dtheta, dt] back to GTSAM's [w, nu]
            self._pose_cov = J @ covariance @ J.T
        if not self._settled:
            self._set_estimate(optimized)
        self._unsettled_tries = 0 if self._settled else self._unsettled_tries + 1
        self._analytic = analytic
        self._initial_error = initial_error
        self._accepted_at_restart = len(self._accepted)
        self.restarts += int(was_started)
        self._lm_iterations.append(optimizer.iterations())

    # --- adding images ------------------------------------------------------------------------------

    def _process_waiting(self) -> None:
        values = gtsam.Values()
        factors = gtsam.NonlinearFactorGraph()
        self._collect(factors, values)
        if factors.size() == 0 and values.size() == 0:
            return
        before = (self._R, self._t, self._pose_cov)
        self._refine_new(factors, values)
        self._factors.push_back(factors)
        try:
            self._update(factors, values)
            diverged = self._pose_step_sigmas(*before) > DIVERGENCE_SIGMAS
        except SolveError:
            diverged = True
        if diverged:
            self._settled = False
            self._restart()

    def _collect(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Move every waiting image that can be added into the graph: new values and factors."""
        ready: list[Measurement] = []
        progress = True
        while progress:
            progress = False
            still_waiting = []
            for image in self._waiting:
                if all((l + 1, m) in self._layout.mirror_keys for l, m in enumerate(image.mirror_configs)):
                    self._add_to_graph(image, ready)
                    progress = True
                else:
                    still_waiting.append(image)
            self._waiting = still_waiting
            if self._waiting:
                start = time.perf_counter()
                found = self._initialise_placements()
                self.timings["initialise"] += time.perf_counter() - start
                for config in sorted(found):
                    self._new_mirror(config, found[config], values)
                    progress = True
        ready.extend(self._initialise_points(values))
        self._add_factors(ready, factors)

    def _add_to_graph(self, image: Image, ready: list[Measurement]) -> None:
        """Put an image in the graph: its measurements go to ``ready``, or wait for their point's value."""
        self._ds.images.append(image)
        normalized = self._ds.normalized(image)
        for name in image.observations:
            meas = Measurement(image.id, name, normalized[name], image.mirror_configs)
            if name in self._ds.fiducials or name in self._layout.point_keys:
                ready.append(meas)
            else:
                self._point_waiting[name].append(meas)

    def _add_factors(self, measurements: list[Measurement], factors: gtsam.NonlinearFactorGraph) -> None:
        """The batch pipeline's fast factors (``factors.batched``) for ``measurements``, into ``factors``.

        One stacked, vectorised factor per image or group of images (a start-up passes every image at
        once) instead of one Python factor per measurement: iSAM2's relinearisation of the pose, a pass
        over every factor, is what dominates an update, and a Python call costs the same for one
        measurement as for many. The layout handed over holds only the keys these measurements use.
        """
        if not measurements:
            return
        configs = {(l + 1, m) for meas in measurements for l, m in enumerate(meas.mirror_configs)}
        names = {meas.point for meas in measurements if meas.point not in self._ds.fiducials}
        layout = GraphLayout(
            pose_key=self._layout.pose_key,
            mirror_keys={config: self._layout.mirror_keys[config] for config in configs},
            point_keys={name: self._layout.point_keys[name] for name in names},
        )
        for factor in batched_factors(self._ds, layout, measurements, self._ds.normalized_sigma, self._robust):
            factors.add(factor)
        self._measurements.extend(measurements)

    def _new_mirror(self, config: tuple[int, int], v: np.ndarray, values: gtsam.Values) -> None:
        key = V(len(self._layout.mirror_keys))
        self._layout.mirror_keys[config] = key
        self._mirrors[config] = np.asarray(v, dtype=float)
        values.insert(key, self._mirrors[config])

    def _initialise_points(self, values: gtsam.Values) -> list[Measurement]:
        """Eq. (20) for every point seen in two images of the graph, from the current estimate.

        Returns the measurements that now have every value they need.
        """
        ready: list[Measurement] = []
        transforms: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}  # per image placements
        for name in sorted(self._point_waiting):
            waiting = self._point_waiting[name]
            if len({m.image_id for m in waiting}) < 2:
                continue
            for m in waiting:
                if m.mirror_configs not in transforms:
                    transforms[m.mirror_configs] = self._transform(m.mirror_configs)
            point = triangulate_point([transforms[m.mirror_configs] for m in waiting], [m.normalized for m in waiting])
            key = L(len(self._layout.point_keys))
            self._layout.point_keys[name] = key
            self._points[name] = point
            values.insert(key, point)
            ready.extend(waiting)
            del self._point_waiting[name]
        return ready

    def _refine_new(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Gauss-Newton on each new unknown alone, every other unknown held at its estimate.

        iSAM2 linearises a new unknown at its initial value and keeps it there until its delta exceeds
        the threshold; starting it at its conditional optimum instead keeps that lag out of the pose
        (measured on a 40-image one-mirror stream: the last estimate 0.25 sigma from the batch
        optimum with the peeled initial values, 0.02 sigma with this).
        """
        new_keys = set(values.keys())
        if not new_keys:
            return
        touching: dict[int, list] = defaultdict(list)
        involved: set[int] = set()
        for i in range(factors.size()):
            factor = factors.at(i)
            keys = factor.keys()
            for key in keys:
                if key in new_keys:
                    touching[key].append(factor)
                    involved.update(keys)
        current = self._values(involved - new_keys)
        current.insert(values)
        for key, key_factors in touching.items():
            for _ in range(REFINE_ITERATIONS):
                normal, rhs = np.zeros((3, 3)), np.zeros(3)
                for factor in key_factors:
                    linear = factor.linearize(current)
                    keys = list(linear.keys())
                    column = sum(6 if k == self._layout.pose_key else 3 for k in keys[: keys.index(key)])
                    A, b = linear.jacobian()  # whitened, A delta = b = -error
                    A_key = A[:, column : column + 3]
                    normal += A_key.T @ A_key
                    rhs += A_key.T @ b
                step = np.linalg.lstsq(normal, rhs, rcond=None)[0]
                current.update(key, current.atPoint3(key) + step)
                if np.max(np.abs(step)) < 1e-9:
                    break
            values.update(key, current.atPoint3(key))

    def _transform(self, mirror_configs: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """``(A_Nv, b_Nv)`` of an image from the current estimate (eqs. 6-7)."""
        return nested_transform(self._R, self._t, [self._mirrors[(l + 1, m)] for l, m in enumerate(mirror_configs)])

    # --- values of new placements (eqs. 6-7, 13-18) -------------------------------------------------

    def _initialise_placements(self) -> dict[tuple[int, int], np.ndarray]:
        """Mirror vectors of the new placements the waiting images determine, from the current estimate.

        Each waiting image is grouped under its lowest placement without a value, ``(j, c)`` (the mirrors
        before it have values). The subtree below ``(j, c)`` gives candidates for ``(A_j, b_j)``; the
        known ``(A_{j-1}, b_{j-1})`` picks the most consistent one and leaves one reflection.
        """
        groups: dict[tuple[int, int], dict[tuple[int, ...], list[Image]]] = defaultdict(lambda: defaultdict(list))
        for image in self._waiting:
            configs = image.mirror_configs
            j = next(l + 1 for l, m in enumerate(configs) if (l + 1, m) not in self._layout.mirror_keys)
            groups[(j, configs[j - 1])][configs[:j]].append(image)
        estimates: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        for (j, c), by_prefix in groups.items():
            for prefix, images in by_prefix.items():
                A_parent, b_parent = nested_transform(
                    self._R, self._t, [self._mirrors[(l + 1, m)] for l, m in enumerate(prefix[:-1])]
                )
                for candidates in self._node_entries(j, prefix, images):
                    misfits, vectors = reflection_fit(
                        np.array([cand.A for cand in candidates]), np.array([cand.b for cand in candidates]),
                        A_parent, b_parent,
                    )
                    best = int(np.argmin(misfits))
                    estimates[(j, c)].append(vectors[best])
                    for config, vs in candidates[best].mirrors.items():
                        estimates[config].extend(vs)
        return {config: np.mean(vs, axis=0) for config, vs in estimates.items()}

    def _node_entries(self, level: int, prefix: tuple[int, ...], images: list[Image]) -> list[list[_Candidate]]:
        """Independent measurements of node ``prefix``'s ``(A_level, b_level)``, each a candidate list.

        Leaves (level Nv): each image's PnP candidates. Inner nodes: a child whose placement has a value
        is peeled off (eqs. 6-7); >= 3 children without values are solved as a node of the analytical
        solution (eqs. 13-18), which also gives their mirror vectors.
        """
        if level == self._ds.num_mirrors:
            return [[_Candidate(A, b) for A, b in self._pnp_of(im)] for im in images if self._pnp_of(im)]
        by_child: dict[int, list[Image]] = defaultdict(list)
        for image in images:
            by_child[image.mirror_configs[level]].append(image)
        entries: list[list[_Candidate]] = []
        unknown: dict[int, list[list[_Candidate]]] = {}
        for c, child_images in by_child.items():
            child_entries = self._node_entries(level + 1, prefix + (c,), child_images)
            if not child_entries:
                continue
            v = self._mirrors.get((level + 1, c))
            if v is None:
                unknown[c] = child_entries
                continue
            M = householder(v)
            for candidates in child_entries:  # A_{l-1} = M_l A_l, b_{l-1} = M_l (b_l - 2 v_l)
                entries.append([_Candidate(M @ cand.A, M @ (cand.b - 2.0 * v), cand.mirrors) for cand in candidates])
        if len(unknown) >= 3:
            node = self._solve_children(level, unknown)
            if node is not None:
                entries.append([node])
        return entries

    def _solve_children(self, level: int, unknown: dict[int, list[list[_Candidate]]]) -> _Candidate | None:
        """Node ``(A_level, b_level)`` and its children's mirror vectors from >= 3 new children (eqs. 13-18)."""
        child_ids = sorted(unknown)
        flat = [(k, candidates) for k, c in enumerate(child_ids) for candidates in unknown[c]]
        parent_det = (-1.0) ** level
        picks, node = solve_node(
            [k for k, _ in flat], [[(cand.A, cand.b) for cand in cands] for _, cands in flat],
            len(child_ids), parent_det, self._rng,
        )
        chosen = [cands[p] for (_, cands), p in zip(flat, picks)]
        normals = np.stack([v / np.linalg.norm(v) for v in node.mirror_vectors])
        if np.linalg.svd(normals, compute_uv=False)[2] < MIN_NORMAL_SPREAD:
            return None  # nearly coplanar normals (eqs. 14-15): wait for more placements
        mirrors: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        for cand in chosen:
            for config, vs in cand.mirrors.items():
                mirrors[config].extend(vs)
        for c, v in zip(child_ids, node.mirror_vectors):
            mirrors[(level + 1, c)].append(v)
        return _Candidate(node.A_parent, node.b_parent, dict(mirrors))

    def _pnp_of(self, image: Image) -> list[tuple[np.ndarray, np.ndarray]]:
        """PnP candidates ``(A_Nv, b_Nv)`` of an image (eqs. 10-12), cached; ``[]`` without 3 fiducials."""
        if image.id not in self._pnp:
            names = [n for n in image.observations if n in self._ds.fiducials]
            if len(names) < MIN_PNP_FIDUCIALS:
                self._pnp[image.id] = []
            else:
                normalized = self._ds.normalized(image)
                self._pnp[image.id] = pnp_candidates(
                    np.array([self._ds.fiducials[n] for n in names]),
                    np.array([normalized[n] for n in names]),
                    self._ds.num_mirrors,
                )
        return self._pnp[image.id]

    # --- iSAM2 ----------------------------------------------------------------------------------------

    def _update(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """One ``ISAM2.update`` with only the new factors and values; refresh the estimate."""
        start = time.perf_counter()
        try:
            self._isam.update(factors, values)
            pose_cov = self._isam.marginalCovariance(self._layout.pose_key)
        except RuntimeError as error:  # IndeterminantLinearSystemException
            raise SolveError(f"{self._ds.source}: {unconstrained_message(error, self._layout)}") from None
        self._updates += 1
        self.timings["isam2"] += time.perf_counter() - start
        start = time.perf_counter()
        before = (self._R, self._t, self._pose_cov)
        self._set_estimate(self._isam.calculateEstimate())
        self._pose_cov = pose_cov
        self._step_sigmas = self._pose_step_sigmas(*before)
        self.timings["estimate"] += time.perf_counter() - start

    def _pose_step_sigmas(self, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> float:
        """Mahalanobis size of the pose step from ``(R, t)`` to the estimate, against ``covariance``
        (GTSAM's tangent; the current covariance when it is undefined, as at a start-up)."""
        step = gtsam.Pose3(gtsam.Rot3(R), t).localCoordinates(gtsam.Pose3(gtsam.Rot3(self._R), self._t))
        reference = covariance if np.all(np.isfinite(covariance)) else self._pose_cov
        return float(np.sqrt(max(step @ np.linalg.solve(reference, step), 0.0)))

    def _new_isam2(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self._thresholds.threshold_map())
        params.relinearizeSkip = 1
        # Full back-substitution on every update (wildfire 0): cheap next to the Python factors, and
        # the estimate never lags the linear solution.
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
        return gtsam.ISAM2(params)

    def _polish(self) -> None:
        """Relinearise every factor at the current estimate until the pose stops moving.

        The thresholds leave variables linearised up to a threshold away from the estimate (second-order
        error); a fresh iSAM2 holding the same factors, linearised at the current estimate, is a full
        Gauss-Newton step (one pass over every factor, like one batch iteration).
        """
        for _ in range(POLISH_UPDATES):
            values = self._values()
            self._isam = self._new_isam2()
            self._update(self._factors, values)
            if self._step_sigmas < POLISH_SIGMAS:
                break

    def _set_estimate(self, values: gtsam.Values) -> None:
        self._R, self._t, self._mirrors, self._points = extract_values(values, self._layout)

    def _values(self, keys: Iterable[int] | None = None) -> gtsam.Values:
        """The current estimate as GTSAM values: every unknown, or those of ``keys``."""
        values = gtsam.Values()
        wanted = None if keys is None else set(keys)
        if wanted is None or self._layout.pose_key in wanted:
            values.insert(self._layout.pose_key, gtsam.Pose3(gtsam.Rot3(self._R), self._t))
        for config, key in self._layout.mirror_keys.items():
            if wanted is None or key in wanted:
                values.insert(key, self._mirrors[config])
        for name, key in self._layout.point_keys.items():
            if wanted is None or key in wanted:
                values.insert(key, self._points[name])
        return values

    # --- helpers ------------------------------------------------------------------------------------

    def _num_fiducials(self, image: Image) -> int:
        return sum(1 for n in image.observations if n in self._ds.fiducials)

    def _require_started(self) -> None:
        if not self.started:
            reason = self.startup_error or "each placement needs >= 3 child placements seen with >= 3 fiducials"
            raise SolveError(f"{self._ds.source}: no estimate yet: {reason}")

    def _make_calibration(
        self, *, covariance, mirror_covs, point_covs, residuals, labels, outliers, final_error
    ) -> Calibration:
        return Calibration(
            R_cam_base=self._R.copy(),
            t_cam_base=self._t.copy(),
            covariance=covariance,
            mirror_vectors=dict(self._mirrors),
            mirror_covariances=mirror_covs,
            points=dict(self._points),
            point_covariances=point_covs,
            analytic=self._analytic,
            iterations=self._updates,
            initial_error=self._initial_error,
            final_error=final_error,
            converged=self._settled,
            residuals=residuals,
            residual_labels=labels,
            residual_units="px" if self._ds.camera is not None else "normalized",
            outliers=outliers,
            timings=dict(self.timings),
        )


def calibrate_incremental(
    dataset: Dataset | Mapping[str, Any],
    *,
    robust: str | None = None,
    on_estimate: Callable[[int, Calibration], None] | None = None,
) -> Calibration:
    """Stream ``dataset``'s images in file order through :class:`IncrementalCalibrator` and return the
    full final calibration (``calibration(full=True)``).

    ``on_estimate(index, estimate)`` is called after every image (1-based index) once an estimate
    exists. Refuses what the batch :func:`~mirror_fg.solver.graph.calibrate` path refuses, with the same
    errors: bad input is DatasetError (at load or in ``add_image``), and a final estimate that did not
    converge is SolveError (:func:`~mirror_fg.solver.graph.require_converged`).
    """
    dataset = as_dataset(dataset)
    calibrator = IncrementalCalibrator(dataset, robust=robust)
    started = False
    for index, image in enumerate(dataset.images, start=1):
        estimate = calibrator.add_image(image)
        if estimate is not None:
            started = True
            if on_estimate is not None:
                on_estimate(index, estimate)
    if not started:
        raise SolveError(f"{dataset.source}: the images never allowed an analytical solution "
                         "(each placement needs >= 3 child placements)")
    return require_converged(calibrator.calibration(full=True), dataset.source, "iSAM2")
