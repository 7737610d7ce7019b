"""The batch solve of the general view model (``solver/views.py``'s problem), as ``calibrate()`` runs
it for data the paper's tree does not describe: analytical start by propagation
(``solver/propagation.py``) -> Levenberg-Marquardt (eq. 23) -> final check (measurements far off the
solution left out, solved again) -> Marginals -> :class:`~mirror_fg.solver.calibration.Calibration`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import Dataset, Image
from mirror_fg.solver.calibration import Calibration, CameraPose, Exclusion
from mirror_fg.solver.consensus import final_check, without
from mirror_fg.solver.lm import cost_scale, lm_params, run_optimizer
from mirror_fg.solver.options import STAGES, SolveOptions
from mirror_fg.solver.propagation import propagate
from mirror_fg.solver.timing import timed
from mirror_fg.solver.views import ViewEstimate, ViewProblem, camera_names

__all__ = ["calibrate_views", "tree_start_for"]

logger = logging.getLogger("mirror_fg")

#: Times the final check may leave measurements out and solve again.
MAX_RECHECKS = 2


@dataclass
class _Label:
    """What ``consensus.final_check`` reads of a measurement."""

    image_id: str
    point: str


def tree_start_for(dataset: Dataset):
    """Rule 2 of the propagation for one camera: its images through one mirror alone (the mirror with the
    most such placements, >= 3) or through the whole tree, solved by the paper's analytical solution
    (``initial.initial_estimate``) on their fiducials; ``((R, t), {placement: v})`` or None."""
    from mirror_fg.solver.initial import initial_estimate

    def start(camera_name: str):
        images = [im for im in dataset.images if dataset.cameras is None or im.camera == camera_name]
        camera = dataset.cameras[camera_name] if dataset.cameras is not None else dataset.camera
        groups: dict[int, list[Image]] = {}
        for im in images:
            if len(im.reflections) == 1:
                groups.setdefault(im.reflections[0][0], []).append(im)
        attempts = []
        tree = [im for im in images if len(im.mirror_configs) == dataset.num_mirrors]
        if tree and dataset.num_mirrors > 1:
            attempts.append((dataset.num_mirrors, None, tree))
        for mirror, group in sorted(groups.items(), key=lambda g: -len({im.reflections[0] for im in g[1]})):
            if len({im.reflections[0] for im in group}) >= 3:
                attempts.append((1, mirror, group))
        for num_mirrors, mirror, group in attempts:
            sub_images = []
            for im in group:
                observations = {n: z for n, z in im.observations.items() if n in dataset.fiducials}
                if len(observations) < 3:
                    continue
                configs = im.mirror_configs if mirror is None else (im.reflections[0][1],)
                sub_images.append(Image(im.id, configs, observations))
            sub = Dataset(num_mirrors=num_mirrors, camera=camera, pixel_sigma=dataset.pixel_sigma,
                          fiducials=dataset.fiducials, images=sub_images, source=dataset.source)
            try:
                solution = initial_estimate(sub)
            except (DatasetError, SolveError, ValueError, np.linalg.LinAlgError) as error:
                logger.debug("%s: camera %s: no start from %s: %s", dataset.source, camera_name,
                             "the tree" if mirror is None else f"mirror {mirror} alone", error)
                continue
            vectors = {((l, m) if mirror is None else (mirror, m)): np.asarray(v, float)
                       for (l, m), v in solution.mirror_vectors.items()}
            return (np.asarray(solution.R_cam_base, float), np.asarray(solution.t_cam_base, float)), vectors
        return None

    return start


def _start(problem: ViewProblem, initial) -> ViewEstimate:
    """The analytical start, or ``initial`` (a :class:`ViewEstimate`, or a single-camera estimate with
    ``R_cam_base``, ``t_cam_base``, ``mirror_vectors``, ``points``)."""
    if isinstance(initial, ViewEstimate):
        return initial
    if initial is not None:
        pose = (np.asarray(initial.R_cam_base, float), np.asarray(initial.t_cam_base, float))
        return ViewEstimate({problem.cameras[0]: pose}, dict(initial.mirror_vectors), dict(initial.points))
    dataset = problem.dataset
    known = propagate(problem.views, dataset.fiducials, problem.cameras, problem.fixed, tree_start_for(dataset),
                      dataset.scale)
    return problem.estimate_from(known)


def calibrate_views(dataset: Dataset, initial=None, options: SolveOptions | None = None) -> Calibration:
    """The MLE and covariances of a dataset in the general view model (module docstring)."""
    options = options or SolveOptions()
    report = options.progress if options.progress is not None else (lambda stage, done, total: None)
    timings: dict[str, float] = {}
    solved, excluded = dataset, []
    start = None
    for recheck in range(MAX_RECHECKS + 1):
        problem = ViewProblem(solved, options.robust)
        with timed(timings, "analytic"):
            start = _start(problem, initial if start is None else start)
        graph = problem.graph()
        values = problem.values(start)
        params = lm_params(options.max_iterations, cost_scale(solved))

        def iteration(number: int, before: float, after: float) -> None:
            report(STAGES[1], number, options.max_iterations)
            if options.on_iteration is not None:
                options.on_iteration(number, before, after)

        with timed(timings, "optimize"):
            optimizer, result, initial_error = run_optimizer(
                graph, values, params, solved.source,
                lambda error: f"the data do not constrain every unknown ({_named(problem, error)})", iteration)
        estimate = problem.read(result)
        residuals, whitened, labels, views = problem.residuals(estimate)
        measurements = [_Label(image, point) for image, point in labels]
        dimension = result.dim() - problem.constraints
        more = final_check(solved, measurements, whitened, dimension) if recheck < MAX_RECHECKS else []  # type: ignore[arg-type]
        if not more:
            break
        logger.warning("%s: %d measurement(s) or image(s) far off the solution left out; solving again",
                       dataset.source, len(more))
        excluded += more
        solved = without(solved, more)
        start = _kept(estimate, ViewProblem(solved, options.robust))
    iterations = int(optimizer.iterations())
    final_error = float(graph.error(result))
    converged = iterations < options.max_iterations
    pose_covs: dict[str, np.ndarray] = {}
    joint = None
    mirror_covs: dict = {}
    point_covs: dict = {}
    if options.compute_covariance:
        report(STAGES[2], 0, 1)
        with timed(timings, "marginals"):
            try:
                pose_covs, joint, mirror_covs, point_covs = problem.covariances(graph, result, estimate)
            except RuntimeError as error:
                raise SolveError(f"{dataset.source}: the data do not constrain every unknown "
                                 f"({_named(problem, error)})") from None
        report(STAGES[2], 1, 1)
    return _calibration(problem, estimate, pose_covs, joint, mirror_covs, point_covs, residuals, whitened, labels,
                        views, iterations=iterations, initial_error=initial_error, final_error=final_error,
                        converged=converged, expected=0.5 * max(len(whitened) * 2 - dimension, 0),
                        excluded=excluded, timings=timings)


def _kept(estimate: ViewEstimate, problem: ViewProblem) -> ViewEstimate:
    """``estimate`` restricted to what ``problem`` still has (after images were left out)."""
    return ViewEstimate({n: p for n, p in estimate.poses.items()},
                        {p: v for p, v in estimate.mirror_vectors.items() if p in problem.mirror_keys},
                        {n: x for n, x in estimate.points.items() if n in problem.point_keys})


def _named(problem: ViewProblem, error: Exception) -> str:
    import gtsam

    text = str(error)
    for key in [*problem.pose_keys.values(), *problem.mirror_keys.values(), *problem.point_keys.values()]:
        if gtsam.DefaultKeyFormatter(key) in text:
            return f"{problem.name_of(key)} is not constrained"
    return "indeterminant linear system"


def _calibration(problem: ViewProblem, estimate: ViewEstimate, pose_covs, joint, mirror_covs, point_covs,
                 residuals, whitened, labels, views, *, iterations, initial_error, final_error, converged, expected,
                 excluded: list[Exclusion], timings) -> Calibration:
    from mirror_fg.solver.residuals import outliers_of

    dataset = problem.dataset
    first = problem.cameras[0]
    R, t = estimate.poses[first]
    cameras = None
    rig: list = []
    if dataset.cameras is not None:
        cameras = {name: CameraPose(name, *estimate.poses[name], pose_covs.get(name), dataset.cameras[name])
                   for name in camera_names(dataset) if name in estimate.poses}
        rig = _rig(cameras, joint)
    calibration = Calibration(
        R_cam_base=R, t_cam_base=t, covariance=pose_covs.get(first),
        mirror_vectors=estimate.mirror_vectors, mirror_covariances=mirror_covs,
        points=estimate.points, point_covariances=point_covs, analytic=None,
        iterations=iterations, initial_error=initial_error, final_error=final_error, converged=converged,
        residuals=residuals, residual_labels=labels,
        residual_units="px" if dataset.camera is not None else "normalized",
        outliers=outliers_of([_Label(i, p) for i, p in labels], whitened),  # type: ignore[arg-type]
        timings=timings, expected_final_error=expected, excluded=list(excluded),
        cameras=cameras, camera_pose_covariance=joint if dataset.cameras is not None else None, rig=rig,
        mirror_frames=dict(problem.owners) if dataset.cameras is not None else {},
        residual_views=views,
    )
    return calibration


def _rig(cameras: dict[str, CameraPose], joint) -> list:
    """Kalibr's ``T_cn_cnm1`` chain (``solver/rig.py``), where it is available."""
    try:
        from mirror_fg.solver.rig import rig_transforms
    except ImportError:
        return []
    names = list(cameras)
    return rig_transforms(names, [(cameras[n].R_cam_base, cameras[n].t_cam_base) for n in names], joint)
