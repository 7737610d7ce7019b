"""GTSAM's Levenberg-Marquardt with the project's settings (eq. 23): the settings scaled to the noise, one
optimizer run with its errors in the user's words, the stall test and the Gauss-Newton polish. What a run
of the paper's tree (``lm.py``) and of the one measurement model (``view_lm.py``, the batch problems) share.
"""
from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from mirror_fg.data import Dataset
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error

__all__ = [
    "REFERENCE_NORMALIZED_SIGMA", "GENERAL_LAMBDA_UPPER_BOUND", "cost_scale", "lm_params", "run_optimizer",
    "polished", "POLISH_STEPS", "POLISH_STEP_TOLERANCE",
]

#: Normalized measurement noise at which the LM settings below were chosen: 1 px at fx = 800 px
#: (the paper's base case).
REFERENCE_NORMALIZED_SIGMA = 1.0 / 800.0


def cost_scale(dataset: Dataset) -> float:
    """How many times larger every whitened cost, gradient and Hessian are than at the reference noise.

    With a uniform ``pixel_sigma`` the MLE does not depend on it, but the cost scales as
    ``1 / sigma^2``: every absolute threshold of LM (its damping, its absolute tolerance, the stall
    test) is multiplied by this factor so that LM takes the same steps whatever the sigma.
    """
    sigma = float(np.sqrt(np.prod(dataset.normalized_sigma)))
    return (REFERENCE_NORMALIZED_SIGMA / sigma) ** 2


def lm_params(max_iterations: int, scale: float = 1.0, lambda_upper_bound: float = 1e5) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt settings of the MLE (eq. 23): tight tolerances, at most ``max_iterations``.

    ``scale``: :func:`cost_scale` of the data; the damping and the absolute tolerance scale with it
    (GTSAM's defaults, 1e-5 and 1e5 for the damping, hold at the reference noise). The general view
    model's solves give the damping room to 1e10 (:data:`GENERAL_LAMBDA_UPPER_BOUND`): from a start far
    off (a gross measurement that no per-image check can see) 1e5 stops LM before its first step.
    """
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12 * scale)
    params.setlambdaInitial(1e-5 * scale)
    params.setlambdaUpperBound(lambda_upper_bound * scale)
    return params


#: The damping's bound in the general view model's solves (:func:`lm_params`).
GENERAL_LAMBDA_UPPER_BOUND = 1e10


def run_optimizer(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, params: gtsam.LevenbergMarquardtParams, source: str,
    unconstrained: Callable[[Exception], str], on_iteration: Callable[[int, float, float], None] | None = None,
) -> tuple[gtsam.LevenbergMarquardtOptimizer, gtsam.Values, float]:
    """GTSAM's Levenberg-Marquardt on ``graph`` from ``values``: ``(optimizer, result, initial error)``.

    ``on_iteration`` becomes the iteration hook; an indeterminant linear system becomes a SolveError
    naming ``source`` and, through ``unconstrained(error)``, the unknown GTSAM found unconstrained.
    """
    if on_iteration is not None:
        # GTSAM's stub types the hook's arguments as SupportsInt/SupportsFloat (what the binding
        # accepts); GTSAM calls it with an int and two floats.
        params.iterationHook = on_iteration  # type: ignore[assignment]
    initial_error = graph.error(values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    with unconstrained_as_solve_error(source, unconstrained):
        result = optimizer.optimize()
    return optimizer, result, float(initial_error)


def _stationary(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, error: float, scale: float) -> bool:
    """Whether the Gauss-Newton step at ``values`` promises (almost) no decrease of the error
    (relative to the error, or to ``scale`` (:func:`cost_scale`) near a zero error)."""
    linear = graph.linearize(values)
    try:
        step = linear.optimize()
    except RuntimeError:  # indeterminant: not a well-defined optimum
        return False
    zero = step.scale(0.0)
    predicted_decrease = linear.error(zero) - linear.error(step)
    return predicted_decrease <= 1e-6 * max(error, scale)


#: Gauss-Newton steps after LM on the eliminated graph (each one linearisation of a small system).
POLISH_STEPS = 10
#: A polishing step this small (radians, metres) ends the polish.
POLISH_STEP_TOLERANCE = 1e-11


def _polished(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Values:
    """``values`` moved by Gauss-Newton steps while they lower the error: LM stops when an iteration
    lowers the cost by less than 1e-10 relative, which leaves the estimate ~1e-7 relative from the
    optimum; on the eliminated graph a few more steps are cheap and reach it to ~1e-12
    (:data:`POLISH_STEP_TOLERANCE`)."""
    error = graph.error(values)
    for _ in range(POLISH_STEPS):
        try:
            step = graph.linearize(values).optimize()
        except RuntimeError:
            break
        candidate = values.retract(step)
        candidate_error = graph.error(candidate)
        if not candidate_error <= error * (1.0 + 1e-12):  # rising beyond the cost's rounding
            break
        values, error = candidate, candidate_error
        # Gauss-Newton converges linearly here (rate ~0.02-0.05 on the benchmark's scenes): after a step
        # below 1e-11 the rest is ~1e-12, so a further step (a linearisation) would change nothing we report
        if np.max(np.abs(step.vector()), initial=0.0) < POLISH_STEP_TOLERANCE:
            break
    return values


#: The polish of any small system (the view model's eliminated graph too).
polished = _polished
