"""A calibration on the tree's own factors: the Levenberg-Marquardt run the pipeline made before the one
measurement model (``mirror_fg/solver/model/lm.py`` runs the view model), with the same settings, stall
test and polish, so that tests and benchmarks compare the two. :func:`use_tree_factors` puts it in the
pipeline's place (``lm._levenberg_marquardt``) for one test.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.data import Dataset
from mirror_fg.solver.model import lm
from mirror_fg.solver.model.graph import GraphLayout, InitialEstimate, Measurement
from mirror_fg.solver.model.marginals import unconstrained_message
from mirror_fg.solver.model.optimizer import _polished, _stationary, cost_scale, lm_params, run_optimizer
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.timing import timed
from reference.eliminated import EliminatedEvaluator
from reference.graph import build_eliminated_graph, build_graph, extract_values
from reference.marginals import eliminated_covariances, marginal_covariances

__all__ = ["LMRun", "tree_factors_run", "use_tree_factors"]


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



def tree_factors_run(
    dataset: Dataset, initial: InitialEstimate, options: SolveOptions, eliminate: bool,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> LMRun:
    """``lm._levenberg_marquardt`` on the tree's own factors: the eliminated graph (``eliminate``, where the
    schedule allows it) or the graph with every placement an unknown (stacked per ``options.stacked``)."""
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


def use_tree_factors(monkeypatch) -> None:
    """Calibrations in this test run on the tree's own factors (:func:`tree_factors_run`)."""
    monkeypatch.setattr(lm, "_levenberg_marquardt", tree_factors_run)


#: The pipeline's own run (the one model), as imported: :func:`select` puts it back.
ONE_MODEL_RUN = lm._levenberg_marquardt


def select(tree_factors: bool) -> None:
    """For the benchmark scripts (no monkeypatch): calibrations from now on run on the tree's own factors
    (``tree_factors``) or on the one model."""
    lm._levenberg_marquardt = tree_factors_run if tree_factors else ONE_MODEL_RUN
