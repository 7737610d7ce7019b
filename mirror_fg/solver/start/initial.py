"""The initial estimate of the MLE: the analytical solution (Sects. 4-5) with every P3P hypothesis of a
mirror placement below the root refined on its own images by Levenberg-Marquardt (eq. 23) before the
levels above choose between them.

Its cost is bounded in the number of images (a video brings a placement of the last mirror in
every frame): a placement with more than ``MAX_RANKING_PLACEMENTS`` placements of the last mirror under
it ranks its hypotheses on the images of that many, spread over them; every other placement's mirror
vector follows from each refined hypothesis by eqs. (6)-(7), a start that the MLE's eliminated factors
solve on every image; the root ranks its combinations on the same images (the peeling's own search is
bounded the same way: ``peeling.MAX_SEARCH_CHILDREN``).

It walks the mirror tree with ``analytic.TreeWalk`` (ask and tell) and runs LM itself, beside the
solver: the analytical solution never calls back into it.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic import AnalyticSolution, TreeNode, TreeWalk, Hypothesis, complete_last_mirror
from mirror_fg.factors.view_eliminated import EliminatedViewStack
from mirror_fg.solver.model.views import ViewEstimate, ViewProblem
from mirror_fg.solver.model.lm import cost_scale, lm_params
from mirror_fg.solver.start.peeling import spread_subset

__all__ = [
    "initial_estimate", "refine_subtree", "scored_nodes", "MAX_RANKING_PLACEMENTS", "SAME_OPTIMUM_TOLERANCE", "SUBTREE_MAX_ITERATIONS", "SUBTREE_RELATIVE_TOLERANCE",
]

logger = logging.getLogger("mirror_fg")

#: LM iterations allowed when refining one subtree hypothesis of the initial estimate.
SUBTREE_MAX_ITERATIONS = 50
#: Relative decrease of the cost below which a subtree refinement stops.
SUBTREE_RELATIVE_TOLERANCE = 1e-4


#: A node of the last mirror ranks its hypotheses by LM on the images of at most this many of its
#: placements, spread over them in capture order; the other placements' mirror vectors then follow from
#: each refined hypothesis (eqs. 6-7). Bounds the cost of a node with hundreds of placements (a video):
#: the ranking needs the cost gap between P3P twins, not the last digits, and the MLE refines every one.
MAX_RANKING_PLACEMENTS = 64


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
    built: dict | None = None,
) -> tuple[float, AnalyticSolution] | None:
    """The MLE (eq. 23) of one subtree's own images from its closed-form hypothesis: its cost and values.

    Solved on the one measurement model (``model/views.py``: the subtree's images as views, each placement
    of its last mirror eliminated inside the stacked factors, ``factors/view_eliminated.py``).
    ``optima``: ``(cost, solution)`` of this subtree already refined from other hypotheses; when the
    refinement comes near one of them (:data:`SAME_OPTIMUM_TOLERANCE`) it stops and returns that one.
    ``built``: an empty dict the first time a subtree is refined, then the same dict for its other
    hypotheses: its problem and graph are built once and restarted from each hypothesis
    (``EliminatedViewStack.restart``: the state of a new one).
    """
    try:
        if built is not None and "graph" in built:
            problem, graph, evaluator = built["graph"]
            start = _view_start(problem, closed_form)
            if evaluator is not None:
                evaluator.restart(start.mirror_vectors)
            values = problem.values(start, skip=set(evaluator.eliminated) if evaluator is not None else frozenset())
        else:
            problem = ViewProblem(subtree)
            start = _view_start(problem, closed_form)
            graph, values, evaluator = _subtree_graph(problem, start)
            if built is not None:
                built["graph"] = (problem, graph, evaluator)
        params = lm_params(SUBTREE_MAX_ITERATIONS, cost_scale(subtree))
        params.setRelativeErrorTol(SUBTREE_RELATIVE_TOLERANCE)  # a start and a ranking: no need for the last digits
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = _optimize(optimizer, params, problem.pose_keys[problem.cameras[0]], optima)
    except (RuntimeError, SolveError):  # an under-determined subtree: no refinement, no score
        return None
    if isinstance(result, tuple):
        return result
    estimate = problem.read(result, evaluator)
    R, t = estimate.poses[problem.cameras[0]]
    return float(optimizer.error()), AnalyticSolution(R, t, estimate.mirror_vectors)


def _subtree_graph(problem: ViewProblem, start: ViewEstimate
                   ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, EliminatedViewStack | None]:
    """A subtree's graph, values and eliminated stack: its views (fiducials only, no scale, intrinsics
    known) with the placements of its last mirror eliminated, solved as the tree's factors solve them
    (``EliminatedViewStack.tree_like``: the ranking of wrong hypotheses depends on it); the graph with
    every placement an unknown where none is. The start's own: the options' linearisation is the MLE's."""
    evaluator = EliminatedViewStack(problem.table, start.mirror_vectors, tree_like=True)
    if not evaluator.eliminated:
        return problem.graph(), problem.values(start), None
    return problem.eliminated_graph(evaluator, start)


def _view_start(problem: ViewProblem, closed_form: AnalyticSolution) -> ViewEstimate:
    """A subtree's closed-form hypothesis as the start of its view problem (one camera, no points)."""
    return ViewEstimate({problem.cameras[0]: (np.asarray(closed_form.R_cam_base, float),
                                              np.asarray(closed_form.t_cam_base, float))},
                        {p: np.asarray(closed_form.mirror_vectors[p], float) for p in problem.placements}, {})


#: Public name (the consensus of ``consensus.py`` refines a node's majority with it); the private name
#: stays for profiles (scripts/benchmark.py attributes time to it by name).
refine_subtree = _refine_subtree


def _ranking_images(node: TreeNode) -> list[Image]:
    """The images a node's hypotheses are refined on: all of them, or for a node of the last mirror with
    more than ``MAX_RANKING_PLACEMENTS`` placements, those of that many placements spread over them."""
    if node.level != node.dataset.num_mirrors:
        return node.images
    placements = sorted({image.mirror_configs[-1] for image in node.images})
    if len(placements) <= MAX_RANKING_PLACEMENTS:
        return node.images
    chosen = {placements[k] for k in spread_subset(len(placements), MAX_RANKING_PLACEMENTS).tolist()}
    return [image for image in node.images if image.mirror_configs[-1] in chosen]


def _refined_scores(node: TreeNode, ranking: list[Image]) -> list[tuple[float, Hypothesis]]:
    """Each proposal of an inner node refined on ``ranking`` (its images or :func:`_ranking_images`): its
    LM cost and refined hypothesis, with every placement's mirror vector (those not in ``ranking`` by
    eqs. 6-7 from the refined ``(A, b)``: a start for the MLE)."""
    subtree = node.subtree(ranking)
    scores = []
    optima: list[tuple[float, AnalyticSolution]] = []  # reached by earlier proposals (not degenerate ones)
    completed: dict[int, Hypothesis] = {}  # each optimum's hypothesis with every placement, made once
    built: dict = {}  # the subtree's problem and graph, built once for every proposal
    for proposal, degenerate in zip(node.proposals, node.degenerate):
        refined = _refine_subtree(subtree, node.subtree_solution(proposal), () if degenerate else optima, built)
        if refined is None or not np.isfinite(refined[0]):
            scores.append((np.inf, proposal))
        else:
            hypothesis = completed.get(id(refined[1]))
            if hypothesis is None:
                hypothesis = node.hypothesis_of(refined[1], proposal)
                if len(ranking) < len(node.images):  # the other placements: eqs. (6)-(7), a start for the MLE
                    hypothesis = complete_last_mirror(hypothesis, node.images, node.level, node.leaf_candidates)
                completed[id(refined[1])] = hypothesis
            scores.append((refined[0], hypothesis))
            if not degenerate and not any(refined is optimum for optimum in optima):
                optima.append(refined)
    return scores


def scored_nodes(walk: TreeWalk) -> Iterator[TreeNode]:
    """Every node of ``walk``, each yielded once scored as :func:`initial_estimate` scores it: below the
    root, every proposal refined by LM (:func:`_refined_scores`, a node of the last mirror on
    :func:`_ranking_images`); the root's combinations by the closed-form cost of the fiducials of the
    images its descendants were ranked on."""
    ranked_on: list[Image] = []  # the images the last mirror's nodes were ranked on
    bounded = False  # some node of the last mirror ranked on a subset of its images
    for node in walk.nodes():
        if node.level > 1:
            ranking = _ranking_images(node)
            node.scores = _refined_scores(node, ranking)
            if node.level == walk.dataset.num_mirrors:
                ranked_on.extend(ranking)
                bounded |= len(ranking) < len(node.images)
        else:
            node.scores = node.closed_form_scores(ranked_on if bounded else None)
        yield node


def initial_estimate(
    dataset: Dataset, seed: int = 0, progress: Callable[[int], None] | None = None,
    pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]] | None = None,
) -> AnalyticSolution:
    """The initial guess of ``calibrate``: the analytical solution with every hypothesis below the root
    refined by LM on its own images; the root's combinations are ranked by every fiducial, as in
    ``analytic.solve_analytic`` (with many placements of the last mirror: on a spread subset of them,
    :func:`scored_nodes`).

    The closed form alone weights every PnP pose equally, so under noise (2 px, or a mirror 0.25 m
    away) a mirror placement whose images mostly took the wrong P3P twin can look better than the
    right one and start LM in another minimum; refined, the right hypothesis is the cheaper one.
    Frames and units as :class:`~mirror_fg.solver.start.analytic.AnalyticSolution`; raises as
    :class:`~mirror_fg.solver.start.analytic.TreeWalk`. ``progress(nodes_done)`` is called after each node of
    the mirror tree is scored. ``pnp``: PnP candidates already computed for some images (as
    :class:`~mirror_fg.solver.start.analytic.TreeWalk` takes them).
    """
    walk = TreeWalk(dataset, seed, pnp)
    started = time.perf_counter()
    for done, node in enumerate(scored_nodes(walk), start=1):
        logger.debug("node %s (level %d, %d images, %d hypotheses): %.3f s", node.prefix, node.level, len(node.images),
                     len(node.proposals), time.perf_counter() - started)
        if progress is not None:
            progress(done)
        started = time.perf_counter()
    return walk.solution()
