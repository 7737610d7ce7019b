"""Levenberg-Marquardt for the MLE (eq. 23) of the paper's tree: one run on the one measurement model
(``view_lm.py``), the plausibility of its final cost, and the restarts from the analytical solution's
runner-up hypotheses. The optimizer's settings, stall test and polish: ``optimizer.py``. (The tree's own
factors, the reference this is checked against, live with the tests: ``tests/reference/``.)
"""
from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.fit import plausible
from mirror_fg.data import Dataset
from mirror_fg.factors.view_eliminated import collapsed
from mirror_fg.solver.model.graph import InitialEstimate
from mirror_fg.solver.model.optimizer import (  # noqa: F401 (the settings' old home: callers import them here too)
    GENERAL_LAMBDA_UPPER_BOUND,
    POLISH_STEP_TOLERANCE,
    POLISH_STEPS,
    REFERENCE_NORMALIZED_SIGMA,
    _polished,
    _stationary,
    cost_scale,
    lm_params,
    polished,
    run_optimizer,
)
from mirror_fg.solver.model import view_lm
from mirror_fg.solver.model.view_lm import ViewLMRun
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.start.analytic import AnalyticSolution, reconstruct_points

__all__ = [
    "REFERENCE_NORMALIZED_SIGMA", "MAX_RESTARTS", "ViewLMRun", "cost_scale", "lm_params", "plausible",
    "levenberg_marquardt", "levenberg_marquardt_with_restarts", "polished",
]

logger = logging.getLogger("mirror_fg")

#: Solve with the photographs' own placements eliminated inside the factors (``factors/view_eliminated.py``)
#: where the options ask for it and the data allow it (no robust kernel, ``SolveOptions.eliminates``):
#: linear cost in the number of images. False: the stacked view factors with every placement in the
#: graph (same estimates).
ELIMINATE = True

#: At most this many restarts of LM from the analytical solution's runner-up hypotheses.
MAX_RESTARTS = 4


def levenberg_marquardt(
    dataset: Dataset, initial: InitialEstimate, options: SolveOptions,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> ViewLMRun:
    """Build the graph from ``initial`` with ``options``' factors and kernel and run LM (eq. 23) for at most
    ``options.max_iterations``; ``on_iteration`` its iteration hook, times added to ``timings``."""
    run = _levenberg_marquardt(dataset, initial, options, options.eliminates(ELIMINATE), on_iteration, timings)
    if run.evaluator is not None and collapsed(list(run.evaluator.mirror_vectors(run.result).values())):
        # a placement ran into the camera centre inside its factor (factors.view_eliminated.COLLAPSED_FRACTION)
        logger.info("%s: an eliminated mirror placement collapsed into the camera centre: solving again with every "
                    "placement an unknown", dataset.source)
        run = _levenberg_marquardt(dataset, initial, options, False, on_iteration, timings)
    return run


def _levenberg_marquardt(
    dataset: Dataset, initial: InitialEstimate, options: SolveOptions, eliminate: bool,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> ViewLMRun:
    """:func:`levenberg_marquardt` on the view model (``view_lm.py``) with the photographs' own placements
    eliminated inside their factors (``eliminate``, where the data allow it) or every placement an
    unknown; polished to the optimum (LM stops ~1e-7 from it)."""
    scale = cost_scale(dataset)
    params = lm_params(options.max_iterations, scale)

    def finish(graph, optimizer, result, polish: bool):
        if polish:  # polished to the optimum (LM stops ~1e-7 from it), whatever the linearisation
            result = polished(graph, result)
        final_error = graph.error(result)
        # LM also stops when its damping hits the upper bound: a stall unless a Gauss-Newton step
        # would no longer lower the error (then it is at a stationary point, e.g. noise-free data).
        stalled = optimizer.lambda_() >= params.getlambdaUpperBound() and not _stationary(graph, result, final_error, scale)
        return result, final_error, bool(np.isfinite(final_error)) and optimizer.iterations() < options.max_iterations and not stalled

    return view_lm.view_model_run(dataset, initial, options, eliminate, on_iteration, timings, params, finish)


def levenberg_marquardt_with_restarts(
    dataset: Dataset, initial: InitialEstimate, analytic: AnalyticSolution | None, options: SolveOptions,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> tuple[ViewLMRun, AnalyticSolution | None, int]:
    """LM from ``initial``; when it ends implausibly and ``analytic`` is that start, LM again from the
    root's runner-up hypotheses (best fiducial reprojection first, at most ``MAX_RESTARTS``).

    Returns the best run (converged first, then lowest cost), the analytical solution it started from
    and the number of restarts.
    """
    run = levenberg_marquardt(dataset, initial, options, on_iteration, timings)
    restarts = 0
    if analytic is None or run.plausible:
        return run, analytic, restarts
    # A cost far above its chi-square range: LM stopped in another minimum. Start again from the
    # root's runner-up hypotheses; keep the lowest cost.
    logger.info("%s: final cost %.6g far above its expected %.6g: restarting from the runner-up hypotheses",
                dataset.source, run.final_error, run.expected_final_error)
    for alternative in analytic.alternatives[:MAX_RESTARTS]:
        if not alternative.points and run.layout.point_keys:
            alternative.points = reconstruct_points(dataset, alternative)
        restarts += 1
        try:
            other = levenberg_marquardt(dataset, alternative, options, None, timings)
        except SolveError:
            continue
        if (other.converged, -other.final_error) > (run.converged, -run.final_error):
            run, analytic = other, alternative
        if run.plausible:
            break
    return run, analytic, restarts
