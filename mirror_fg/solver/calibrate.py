"""``calibrate``: the batch pipeline, read top to bottom (as Kalibr's ``main()``).

initial estimate (analytical solution, Sects. 4-5, ``initial.py``) -> Levenberg-Marquardt MLE (eq. 23)
with its restarts (``lm.py``) -> marginal covariances (``marginals.py``) -> residuals (``residuals.py``)
-> :class:`~mirror_fg.solver.calibration.Calibration`.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import Dataset, dataset_from_dict
from mirror_fg.solver.analytic import AnalyticSolution
from mirror_fg.solver.calibration import Calibration
from mirror_fg.solver.graph import InitialEstimate
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.lm import levenberg_marquardt_with_restarts
from mirror_fg.solver.residuals import outliers_of, predicted_normalized, residual_statistics
from mirror_fg.solver.timing import timed

__all__ = ["as_dataset", "calibrate", "Progress", "STAGES"]

logger = logging.getLogger("mirror_fg")

#: ``progress(stage, done, total)``: called as each stage of ``calibrate`` advances (``total`` None
#: where it is not known in advance).
Progress = Callable[[str, int, "int | None"], None]
#: The stages ``calibrate`` reports, in order.
STAGES = ("initial estimate", "Levenberg-Marquardt", "marginals")


def as_dataset(data: Dataset | Mapping[str, Any], what: str = "calibrate()") -> Dataset:
    """``data`` as a :class:`Dataset` (a dataset@1 dictionary is validated) that the solver can take.

    Raises DatasetError on anything else, or where the dataset asks for what this version cannot do
    (intrinsics estimated through the mirrors, ``camera.estimate``).
    """
    if isinstance(data, Mapping):
        data = dataset_from_dict(data, source="<dataset dict>")
    if not isinstance(data, Dataset):
        raise DatasetError(f"{what}: expected a mirror_fg.Dataset or a dataset@1 dictionary, got {type(data).__name__}")
    if data.camera is not None and data.camera.estimate:
        raise DatasetError(f"{data.source}: camera.estimate ({', '.join(data.camera.estimate)}): estimating "
                           "intrinsics through the mirrors is not supported by this version")
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
) -> Calibration:
    """Analytical solution (Sects. 4-5), then the MLE by Levenberg-Marquardt (eq. 23) and Marginals.

    initial: start the MLE from these values instead of the analytical solution (e.g. the ground truth).
    robust: ``None``, ``"huber"`` or ``"cauchy"`` kernel on every measurement. on_iteration: called with
    ``(iteration, error_before, error_after)`` after each LM iteration. fast: stacked vectorised
    factors (default) or the per-measurement reference factors (same estimates). progress: called
    ``progress(stage, done, total)`` per stage (:data:`STAGES`): nodes of the mirror tree scored,
    LM iterations (of ``max_iterations``), marginals (0 then 1 of 1). Stage times are logged on the
    ``"mirror_fg"`` logger (INFO).
    """
    dataset = as_dataset(dataset)
    timings: dict[str, float] = {}
    report = progress if progress is not None else (lambda stage, done, total: None)
    logger.info("%s: calibrating %d images, %d mirror placements", dataset.source, len(dataset.images),
                len(dataset.configurations))
    with timed(timings, "analytic"):
        analytic: AnalyticSolution | None = None
        start = initial
        if start is None:
            start = analytic = initial_estimate(dataset, progress=lambda done: report(STAGES[0], done, None))
    logger.info("initial estimate: %.3f s", timings["analytic"])

    def iteration(number: int, error_before: float, error_after: float) -> None:
        report(STAGES[1], number, max_iterations)
        if on_iteration is not None:
            on_iteration(number, error_before, error_after)

    report(STAGES[1], 0, max_iterations)
    run, analytic, restarts = levenberg_marquardt_with_restarts(
        dataset, start, analytic, robust, fast, max_iterations, iteration,
        timings,
    )
    logger.info("Levenberg-Marquardt: %d iterations, %d restart(s), %.3f s (build %.3f s)", run.iterations, restarts,
                timings.get("optimize", 0.0), timings.get("build", 0.0))
    if not run.converged:
        logger.warning("%s: Levenberg-Marquardt did not converge in %d iterations", dataset.source, run.iterations)

    with timed(timings, "marginals"):
        covariance: np.ndarray | None = None
        mirror_covs: dict[tuple[int, int], np.ndarray] = {}
        point_covs: dict[str, np.ndarray] = {}
        if compute_covariance:
            report(STAGES[2], 0, 1)
            covariance, mirror_covs, point_covs = run.covariances(dataset)
            report(STAGES[2], 1, 1)
    logger.debug("marginals: %.3f s", timings["marginals"])

    with timed(timings, "residuals"):
        R, t, mirror_vectors, points = run.estimate()
        predicted = predicted_normalized(dataset, run.measurements, R, t, mirror_vectors, points)
        residuals, whitened = residual_statistics(dataset, run.measurements, predicted)
    return Calibration(
        R_cam_base=R,
        t_cam_base=t,
        covariance=covariance,
        mirror_vectors=mirror_vectors,
        mirror_covariances=mirror_covs,
        points=points,
        point_covariances=point_covs,
        analytic=analytic,
        iterations=run.iterations,
        initial_error=run.initial_error,
        expected_final_error=run.expected_final_error,
        restarts=restarts,
        final_error=run.final_error,
        converged=run.converged,
        residuals=residuals,
        residual_labels=[(m.image_id, m.point) for m in run.measurements],
        residual_units="px" if dataset.camera is not None else "normalized",
        outliers=outliers_of(run.measurements, whitened),
        timings=timings,
    )
