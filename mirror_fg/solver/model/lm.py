"""Levenberg-Marquardt for the MLE (eq. 23) of the paper's tree: one run (on the one measurement model,
``view_lm.py``, or the tree's own factors), the plausibility of its final cost, and the restarts from the
analytical solution's runner-up hypotheses. The optimizer's settings, stall test and polish:
``optimizer.py``.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.factors.eliminated import EliminatedEvaluator
from mirror_fg.factors.view_eliminated import collapsed
from mirror_fg.data import Dataset
from mirror_fg.solver.start.analytic import AnalyticSolution, reconstruct_points
from mirror_fg.solver.model.graph import (
    GraphLayout,
    InitialEstimate,
    Measurement,
    build_eliminated_graph,
    build_graph,
    extract_values,
)
from mirror_fg.solver.model.marginals import (
    eliminated_covariances,
    marginal_covariances,
    unconstrained_message,
)
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
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.timing import timed

__all__ = [
    "REFERENCE_NORMALIZED_SIGMA", "MAX_RESTARTS", "LMRun", "cost_scale", "lm_params", "plausible",
    "levenberg_marquardt", "levenberg_marquardt_with_restarts", "polished",
]

logger = logging.getLogger("mirror_fg")

#: Solve with the last mirror's placements eliminated inside the factors (``factors/eliminated.py``)
#: where the options ask for it and the data allow it (no robust kernel, ``SolveOptions.eliminates``):
#: linear cost in the number of images. False: the stacked factors of ``factors/batched.py`` with
#: every placement in the graph (same estimates).
ELIMINATE = True

#: The paper's tree solved on the general view model, the one measurement model (``view_lm.py``: the view
#: factors, a photograph's own placement eliminated inside them; the default). False: the tree's own
#: factors (``factors/eliminated.py``, ``factors/batched.py``, ``factors/reflection.py``), the same
#: estimates, kept as the reference the view model is checked against (``tests/test_view_lm.py``).
VIEW_MODEL = True

#: At most this many restarts of LM from the analytical solution's runner-up hypotheses.
MAX_RESTARTS = 4


@dataclass
class LMRun:
    """One Levenberg-Marquardt run: its graph, start and result values, costs and convergence."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    result: gtsam.Values
    layout: GraphLayout
    measurements: list[Measurement]
    initial_error: float
    final_error: float
    iterations: int
    converged: bool
    dimension: int  # number of scalar unknowns (eliminated placements included)
    evaluator: EliminatedEvaluator | None = None  # the eliminated placements' solver, if any

    @property
    def expected_final_error(self) -> float:
        """Mean of the final cost 0.5 chi^2 at the optimum: half the degrees of freedom."""
        return expected_cost(2 * len(self.measurements), self.dimension)

    def estimate(self) -> tuple[np.ndarray, np.ndarray, dict, dict]:
        """``(R_cam_base, t_cam_base, mirror_vectors, points)`` at the result (``graph.extract_values``)."""
        return extract_values(self.result, self.layout, self.evaluator)

    def covariances(self, dataset: Dataset) -> tuple[np.ndarray, dict, dict]:
        """Pose (docs/formats.md convention), mirror and point covariances at the result (``marginals.py``)."""
        if self.evaluator is not None:
            return eliminated_covariances(dataset, self.evaluator, self.result, self.layout)
        return marginal_covariances(self.graph, self.result, self.layout, dataset.source)

    @property
    def plausible(self) -> bool:
        """Converged with a final cost within its chi-square range (:func:`plausible`)."""
        return self.converged and plausible(self.final_error, self.expected_final_error)


def levenberg_marquardt(
    dataset: Dataset, initial: InitialEstimate, options: SolveOptions,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> LMRun:
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
) -> LMRun:
    """:func:`levenberg_marquardt` on the eliminated graph (``eliminate``, where the schedule allows it) or
    on the graph with every placement an unknown (the view model's where :data:`VIEW_MODEL`)."""
    if VIEW_MODEL:
        from mirror_fg.solver.model.view_lm import view_model_run

        scale = cost_scale(dataset)
        params = lm_params(options.max_iterations, scale)

        def finish(graph, optimizer, result, polish: bool):
            if polish:  # polished to the optimum (LM stops ~1e-7 from it), whatever the linearisation
                result = polished(graph, result)
            final_error = graph.error(result)
            stalled = optimizer.lambda_() >= params.getlambdaUpperBound() and not _stationary(graph, result, final_error, scale)
            return result, final_error, bool(np.isfinite(final_error)) and optimizer.iterations() < options.max_iterations and not stalled

        return view_model_run(dataset, initial, options, eliminate, on_iteration, timings, params, finish)  # type: ignore[return-value]
    with timed(timings, "build"):
        eliminated = build_eliminated_graph(dataset, initial) if eliminate else None
        if eliminated is not None:
            graph, values, layout, measurements = eliminated.graph, eliminated.values, eliminated.layout, eliminated.measurements
            evaluator, dimension = eliminated.evaluator, eliminated.evaluator.dimension
        else:
            graph, values, layout, measurements = build_graph(dataset, initial, options.robust, fast=options.stacked)
            evaluator, dimension = None, values.dim()

    max_iterations = options.max_iterations
    with timed(timings, "optimize"):
        scale = cost_scale(dataset)
        params = lm_params(max_iterations, scale)
        optimizer, result, initial_error = run_optimizer(
            graph, values, params, dataset.source, lambda error: unconstrained_message(error, layout), on_iteration)
        iterations = optimizer.iterations()
        if evaluator is not None:
            result = _polished(graph, result)
        final_error = graph.error(result)
        # LM also stops when its damping hits the upper bound: a stall unless a Gauss-Newton step
        # would no longer lower the error (then it is at a stationary point, e.g. noise-free data).
        stalled = optimizer.lambda_() >= params.getlambdaUpperBound() and not _stationary(graph, result, final_error, scale)
        converged = bool(np.isfinite(final_error)) and iterations < max_iterations and not stalled
    return LMRun(graph, values, result, layout, measurements, float(initial_error), float(final_error), iterations,
                 converged, dimension, evaluator)


def levenberg_marquardt_with_restarts(
    dataset: Dataset, initial: InitialEstimate, analytic: AnalyticSolution | None, options: SolveOptions,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> tuple[LMRun, AnalyticSolution | None, int]:
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
