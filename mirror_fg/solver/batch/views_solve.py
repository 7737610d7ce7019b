"""The batch solve of the general view model (``solver/model/views.py``'s problem), as ``calibrate()`` runs
it for data the paper's tree does not describe: analytical start by propagation
(``solver/start/propagation.py``) -> Levenberg-Marquardt (eq. 23) -> final check (measurements far off the
solution left out, solved again) -> Marginals -> :class:`~mirror_fg.solver.result.calibration.Calibration`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.factors.view_eliminated import EliminatedViewStack
from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.result.calibration import POOR_FIT_RATIO
from mirror_fg.solver.result.calibration import Calibration, CameraPose, EstimatedCamera, Exclusion
from mirror_fg.solver.screen.camera_labels import lone_image_hint
from mirror_fg.solver.screen.consensus import check_images, screen, without
from mirror_fg.solver.model.lm import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params, polished, run_optimizer
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.solver.options import STAGES, SolveOptions
from mirror_fg.solver.pipeline import run_pipeline
from mirror_fg.solver.screen.placement_consensus import fiducial_names
from mirror_fg.solver.start.propagation import KnownPnP, Unsolvable, propagate
from mirror_fg.solver.screen.rechecks import Checked, Rechecked, solve_with_rechecks
from mirror_fg.solver.result.builder import Label, build_calibration
from mirror_fg.solver.model.rig import rig_transforms
from mirror_fg.solver.fit.dispersion import dispersion_of_solve
from mirror_fg.solver.timing import timed
from mirror_fg.solver.batch.tree_problem import TreeProblem
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem, camera_names

__all__ = ["calibrate_views", "ViewsProblem", "tree_start_for", "calibration_of"]

logger = logging.getLogger("mirror_fg")




def tree_start_for(dataset: Dataset, options: SolveOptions, minima: dict | None = None):
    """Rule 2 of the propagation for one camera: its images through the whole tree (the largest subtree
    with three placements under every node, then the one of its three best-seen placements of mirror 1)
    or through one mirror alone (>= 3 placements), each solved as the paper's problem by ``calibrate``
    on their fiducials (``tree_problem.TreeProblem``: analytical solution, then LM with its restarts); the
    first that fits the noise (``Calibration.fit_ratio`` at most ``calibration.POOR_FIT_RATIO``) gives
    ``((R, t), {placement: v})``, else None. ``options``: the user's (``SolveOptions.nested``);
    ``minima``: the screen's PnP minima (``consensus.ImageChecks.minima``), which rule 2's checks of the
    same images take instead of solving again (the same camera, fiducials and parity)."""
    nested = options.nested()

    def start(camera_name: str):
        images = [im for im in dataset.images if dataset.cameras is None or im.camera == camera_name]
        camera = dataset.cameras[camera_name] if dataset.cameras is not None else dataset.camera
        if camera is not None and camera.estimate:
            camera = replace(camera, estimate=(), prior_sigma=())
        attempts: list[tuple[int, int | None, list[Image]]] = []
        if dataset.num_mirrors > 1:
            tree = _solvable_subtree([im for im in images if len(im.mirror_configs) == dataset.num_mirrors])
            if tree:
                attempts.append((dataset.num_mirrors, None, tree))
                counts: dict[int, int] = {}
                for im in tree:
                    counts[im.mirror_configs[0]] = counts.get(im.mirror_configs[0], 0) + 1
                best = set(sorted(counts, key=lambda m: -counts[m])[:3])
                if len(counts) > 3:
                    attempts.append((dataset.num_mirrors, None, [im for im in tree if im.mirror_configs[0] in best]))
        groups: dict[int, list[Image]] = {}
        for im in images:
            if len(im.reflections) == 1:
                groups.setdefault(im.reflections[0][0], []).append(im)
        for alone, group in sorted(groups.items(), key=lambda g: -len({im.reflections[0] for im in g[1]})):
            if len({im.reflections[0] for im in group}) >= 3:
                attempts.append((1, alone, group))
        for num_mirrors, mirror, group in attempts:
            sub_images = []
            for im in group:
                observations = {n: z for n, z in im.observations.items() if n in dataset.fiducials}
                if len(observations) >= 3:
                    configs = im.mirror_configs if mirror is None else (im.reflections[0][1],)
                    sub_images.append(Image(im.id, configs, observations))
            sub = Dataset(num_mirrors=num_mirrors, camera=camera, pixel_sigma=dataset.pixel_sigma,
                          fiducials=dataset.fiducials, images=sub_images, source=dataset.source,
                          point_sigma={n: s for n, s in dataset.point_sigma.items() if n in dataset.fiducials})
            try:
                solution = run_pipeline(TreeProblem(None, nested, minima), sub)
            except (DatasetError, SolveError, ValueError, np.linalg.LinAlgError) as error:
                logger.debug("%s: camera %s: no start from %s: %s", dataset.source, camera_name,
                             "the tree" if mirror is None else f"mirror {mirror} alone", error)
                continue
            if not solution.fit_ratio <= POOR_FIT_RATIO:
                continue
            vectors = {((l, m) if mirror is None else (mirror, m)): np.asarray(v, float)
                       for (l, m), v in solution.mirror_vectors.items()}
            return (np.asarray(solution.R_cam_base, float), np.asarray(solution.t_cam_base, float)), vectors
        return None

    return start


def _other_start(problem: ViewProblem, options: SolveOptions, known_pnp: KnownPnP | None = None,
                 minima: dict | None = None) -> ViewEstimate | None:
    """The analytical start with rule 2 first for every camera, or None where it cannot be formed."""
    try:
        return _start(problem, None, options, tree_first=True, known_pnp=known_pnp, minima=minima)
    except SolveError:
        return None


def _solvable_subtree(images: list[Image], children: int = 3) -> list[Image]:
    """The images of the largest subtree in which every node has ``children`` or more placements of the next
    mirror under it (the paper's Sect. 5 condition): the rest are started by propagation afterwards."""
    while True:
        below: dict[tuple[int, ...], set[int]] = {}
        for im in images:
            for level in range(len(im.mirror_configs)):
                below.setdefault(im.mirror_configs[:level], set()).add(im.mirror_configs[level])
        kept = [im for im in images
                if all(len(below[im.mirror_configs[:level]]) >= children for level in range(len(im.mirror_configs)))]
        if len(kept) == len(images):
            return kept
        images = kept


def _start(problem: ViewProblem, initial, options: SolveOptions, tree_first: bool = False,
           known_pnp: KnownPnP | None = None, minima: dict | None = None) -> ViewEstimate:
    """The analytical start, or ``initial`` (a :class:`ViewEstimate`, or a single-camera estimate with
    ``R_cam_base``, ``t_cam_base``, ``mirror_vectors``, ``points``). ``options`` reach rule 2's solves;
    ``known_pnp``: the screen's PnP candidates (``propagation.propagate``), ``minima`` its PnP minima
    (:func:`tree_start_for`)."""
    if isinstance(initial, ViewEstimate):
        return initial
    if initial is not None:
        pose = (np.asarray(initial.R_cam_base, float), np.asarray(initial.t_cam_base, float))
        return ViewEstimate({problem.cameras[0]: pose}, dict(initial.mirror_vectors), dict(initial.points))
    dataset = problem.dataset
    try:
        known = propagate(problem.views, dataset.fiducials, problem.cameras, problem.fixed,
                          tree_start_for(dataset, options, minima),
                          dataset.scale, tree_first, known_pnp)
    except Unsolvable as error:
        labels = lone_image_hint(dataset)  # a rig image naming the wrong camera leaves its plane unsolvable
        raise Unsolvable(f"{dataset.source}: {labels} (the start fails: {error})" if labels else
                         f"{dataset.source}: {error}") from None
    return problem.estimate_from(known)


@dataclass
class _Run:
    """One solve with its rechecks: the problem, graph and values it ended with and what it left out."""

    problem: ViewProblem
    graph: gtsam.NonlinearFactorGraph
    result: gtsam.Values
    estimate: ViewEstimate
    residuals: np.ndarray
    whitened: np.ndarray
    labels: list
    dimension: int
    iterations: int
    initial_error: float
    excluded: list[Exclusion]
    timings: dict[str, float]
    eliminated: EliminatedViewStack | None = None  # the placements solved inside the factors, if any


def calibrate_views(dataset: Dataset, initial=None, options: SolveOptions | None = None) -> Calibration:
    """The MLE and covariances of a dataset in the general view model (module docstring), by the
    pipeline (``pipeline.py``) over :class:`ViewsProblem`."""
    options = options or SolveOptions()
    return run_pipeline(ViewsProblem(initial, options, _intrinsics_models(dataset)), dataset)


def _intrinsics_models(dataset: Dataset) -> dict:
    """``{camera: IntrinsicsModel}`` of the cameras that estimate intrinsics, after the refusals that need
    no solve (``intrinsics.check_supported``, per camera)."""
    from mirror_fg.factors.intrinsics import IntrinsicsModel
    from mirror_fg.solver.batch.intrinsics import camera_intrinsics, check_supported

    cameras = dataset.cameras if dataset.cameras is not None else {SINGLE_CAMERA: dataset.camera}
    models = {}
    for name, camera in cameras.items():
        if camera is None or not camera.estimate:
            continue
        own = [im for im in dataset.images if dataset.cameras is None or im.camera == name]
        check_supported(replace(dataset, camera=camera, cameras=None, images=own,
                                source=dataset.source if dataset.cameras is None else f"{dataset.source}: camera {name!r}"))
        models[name] = IntrinsicsModel(camera_intrinsics(camera), camera.estimate)
    return models


def _fixed_intrinsics(dataset: Dataset) -> Dataset:
    """``dataset`` with every camera's intrinsics fixed at their given values and the start's noise
    (``intrinsics.with_start_noise``)."""
    from mirror_fg.solver.batch.intrinsics import with_start_noise

    def fixed(camera):
        return None if camera is None else replace(camera, estimate=(), prior_sigma=())

    cameras = None if dataset.cameras is None else {n: fixed(c) for n, c in dataset.cameras.items()}
    every = [c for c in (cameras or {SINGLE_CAMERA: dataset.camera}).values() if c is not None]
    return with_start_noise(replace(dataset, camera=fixed(dataset.camera) if cameras is None else every[0],
                                    cameras=cameras), every)


class ViewsProblem:
    """The general view model in ``calibrate()``'s pipeline (``pipeline.py``).

    screen: each image's own PnP fit (``consensus.screen``: wrong corner orders, gross corners); where
    cameras estimate intrinsics (``models``), the whole pipeline with them fixed at their given values
    first (its pixel sigma at least ``intrinsics.START_SIGMA_FRACTION`` of the image diagonal, so that
    their error is not taken for outliers), whose estimate starts the joint solve in pixels. solve: the
    start (propagation, ``initial``, or the last solve's estimate after leaving some out) and LM; an
    analytical start whose LM ends implausibly is followed by the other analytical start (rule 2 first)
    and the better kept. finish: marginals and the :class:`Calibration`."""

    def __init__(self, initial, options: SolveOptions, models: dict | None = None):
        self.options, self.models = options, dict(models or {})
        self.analytic = initial is None
        self.last: ViewEstimate | None = initial
        self.timings: dict[str, float] = {}
        #: The analytical start LM began from (propagation's), for the result's ``analytic``; None from ``initial``.
        self.analytic_start: ViewEstimate | None = None
        #: The screen's PnP candidates of the images it left untouched, with the fiducials they are of:
        #: the propagation's rules 1 and 3 use them instead of solving the same PnP again.
        self.known_pnp: KnownPnP = {}
        #: The screen's PnP minima of every image (``consensus.ImageChecks.minima``): rule 2's checks of
        #: the same photographs take them.
        self.minima: dict = {}

    def screen(self, dataset: Dataset) -> tuple[Dataset, list[Exclusion]]:
        if not self.models:
            checked = check_images(dataset)
            self.minima = checked.minima
            screened, excluded, candidates = screen(dataset, checked=checked)
            by_id = {image.id: image for image in screened.images}
            self.known_pnp = {image_id: (tuple(fiducial_names(screened, by_id[image_id])), poses)
                              for image_id, poses in candidates.items() if image_id in by_id}
            return screened, excluded
        fixed = ViewsProblem(self.last, replace(self.options, compute_covariance=False))
        screened, excluded = fixed.screen(_fixed_intrinsics(dataset))
        first = solve_with_rechecks(screened, fixed.solve, fixed.check, excluded)
        self.last, self.analytic = first.run.estimate, False
        self.analytic_start = fixed.analytic_start  # the start of the solve with the given intrinsics
        self.timings.update({f"start: {k}": v for k, v in fixed.timings.items()})
        return (without(dataset, first.excluded) if first.excluded else dataset), list(first.excluded)

    def solve(self, solved: Dataset, left_out: list[Exclusion]) -> _Run:
        options, timings = self.options, self.timings
        problem = ViewProblem(solved, options.robust, self.models)
        with timed(timings, "analytic"):
            begin = _start(problem, self.last, options, known_pnp=self.known_pnp, minima=self.minima)
        params = lm_params(options.max_iterations, cost_scale(solved), GENERAL_LAMBDA_UPPER_BOUND)

        def optimize(first: ViewEstimate):
            """LM from ``first`` on the graph with the placements one factor alone sees eliminated inside
            it where the data allow (``ViewProblem.solve_graph``)."""
            with timed(timings, "build"):
                graph, values, eliminated = problem.solve_graph(first, options.eliminates(True))
            with timed(timings, "optimize"):
                optimizer, result, initial_error = run_optimizer(
                    graph, values, params, solved.source, lambda error: unconstrained_message(error, problem),
                    options.iteration)
                if eliminated is not None:  # a few Gauss-Newton steps on the small system (lm._polished)
                    result = polished(graph, result)
            return optimizer, result, initial_error, graph, eliminated

        if self.analytic and self.last is None:
            self.analytic_start = begin
        optimizer, result, initial_error, graph, eliminated = optimize(begin)
        dimension = result.dim() + (eliminated.dimension if eliminated is not None else 0) - problem.constraints
        if self.analytic and self.last is None and not plausible(graph.error(result),
                                                                 expected_cost(problem.size, dimension)):
            other = _other_start(problem, options, self.known_pnp, self.minima)  # the analytical start ended implausibly: try the other one
            if other is not None:
                tried = optimize(other)
                if tried[3].error(tried[1]) < graph.error(result):
                    logger.info("%s: the second analytical start fits better", solved.source)
                    optimizer, result, initial_error, graph, eliminated = tried
                    self.analytic_start = other
        estimate = problem.read(result, eliminated)
        self.last = estimate  # the start of the next solve, after leaving some out
        residuals, whitened, labels = problem.residuals(estimate)
        return _Run(problem, graph, result, estimate, residuals, whitened, labels, dimension,
                    int(optimizer.iterations()), initial_error, list(left_out), timings, eliminated)

    def check(self, run: _Run) -> Checked:
        return Checked([Label(i, p) for i, p in run.labels], run.whitened, run.dimension)

    def finish(self, rechecked: Rechecked[_Run]) -> Calibration:
        run = rechecked.run
        run.excluded = rechecked.excluded
        calibration = _finish(run, self.options)
        calibration.analytic = analytic_of(self.analytic_start, run.problem)
        if calibration.covariance is not None and not any(e.point is not None for e in run.excluded):
            # every measurement of the kept images used: the solve's own problem is the dispersion's
            calibration.dispersion = dispersion_of_solve(run.problem, run.estimate)
        return calibration


def analytic_of(start: ViewEstimate | None, problem: ViewProblem) -> AnalyticSolution | None:
    """The analytical start (propagation's, docs/formats.md "Views of any reflection order") as the result's
    ``analytic``: the first camera's ``T_cam_base``, the mirrors and points, and every camera's pose."""
    if start is None:
        return None
    first = problem.cameras[0]
    if first not in start.poses:
        return None
    R, t = start.poses[first]
    poses = ({name: (np.asarray(R_c, float), np.asarray(t_c, float)) for name, (R_c, t_c) in start.poses.items()}
             if problem.dataset.cameras is not None else {})
    return AnalyticSolution(np.asarray(R, float), np.asarray(t, float), dict(start.mirror_vectors),
                            dict(start.points), camera_poses=poses)


def _finish(run: _Run, options: SolveOptions) -> Calibration:
    """The run's marginals and its :class:`Calibration`."""
    report = options.report
    problem = run.problem
    covariances = None
    if options.compute_covariance:
        report(STAGES[2], 0, 1)
        with timed(run.timings, "marginals"), unconstrained_as_solve_error(
                problem.dataset.source, lambda error: unconstrained_message(error, problem)):
            covariances = problem.covariances(run.graph, run.result, run.estimate, run.eliminated)
        report(STAGES[2], 1, 1)
    return calibration_of(run.problem, run.estimate, covariances, run.residuals, run.whitened, run.labels,
                          iterations=run.iterations, initial_error=run.initial_error,
                          final_error=float(run.graph.error(run.result)),
                          converged=run.iterations < options.max_iterations,
                          dimension=run.dimension, excluded=run.excluded,
                          timings=run.timings)


def calibration_of(problem: ViewProblem, estimate: ViewEstimate, covariances, residuals: np.ndarray,
                   whitened: np.ndarray, labels: list, *, iterations: int, initial_error: float,
                   final_error: float, converged: bool, dimension: int, excluded: list[Exclusion],
                   timings: dict[str, float]) -> Calibration:
    """The :class:`Calibration` of an estimate of ``problem`` (batch or incremental): ``covariances`` as
    ``ViewProblem.covariances`` gives them (or None), the residuals and their labels as
    ``ViewProblem.residuals``, and what the solve reports (``dimension``: its scalar unknowns)."""
    from mirror_fg.solver.batch.intrinsics import camera_of

    pose_covs: dict[str, np.ndarray] = {}
    joint: np.ndarray | None = None
    mirror_covs: dict[tuple[int, int], np.ndarray] = {}
    point_covs: dict[str, np.ndarray] = {}
    intrinsics_covs: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    if covariances is not None:
        pose_covs, joint, mirror_covs, point_covs, intrinsics_covs = covariances
    dataset = problem.dataset
    first = problem.cameras[0]
    R, t = estimate.poses[first]
    estimated: dict[str, EstimatedCamera] = {}
    for name, model in problem.intrinsics.items():
        given = dataset.cameras[name] if dataset.cameras is not None else dataset.camera
        assert given is not None and estimate.theta is not None
        cov, cross = intrinsics_covs.get(name, (None, None))
        estimated[name] = EstimatedCamera(camera_of(given, estimate.theta[name]), model.estimated, cov, cross)
    cameras = None
    rig: list = []
    if dataset.cameras is not None:
        cameras = {name: CameraPose(name, *estimate.poses[name], pose_covs.get(name),
                                    estimated[name].camera if name in estimated else dataset.cameras[name],
                                    estimated.get(name))
                   for name in camera_names(dataset) if name in estimate.poses}
        rig = _rig(cameras, joint)
    return build_calibration(
        dataset, (R, t), pose_covs.get(first), mirror_vectors=estimate.mirror_vectors,
        mirror_covariances=mirror_covs, points=estimate.points, point_covariances=point_covs,
        residuals=residuals, whitened=whitened, labels=labels, unknowns=dimension, iterations=iterations,
        initial_error=initial_error, final_error=final_error, converged=converged, timings=timings,
        excluded=excluded, camera=estimated.get(first), cameras=cameras,
        camera_pose_covariance=joint if dataset.cameras is not None else None, rig=rig,
        mirror_frames=dict(problem.owners) if dataset.cameras is not None else {},
    )


def _rig(cameras: dict[str, CameraPose], joint) -> list:
    """Kalibr's ``T_cn_cnm1`` chain of the cameras (``solver/model/rig.py``), with its covariance."""
    names = list(cameras)
    return rig_transforms(names, [(cameras[n].R_cam_base, cameras[n].t_cam_base) for n in names], joint)
