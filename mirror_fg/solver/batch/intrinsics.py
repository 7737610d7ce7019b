"""The pixel problem: the MLE (eq. 23) with the camera intrinsics among the unknowns.

Its pieces, which ``calibrate.calibrate_with_intrinsics`` (the pipeline) puts together: the dataset's
camera holds the start intrinsics (the given values; where fx, fy, cx or cy was absent,
:func:`mirror_fg.core.camera.initial_intrinsics` computed them from the photographs when the dataset was
loaded, :func:`photograph_start` again when the given ones give no usable start); the joint graph of the
one measurement model's view factors in pixels (``model/views.py`` with the camera's ``IntrinsicsModel``:
``factors/views.py`` through ``factors/intrinsics.py``) with the optional Gaussian prior
``camera.prior_sigma`` (:func:`joint_problem`, :func:`joint_values`); joint Levenberg-Marquardt with Marquardt's diagonal damping
(:func:`run_joint_lm`); ``gtsam.Marginals`` (:func:`joint_covariances`: the pose's covariance *including*
the intrinsics' uncertainty, their own covariance and their cross-covariance with the pose).
This module imports nothing of the pipeline (``calibrate.py``), which imports it.

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

from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from mirror_fg.core.camera import Camera, initial_intrinsics
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.factors.intrinsics import IntrinsicsModel, intrinsics_key
from mirror_fg.data import Dataset
from mirror_fg.solver.batch.intrinsics_observability import (  # noqa: F401 (public here too)
    ADVICE, UNOBSERVABLE_FRACTION, UNOBSERVABLE_RCOND, WEAK_CORNER_PX, IntrinsicsObservability, WeakIntrinsicsWarning,
    corner_sensitivity, intrinsics_observability, unobservable_refusal, warn_weak,
)
from mirror_fg.solver.model.graph import InitialEstimate, Measurement, measurements_of
from mirror_fg.solver.model.lm import cost_scale, lm_params, run_optimizer
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem

__all__ = [
    "WeakIntrinsicsWarning", "IntrinsicsObservability", "intrinsics_observability",
    "corner_sensitivity", "camera_intrinsics", "WEAK_CORNER_PX", "UNOBSERVABLE_RCOND", "UNOBSERVABLE_FRACTION", "MIN_BOARD_VIEWS",
    "START_SIGMA_FRACTION", "with_start_noise", "JointRun", "camera_of", "check_supported", "joint_covariances", "joint_problem",
    "joint_values", "photograph_start", "pixel_sigmas", "run_joint_lm",
]


#: The fixed-intrinsics start is solved with at least this fraction of the image diagonal as its pixel
#: sigma, so that the start intrinsics' error is not taken for outliers (only gross ones are left out).
START_SIGMA_FRACTION = 0.003
#: fx, fy, cx, cy are estimated only with at least this many photographs of 4 or more fiducials.
MIN_BOARD_VIEWS = 2
#: Distortion terms beyond OpenCV's k1, k2, p1, p2, k3 that the pixel factors do not model.
_MODELLED_DIST = 5


def with_start_noise(dataset: Dataset, cameras: Iterable[Camera]) -> Dataset:
    """``dataset`` with the noise of a fixed-intrinsics start: its pixel sigma (and each ``point_sigma``) at
    least :data:`START_SIGMA_FRACTION` of the largest image diagonal of ``cameras``. The start intrinsics
    may be off by many pixels: with the file's sigma the fixed-intrinsics solve would leave out sound
    measurements as outliers, and its estimate does not depend on a uniform sigma."""
    diagonal = max(float(np.hypot(camera.width, camera.height)) for camera in cameras)
    sigma = max(dataset.pixel_sigma, START_SIGMA_FRACTION * diagonal)
    return replace(dataset, pixel_sigma=sigma,
                   point_sigma={name: max(value, sigma) for name, value in dataset.point_sigma.items()})


def camera_intrinsics(camera: Camera) -> np.ndarray:
    """The nine intrinsics of ``camera`` in INTRINSIC_NAMES order (dist padded with zeros)."""
    dist = list(camera.dist) + [0.0] * max(0, 5 - len(camera.dist))
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, dist[0], dist[1], dist[2], dist[3], dist[4]],
                    dtype=float)


def camera_of(camera: Camera, theta: np.ndarray) -> Camera:
    """``camera`` with the nine intrinsics ``theta``, nothing left to estimate."""
    dist = list(camera.dist)
    dist[:4] = [float(v) for v in theta[4:8]]
    if len(dist) >= 5:
        dist[4] = float(theta[8])
    return replace(camera, fx=float(theta[0]), fy=float(theta[1]), cx=float(theta[2]), cy=float(theta[3]),
                   dist=tuple(dist), estimate=(), prior_sigma=())


def check_supported(dataset: Dataset) -> Camera:
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
class JointRun:
    """One joint LM run over pose, mirrors, points and the intrinsics, with what it was built from."""

    dataset: Dataset
    graph: gtsam.NonlinearFactorGraph
    layout: ViewProblem  # its keys, and the names of an unconstrained unknown
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


def joint_problem(dataset: Dataset, fixed: Dataset, model: IntrinsicsModel, robust: str | None,
                   ) -> tuple[gtsam.NonlinearFactorGraph, ViewProblem, list[Measurement], np.ndarray]:
    """The graph of ``dataset``'s views in pixels through ``model`` (every placement a plane, the intrinsics
    vector ``K(0)``) and the prior, its problem (keys, estimate, names), and the measurements and pixels of
    ``fixed``, the same images with the start camera (in file order: the residuals' order)."""
    assert dataset.camera is not None
    problem = ViewProblem(dataset, robust, intrinsics={SINGLE_CAMERA: model})
    measurements = measurements_of(fixed)
    by_id = {image.id: image for image in dataset.images}
    pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements]).reshape(-1, 2)
    return problem.graph(), problem, measurements, pixels


def run_joint_lm(dataset: Dataset, fixed: Dataset, graph: gtsam.NonlinearFactorGraph, layout: ViewProblem,
            measurements: list[Measurement], pixels: np.ndarray, values: gtsam.Values, max_iterations: int,
            on_iteration: Callable[[int, float, float], None] | None) -> JointRun:
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
    return JointRun(dataset, graph, layout, measurements, pixels, result, float(initial_error), float(final_error),
                     iterations, converged)


def joint_values(problem: ViewProblem, model: IntrinsicsModel, intrinsics: np.ndarray,
                 estimate: InitialEstimate) -> gtsam.Values:
    """Start values of ``problem``'s unknowns from an estimate, and of the ``K(0)`` vector (``intrinsics``:
    the estimated ones, in ``model.estimated`` order)."""
    theta = model.theta(np.asarray(intrinsics, dtype=float))
    return problem.values(ViewEstimate({SINGLE_CAMERA: (np.asarray(estimate.R_cam_base, float),
                                                        np.asarray(estimate.t_cam_base, float))},
                                       {p: np.asarray(v, float) for p, v in estimate.mirror_vectors.items()},
                                       {n: np.asarray(x, float) for n, x in estimate.points.items()},
                                       {SINGLE_CAMERA: theta}))


def photograph_start(dataset: Dataset, camera: Camera) -> Camera | None:
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


def joint_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, problem: ViewProblem,
                      source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict]:
    """Pose (docs/formats.md convention, intrinsics marginalised), intrinsics (k, k), their cross-covariance with
    the pose (k, 6, docs/formats.md convention), mirror and point covariances (``ViewProblem.covariances``)."""
    with unconstrained_as_solve_error(source, lambda error: _unconstrained(error, problem)):
        poses, _, mirrors, points, intrinsics = problem.covariances(graph, values, problem.read(values))
    covariance, cross = intrinsics[SINGLE_CAMERA]
    assert cross is not None  # (the camera's pose is an unknown: a known target)
    return poses[SINGLE_CAMERA], covariance, cross, mirrors, points


def _unconstrained(error: Exception, layout: ViewProblem) -> str:
    """:func:`unconstrained_message`, naming the intrinsics vector too."""
    if gtsam.DefaultKeyFormatter(intrinsics_key()) in str(error):
        return "the data do not constrain the estimated intrinsics (indeterminant system near them)"
    return unconstrained_message(error, layout)

