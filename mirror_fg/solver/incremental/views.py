"""Incremental calibration of the general view model (docs/formats.md, "Views of any reflection order,
and several cameras") on iSAM2: direct views, fixed mirrors, any order of reflections, several cameras,
no known target. ``IncrementalCalibrator`` and ``calibrate_incremental`` (``calibrator.py``) send every
dataset that is not the paper's tree (``Dataset.is_tree``) here.

Same unknowns, keys, factors and noise as the batch (``views.py``'s :class:`ViewProblem`: its key layout
of the dataset given at construction, ``calibrate_incremental``: the whole file); a placement, point or
camera an added image brings beyond it gets the next key, its owner being that image's camera.

Life of an image (:meth:`ViewsIncrementalCalibrator.add_image`): validated (``dataset.validate_image``,
DatasetError before anything changes), then it waits. After every image the waiting ones are offered to
the propagation (``incremental_views_start.py``: the propagation's rules seeded with the current
estimate); those it can start, and whose factors determine what they bring, go into one ``ISAM2.update``
with their factors and the values of their new unknowns, each first moved to its optimum under those
factors with the graph's unknowns held (Levenberg-Marquardt, eq. 23). The others wait for later images.
The first update is the start (with the scale prior): before it ``add_image`` returns None, and a start
whose measurements fit it worse than ``calibration.POOR_FIT_RATIO`` allows, by their median (three nearly
parallel placements of one mirror, a minimal and ill-conditioned case of Sect. 4) is not taken: the
images wait for more.

Between updates iSAM2 relinearises a variable only when its step exceeds the relinearisation thresholds
(``state.RelinearizeThresholds``, the same as the tree's): every factor touches a camera
pose, so a tighter threshold makes every update a pass over every image (measured on a 480-image
three-camera rig: median update 45 ms and growing 7x over the stream at 1e-6, 6 ms and flat with these).
``calibration(full=True)``: Levenberg-Marquardt on every factor from iSAM2's estimate (the batch's
settings), a fresh iSAM2 at its result, then ``gtsam.Marginals`` on iSAM2's factors at its estimate gives the
covariances and residuals as ``views_solve.calibrate_views`` reports them; ``calibrate_views_incremental``
then runs the batch's final check. Not done here: the consensus on each image as it comes.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.robust import check_kernel
from mirror_fg.factors.views import ViewFactor, vector_of_plane, vectors_of_planes
from mirror_fg.io.dataset import validate_image
from mirror_fg.data import Dataset, Image
from mirror_fg.io.point_sigma import normalized_sigmas
from mirror_fg.solver.result.calibration import POOR_FIT_RATIO, require_converged
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.screen.consensus import final_check, without
from mirror_fg.solver.incremental.state import RelinearizeThresholds, new_isam2
from mirror_fg.solver.incremental.views_start import (
    determines_new_unknowns,
    joining_views,
    lm_settings,
    refined_new,
    scaled_start,
)
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.start.propagation import ViewObs
from mirror_fg.solver.screen.rechecks import MAX_RECHECKS
from mirror_fg.solver.result.builder import Label
from mirror_fg.solver.timing import timed
from mirror_fg.solver.model.views import (
    ViewEstimate,
    ViewProblem,
    camera_names,
    plane_of,
    scale_prior,
    views_of,
)
from mirror_fg.solver.batch.views_solve import calibration_of

__all__ = ["ViewsIncrementalCalibrator", "calibrate_views_incremental"]

logger = logging.getLogger("mirror_fg")

#: ``calibration(full=True)``: Levenberg-Marquardt on every factor with at most this many iterations.
FINAL_LM_ITERATIONS = 100
#: Extra iSAM2 updates (relinearising what moved) after an update that added new unknowns.
SETTLE_UPDATES = 1


class ViewsIncrementalCalibrator:
    """Incremental calibration of a general dataset (module docstring); the backend of
    ``incremental.IncrementalCalibrator`` off the tree: ``add_image``, ``calibration``, ``marginal_covariance``,
    ``status``, ``started``, ``settled``, ``num_images``, ``waiting_images``, ``excluded`` (no
    ``suggest_next``). ``points``, ``robust`` and ``thresholds`` (iSAM2's relinearisation,
    ``state.new_isam2``) as there; ``seed`` is taken for the same signature and not used (the
    propagation is deterministic)."""

    def __init__(self, dataset: Dataset, *, points: Iterable[str] | None = None, robust: str | None = None,
                 thresholds: RelinearizeThresholds | None = None, seed: int = 0) -> None:
        check_kernel(robust)
        self.robust = robust
        self.thresholds = thresholds if thresholds is not None else RelinearizeThresholds()
        #: What reaches the batch solves the start runs (rule 2 of the propagation): the kernel.
        self.options = SolveOptions(robust=robust, compute_covariance=False, diagnose=False)
        self._ds = replace(dataset, images=[])  # the images in the graph
        self._order = {image.id: k for k, image in enumerate(dataset.images)}
        if any(c is not None and c.estimate for c in (list(dataset.cameras.values()) if dataset.cameras else [dataset.camera])):
            raise DatasetError(f"{dataset.source}: camera.estimate: estimating intrinsics needs the batch solver")
        self._known_points: set[str] | None = (set(points) if points is not None else
                                               set(dataset.reconstruction_point_names) if dataset.images else None)
        self.cameras = camera_names(dataset)
        self.fixed = {} if dataset.fiducials else {self.cameras[0]: (np.eye(3), np.zeros(3))}
        self.pose_keys = {name: X(k) for k, name in enumerate(self.cameras) if name not in self.fixed}
        layout = ViewProblem(dataset, robust) if dataset.images else None
        self.mirror_keys = dict(layout.mirror_keys) if layout else {}
        self.owners = dict(layout.owners) if layout else {}
        self.point_keys = dict(layout.point_keys) if layout else {}
        self._ids: set[str] = set()
        self._waiting: list[tuple[Image, ViewObs]] = []
        self._views: list[ViewObs] = []  # of the images in the graph
        self._isam: gtsam.ISAM2 | None = None
        self._graph = gtsam.NonlinearFactorGraph()  # every factor given to iSAM2
        self._estimate = ViewEstimate(dict(self.fixed), {}, {})
        self._updates = 0
        self._full_problem: ViewProblem | None = None
        self._initial_error = float("nan")
        #: What the final check left out (:meth:`leave_out_far_measurements`); images are not screened
        #: as they come (no consensus yet).
        self.excluded: list[Exclusion] = []
        self.misfits: list[Image] = []
        #: Why the latest update failed (the data did not determine what the joining images bring).
        self.startup_error: Exception | None = None
        self.restarts = 0
        self.timings: dict[str, float] = {}

    # --- public -------------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self._isam is not None

    @property
    def settled(self) -> bool:
        return self.started

    @property
    def dataset(self) -> Dataset:
        """The calibration's cameras, fiducials and noise, with the images in the graph."""
        return self._ds

    @property
    def num_images(self) -> int:
        return len(self._ds.images)

    @property
    def waiting_images(self) -> list[str]:
        return [image.id for image, _ in self._waiting]

    @property
    def status(self) -> str:
        if self.started:
            return f"settled (iSAM2): {self.num_images} image(s) in the graph, {len(self._waiting)} waiting"
        if not self._waiting:
            return "waiting: no image yet"
        why = f": {self.startup_error}" if self.startup_error is not None else ""
        return (f"waiting: the propagation cannot start every unknown of any {len(self._waiting)} image(s) "
                f"so far{why}")

    def __repr__(self) -> str:
        return f"ViewsIncrementalCalibrator({self._ds.source!r}: {len(self._ids)} image(s) given; {self.status})"

    def add_image(self, image: Image | Mapping[str, Any]) -> Calibration | None:
        """Take one image (an ``Image`` or its dataset@1 dict); None until the start, then the cheap
        ``Calibration``. DatasetError on bad input, before anything changes."""
        if isinstance(image, Image) and len(image.mirror_configs) != self._ds.num_mirrors:
            # validate_image reads an Image's empty mirror_configs as the tree's (a direct view is refused)
            image = {"id": image.id, "reflections": [list(p) for p in image.reflections],
                     "observations": image.observations, **({"camera": image.camera} if image.camera else {})}
        checked = validate_image(image, self._ds, known_points=self._known_points)
        if checked.id in self._ids:
            raise DatasetError(f"{self._ds.source}: image {checked.id!r}: duplicate image id (already given)")
        self._ids.add(checked.id)
        self._extend_layout(checked)
        view = views_of(replace(self._ds, images=[checked]))[0]
        self._waiting.append((checked, view))
        with timed(self.timings, "update"):
            self._join_waiting()
        return self.calibration() if self.started else None

    def calibration(self, full: bool = False) -> Calibration:
        """The estimate as a ``Calibration`` (batch shape). ``full=False``: camera pose covariances from
        iSAM2, no mirror or point covariances, no residuals. ``full=True``: relinearised to convergence,
        every covariance by ``gtsam.Marginals`` on the graph at the estimate, every residual."""
        if not self.started:
            raise SolveError(f"{self._ds.source}: no estimate yet: {self.status}")
        isam = self._isam
        assert isam is not None
        values, converged = self._polish() if full else (isam.calculateEstimate(), True)
        problem = self._problem(full)
        # the cheap one: the estimate read at the last update (every placement's vector, once per update)
        estimate = problem.read(values) if full else self._estimate
        if full:
            with unconstrained_as_solve_error(self._ds.source, lambda error: unconstrained_message(error, problem)):
                covariances = problem.covariances(self._graph, values, estimate)
            residuals, whitened, labels = problem.residuals(estimate)
        else:
            pose_covs = {name: np.zeros((6, 6)) for name in self.fixed}
            for name, key in problem.pose_keys.items():
                pose_covs[name] = covariance_from_pose3(estimate.poses[name][0], isam.marginalCovariance(key))
            covariances = (pose_covs, None, {}, {}, {})
            residuals, whitened, labels = np.zeros((0, 2)), np.zeros(0), []
        dimension = values.dim() - problem.constraints
        final_error = float(self._graph.error(values)) if full else float("nan")
        calibration = calibration_of(problem, estimate, covariances, residuals, whitened, labels,
                                     iterations=self._updates, initial_error=self._initial_error,
                                     final_error=final_error, converged=converged, dimension=dimension,
                                     excluded=list(self.excluded), timings=dict(self.timings))
        if not full and self._ds.cameras is not None:
            calibration.camera_pose_covariance = None
        return calibration

    def marginal_covariance(self, unknown: tuple[int, int] | str | None = None) -> np.ndarray:
        """iSAM2's marginal covariance: ``None`` the first camera's pose (6x6, docs/formats.md's convention; zero
        where it is fixed), a camera name its pose, ``(l, m)`` a mirror vector (owner frame), a point."""
        if not self.started:
            raise SolveError(f"{self._ds.source}: no estimate yet: {self.status}")
        isam = self._isam
        assert isam is not None
        name = self.cameras[0] if unknown is None else unknown
        if isinstance(name, str) and name in self.cameras:
            if name in self.fixed:
                return np.zeros((6, 6))
            return covariance_from_pose3(self._estimate.poses[name][0], isam.marginalCovariance(self.pose_keys[name]))
        key = self.point_keys.get(name) if isinstance(name, str) else self.mirror_keys.get((*name,))  # a list too
        if key is None or not isam.valueExists(key):
            raise KeyError(f"{unknown!r} has no value in the graph yet")
        if isinstance(name, str):
            return isam.marginalCovariance(key)
        J = vector_of_plane(isam.calculateEstimate().atOrientedPlane3(key))[1]  # v = d n, from the plane's coordinates
        return J @ isam.marginalCovariance(key) @ J.T

    def leave_out_far_measurements(self) -> list[Exclusion]:
        """The batch's final check (``consensus.final_check``) at the estimate (after ``calibration(full=
        True)``): the measurements (or whole images) far off the solution are left out, iSAM2 restarted on
        the rest at the estimate, its unknowns that nothing sees any more dropped. Returns what was left
        out (empty: nothing)."""
        problem = self._problem(full=True)
        _, whitened, labels = problem.residuals(self._estimate)
        dimension = problem.values(self._estimate).dim() - problem.constraints
        excluded = final_check(problem.dataset, [Label(i, p) for i, p in labels], whitened, dimension)
        if not excluded:
            return []
        self.excluded.extend(excluded)
        kept = without(problem.dataset, excluded).images
        self._ds.images = kept
        self._views = views_of(replace(self._ds, images=kept))
        self._graph = gtsam.NonlinearFactorGraph()
        for image, view in zip(kept, self._views):
            self._graph.add(self._factor(image, view).factor())
        self._graph.push_back(self._scale_prior())
        seen = set(self._graph.keyVector())
        self._estimate = ViewEstimate(
            {n: pose for n, pose in self._estimate.poses.items() if n in self.fixed or self.pose_keys[n] in seen},
            {p: v for p, v in self._estimate.mirror_vectors.items() if self.mirror_keys[p] in seen},
            {n: x for n, x in self._estimate.points.items() if self.point_keys[n] in seen})
        self._full_problem = None
        self._isam = new_isam2(self.thresholds)
        self._rebuild()
        return excluded

    # --- the graph ------------------------------------------------------------------------------------

    def _extend_layout(self, image: Image) -> None:
        """Keys for what ``image`` brings beyond the layout (module docstring)."""
        camera = image.camera if image.camera is not None else self.cameras[0]
        for p in image.reflections:
            if p not in self.mirror_keys:
                self.mirror_keys[p] = V(len(self.mirror_keys))
                self.owners[p] = camera
        for name in image.observations:
            if name not in self._ds.fiducials and name not in self.point_keys:
                self.point_keys[name] = L(len(self.point_keys))

    def _factor(self, image: Image, view: ViewObs) -> ViewFactor:
        """The image's factor exactly as ``ViewProblem`` builds it."""
        camera = self._ds.camera_of(image)
        sigmas = normalized_sigmas(camera, self._ds.pixel_sigma, self._ds.point_sigma, view.names).T
        base = np.full((3, len(view.names)), np.nan)
        landmarks = []
        for k, name in enumerate(view.names):
            if name in self._ds.fiducials:
                base[:, k] = self._ds.fiducials[name]
                landmarks.append(-1)
            else:
                landmarks.append(self.point_keys[name])
        return ViewFactor(view.camera, view.reflections, self.pose_keys, self.fixed, self.mirror_keys, self.owners,
                          base, landmarks, view.normalized.T, sigmas, self.robust)

    def _scale_prior(self) -> gtsam.NonlinearFactorGraph:
        return scale_prior(self._ds, self.mirror_keys, self.point_keys)

    def _join_waiting(self) -> None:
        """The waiting images the propagation can start, into iSAM2 in one update (module docstring)."""
        if not self._waiting:
            return
        joining = joining_views(self._ds, self._waiting, self._estimate, self.owners, self.cameras, self.fixed,
                                self._views, self.options)
        if not joining.indices:
            return
        new = ViewEstimate(joining.poses, joining.mirror_vectors, joining.points)
        if not self.started:
            scaled = scaled_start(new, self._ds.scale)
            if scaled is None:  # the scale's placement or points are not among the first images
                return
            new = scaled
        factors = gtsam.NonlinearFactorGraph()
        images = [self._waiting[k] for k in joining.indices]
        view_factors: list[ViewFactor] = []
        for image, view in images:
            view_factors.append(self._factor(image, view))
            factors.add(view_factors[-1].factor())
        if not self.started:
            factors.push_back(self._scale_prior())
        values = gtsam.Values()
        for name, (R, t) in new.poses.items():
            values.insert(self.pose_keys[name], gtsam.Pose3(gtsam.Rot3(R), np.asarray(t, float)))
        for p, v in new.mirror_vectors.items():
            values.insert(self.mirror_keys[p], plane_of(v))
        for name, x in new.points.items():
            values.insert(self.point_keys[name], np.asarray(x, float))
        everything = gtsam.Values(values)
        if self.started:
            everything.insert(self._isam.calculateEstimate())  # type: ignore[union-attr]
        if not determines_new_unknowns(factors, everything, list(values.keys())):
            self.startup_error = SolveError(f"images {', '.join(im.id for im, _ in images)} do not determine "
                                            "what they bring yet")
            return
        start_error = float(factors.error(everything))  # at the propagation's values
        values = refined_new(factors, values, everything, self._ds)
        if not self.started:  # a start the data contradict (a minimal, ill-conditioned one): wait for more images
            fit = _median_fit(view_factors, values)
            if not fit <= POOR_FIT_RATIO:
                self.startup_error = SolveError(f"images {', '.join(im.id for im, _ in images)} fit the start "
                                                f"{fit:.3g} times worse than the noise model allows")
                return
        isam = self._isam if self._isam is not None else new_isam2(self.thresholds)
        try:
            isam.update(factors, values)
            for _ in range(SETTLE_UPDATES if values.size() else 0):
                isam.update()
        except RuntimeError as error:  # undamped steps failed: Levenberg-Marquardt on it all, a fresh iSAM2
            graph = gtsam.NonlinearFactorGraph(self._graph)
            graph.push_back(factors)
            start = gtsam.Values(values)
            if self.started:
                start.insert(self._problem().values(self._estimate))
            fresh = self._fresh_isam(graph, start)
            if fresh is None:  # the images wait; iSAM2 starts over from the graph so far
                self.startup_error = SolveError(f"{self._ds.source}: images {', '.join(im.id for im, _ in images)}: "
                                                f"{str(error).strip().splitlines()[0]}")
                self._rebuild()
                return
            isam = fresh
        if not self.started:
            self._initial_error = start_error
        self._isam = isam
        self._graph.push_back(factors)
        self._updates += 1
        self.startup_error = None
        joined = set(joining.indices)
        self._ds.images = self._ds.images + [image for image, _ in images]
        self._views.extend(view for _, view in images)
        self._waiting = [w for k, w in enumerate(self._waiting) if k not in joined]
        self._estimate = self._read(isam.calculateEstimate())

    def _rebuild(self) -> None:
        """A fresh iSAM2 holding the graph so far, from the last estimate (after iSAM2 refused an update,
        Levenberg-Marquardt polished the estimate, or measurements were left out)."""
        if self._isam is None:
            return
        isam = self._fresh_isam(self._graph, self._problem().values(self._estimate))
        if isam is None:
            raise SolveError(f"{self._ds.source}: the data do not constrain every unknown (iSAM2 and "
                             "Levenberg-Marquardt both failed on the images in the graph)")
        self._isam = isam
        self._estimate = self._read(isam.calculateEstimate())

    def _fresh_isam(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.ISAM2 | None:
        """Levenberg-Marquardt on ``graph`` from ``values`` (eq. 23), then a fresh iSAM2 at its result;
        None where the system is indeterminate."""
        try:
            settings = lm_settings(FINAL_LM_ITERATIONS, self._ds)
            result = gtsam.LevenbergMarquardtOptimizer(graph, values, settings).optimize()
            isam = new_isam2(self.thresholds)
            isam.update(graph, result)
        except RuntimeError:
            return None
        self.restarts += 1
        return isam

    def _polish(self) -> tuple[gtsam.Values, bool]:
        """Every factor relinearised to convergence: Levenberg-Marquardt on iSAM2's factors from its
        estimate (eq. 23, the batch's settings; a few iterations from that close), then a fresh iSAM2 at
        the result. (iSAM2's own ``force_relinearize`` only relinearises the variables whose step exceeds
        the relinearisation thresholds, so it stops short of the optimum.) Returns ``(values, converged)``."""
        isam = self._isam
        assert isam is not None
        optimizer = gtsam.LevenbergMarquardtOptimizer(self._graph, isam.calculateEstimate(),
                                                      lm_settings(FINAL_LM_ITERATIONS, self._ds))
        values = optimizer.optimize()
        self._updates += int(optimizer.iterations())
        self._estimate = self._read(values)
        fresh = new_isam2(self.thresholds)
        fresh.update(self._graph, values)
        self._isam = fresh
        return values, int(optimizer.iterations()) < FINAL_LM_ITERATIONS

    def _read(self, values: gtsam.Values) -> ViewEstimate:
        """The estimate of every unknown in ``values``."""
        poses = dict(self.fixed)
        for name, key in self.pose_keys.items():
            if values.exists(key):
                pose = values.atPose3(key)
                poses[name] = (pose.rotation().matrix(), np.asarray(pose.translation(), float))
        placements = [(p, k) for p, k in self.mirror_keys.items() if values.exists(k)]
        return ViewEstimate(poses, _mirror_vectors(values, placements),
                            {n: np.asarray(values.atPoint3(k), float) for n, k in self.point_keys.items()
                             if values.exists(k)})

    def _problem(self, full: bool = False) -> ViewProblem:
        """A ViewProblem keyed as this calibrator is, of the unknowns in the graph; ``full``: with every
        image in the graph (file order where known) for its residuals, else none (cheap)."""
        if full and self._full_problem is not None and len(self._full_problem.views) == self.num_images:
            return self._full_problem
        images = sorted(self._ds.images, key=lambda im: self._order.get(im.id, len(self._order))) if full else []
        problem = ViewProblem(replace(self._ds, images=images), self.robust)
        problem.pose_keys = {n: k for n, k in self.pose_keys.items() if n in self._estimate.poses}
        problem.placements = sorted(self._estimate.mirror_vectors)
        problem.mirror_keys = {p: self.mirror_keys[p] for p in problem.placements}
        problem.owners = {p: self.owners[p] for p in problem.placements}
        problem.point_names = sorted(self._estimate.points)
        problem.point_keys = {n: self.point_keys[n] for n in problem.point_names}
        if full:
            self._full_problem = problem
        return problem


def _median_fit(view_factors: list[ViewFactor], values: gtsam.Values) -> float:
    """How many times worse than the noise model the measurements fit at ``values``, by their median
    (a few gross ones do not count): ``sqrt(median(|whitened|^2) / (2 ln 2))``, the median of a chi^2
    with 2 degrees of freedom being ``2 ln 2``."""
    whitened = np.concatenate([np.sum(((f.predict(values) - f.observed) / f.sigmas) ** 2, axis=0)
                               for f in view_factors])
    return float(np.sqrt(np.median(whitened) / (2.0 * np.log(2.0))))


def calibrate_views_incremental(dataset: Dataset, *, robust: str | None = None,
                                on_estimate: Callable[[int, Calibration], None] | None = None,
                                on_wait: Callable[[int, str], None] | None = None,
                                accept_poor_fit: bool = False) -> Calibration:
    """``incremental.calibrate_incremental`` for a general dataset: its images in file order through
    :class:`ViewsIncrementalCalibrator`, then ``calibration(full=True)`` under ``require_converged``.
    SolveError when images are still waiting at the end (what the batch could not start either)."""
    calibrator = ViewsIncrementalCalibrator(dataset, robust=robust)
    for index, image in enumerate(dataset.images, start=1):
        estimate = calibrator.add_image(image)
        if estimate is not None:
            if on_estimate is not None:
                on_estimate(index, estimate)
        elif on_wait is not None:
            on_wait(index, calibrator.status)
    if not calibrator.started:
        raise SolveError(f"{dataset.source}: the images never allowed a start by propagation ({calibrator.status})")
    if calibrator.waiting_images:
        raise SolveError(f"{dataset.source}: image(s) {', '.join(calibrator.waiting_images)} could not be started "
                         "from the others (the batch names what they lack: mirror-fg calibrate without --incremental)")
    calibration = calibrator.calibration(full=True)
    for _ in range(MAX_RECHECKS):  # as the batch: what is far off the solution left out, solved again
        if not calibrator.leave_out_far_measurements():
            break
        logger.warning("%s: %d measurement(s) or image(s) far off the solution left out; solving again",
                       dataset.source, len(calibrator.excluded))
        calibration = calibrator.calibration(full=True)
    return require_converged(calibration, dataset.source, "iSAM2", accept_poor_fit=accept_poor_fit)


def _mirror_vectors(values: gtsam.Values, placements: list[tuple[tuple[int, int], int]]
                    ) -> dict[tuple[int, int], np.ndarray]:
    """``{placement: mirror_vector_at(values, key)}`` of ``placements`` (``(placement, key)``), read after
    every update: every plane at once (``views.vectors_of_planes``, the same numbers)."""
    coefficients = np.array([values.atOrientedPlane3(k).planeCoefficients() for _, k in placements]).reshape(-1, 4)
    return {p: v for (p, _), v in zip(placements, vectors_of_planes(coefficients)[0])}
