"""``calibrate``: the batch pipeline, read top to bottom (as Kalibr's ``main()``).

consensus (images and corners that disagree with the rest left out, ``consensus.py``) -> initial
estimate (analytical solution, Sects. 4-5, ``initial.py``) -> Levenberg-Marquardt MLE (eq. 23) with its
restarts (``lm.py``) -> marginal covariances (``marginals.py``) -> residuals (``residuals.py``) -> final
check (measurements far off the solution left out, solve again) -> what the data contradict: a split
of the images into consistent groups, images of one placement that see different mirrors, a camera that
moved between placements of mirror 1 (``consistency.py``) ->
:class:`~mirror_fg.solver.calibration.Calibration`, with everything left out in ``excluded``.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import Dataset, dataset_from_dict
from mirror_fg.solver.analytic import AnalyticSolution
from mirror_fg.solver.calibration import Calibration, Exclusion
from mirror_fg.solver.consensus import PnPCandidates, check_images, final_check, screen, without
from mirror_fg.solver.consistency import diagnose_inconsistency
from mirror_fg.solver.graph import InitialEstimate, Measurement
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.lm import levenberg_marquardt_with_restarts
from mirror_fg.solver.options import STAGES, Linearization, Progress, SolveOptions
from mirror_fg.solver.residuals import outliers_of, predicted_normalized, residual_statistics
from mirror_fg.solver.timing import timed

__all__ = ["as_dataset", "calibrate", "Progress", "SolveOptions", "STAGES"]

logger = logging.getLogger("mirror_fg")

#: Times the final check may leave measurements out and solve again.
MAX_RECHECKS = 2


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
    if dataset.camera is not None and dataset.camera.estimate:  # intrinsics estimated too (camera.estimate)
        from mirror_fg.solver.intrinsics import calibrate_with_intrinsics

        return calibrate_with_intrinsics(dataset, initial=initial, options=options)
    timings: dict[str, float] = {}
    with timed(timings, "pnp"):
        checked = check_images(dataset)  # Sect. 4.1 per image, checked; the initial estimate starts from it
    with timed(timings, "consensus"):
        solved, excluded, pnp = screen(dataset, checked=checked)  # what disagrees with the rest, named
    for recheck in range(MAX_RECHECKS + 1):
        try:
            calibration, measurements, whitened = _solve(solved, initial, options, timings, pnp)
        except (DatasetError, SolveError) as error:
            if not excluded:
                raise
            raise type(error)(f"{error} (after leaving out {_listed(excluded)})") from None
        dimension = 2 * len(measurements) - round(2 * calibration.expected_final_error)  # unknowns (lm.LMRun)
        more = final_check(solved, measurements, whitened, dimension) if recheck < MAX_RECHECKS else []
        if not more:
            break
        logger.warning("%s: %d measurement(s) or image(s) far off the solution left out; solving again", dataset.source,
                       len(more))
        for exclusion in more:
            logger.warning("%s: image '%s'%s left out: %s", dataset.source, exclusion.image,
                           f" point '{exclusion.point}'" if exclusion.point else "", exclusion.reason)
        excluded = excluded + more
        solved = without(solved, more)
        pnp = {image_id: poses for image_id, poses in pnp.items() if image_id not in {e.image for e in more}}
    calibration.excluded = list(excluded)
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
    ), run.measurements, whitened
