"""The paper's problem with intrinsics estimated through the mirrors (``camera.estimate``), for
``calibrate()``'s pipeline (``pipeline.py``).

screen: the dataset's camera holds the start intrinsics -> the paper's problem with them fixed
(``tree_problem.py``: consensus, analytical solution on the images normalised with them, LM, restarts,
what is far off left out) for the start of pose, mirrors and points -> the observability check at that
start (``intrinsics_observability.py``); where that start did not converge or fails the check, the same
again with fx, fy, cx, cy started from the photographs (a given value too far off can make the
analytical solution degenerate) -> solve: joint Levenberg-Marquardt with pixel factors (the pixel
problem's pieces: ``intrinsics.py``) -> finish: where it did not converge from the given values, the
same from the photographs; Marginals; residuals in pixels. Estimating fx, fy, cx or cy is refused before
any solve unless ``intrinsics.MIN_BOARD_VIEWS`` photographs show 4 or more fiducials
(``intrinsics.check_supported``).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import SolveError
from mirror_fg.factors.intrinsics import IntrinsicsModel, intrinsics_key, predict_pixels
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Calibration, EstimatedCamera, Exclusion
from mirror_fg.solver.screen.consensus import without
from mirror_fg.solver.model.graph import Estimate, InitialEstimate, Measurement
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewProblem
from mirror_fg.solver.batch.intrinsics import (
    JointRun,
    camera_intrinsics,
    camera_of,
    check_supported,
    joint_covariances,
    joint_problem,
    joint_values,
    photograph_start,
    pixel_sigmas,
    run_joint_lm,
    with_start_noise,
)
from mirror_fg.solver.batch.intrinsics_observability import unobservable_refusal, warn_weak
from mirror_fg.solver.options import STAGES, Linearization, SolveOptions
from mirror_fg.solver.screen.rechecks import Checked, Rechecked, solve_with_rechecks
from mirror_fg.solver.model.residuals import predicted_normalized
from mirror_fg.solver.result.builder import build_calibration
from mirror_fg.solver.timing import timed

__all__ = ["PixelProblem"]

logger = logging.getLogger("mirror_fg")


@dataclass
class _Start:
    """The fixed-intrinsics solve from one start camera and the joint problem built on it."""

    camera: Camera
    start: Calibration
    solved: Dataset  # the dataset without what the start left out
    graph: gtsam.NonlinearFactorGraph
    layout: ViewProblem
    measurements: list[Measurement]
    pixels: np.ndarray
    values: gtsam.Values
    refusal: str | None  # why the intrinsics are unobservable from this start, or None

    @property
    def usable(self) -> bool:
        return self.start.converged and self.refusal is None


def _fixed_start(dataset: Dataset, camera: Camera, model: IntrinsicsModel, options: SolveOptions,
                 initial: InitialEstimate | None, fixed_calibrate: Callable[..., Calibration]) -> _Start:
    """``fixed_calibrate`` (``calibrate``) with the intrinsics fixed at ``camera`` (``intrinsics.with_start_noise``), the joint problem
    at its solution and the observability check there (module docstring). Of ``options`` the start takes
    the kernel, the iterations and the progress; no covariance, no diagnosis, the default factors."""
    # diagnose=False: with first-guess intrinsics the fit is often implausible; the split search belongs
    # to the joint solution, not to this start.
    start_options = replace(options, linearization=Linearization.ELIMINATED, compute_covariance=False,
                            on_iteration=None, diagnose=False)
    start = fixed_calibrate(with_start_noise(replace(dataset, camera=camera), [camera]), initial=initial,
                            options=start_options)
    solved = without(dataset, start.excluded) if start.excluded else dataset
    graph, layout, measurements, pixels = joint_problem(solved, replace(solved, camera=camera), model, options.robust)
    values = joint_values(layout, model, camera_intrinsics(camera)[model.index], start)
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


class PixelProblem:
    """The paper's problem with intrinsics estimated (module docstring). ``fixed_calibrate``: the pipeline
    for the fixed-intrinsics start (``calibrate``; given, so that this module does not import it back)."""

    def __init__(self, initial: InitialEstimate | None, options: SolveOptions,
                 fixed_calibrate: Callable[..., Calibration]):
        self.initial, self.options, self.fixed_calibrate = initial, options, fixed_calibrate
        self.timings: dict[str, float] = {}
        self.runs: list[_JointSolution] = []

    def _start(self, camera: Camera) -> _Start:
        return _fixed_start(self.dataset, camera, self.model, self.options, self.initial, self.fixed_calibrate)

    def screen(self, dataset: Dataset) -> tuple[Dataset, list[Exclusion]]:
        self.dataset = dataset
        camera = self.camera = check_supported(dataset)
        self.model = IntrinsicsModel(camera_intrinsics(camera), camera.estimate)
        self.given_camera = replace(camera, estimate=(), prior_sigma=())
        attempts: list[_Start] = []
        failure: SolveError | None = None  # the given start's own failure, raised if no start works
        with timed(self.timings, "fixed intrinsics"):
            for start_camera in (self.given_camera, None):
                if start_camera is None:
                    # The given values were too far off for the analytical solution (measured: fx 16 % off
                    # and no distortion gave mirror vectors near zero on a simulation): start from the photographs.
                    start_camera = photograph_start(dataset, self.given_camera)
                    if start_camera is None:
                        break
                    logger.info("%s: no usable start with the given intrinsics; starting them from the photographs: %s",
                                dataset.source,
                                ", ".join(f"{k}={getattr(start_camera, k):.6g}" for k in ("fx", "fy", "cx", "cy")))
                try:
                    attempts.append(self._start(start_camera))
                except SolveError as error:  # e.g. LM from a degenerate analytical solution
                    failure = failure or error
                    continue
                if attempts[-1].usable:
                    break
        chosen = next((a for a in attempts if a.usable), next((a for a in attempts if a.refusal is None), None))
        if chosen is None:
            if failure is not None and (not attempts or attempts[0].camera is not self.given_camera):
                raise failure
            raise SolveError(attempts[0].refusal)
        logger.info("%s: start of the joint estimate (intrinsics fixed): %d iterations, %.3f s", dataset.source,
                    chosen.start.iterations, self.timings["fixed intrinsics"])
        self.chosen = chosen
        self.options.report(STAGES[1], 0, self.options.max_iterations)
        return chosen.solved, list(chosen.start.excluded)

    def solve(self, solved: Dataset, excluded: list[Exclusion]) -> _JointSolution:
        """Joint LM; after leaving some out, the problem again from the last estimate."""
        chosen, model, options = self.chosen, self.model, self.options
        graph, layout, measurements, pixels, values = (chosen.graph, chosen.layout, chosen.measurements,
                                                        chosen.pixels, chosen.values)
        if solved is not chosen.solved:
            last = self.runs[-1]
            estimate = Estimate(last.R, last.t, last.mirror_vectors, last.points)
            graph, layout, measurements, pixels = joint_problem(solved, replace(solved, camera=chosen.camera), model,
                                                                options.robust)
            values = joint_values(layout, model, last.run.result.atVector(intrinsics_key()), estimate)
        with timed(self.timings, "optimize"):
            run = run_joint_lm(solved, replace(solved, camera=chosen.camera), graph, layout, measurements, pixels,
                               values, options.max_iterations, options.on_iteration)
        read = layout.read(run.result)
        (R, t), mirror_vectors, points = read.poses[SINGLE_CAMERA], read.mirror_vectors, read.points
        theta = model.theta(np.asarray(run.result.atVector(intrinsics_key()), dtype=float))
        predicted = predicted_normalized(solved, measurements, R, t, mirror_vectors, points)
        residuals = predict_pixels(theta, predicted) - pixels
        whitened = np.linalg.norm(residuals, axis=1) / pixel_sigmas(self.dataset, measurements)
        self.runs.append(_JointSolution(run=run, solved=solved, excluded=list(excluded), measurements=measurements,
                                        R=R, t=t, mirror_vectors=mirror_vectors, points=points, theta=theta,
                                        residuals=residuals, whitened=whitened))
        return self.runs[-1]

    def check(self, joint: _JointSolution) -> Checked:
        return Checked(joint.measurements, joint.whitened, joint.run.result.dim())

    def finish(self, rechecked: Rechecked[_JointSolution]) -> Calibration:
        joint, excluded = rechecked.run, rechecked.excluded
        dataset, chosen = self.dataset, self.chosen
        if not joint.run.converged and chosen.camera is self.given_camera:
            # The given values let the fixed-intrinsics solve through but left the joint solve stuck (the
            # analytical solution from a rough camera can be another optimum): start from the photographs.
            photographs = photograph_start(dataset, self.given_camera)
            other = None
            if photographs is not None:
                try:
                    other = self._start(photographs)
                except SolveError:
                    other = None
            if other is not None and other.refusal is None:
                logger.info("%s: the joint estimate from the given intrinsics did not converge; starting them from "
                            "the photographs", dataset.source)
                self.chosen, self.runs = other, []
                retry = solve_with_rechecks(other.solved, self.solve, self.check, other.start.excluded)
                if retry.run.run.converged:
                    chosen, joint, excluded = other, retry.run, retry.excluded
                self.chosen = chosen
        return self._calibration(chosen, joint, excluded)

    def _calibration(self, chosen: _Start, joint: _JointSolution, excluded: list[Exclusion]) -> Calibration:
        dataset, options, timings = self.dataset, self.options, self.timings
        report = options.report
        start, run, measurements = chosen.start, joint.run, joint.measurements
        logger.info("joint Levenberg-Marquardt with intrinsics: %d iterations, %.3f s", run.iterations,
                    timings.get("optimize", 0.0))
        if not run.converged:
            logger.warning("%s: Levenberg-Marquardt with intrinsics did not converge in %d iterations",
                           dataset.source, run.iterations)
        estimated_camera = camera_of(self.camera, joint.theta)
        covariance = None
        mirror_covs: dict[tuple[int, int], np.ndarray] = {}
        point_covs: dict[str, np.ndarray] = {}
        intrinsics_cov: np.ndarray | None = None
        cross: np.ndarray | None = None
        with timed(timings, "marginals"):
            if options.compute_covariance:
                report(STAGES[2], 0, 1)
                covariance, intrinsics_cov, cross, mirror_covs, point_covs = joint_covariances(
                    run.graph, run.result, run.layout, dataset.source)
                report(STAGES[2], 1, 1)
                warn_weak(intrinsics_cov, estimated_camera, self.model.estimated, dataset.source)
        return build_calibration(
            dataset, (joint.R, joint.t), covariance, mirror_vectors=joint.mirror_vectors,
            mirror_covariances=mirror_covs, points=joint.points, point_covariances=point_covs,
            residuals=joint.residuals, whitened=joint.whitened,
            labels=[(m.image_id, m.point) for m in measurements], unknowns=run.result.dim(),
            iterations=run.iterations, initial_error=run.initial_error, final_error=run.final_error,
            converged=run.converged, in_pixels=True,
            timings={**{f'start: {k}': v for k, v in start.timings.items()}, **timings},
            analytic=start.analytic, restarts=start.restarts, excluded=excluded,
            camera=EstimatedCamera(camera=estimated_camera, estimated=self.model.estimated, covariance=intrinsics_cov,
                                   pose_cross_covariance=cross),
        )
