"""A start-up of an :class:`~mirror_fg.solver.incremental.graph.IncrementalGraph`: from the analytical
solution, Levenberg-Marquardt on every image it admits, then a fresh iSAM2 at the LM solution.

Settling. On the smallest tree (a placement seen with only three children) the analytical solution
can be far off: on the issue's 300-image stream (seed 0) it is 1.5 m off at image 203, where the
likelihood has a long curved valley; Levenberg-Marquardt stalls in it and undamped Gauss-Newton, what
iSAM2 does, diverged from there (65 deg off after two steps, then an indeterminant system). So a
start-up counts as *settled* only when iSAM2's Gauss-Newton step at the LM solution moves the pose by
less than ``SETTLED_SIGMAS`` of its own standard deviation, and LM itself stopped within its budget (with
a Cauchy kernel a start-up 0.47 m off crawled for all its iterations where iSAM2's step looked small too,
then refused good images against it). Until then the estimate reported is the LM
one and the start-up is re-run on every image so far (on that stream it settles five images later,
when the analytical solution is 0.3 m off). A settled calibrator whose pose jumps by more than
``DIVERGENCE_SIGMAS`` in one update, or meets an indeterminant system, restarts the same way; a failed
start-up rolls the graph's :class:`~mirror_fg.solver.incremental.state.GraphState` back.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.transform import covariance_to_pose3
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.incremental.graph import IncrementalGraph
from mirror_fg.solver.model.lm import cost_scale, lm_params, run_optimizer
from mirror_fg.solver.model.marginals import unconstrained_message
from mirror_fg.solver.timing import timed

__all__ = [
    "DIVERGENCE_SIGMAS", "FINAL_LM_ITERATIONS", "SETTLED_SIGMAS", "STARTUP_LM_ITERATIONS", "StartUp", "start_graph",
]

#: Levenberg-Marquardt iterations at most per start-up (a stalled start-up is retried with more images).
STARTUP_LM_ITERATIONS = 30
#: ... and for ``calibration(full=True)`` of an unsettled calibrator (as ``calibrate``).
FINAL_LM_ITERATIONS = 100
#: A start-up is settled when iSAM2's Gauss-Newton step at the LM solution moves the pose by less than
#: this many of its own standard deviations (Mahalanobis distance).
SETTLED_SIGMAS = 0.5
#: A settled calibrator restarts when one update moves the pose by more than this (Mahalanobis).
DIVERGENCE_SIGMAS = 5.0


@dataclass(frozen=True)
class StartUp:
    """How a start-up went: ``settled`` (module docstring) and the LM iterations it took."""

    settled: bool
    lm_iterations: int


def start_graph(graph: IncrementalGraph, analytic: AnalyticSolution, lm_iterations: int) -> StartUp:
    """Start ``graph`` (just reset, its accepted images waiting) from ``analytic``: every image whose
    placements it determines joins the graph, LM (at most ``lm_iterations``) refines it and a fresh iSAM2
    gets the whole graph at the LM solution. Sets ``analytic.points`` (eq. 20 at the analytical solution).
    Raises SolveError when LM meets an indeterminant system."""
    g = graph.state
    source = graph.dataset.source
    g.R = analytic.R_cam_base.copy()
    g.t = np.asarray(analytic.t_cam_base, dtype=float).copy()
    values = gtsam.Values()
    values.insert(g.layout.pose_key, gtsam.Pose3(gtsam.Rot3(g.R), g.t))
    for config in sorted(analytic.mirror_vectors):
        graph.new_mirror(config, analytic.mirror_vectors[config], values)
    factors = gtsam.NonlinearFactorGraph()
    graph.collect(factors, values)
    analytic.points = dict(g.points)  # eq. (20) at the analytical solution
    with timed(graph.timings, "startup_lm"):
        params = lm_params(lm_iterations, cost_scale(graph.dataset))
        optimizer, optimized, initial_error = run_optimizer(factors, values, params, source, graph.unconstrained)
        if graph.placements_collapsed(optimized):  # a placement run into the camera centre
            # (factors.view_eliminated.COLLAPSED_FRACTION): LM again from the start-up's values with every
            # placement an unknown, as the batch does without elimination; then the blocks made anew there.
            problem, start = graph.explicit_problem(refresh=False)
            optimizer, solution, _ = run_optimizer(problem.graph(), problem.values(start), params, source,
                                                   lambda error: unconstrained_message(error, problem))
            factors = graph.remake_blocks(problem.read(solution))
            optimized = graph.estimate_values()
    g.isam = graph.new_isam2()
    graph.set_estimate(optimized)  # the pose the update's step is measured from; placements below
    try:
        graph.update(factors, optimized)
        # Settled when iSAM2's own Gauss-Newton step from the LM solution is small: the linear
        # model there can be trusted. Otherwise report the LM solution (iSAM2's covariance is the
        # one there: its linearisation point) and retry with later images.
        # and only when LM itself stopped within its budget: a robust kernel (Cauchy) flattens the cost far
        # from the optimum, where LM crawls for its whole budget and iSAM2's step there looks small too
        settled = g.step_sigmas < SETTLED_SIGMAS and optimizer.iterations() < lm_iterations
    except SolveError:  # iSAM2's Cholesky gave up near the LM solution (nearly indeterminant)
        settled = False
        graph.set_estimate(optimized)  # and every eliminated placement there, by explicit_covariances
        _, _, (covariance, _, _) = graph.explicit_covariances()
        g.pose_cov = covariance_to_pose3(g.R, covariance)  # GTSAM's [w, nu]
    else:
        if not settled:
            graph.set_estimate(optimized, g.blocks)
    g.initial_error = initial_error
    return StartUp(settled, optimizer.iterations())
