"""The initial estimate of the MLE: the analytical solution (Sects. 4-5) with every P3P hypothesis of a
mirror placement below the root refined on its own images by Levenberg-Marquardt (eq. 23) before the
levels above choose between them.

It walks the mirror tree with ``analytic.TreeWalk`` (ask and tell) and runs LM itself, beside the
solver: the analytical solution never calls back into it.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.io.dataset import Dataset
from mirror_fg.solver.analytic import AnalyticSolution, TreeNode, TreeWalk, Hypothesis
from mirror_fg.solver.graph import (
    Measurement, build_eliminated_graph, build_graph, extract_values, measurement_sigmas, measurements_of,
)
from mirror_fg.solver.lm import cost_scale, lm_params

__all__ = [
    "initial_estimate", "refine_subtree", "SAME_OPTIMUM_TOLERANCE", "SUBTREE_MAX_ITERATIONS", "SUBTREE_RELATIVE_TOLERANCE",
]

logger = logging.getLogger("mirror_fg")

#: LM iterations allowed when refining one subtree hypothesis of the initial estimate.
SUBTREE_MAX_ITERATIONS = 50
#: Relative decrease of the cost below which a subtree refinement stops.
SUBTREE_RELATIVE_TOLERANCE = 1e-4


#: A subtree refinement ends as soon as its pose comes this close (``analytic._same_transform``: unitless,
#: and relative for the translation) to an optimum another hypothesis of the node already reached: the
#: node keeps that optimum once anyway, and P3P twins are centimetres and degrees apart.
SAME_OPTIMUM_TOLERANCE = 1e-3


def _near(R: np.ndarray, t: np.ndarray, optima: Sequence[tuple[float, AnalyticSolution]]) -> tuple[float, AnalyticSolution] | None:
    """The first of ``optima`` whose pose is within ``SAME_OPTIMUM_TOLERANCE`` of ``(R, t)``, if any."""
    for optimum in optima:
        solution = optimum[1]
        scale = max(1.0, float(np.linalg.norm(solution.t_cam_base)))
        if (np.max(np.abs(R - solution.R_cam_base)) < SAME_OPTIMUM_TOLERANCE
                and np.linalg.norm(t - solution.t_cam_base) < SAME_OPTIMUM_TOLERANCE * scale):
            return optimum
    return None


def _optimize(
    optimizer: gtsam.LevenbergMarquardtOptimizer, params: gtsam.LevenbergMarquardtParams, pose_key: int,
    optima: Sequence[tuple[float, AnalyticSolution]],
) -> gtsam.Values | tuple[float, AnalyticSolution]:
    """``optimizer.optimize()`` (GTSAM's loop: iterate until ``checkConvergence`` or the iteration limit),
    or the optimum of ``optima`` the iterate came near (:func:`_near`). The optimizer's ``error()`` is
    then the cost at its ``values()``."""
    new_error = optimizer.error()
    if new_error <= params.getErrorTol() or optimizer.iterations() >= params.getMaxIterations():
        return optimizer.values()
    while True:
        current_error = new_error
        optimizer.iterate()
        new_error = optimizer.error()
        if optima:
            pose = optimizer.values().atPose3(pose_key)
            reached = _near(pose.rotation().matrix(), np.asarray(pose.translation()), optima)
            if reached is not None:
                return reached
        if (optimizer.iterations() >= params.getMaxIterations() or not np.isfinite(current_error)
                or gtsam.checkConvergence(params, current_error, new_error)):
            return optimizer.values()


def _refine_subtree(
    subtree: Dataset, closed_form: AnalyticSolution, optima: Sequence[tuple[float, AnalyticSolution]] = (),
    measurements: list[Measurement] | None = None, sigmas: np.ndarray | None = None,
) -> tuple[float, AnalyticSolution] | None:
    """The MLE (eq. 23) of one subtree's own images from its closed-form hypothesis: its cost and values.

    ``optima``: ``(cost, solution)`` of this subtree already refined from other hypotheses; when the
    refinement comes near one of them (:data:`SAME_OPTIMUM_TOLERANCE`) it stops and returns that one.
    ``measurements``, ``sigmas``: ``graph.measurements_of(subtree)`` and their ``measurement_sigmas``,
    when already computed.
    """
    try:
        eliminated = build_eliminated_graph(subtree, closed_form, measurements, sigmas)  # its placements solved inside
        if eliminated is not None:
            graph, values, layout, evaluator = eliminated.graph, eliminated.values, eliminated.layout, eliminated.evaluator
        else:
            (graph, values, layout, _), evaluator = build_graph(subtree, closed_form, None), None
        params = lm_params(SUBTREE_MAX_ITERATIONS, cost_scale(subtree))
        params.setRelativeErrorTol(SUBTREE_RELATIVE_TOLERANCE)  # a start and a ranking: no need for the last digits
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = _optimize(optimizer, params, layout.pose_key, optima)
    except (RuntimeError, SolveError):  # an under-determined subtree: no refinement, no score
        return None
    if isinstance(result, tuple):
        return result
    R, t, mirror_vectors, _ = extract_values(result, layout, evaluator)
    return float(optimizer.error()), AnalyticSolution(R, t, mirror_vectors)


#: Public name (the consensus of ``consensus.py`` refines a node's majority with it); the private name
#: stays for profiles (scripts/benchmark.py attributes time to it by name).
refine_subtree = _refine_subtree


def _refined_scores(node: TreeNode) -> list[tuple[float, Hypothesis]]:
    """Each proposal of an inner node refined on the node's images: its LM cost and refined hypothesis."""
    subtree = node.subtree()
    measurements = measurements_of(subtree)  # the same for every proposal
    sigmas = measurement_sigmas(subtree, measurements)
    scores = []
    optima: list[tuple[float, AnalyticSolution]] = []  # reached by earlier proposals (not degenerate ones)
    for proposal, degenerate in zip(node.proposals, node.degenerate):
        refined = _refine_subtree(subtree, node.subtree_solution(proposal), () if degenerate else optima,
                                  measurements, sigmas)
        if refined is None or not np.isfinite(refined[0]):
            scores.append((np.inf, proposal))
        else:
            scores.append((refined[0], node.hypothesis_of(refined[1], proposal)))
            if not degenerate and not any(refined is optimum for optimum in optima):
                optima.append(refined)
    return scores


def initial_estimate(
    dataset: Dataset, seed: int = 0, progress: Callable[[int], None] | None = None,
    pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]] | None = None,
) -> AnalyticSolution:
    """The initial guess of ``calibrate``: the analytical solution with every hypothesis below the root
    refined by LM on its own images; the root's combinations are ranked by every fiducial, as in
    ``analytic.solve_analytic``.

    The closed form alone weights every PnP pose equally, so under noise (2 px, or a mirror 0.25 m
    away) a mirror placement whose images mostly took the wrong P3P twin can look better than the
    right one and start LM in another minimum; refined, the right hypothesis is the cheaper one.
    Frames and units as :class:`~mirror_fg.solver.analytic.AnalyticSolution`; raises as
    :class:`~mirror_fg.solver.analytic.TreeWalk`. ``progress(nodes_done)`` is called after each node of
    the mirror tree is scored. ``pnp``: PnP candidates already computed for some images (as
    :class:`~mirror_fg.solver.analytic.TreeWalk` takes them).
    """
    walk = TreeWalk(dataset, seed, pnp)
    for done, node in enumerate(walk.nodes(), start=1):
        started = time.perf_counter()
        node.scores = _refined_scores(node) if node.level > 1 else node.closed_form_scores()
        logger.debug("node %s (level %d, %d images, %d hypotheses): %.3f s", node.prefix, node.level, len(node.images),
                     len(node.proposals), time.perf_counter() - started)
        if progress is not None:
            progress(done)
    return walk.solution()
