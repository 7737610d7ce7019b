"""``calibrate``: the batch pipeline, read top to bottom (as Kalibr's ``main()``).

consensus (images and corners that disagree with the rest left out, ``consensus.py``) -> initial
estimate (analytical solution, Sects. 4-5, ``initial.py``) -> Levenberg-Marquardt MLE (eq. 23) with its
restarts (``lm.py``) -> marginal covariances (``marginals.py``) -> residuals (``residuals.py``) -> final
check (measurements far off the solution left out, solve again) -> what the data contradict: a split
of the images into consistent groups, images of one placement that see different mirrors, a camera that
moved between placements of mirror 1 (``consistency.py``) ->
:class:`~mirror_fg.solver.calibration.Calibration`, with everything left out in ``excluded``.

With intrinsics among the unknowns (``camera.estimate``, issue 16) the same pipeline gives the start
(:func:`calibrate_with_intrinsics`): the dataset's camera holds the start intrinsics -> this pipeline
with them fixed (analytical solution on the image normalised with them, LM, restarts, left-out
outliers) for the start of pose, mirrors and points -> the observability check at that start
(``intrinsics_observability.py``); where that start did not converge or fails the check, the same again
with fx, fy, cx, cy started from the photographs (a given value too far off can make the analytical
solution degenerate) -> joint Levenberg-Marquardt with pixel factors, its final check -> Marginals ->
residuals in pixels (the pixel problem's pieces: ``intrinsics.py``). Estimating fx, fy, cx or cy is
refused before any solve unless ``intrinsics.MIN_BOARD_VIEWS`` photographs show 4 or more fiducials
(``intrinsics.check_supported``).
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.factors.intrinsics import IntrinsicsModel, intrinsics_key, predict_pixels
from mirror_fg.io.dataset import Dataset, dataset_from_dict
from mirror_fg.solver.analytic import AnalyticSolution
from mirror_fg.solver.calibration import Calibration, EstimatedCamera, Exclusion
from mirror_fg.solver.consensus import PnPCandidates, check_images, screen, without
from mirror_fg.solver.consistency import diagnose_inconsistency
from mirror_fg.solver.graph import Estimate, GraphLayout, InitialEstimate, Measurement, extract_values
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.intrinsics import (
    START_SIGMA_FRACTION, JointRun, camera_intrinsics, camera_of, check_supported, joint_covariances, joint_problem, joint_values,
    photograph_start, pixel_sigmas, run_joint_lm,
)
from mirror_fg.solver.intrinsics_observability import unobservable_refusal, warn_weak
from mirror_fg.solver.lm import levenberg_marquardt_with_restarts
from mirror_fg.solver.rechecks import MAX_RECHECKS, Checked, solve_with_rechecks  # noqa: F401 (MAX_RECHECKS public here)
from mirror_fg.solver.options import STAGES, Linearization, Progress, SolveOptions
from mirror_fg.solver.residuals import outliers_of, predicted_normalized, residual_statistics
from mirror_fg.solver.timing import timed

__all__ = ["as_dataset", "calibrate", "calibrate_with_intrinsics", "Progress", "SolveOptions", "STAGES"]

logger = logging.getLogger("mirror_fg")




def as_dataset(data: Dataset | Mapping[str, Any], what: str = "calibrate()") -> Dataset:
    """``data`` as a :class:`Dataset` (a dataset@1 dictionary is validated) that the solver can take.

    Raises DatasetError on anything else.
    """
    if isinstance(data, Mapping):
        data = dataset_from_dict(data, source="<dataset dict>")
    if not isinstance(data, Dataset):
        raise DatasetError(f"{what}: expected a mirror_fg.Dataset or a dataset@1 dictionary, got {type(data).__name__}")
    return data


def calibrate(
    dataset: Dataset | Mapping[str, Any],
    *,
    initial: InitialEstimate | None = None,
    robust: str | None = None,
    compute_covariance: bool = True,
    max_iterations: int = 100,
    on_iteration: Callable[[int, float, float], None] | None = None,
    fast: bool = True,
    progress: Progress | None = None,
    diagnose: bool = True,
    options: SolveOptions | None = None,
) -> Calibration:
    """Analytical solution (Sects. 4-5), then the MLE by Levenberg-Marquardt (eq. 23) and Marginals.

    initial: start the MLE from these values instead of the analytical solution (e.g. the ground truth).
    robust: ``None``, ``"huber"`` or ``"cauchy"`` kernel on every measurement (another name: ValueError).
    on_iteration: called with ``(iteration, error_before, error_after)`` after each LM iteration. fast:
    stacked vectorised factors (default) or the per-measurement reference factors (same estimates). progress: called
    ``progress(stage, done, total)`` per stage (:data:`STAGES`): nodes of the mirror tree scored,
    LM iterations (of ``max_iterations``), marginals (0 then 1 of 1). Stage times are logged on the
    ``"mirror_fg"`` logger (INFO).

    Images or fiducials that disagree with the rest (a wrong corner order, a gross corner, an image
    inconsistent with the other placements of its mirror) are left out before the solve, measurements
    far off the solution (``consensus.FINAL_SIGMAS``) after it, and the solve repeated: each is in
    ``Calibration.excluded`` with its reason (``consensus.py``); with nothing left out the answer is
    exactly that of the solve alone. ``Calibration.inconsistency`` names what the data contradict
    (``consistency.diagnose_inconsistency``): where the final cost is implausible, a split of the images
    (in capture order) into groups each consistent alone, else two images labelled as one placement whose
    mirrors differ; whatever the cost, a split at a boundary between placements of mirror 1 whose two
    sides' poses differ beyond their covariances (a camera that moved). A few dozen solves of the groups
    at most: ``diagnose=False`` skips it, e.g. for a first solve that is expected to fit badly.
    Whether the result may be written is :func:`~mirror_fg.solver.calibration.require_converged`'s call.

    options: all of the settings above in one :class:`~mirror_fg.solver.options.SolveOptions` (then give
    none of them separately: TypeError); ``fast=True`` is ``linearization="eliminated"``, ``fast=False``
    ``"reference"``, and ``SolveOptions(linearization="stacked")`` the stacked factors without elimination.
    """
    separate = (robust, compute_covariance, max_iterations, on_iteration, fast, progress, diagnose)
    if options is None:
        options = SolveOptions(robust=robust, compute_covariance=compute_covariance, max_iterations=max_iterations,
                               on_iteration=on_iteration, progress=progress, diagnose=diagnose,
                               linearization=Linearization.ELIMINATED if fast else Linearization.REFERENCE)
    elif separate != (None, True, 100, None, True, None, True):
        raise TypeError("calibrate(): give the settings either in options= or as separate arguments, not both")
    dataset = as_dataset(dataset)
    if not dataset.is_tree:  # direct views, fixed mirrors, any order, no known target, several cameras
        from mirror_fg.solver.views_solve import calibrate_views

        return calibrate_views(dataset, initial, options)
    if dataset.camera is not None and dataset.camera.estimate:  # intrinsics estimated too (camera.estimate)
        return calibrate_with_intrinsics(dataset, initial=initial, options=options)
    timings: dict[str, float] = {}
    with timed(timings, "pnp"):
        checked = check_images(dataset)  # Sect. 4.1 per image, checked; the initial estimate starts from it
    with timed(timings, "consensus"):
        solved, excluded, pnp = screen(dataset, checked=checked)  # what disagrees with the rest, named
    screened = len(excluded)

    def solve(solved: Dataset, excluded: list[Exclusion]) -> tuple[Calibration, list[Measurement], np.ndarray]:
        left_out = {e.image for e in excluded[screened:]}  # by the final check: their PnP is of other data
        try:
            return _solve(solved, initial, options, timings, {i: p for i, p in pnp.items() if i not in left_out})
        except (DatasetError, SolveError) as error:
            if not excluded:
                raise
            raise type(error)(f"{error} (after leaving out {_listed(excluded)})") from None

    def check_of(run: tuple[Calibration, list[Measurement], np.ndarray]) -> Checked:
        calibration, measurements, whitened = run
        return Checked(measurements, whitened, 2 * len(measurements) - round(2 * calibration.expected_final_error))

    rechecked = solve_with_rechecks(solved, solve, check_of, excluded)
    (calibration, _, _), solved = rechecked.run, rechecked.solved
    calibration.excluded = list(rechecked.excluded)
    if options.diagnose:
        with timed(timings, "consistency"):
            calibration.inconsistency = diagnose_inconsistency(solved, calibration, pnp)
        if calibration.inconsistency is not None:
            logger.warning("%s: %s", dataset.source, calibration.inconsistency.message)
    return calibration


def _listed(excluded: list[Exclusion], limit: int = 5) -> str:
    """The exclusions in a few words each, for an error message."""
    words = [f"image '{e.image}'" + (f" point '{e.point}'" if e.point else "") + f": {e.reason}" for e in excluded[:limit]]
    more = f"; and {len(excluded) - limit} more" if len(excluded) > limit else ""
    return "; ".join(words) + more


def _solve(
    dataset: Dataset, initial: InitialEstimate | None, options: SolveOptions, timings: dict[str, float],
    pnp: PnPCandidates,
) -> tuple[Calibration, list[Measurement], np.ndarray]:
    """One solve of ``dataset`` as it is: the analytical solution, LM with its restarts, marginals; the
    calibration with its measurements and their whitened residual norms (sigmas)."""
    progress, on_iteration, max_iterations = options.progress, options.on_iteration, options.max_iterations
    report = progress if progress is not None else (lambda stage, done, total: None)
    logger.info("%s: calibrating %d images, %d mirror placements", dataset.source, len(dataset.images),
                len(dataset.configurations))
    with timed(timings, "analytic"):
        analytic: AnalyticSolution | None = None
        start = initial
        if start is None:
            start = analytic = initial_estimate(dataset, progress=lambda done: report(STAGES[0], done, None), pnp=pnp)
    logger.info("initial estimate: %.3f s", timings["analytic"])

    def iteration(number: int, error_before: float, error_after: float) -> None:
        report(STAGES[1], number, max_iterations)
        if on_iteration is not None:
            on_iteration(number, error_before, error_after)

    report(STAGES[1], 0, max_iterations)
    run, analytic, restarts = levenberg_marquardt_with_restarts(dataset, start, analytic, options, iteration, timings)
    logger.info("Levenberg-Marquardt: %d iterations, %d restart(s), %.3f s (build %.3f s)", run.iterations, restarts,
                timings.get("optimize", 0.0), timings.get("build", 0.0))
    if not run.converged:
        logger.warning("%s: Levenberg-Marquardt did not converge in %d iterations", dataset.source, run.iterations)

    with timed(timings, "marginals"):
        covariance: np.ndarray | None = None
        mirror_covs: dict[tuple[int, int], np.ndarray] = {}
        point_covs: dict[str, np.ndarray] = {}
        if options.compute_covariance:
            report(STAGES[2], 0, 1)
            covariance, mirror_covs, point_covs = run.covariances(dataset)
            report(STAGES[2], 1, 1)
    logger.debug("marginals: %.3f s", timings["marginals"])

    with timed(timings, "residuals"):
        R, t, mirror_vectors, points = run.estimate()
        predicted = predicted_normalized(dataset, run.measurements, R, t, mirror_vectors, points)
        residuals, whitened = residual_statistics(dataset, run.measurements, predicted)
    return _calibration(
        (R, t, mirror_vectors, points), (covariance, mirror_covs, point_covs), run.measurements, whitened,
        analytic=analytic,
        iterations=run.iterations,
        initial_error=run.initial_error,
        expected_final_error=run.expected_final_error,
        restarts=restarts,
        final_error=run.final_error,
        converged=run.converged,
        residuals=residuals,
        residual_units="px" if dataset.camera is not None else "normalized",
        timings=timings,
    ), run.measurements, whitened


def _calibration(
    estimate: tuple[np.ndarray, np.ndarray, dict, dict], covariances: tuple[np.ndarray | None, dict, dict],
    measurements: list[Measurement], whitened: np.ndarray, **solve: Any,
) -> Calibration:
    """The :class:`Calibration` of an estimate ``(R_cam_base, t_cam_base, mirror_vectors, points)``, its
    covariances ``(pose, mirrors, points)``, its measurements' labels and outliers (whitened residual
    norms ``whitened``) and what the solve reports (``solve``: iterations, costs, residuals, ...)."""
    (R, t, mirror_vectors, points), (covariance, mirror_covs, point_covs) = estimate, covariances
    return Calibration(
        R_cam_base=R,
        t_cam_base=t,
        covariance=covariance,
        mirror_vectors=mirror_vectors,
        mirror_covariances=mirror_covs,
        points=points,
        point_covariances=point_covs,
        residual_labels=[(m.image_id, m.point) for m in measurements],
        outliers=outliers_of(measurements, whitened),
        **solve,
    )


@dataclass
class _Start:
    """The fixed-intrinsics solve from one start camera and the joint problem built on it."""

    camera: Camera
    start: Calibration
    solved: Dataset  # the dataset without what the start left out
    graph: gtsam.NonlinearFactorGraph
    layout: GraphLayout
    measurements: list[Measurement]
    pixels: np.ndarray
    values: gtsam.Values
    refusal: str | None  # why the intrinsics are unobservable from this start, or None

    @property
    def usable(self) -> bool:
        return self.start.converged and self.refusal is None


def _fixed_start(dataset: Dataset, camera: Camera, sigma: float, model: IntrinsicsModel, options: SolveOptions,
                 initial: InitialEstimate | None) -> _Start:
    """``calibrate`` with the intrinsics fixed at ``camera`` (pixel sigma ``sigma``), the joint problem
    at its solution and the observability check there (module docstring, second paragraph). Of ``options`` the start takes
    the kernel, the iterations and the progress; no covariance, no diagnosis, the default factors."""
    # diagnose=False: with first-guess intrinsics the fit is often implausible; the split search belongs
    # to the joint solution, not to this start.
    inflated = {name: max(value, sigma) for name, value in dataset.point_sigma.items()}
    start_options = replace(options, linearization=Linearization.ELIMINATED, compute_covariance=False,
                            on_iteration=None, diagnose=False)
    start = calibrate(replace(dataset, camera=camera, pixel_sigma=sigma, point_sigma=inflated), initial=initial,
                      options=start_options)
    solved = without(dataset, start.excluded) if start.excluded else dataset
    graph, layout, measurements, pixels = joint_problem(solved, replace(solved, camera=camera), model, options.robust)
    values = joint_values(layout, camera_intrinsics(camera)[model.index], start)
    refusal = unobservable_refusal(graph, values, layout, camera, model.estimated, dataset.source)
    return _Start(camera, start, solved, graph, layout, measurements, pixels, values, refusal)


@dataclass
class _JointSolution:
    """The joint solve's last run, what it was solved on, its estimate, intrinsics and pixel residuals."""

    run: JointRun
    solved: Dataset
    excluded: list[Exclusion]
    measurements: list[Measurement]
    R: np.ndarray
    t: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]
    theta: np.ndarray
    residuals: np.ndarray
    whitened: np.ndarray


def _joint_solve(dataset: Dataset, chosen: _Start, model: IntrinsicsModel, options: SolveOptions) -> _JointSolution:
    """Joint LM from a start, leaving out what ends far off (``rechecks.solve_with_rechecks``) and solving
    again from the last estimate; the run and what it was solved on (``solved``, ``excluded``,
    ``measurements``), the estimate and the pixel residuals (``residuals``, ``whitened``)."""
    start_camera = chosen.camera

    def solve(solved: Dataset, excluded: list[Exclusion]) -> _JointSolution:
        graph, layout, measurements, pixels, values = (chosen.graph, chosen.layout, chosen.measurements,
                                                        chosen.pixels, chosen.values)
        if solved is not chosen.solved:  # after leaving some out: the problem again, from the last estimate
            last = runs[-1]
            estimate = Estimate(last.R, last.t, last.mirror_vectors, last.points)
            graph, layout, measurements, pixels = joint_problem(solved, replace(solved, camera=start_camera), model,
                                                                options.robust)
            values = joint_values(layout, last.run.result.atVector(intrinsics_key()), estimate)
        run = run_joint_lm(solved, replace(solved, camera=start_camera), graph, layout, measurements, pixels, values,
                           options.max_iterations, options.on_iteration)
        R, t, mirror_vectors, points = extract_values(run.result, layout)
        theta = model.theta(np.asarray(run.result.atVector(intrinsics_key()), dtype=float))
        predicted = predicted_normalized(solved, measurements, R, t, mirror_vectors, points)
        residuals = predict_pixels(theta, predicted) - pixels
        whitened = np.linalg.norm(residuals, axis=1) / pixel_sigmas(dataset, measurements)
        runs.append(_JointSolution(run=run, solved=solved, excluded=list(excluded), measurements=measurements, R=R,
                                   t=t, mirror_vectors=mirror_vectors, points=points, theta=theta, residuals=residuals,
                                   whitened=whitened))
        return runs[-1]

    runs: list[_JointSolution] = []
    rechecked = solve_with_rechecks(chosen.solved, solve,
                                    lambda joint: Checked(joint.measurements, joint.whitened, joint.run.result.dim()),
                                    chosen.start.excluded)
    joint = rechecked.run
    joint.excluded = rechecked.excluded
    return joint


def calibrate_with_intrinsics(
    dataset: Dataset,
    *,
    initial: InitialEstimate | None = None,
    robust: str | None = None,
    compute_covariance: bool = True,
    max_iterations: int = 100,
    on_iteration: Callable[[int, float, float], None] | None = None,
    progress: Progress | None = None,
    options: SolveOptions | None = None,
) -> Calibration:
    """The MLE of every unknown and of the intrinsics named in ``dataset.camera.estimate`` (module
    docstring, second paragraph). Arguments as :func:`calibrate`; ``initial`` starts the
    fixed-intrinsics stage (pose, mirrors, points), the intrinsics start at the camera's values.

    Measurements or images that ``calibrate`` leaves out at the start (far off even with the start
    intrinsics' sigma, see ``intrinsics.START_SIGMA_FRACTION``) or that end far off the joint solution
    (``consensus.final_check``) are left out, as ``calibrate`` does, and listed in ``excluded``.

    Raises DatasetError (a fisheye camera, unmodelled distortion terms) or SolveError (unobservable
    intrinsics, an indeterminant system); warns
    :class:`~mirror_fg.solver.intrinsics_observability.WeakIntrinsicsWarning` on weak ones.
    ``options``: the settings in one :class:`SolveOptions` instead (its ``linearization`` and ``diagnose``
    are not used: the start takes the default factors, the joint solve pixel factors).
    """
    if options is None:
        options = SolveOptions(robust=robust, compute_covariance=compute_covariance, max_iterations=max_iterations,
                               on_iteration=on_iteration, progress=progress)
    camera = check_supported(dataset)
    timings: dict[str, float] = {}
    max_iterations = options.max_iterations
    report = options.progress if options.progress is not None else (lambda stage, done, total: None)
    model = IntrinsicsModel(camera_intrinsics(camera), camera.estimate)
    names = model.estimated
    # The start intrinsics may be off by many pixels: with the file's sigma the fixed-intrinsics solve
    # would leave out sound measurements as outliers. Its estimate does not depend on a uniform sigma.
    start_sigma = max(dataset.pixel_sigma, START_SIGMA_FRACTION * float(np.hypot(camera.width, camera.height)))
    given_camera = replace(camera, estimate=(), prior_sigma=())
    attempts: list[_Start] = []
    failure: SolveError | None = None  # the given start's own failure, raised if no start works
    with timed(timings, "fixed intrinsics"):
        for start_camera in (given_camera, None):
            if start_camera is None:
                # The given values were too far off for the analytical solution (measured: fx 16 % off
                # and no distortion gave mirror vectors near zero on a simulation): start from the photographs.
                start_camera = photograph_start(dataset, given_camera)
                if start_camera is None:
                    break
                logger.info("%s: no usable start with the given intrinsics; starting them from the photographs: %s",
                            dataset.source, ", ".join(f"{k}={getattr(start_camera, k):.6g}" for k in ("fx", "fy", "cx", "cy")))
            try:
                attempts.append(_fixed_start(dataset, start_camera, start_sigma, model, options, initial))
            except SolveError as error:  # e.g. LM from a degenerate analytical solution
                failure = failure or error
                continue
            if attempts[-1].usable:
                break
    chosen = next((a for a in attempts if a.usable), next((a for a in attempts if a.refusal is None), None))
    if chosen is None:
        if failure is not None and (not attempts or attempts[0].camera is not given_camera):
            raise failure
        raise SolveError(attempts[0].refusal)
    logger.info("%s: start of the joint estimate (intrinsics fixed): %d iterations, %.3f s", dataset.source,
                chosen.start.iterations, timings["fixed intrinsics"])
    with timed(timings, "optimize"):
        report(STAGES[1], 0, max_iterations)
        joint = _joint_solve(dataset, chosen, model, options)
        if not joint.run.converged and chosen.camera is given_camera:
            # The given values let the fixed-intrinsics solve through but left the joint solve stuck (the
            # analytical solution from a rough camera can be another optimum): start from the photographs.
            photographs = photograph_start(dataset, given_camera)
            other = None
            if photographs is not None:
                try:
                    other = _fixed_start(dataset, photographs, start_sigma, model, options, initial)
                except SolveError:
                    other = None
            if other is not None and other.refusal is None:
                logger.info("%s: the joint estimate from the given intrinsics did not converge; starting them from "
                            "the photographs", dataset.source)
                retry = _joint_solve(dataset, other, model, options)
                if retry.run.converged:
                    chosen, joint = other, retry
    start, run, excluded, measurements = chosen.start, joint.run, joint.excluded, joint.measurements
    R, t, mirror_vectors, points, theta, residuals, whitened = (joint.R, joint.t, joint.mirror_vectors, joint.points,
                                                                joint.theta, joint.residuals, joint.whitened)
    logger.info("joint Levenberg-Marquardt with intrinsics: %d iterations, %.3f s", run.iterations, timings["optimize"])
    if not run.converged:
        logger.warning("%s: Levenberg-Marquardt with intrinsics did not converge in %d iterations",
                       dataset.source, run.iterations)
    estimated_camera = camera_of(camera, theta)

    covariance = None
    mirror_covs: dict[tuple[int, int], np.ndarray] = {}
    point_covs: dict[str, np.ndarray] = {}
    intrinsics_cov: np.ndarray | None = None
    cross: np.ndarray | None = None
    with timed(timings, "marginals"):
        if options.compute_covariance:
            report(STAGES[2], 0, 1)
            covariance, intrinsics_cov, cross, mirror_covs, point_covs = joint_covariances(
                run.graph, run.result, run.layout, R, dataset.source)
            report(STAGES[2], 1, 1)
            warn_weak(intrinsics_cov, estimated_camera, names, dataset.source)

    return _calibration(
        (R, t, mirror_vectors, points), (covariance, mirror_covs, point_covs), measurements, whitened,
        analytic=start.analytic,
        iterations=run.iterations,
        initial_error=run.initial_error,
        final_error=run.final_error,
        converged=run.converged,
        residuals=residuals,
        residual_units="px",
        timings={**{f'start: {k}': v for k, v in start.timings.items()}, **timings},
        expected_final_error=0.5 * max(2 * len(measurements) - run.result.dim(), 0),
        restarts=start.restarts,
        excluded=excluded,
        camera=EstimatedCamera(camera=estimated_camera, estimated=names, covariance=intrinsics_cov,
                               pose_cross_covariance=cross),
    )
