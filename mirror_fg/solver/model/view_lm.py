"""One Levenberg-Marquardt run (eq. 23) of the paper's tree on the general view model
(``solver/model/views.py``): the tree's analytical solution (Sects. 4-5) as the start, the view factors as
the linearisation (a photograph's own placement eliminated inside its stacked factor,
``factors/view_eliminated.py``, where the options allow it; else stacked, or one ``ViewFactor`` per image
for ``Linearization.REFERENCE``), read back as the run the tree's pipeline (restarts, checks, result) reads:
its estimate, covariances and costs.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mirror_fg.data import Dataset
from mirror_fg.solver.model.graph import InitialEstimate, measurements_of
from mirror_fg.solver.options import Linearization, SolveOptions

__all__ = ["ViewLMRun", "view_model_run"]


@dataclass
class ViewLMRun:
    """One LM run of the view model: its graph, start and result values, costs, convergence and the
    eliminated placements' stack (if any); its estimate and covariances read back in the tree's terms."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    result: gtsam.Values
    layout: Any  # the ViewProblem: its keys and ``name_of`` name an unconstrained unknown
    measurements: list
    initial_error: float
    final_error: float
    iterations: int
    converged: bool
    dimension: int
    evaluator: Any = None  # the EliminatedViewStack, if any
    _estimate: Any = field(default=None, repr=False)

    @property
    def expected_final_error(self) -> float:
        from mirror_fg.core.fit import expected_cost

        return expected_cost(2 * len(self.measurements), self.dimension)

    @property
    def plausible(self) -> bool:
        from mirror_fg.core.fit import plausible

        return self.converged and plausible(self.final_error, self.expected_final_error)

    def _read(self):
        if self._estimate is None:
            self._estimate = self.layout.read(self.result, self.evaluator)
        return self._estimate

    def estimate(self) -> tuple[np.ndarray, np.ndarray, dict, dict]:
        estimate = self._read()
        R, t = estimate.poses[self.layout.cameras[0]]
        return np.asarray(R, float), np.asarray(t, float), dict(estimate.mirror_vectors), dict(estimate.points)

    def covariances(self, dataset: Dataset) -> tuple[np.ndarray, dict, dict]:
        poses, _, mirrors, points, _ = self.layout.covariances(self.graph, self.result, self._read(), self.evaluator)
        return poses[self.layout.cameras[0]], mirrors, points


def view_model_run(dataset: Dataset, initial: InitialEstimate, options: SolveOptions, eliminate: bool,
                   on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
                   params: gtsam.LevenbergMarquardtParams, finish: Callable) -> ViewLMRun:
    """LM from ``initial`` on ``dataset``'s view model; ``finish(graph, optimizer, result, params)`` gives
    ``(result, final error, converged)`` as the tree's run decides them (``lm._levenberg_marquardt``)."""
    from mirror_fg.solver.model.optimizer import run_optimizer
    from mirror_fg.solver.model.marginals import unconstrained_message
    from mirror_fg.solver.model.views import ViewEstimate, ViewProblem
    from mirror_fg.solver.timing import timed

    with timed(timings, "build"):
        problem = ViewProblem(dataset, options.robust)
        start = ViewEstimate({problem.cameras[0]: (np.asarray(initial.R_cam_base, float), np.asarray(initial.t_cam_base, float))},
                             {p: np.asarray(v, float) for p, v in initial.mirror_vectors.items()},
                             {n: np.asarray(x, float) for n, x in initial.points.items()})
        if options.linearization is Linearization.REFERENCE:
            graph, values, evaluator = problem.graph(stacked=False), problem.values(start), None
        else:
            graph, values, evaluator = problem.solve_graph(start, eliminate)
    with timed(timings, "optimize"):
        optimizer, result, initial_error = run_optimizer(
            graph, values, params, dataset.source, lambda error: unconstrained_message(error, problem), on_iteration)
        result, final_error, converged = finish(graph, optimizer, result, True)
    dimension = result.dim() + (evaluator.dimension if evaluator is not None else 0)
    return ViewLMRun(graph, values, result, problem, measurements_of(dataset), float(initial_error), float(final_error),
                     int(optimizer.iterations()), converged, dimension, evaluator)
