"""The paper's problem for ``calibrate()``'s pipeline (``pipeline.py``): one camera, a known target, every
image through mirrors 1..Nv (``mirror_configs``), normalized measurements.

screen: each image's PnP and its check, then the placements' consensus (``consensus.py``) -> solve: the
analytical solution (Sects. 4-5, ``initial.py``), Levenberg-Marquardt with its restarts (``lm.py``;
stacked or eliminated factors, ``SolveOptions.linearization``), marginals (``marginals.py``), residuals
(``residuals.py``) -> finish: what the data contradict (a split of the images into consistent groups,
two images labelled as one placement whose mirrors differ, a camera that moved; ``consistency.py``).
"""
from __future__ import annotations

import logging

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.data import Dataset
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.screen.consensus import PnPCandidates, check_images, screen
from mirror_fg.solver.screen.consistency import diagnose_inconsistency
from mirror_fg.solver.model.graph import InitialEstimate, Measurement
from mirror_fg.solver.start.initial import initial_estimate
from mirror_fg.solver.model.lm import levenberg_marquardt_with_restarts
from mirror_fg.solver.options import STAGES, SolveOptions
from mirror_fg.solver.screen.rechecks import Checked, Rechecked
from mirror_fg.solver.model.residuals import predicted_normalized, residual_statistics
from mirror_fg.solver.result.builder import build_calibration
from mirror_fg.solver.timing import timed

__all__ = ["TreeProblem"]

logger = logging.getLogger("mirror_fg")

#: One solve's result: the calibration, its measurements and their whitened residual norms.
TreeRun = tuple[Calibration, list[Measurement], np.ndarray]


class TreeProblem:
    """The paper's problem (module docstring); ``initial`` starts LM instead of the analytical solution."""

    def __init__(self, initial: InitialEstimate | None, options: SolveOptions, known_minima: dict | None = None):
        """``known_minima``: another check's PnP minima of the same photographs (``consensus.ImageChecks.minima``)."""
        self.initial, self.options = initial, options
        self.known_minima = known_minima
        self.timings: dict[str, float] = {}
        self.pnp: PnPCandidates = {}
        self.screened = 0

    def screen(self, dataset: Dataset) -> tuple[Dataset, list[Exclusion]]:
        with timed(self.timings, "pnp"):
            checked = check_images(dataset, self.known_minima)  # Sect. 4.1 per image, checked; the initial estimate starts from it
        with timed(self.timings, "consensus"):
            solved, excluded, self.pnp = screen(dataset, checked=checked)  # what disagrees with the rest, named
        self.screened = len(excluded)
        return solved, excluded

    def solve(self, solved: Dataset, excluded: list[Exclusion]) -> TreeRun:
        left_out = {e.image for e in excluded[self.screened:]}  # by the final check: their PnP is of other data
        try:
            return _solve(solved, self.initial, self.options, self.timings,
                          {i: p for i, p in self.pnp.items() if i not in left_out})
        except (DatasetError, SolveError) as error:
            if not excluded:
                raise
            raise type(error)(f"{error} (after leaving out {_listed(excluded)})") from None

    def check(self, run: TreeRun) -> Checked:
        calibration, measurements, whitened = run
        return Checked(measurements, whitened, 2 * len(measurements) - round(2 * calibration.expected_final_error))

    def finish(self, rechecked: Rechecked[TreeRun]) -> Calibration:
        (calibration, _, _), solved = rechecked.run, rechecked.solved
        calibration.excluded = list(rechecked.excluded)
        if self.options.diagnose:
            with timed(self.timings, "consistency"):
                calibration.inconsistency = diagnose_inconsistency(solved, calibration, self.pnp, self.options)
            if calibration.inconsistency is not None:
                logger.warning("%s: %s", solved.source, calibration.inconsistency.message)
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
    report = options.report
    logger.info("%s: calibrating %d images, %d mirror placements", dataset.source, len(dataset.images),
                len(dataset.configurations))
    with timed(timings, "analytic"):
        analytic: AnalyticSolution | None = None
        start = initial
        if start is None:
            start = analytic = initial_estimate(dataset, progress=lambda done: report(STAGES[0], done, None), pnp=pnp)
    logger.info("initial estimate: %.3f s", timings["analytic"])

    report(STAGES[1], 0, options.max_iterations)
    run, analytic, restarts = levenberg_marquardt_with_restarts(dataset, start, analytic, options, options.iteration,
                                                                timings)
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
    return build_calibration(
        dataset, (R, t), covariance, mirror_vectors=mirror_vectors, mirror_covariances=mirror_covs, points=points,
        point_covariances=point_covs, residuals=residuals, whitened=whitened,
        labels=[(m.image_id, m.point) for m in run.measurements], unknowns=run.dimension,
        iterations=run.iterations, initial_error=run.initial_error, final_error=run.final_error,
        converged=run.converged, timings=timings, analytic=analytic, restarts=restarts,
    ), run.measurements, whitened
