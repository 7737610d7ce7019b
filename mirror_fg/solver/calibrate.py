"""``calibrate``: the batch pipeline, read top to bottom (as Kalibr's ``main()``).

initial estimate (analytical solution, Sects. 4-5, ``initial.py``) -> Levenberg-Marquardt MLE (eq. 23)
with its restarts (``lm.py``) -> marginal covariances (``marginals.py``) -> residuals (``residuals.py``)
-> :class:`~mirror_fg.solver.calibration.Calibration`.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import Dataset, dataset_from_dict
from mirror_fg.solver.calibration import Calibration
from mirror_fg.solver.graph import InitialEstimate, extract_values
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.lm import levenberg_marquardt_with_restarts
from mirror_fg.solver.marginals import marginal_covariances
from mirror_fg.solver.residuals import outliers_of, predicted_normalized, residual_statistics
from mirror_fg.solver.timing import timed

__all__ = ["as_dataset", "calibrate"]


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
) -> Calibration:
    """Analytical solution (Sects. 4-5), then the MLE by Levenberg-Marquardt (eq. 23) and Marginals.

    initial: start the MLE from these values instead of the analytical solution (e.g. the ground truth).
    robust: ``None``, ``"huber"`` or ``"cauchy"`` kernel on every measurement. on_iteration: called with
    ``(iteration, error_before, error_after)`` after each LM iteration. fast: stacked vectorised
    factors (default) or the per-measurement reference factors (same estimates).
    """
    dataset = as_dataset(dataset)
    timings: dict[str, float] = {}
    with timed(timings, "analytic"):
        analytic = initial_estimate(dataset) if initial is None else None

    run, analytic, restarts = levenberg_marquardt_with_restarts(
        dataset, initial if initial is not None else analytic, analytic, robust, fast, max_iterations, on_iteration,
        timings,
    )

    with timed(timings, "marginals"):
        covariance, mirror_covs, point_covs = (None, {}, {})
        if compute_covariance:
            covariance, mirror_covs, point_covs = marginal_covariances(run.graph, run.result, run.layout, dataset.source)

    with timed(timings, "residuals"):
        R, t, mirror_vectors, points = extract_values(run.result, run.layout)
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
