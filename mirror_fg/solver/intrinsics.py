"""``calibrate_with_intrinsics``: the MLE (eq. 23) with the camera intrinsics among the unknowns (issue 16).

Pipeline: the dataset's camera holds the start intrinsics (the given values; where fx, fy, cx or cy
was absent, :func:`mirror_fg.core.camera.initial_intrinsics` computed them from the photographs when
the dataset was loaded) -> ``calibrate()`` with those intrinsics fixed (analytical solution on the
image normalised with them, LM, restarts, left-out outliers) for the start of pose, mirrors and
points -> the observability check below at that start; where that start did not converge or fails
the check, the same again with fx, fy, cx, cy started from the photographs (a given value too far
off can make the analytical solution degenerate) -> joint Levenberg-Marquardt (Marquardt's diagonal
damping) over pose, mirrors, points and the intrinsics named in ``camera.estimate`` with pixel factors (``factors/intrinsics.py``) and the optional Gaussian
prior ``camera.prior_sigma`` -> ``gtsam.Marginals`` (the pose's covariance *including* the intrinsics'
uncertainty, their own covariance and their cross-covariance with the pose) -> residuals in pixels.

Observability: ``intrinsics_observability.py`` (the Fisher information criterion, unobservable refused,
weak warned).

Before any solve, estimating fx, fy, cx or cy is refused (SolveError) unless at least ``MIN_BOARD_VIEWS``
photographs show 4 or more fiducials: a photograph of 3 points fits *any* focal length and centre
exactly (P3P has solutions for every ``K``), so those intrinsics would rest on the mirror geometry
alone. Measured on a simulation (two mirrors at 0.2 m, 12 images of a 3-point triangle): 3-sigma of
fx ~50 px at the corner (below the Fisher refusal) and LM not converged in 100 iterations.

Both messages name the intrinsics and what to add: more points per image, more tilt of the target
in the mirror, more mirror placements.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any

import gtsam
import numpy as np

from mirror_fg.core.camera import Camera, initial_intrinsics
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.intrinsics import (
    IntrinsicsModel, intrinsics_factors, intrinsics_key, intrinsics_prior_factor, predict_pixels,
)
from mirror_fg.io.dataset import Dataset
from mirror_fg.solver.calibration import Calibration, EstimatedCamera
from mirror_fg.solver.intrinsics_observability import (  # noqa: F401 (public here too)
    ADVICE, UNOBSERVABLE_FRACTION, UNOBSERVABLE_RCOND, WEAK_CORNER_PX, IntrinsicsObservability, WeakIntrinsicsWarning,
    corner_sensitivity, intrinsics_observability, unobservable_refusal, warn_weak,
)
from mirror_fg.solver.graph import GraphLayout, InitialEstimate, Measurement, extract_values, initial_values, measurements_of
from mirror_fg.solver.lm import cost_scale, lm_params, run_optimizer
from mirror_fg.solver.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.solver.options import STAGES, Linearization, Progress, SolveOptions
from mirror_fg.solver.residuals import outliers_of, predicted_normalized
from mirror_fg.solver.timing import timed

__all__ = [
    "calibrate_with_intrinsics", "WeakIntrinsicsWarning", "IntrinsicsObservability", "intrinsics_observability",
    "corner_sensitivity", "camera_intrinsics", "WEAK_CORNER_PX", "UNOBSERVABLE_RCOND", "UNOBSERVABLE_FRACTION", "MIN_BOARD_VIEWS",
]

logger = logging.getLogger("mirror_fg")

#: The fixed-intrinsics start is solved with at least this fraction of the image diagonal as its pixel
#: sigma, so that the start intrinsics' error is not taken for outliers (only gross ones are left out).
START_SIGMA_FRACTION = 0.003
#: fx, fy, cx, cy are estimated only with at least this many photographs of 4 or more fiducials.
MIN_BOARD_VIEWS = 2
#: Distortion terms beyond OpenCV's k1, k2, p1, p2, k3 that the pixel factors do not model.
_MODELLED_DIST = 5


def camera_intrinsics(camera: Camera) -> np.ndarray:
    """The nine intrinsics of ``camera`` in INTRINSIC_NAMES order (dist padded with zeros)."""
    dist = list(camera.dist) + [0.0] * max(0, 5 - len(camera.dist))
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, dist[0], dist[1], dist[2], dist[3], dist[4]],
                    dtype=float)


def _camera_of(camera: Camera, theta: np.ndarray) -> Camera:
    """``camera`` with the nine intrinsics ``theta``, nothing left to estimate."""
    dist = list(camera.dist)
    dist[:4] = [float(v) for v in theta[4:8]]
    if len(dist) >= 5:
        dist[4] = float(theta[8])
    return replace(camera, fx=float(theta[0]), fy=float(theta[1]), cx=float(theta[2]), cy=float(theta[3]),
                   dist=tuple(dist), estimate=(), prior_sigma=())


def _check_supported(dataset: Dataset) -> Camera:
    """The camera, after the refusals that need no solve: a fisheye model, unmodelled distortion terms
    (DatasetError); fx, fy, cx or cy estimated from fewer than ``MIN_BOARD_VIEWS`` photographs of 4
    or more fiducials (SolveError, module docstring)."""
    camera = dataset.camera
    assert camera is not None and camera.estimate
    pinhole = [n for n in ("fx", "fy", "cx", "cy") if n in camera.estimate]
    views = sum(1 for image in dataset.images if sum(n in dataset.fiducials for n in image.observations) >= 4)
    if pinhole and views < MIN_BOARD_VIEWS:
        most = max(sum(n in dataset.fiducials for n in image.observations) for image in dataset.images)
        raise SolveError(f"{dataset.source}: camera.estimate: the photographs do not determine {', '.join(pinhole)}: "
                         f"{views} image(s) show 4 or more fiducials (at most {most} per image), need {MIN_BOARD_VIEWS} "
                         f"(any focal length and centre fit 3 points exactly); {ADVICE}, or give them")
    if camera.model != "pinhole":
        raise DatasetError(f"{dataset.source}: camera.estimate: estimating intrinsics is supported for the "
                           f"pinhole model only, not {camera.model}")
    if any(float(v) != 0.0 for v in camera.dist[_MODELLED_DIST:]):
        raise DatasetError(f"{dataset.source}: camera.estimate: dist has terms beyond k1, k2, p1, p2, k3 "
                           "(rational or thin-prism), which the estimation does not model")
    return camera


@dataclass
class _JointRun:
    """One joint LM run over pose, mirrors, points and the intrinsics, with what it was built from."""

    dataset: Dataset
    graph: gtsam.NonlinearFactorGraph
    layout: GraphLayout
    measurements: list[Measurement]
    pixels: np.ndarray  # (M, 2) observed
    result: gtsam.Values
    initial_error: float
    final_error: float
    iterations: int
    converged: bool


def pixel_sigmas(dataset: Dataset, measurements: list[Measurement]) -> np.ndarray:
    """Each measurement's noise (M,), pixels: its point's ``point_sigma``, else ``pixel_sigma``."""
    return np.array([dataset.point_sigma.get(m.point, dataset.pixel_sigma) for m in measurements], dtype=float)


def _joint_problem(dataset: Dataset, fixed: Dataset, model: IntrinsicsModel, robust: str | None,
                   ) -> tuple[gtsam.NonlinearFactorGraph, GraphLayout, list[Measurement], np.ndarray]:
    """The graph of pixel factors (and the prior) of ``dataset``; ``fixed`` the same images with the
    start camera (its measurements give the structure)."""
    assert dataset.camera is not None
    layout = GraphLayout.for_dataset(dataset)
    measurements = measurements_of(fixed)
    by_id = {image.id: image for image in dataset.images}
    pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements]).reshape(-1, 2)
    graph = gtsam.NonlinearFactorGraph()
    for factor in intrinsics_factors(dataset, layout, measurements, pixels, model, pixel_sigmas(dataset, measurements),
                                     robust):
        graph.add(factor)
    prior = intrinsics_prior_factor(model, dict(dataset.camera.prior_sigma))
    if prior is not None:
        graph.add(prior)
    return graph, layout, measurements, pixels


def _run_lm(dataset: Dataset, fixed: Dataset, graph: gtsam.NonlinearFactorGraph, layout: GraphLayout,
            measurements: list[Measurement], pixels: np.ndarray, values: gtsam.Values, max_iterations: int,
            on_iteration: Callable[[int, float, float], None] | None) -> _JointRun:
    """Levenberg-Marquardt (eq. 23) from ``values`` with the project's settings (``lm.lm_params``)."""
    params = lm_params(max_iterations, cost_scale(fixed))
    # Marquardt's damping (lambda diag(J^T J)): the unknowns' units differ by orders of magnitude
    # (pixels, unitless k1..k3, metres, radians). With lambda I a rough start (fx 130 px off, no
    # distortion) gave up at once on simulated data; scaled damping descends from it.
    params.setDiagonalDamping(True)
    optimizer, result, initial_error = run_optimizer(
        graph, values, params, dataset.source, lambda error: _unconstrained(error, layout), on_iteration)
    iterations = optimizer.iterations()
    final_error = graph.error(result)
    converged = bool(np.isfinite(final_error)) and iterations < max_iterations
    return _JointRun(dataset, graph, layout, measurements, pixels, result, float(initial_error), float(final_error),
                     iterations, converged)


def _values_for(layout: GraphLayout, intrinsics: np.ndarray, estimate: Any) -> gtsam.Values:
    """Start values of ``layout``'s unknowns from an estimate, and of the ``K(0)`` vector."""
    values = initial_values(layout, estimate)
    values.insert(intrinsics_key(), np.array(intrinsics, dtype=float))
    return values


def _photograph_start(dataset: Dataset, camera: Camera) -> Camera | None:
    """``camera`` with the estimated ones of fx, fy, cx, cy started from the photographs
    (:func:`~mirror_fg.core.camera.initial_intrinsics`), or None where they cannot be (none of them
    estimated, fiducials not coplanar, too few board views)."""
    assert dataset.camera is not None
    estimate = dataset.camera.estimate
    if not any(n in estimate for n in ("fx", "fy", "cx", "cy")):
        return None
    given = {n: (None if n in estimate else float(getattr(camera, n))) for n in ("fx", "fy", "cx", "cy")}
    try:
        start = initial_intrinsics(camera.width, camera.height, dataset.fiducials,
                                   [image.observations for image in dataset.images], dataset.num_mirrors % 2 == 1,
                                   given, camera.dist, dataset.source, free_k1="k1" in estimate)
    except DatasetError:
        return None
    return replace(camera, fx=start["fx"], fy=start["fy"], cx=start["cx"], cy=start["cy"])


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
    at its solution and the observability check there (module docstring). Of ``options`` the start takes
    the kernel, the iterations and the progress; no covariance, no diagnosis, the default factors."""
    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.consensus import without

    # diagnose=False: with first-guess intrinsics the fit is often implausible; the split search belongs
    # to the joint solution, not to this start.
    inflated = {name: max(value, sigma) for name, value in dataset.point_sigma.items()}
    start_options = replace(options, linearization=Linearization.ELIMINATED, compute_covariance=False,
                            on_iteration=None, diagnose=False)
    start = calibrate(replace(dataset, camera=camera, pixel_sigma=sigma, point_sigma=inflated), initial=initial,
                      options=start_options)
    solved = without(dataset, start.excluded) if start.excluded else dataset
    graph, layout, measurements, pixels = _joint_problem(solved, replace(solved, camera=camera), model, options.robust)
    values = _values_for(layout, camera_intrinsics(camera)[model.index], start)
    refusal = unobservable_refusal(graph, values, layout, camera, model.estimated, dataset.source)
    return _Start(camera, start, solved, graph, layout, measurements, pixels, values, refusal)


def _joint_solve(dataset: Dataset, chosen: _Start, model: IntrinsicsModel, options: SolveOptions) -> SimpleNamespace:
    """Joint LM from a start, leaving out what ends far off (``consensus.final_check``) and solving again;
    the run and what it was solved on (``solved``, ``excluded``, ``measurements``), the estimate and the
    pixel residuals (``residuals``, ``whitened``)."""
    from mirror_fg.solver.calibrate import MAX_RECHECKS
    from mirror_fg.solver.consensus import final_check, without

    start_camera, solved, excluded = chosen.camera, chosen.solved, list(chosen.start.excluded)
    graph, layout, measurements, pixels, values = chosen.graph, chosen.layout, chosen.measurements, chosen.pixels, chosen.values
    for recheck in range(MAX_RECHECKS + 1):
        fixed = replace(solved, camera=start_camera)
        run = _run_lm(solved, fixed, graph, layout, measurements, pixels, values, options.max_iterations,
                      options.on_iteration)
        R, t, mirror_vectors, points = extract_values(run.result, layout)
        theta = model.theta(np.asarray(run.result.atVector(intrinsics_key()), dtype=float))
        predicted = predicted_normalized(solved, measurements, R, t, mirror_vectors, points)
        residuals = predict_pixels(theta, predicted) - pixels
        whitened = np.linalg.norm(residuals, axis=1) / pixel_sigmas(dataset, measurements)
        more = final_check(solved, measurements, whitened, run.result.dim()) if recheck < MAX_RECHECKS else []
        if not more:
            break
        logger.warning("%s: %d measurement(s) or image(s) far off the solution left out; solving again",
                       dataset.source, len(more))
        excluded += more
        solved = without(solved, more)
        estimate = SimpleNamespace(R_cam_base=R, t_cam_base=t, mirror_vectors=mirror_vectors, points=points)
        graph, layout, measurements, pixels = _joint_problem(solved, replace(solved, camera=start_camera), model,
                                                             options.robust)
        values = _values_for(layout, run.result.atVector(intrinsics_key()), estimate)
    return SimpleNamespace(run=run, solved=solved, excluded=excluded, measurements=measurements, R=R, t=t,
                           mirror_vectors=mirror_vectors, points=points, theta=theta, residuals=residuals,
                           whitened=whitened)


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
    docstring). Arguments as :func:`mirror_fg.solver.calibrate.calibrate`; ``initial`` starts the
    fixed-intrinsics stage (pose, mirrors, points), the intrinsics start at the camera's values.

    Measurements or images that ``calibrate`` leaves out at the start (far off even with the start
    intrinsics' sigma, see ``START_SIGMA_FRACTION``) or that end far off the joint solution
    (``consensus.final_check``) are left out, as ``calibrate`` does, and listed in ``excluded``.

    Raises DatasetError (a fisheye camera, unmodelled distortion terms) or SolveError (unobservable
    intrinsics, an indeterminant system); warns :class:`WeakIntrinsicsWarning` on weak ones.
    ``options``: the settings in one :class:`SolveOptions` instead (its ``linearization`` and ``diagnose``
    are not used: the start takes the default factors, the joint solve pixel factors).
    """
    if options is None:
        options = SolveOptions(robust=robust, compute_covariance=compute_covariance, max_iterations=max_iterations,
                               on_iteration=on_iteration, progress=progress)
    camera = _check_supported(dataset)
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
                start_camera = _photograph_start(dataset, given_camera)
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
            photographs = _photograph_start(dataset, given_camera)
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
    estimated_camera = _camera_of(camera, theta)

    covariance = None
    mirror_covs: dict[tuple[int, int], np.ndarray] = {}
    point_covs: dict[str, np.ndarray] = {}
    intrinsics_cov: np.ndarray | None = None
    cross: np.ndarray | None = None
    with timed(timings, "marginals"):
        if options.compute_covariance:
            report(STAGES[2], 0, 1)
            covariance, intrinsics_cov, cross, mirror_covs, point_covs = _covariances(
                run.graph, run.result, run.layout, R, dataset.source)
            report(STAGES[2], 1, 1)
            warn_weak(intrinsics_cov, estimated_camera, names, dataset.source)

    return Calibration(
        R_cam_base=R,
        t_cam_base=t,
        covariance=covariance,
        mirror_vectors=mirror_vectors,
        mirror_covariances=mirror_covs,
        points=points,
        point_covariances=point_covs,
        analytic=start.analytic,
        iterations=run.iterations,
        initial_error=run.initial_error,
        final_error=run.final_error,
        converged=run.converged,
        residuals=residuals,
        residual_labels=[(m.image_id, m.point) for m in measurements],
        residual_units="px",
        outliers=outliers_of(measurements, whitened),
        timings={**{f'start: {k}': v for k, v in start.timings.items()}, **timings},
        expected_final_error=0.5 * max(2 * len(measurements) - run.result.dim(), 0),
        restarts=start.restarts,
        excluded=excluded,
        camera=EstimatedCamera(camera=estimated_camera, estimated=names, covariance=intrinsics_cov,
                               pose_cross_covariance=cross),
    )


def _covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: GraphLayout, R: np.ndarray,
                 source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict]:
    """Pose (SPEC convention, intrinsics marginalised), intrinsics (k, k), their cross-covariance with
    the pose (k, 6, SPEC convention), mirror and point covariances, from ``gtsam.Marginals``."""
    with unconstrained_as_solve_error(source, lambda error: _unconstrained(error, layout)):
        marginals = gtsam.Marginals(graph, values)
        joint = marginals.jointMarginalCovariance([layout.pose_key, intrinsics_key()]).fullMatrix()
    to_spec = np.zeros((6, 6))
    to_spec[:3, :3] = R  # dtheta = R w, dt = R nu (SPEC's uncertainty convention)
    to_spec[3:, 3:] = R
    pose = covariance_from_pose3(R, joint[:6, :6])
    intrinsics = joint[6:, 6:]
    cross = joint[6:, :6] @ to_spec.T
    mirrors = {config: marginals.marginalCovariance(key) for config, key in layout.mirror_keys.items()}
    points = {name: marginals.marginalCovariance(key) for name, key in layout.point_keys.items()}
    return pose, intrinsics, cross, mirrors, points


def _unconstrained(error: Exception, layout: GraphLayout) -> str:
    """:func:`unconstrained_message`, naming the intrinsics vector too."""
    if gtsam.DefaultKeyFormatter(intrinsics_key()) in str(error):
        return "the data do not constrain the estimated intrinsics (indeterminant system near them)"
    return unconstrained_message(error, layout)

