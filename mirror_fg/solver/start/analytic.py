"""Analytical solution (Hesch et al., Sects. 4-5, eqs. 10-20): PnP per image, mirror peeling, points.

Everything is in the camera frame {C} (metres) except base-frame points. Configuration ``(l, m)`` is
placement ``m`` of mirror ``l`` (1-based). A *node* at level ``l`` is a prefix ``(c_1, ..., c_{l-1})`` of
mirror configurations; its children are the configurations of mirror ``l`` seen under it.

:class:`TreeWalk` walks the tree bottom-up in the ask-and-tell style: it proposes each node's hypotheses
(PnP in ``pnp.py``, peeling in ``peeling.py``) and the caller ranks them, by their closed-form
reprojection cost here (:func:`solve_analytic`) or after refining them by Levenberg-Marquardt beside the
solver (``solver/start/initial.py``), so this module never calls back into the solver.
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from itertools import product

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.geometry import FLIP_Y, nested_transforms, predict_camera_points, project, project_to_orthogonal
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic_solution import AnalyticSolution
from mirror_fg.solver.start.peeling import (
    MIN_NORMAL_SPREAD, NodeSolution, StackedCandidates, choose_candidates, consistent_mirror_vectors, solve_children_many,
)
from mirror_fg.solver.start.pnp import pnp_candidates_many
from mirror_fg.solver.start.reconstruction import image_transform, reconstruct_points, triangulate_point  # noqa: F401 (public here too)
from mirror_fg.solver.start.placement_rule import too_few_placements

__all__ = [
    "AnalyticSolution", "Hypothesis", "TreeNode", "TreeWalk", "complete_last_mirror", "hypothesis_of_subtree", "reconstruct_points",
    "solve_analytic", "subtree_dataset", "subtree_solution", "triangulate_point",
]

#: Best solutions of an inner node handed to the level above (a subtree's P3P "twin" is only told
#: apart from the truth by the images of the other subtrees).
NODE_HYPOTHESES_KEPT = 3
#: At most this many combinations of the root's child hypotheses are each solved and scored.
MAX_ROOT_COMBINATIONS = 64


@dataclass
class Hypothesis:
    """One candidate ``(A_l, b_l)`` of a tree node with what its subtree chose to get there."""

    A: np.ndarray
    b: np.ndarray
    mirror_vectors: dict[tuple[int, int], list[np.ndarray]]
    image_transforms: dict[str, tuple[np.ndarray, np.ndarray]]


#: Hypotheses of one observation of a node: ``(child placement m, its hypotheses)``.
_Entry = tuple[int, list[Hypothesis]]


def _node_proposals(
    entries: list[_Entry], level: int, child_ids: list[int], rng: np.random.Generator, exhaustive: bool
) -> tuple[list[Hypothesis], list[bool]]:
    """Solutions of one node from its observations' hypotheses, ranked by the algebraic residual of
    eqs. (13) and (16), each with whether its mirror normals are nearly coplanar (eqs. 14-15 cannot be
    trusted then).

    ``exhaustive``: solve every combination of the observations' hypotheses (when there are at most
    ``MAX_ROOT_COMBINATIONS``) instead of the sampled search of ``peeling.choose_candidates``.
    """
    index_of = {m: k for k, m in enumerate(child_ids)}
    children = [index_of[m] for m, _ in entries]
    candidates = [[(h.A, h.b) for h in hyps] for _, hyps in entries]
    parent_det = (-1.0) ** (level - 1)
    if exhaustive and math.prod(len(c) for c in candidates) <= MAX_ROOT_COMBINATIONS:  # no int64 overflow
        combos = list(product(*(range(len(c)) for c in candidates)))
        picked = [[cands[c] for cands, c in zip(candidates, combo)] for combo in combos]
        solutions = solve_children_many(  # every combination at once
            np.array(children), np.array([[A for A, _ in p] for p in picked]), np.array([[b for _, b in p] for p in picked]),
            len(child_ids), parent_det,
        )
        ranked: list[tuple[list[int], NodeSolution]] = [(list(combo), node) for combo, node in zip(combos, solutions)]
        ranked.sort(key=lambda item: item[1].residual)
    else:
        ranked = choose_candidates(children, candidates, len(child_ids), parent_det, rng)
    proposals, degenerate = [], []
    for picks, node in ranked:
        stacked = np.array(node.mirror_vectors)
        normals = stacked / np.linalg.norm(stacked, axis=1, keepdims=True)
        degenerate.append(bool(np.linalg.svd(normals, compute_uv=False)[2] < MIN_NORMAL_SPREAD))
        chosen = [hyps[p] for (_, hyps), p in zip(entries, picks)]
        hypothesis = Hypothesis(node.A_parent, node.b_parent, defaultdict(list),
                                {image: pose for h in chosen for image, pose in h.image_transforms.items()})
        for h in chosen:
            for config, vectors in h.mirror_vectors.items():
                hypothesis.mirror_vectors[config].extend(vectors)
        for m, v in zip(child_ids, node.mirror_vectors):
            hypothesis.mirror_vectors[(level, m)].append(v)
        proposals.append(hypothesis)
    return proposals, degenerate


def _mean_vector(vectors: list[np.ndarray]) -> np.ndarray:
    """The mean of a placement's mirror vectors (most have one: no ``np.mean`` call, the same value)."""
    return np.array(vectors[0], dtype=float) if len(vectors) == 1 else np.mean(vectors, axis=0)


def _same_transform(first: Hypothesis, second: Hypothesis, tolerance: float = 1e-3) -> bool:
    """Whether two hypotheses' ``(A, b)`` agree to ``tolerance`` (unitless, and relative for ``b``)."""
    scale = max(1.0, float(np.linalg.norm(first.b)))
    return bool(np.max(np.abs(first.A - second.A)) < tolerance
                and np.linalg.norm(first.b - second.b) < tolerance * scale)


class _FiducialObservations:
    """Every fiducial observation of a dataset, flattened for a vectorised reprojection cost."""

    def __init__(self, dataset: Dataset, images: list[Image], normalized: dict[str, dict[str, np.ndarray]]):
        self.configs = [im.mirror_configs for im in images]
        image_index, points, observed = [], [], []
        for i, im in enumerate(images):
            for name in im.observations:
                if name in dataset.fiducials:
                    image_index.append(i)
                    points.append(dataset.fiducials[name])
                    observed.append(normalized[im.id][name])
        self.image_index = np.array(image_index, dtype=np.intp)
        self.points = np.array(points, dtype=float).reshape(-1, 3)
        self.observed = np.array(observed, dtype=float).reshape(-1, 2)
        self.sigma = dataset.normalized_sigma

    def placements(self, first_mirror: int = 1) -> set[tuple[int, int]]:
        """The configurations ``(l, m)`` of mirrors ``first_mirror..Nv`` these observations were made in."""
        return {(level + 1, configs[level]) for configs in set(self.configs) for level in range(first_mirror - 1, len(configs))}

    def cost(
        self, A_start: np.ndarray, b_start: np.ndarray, mirror_vectors: dict[tuple[int, int], np.ndarray],
        first_mirror: int = 1,
    ) -> float:
        """Sum of squared whitened reprojection errors of every fiducial (eq. 23 without the points),
        given ``(A, b)`` before mirror ``first_mirror`` (``R_cam_base, t_cam_base`` for mirror 1) and the
        vectors of that mirror's and every later mirror's placements."""
        num_mirrors = len(self.configs[0]) if self.configs else 0
        vectors = [
            np.array([mirror_vectors[(level + 1, configs[level])] for configs in self.configs])
            for level in range(first_mirror - 1, num_mirrors)
        ]
        A, b = nested_transforms(A_start, b_start, vectors)  # eqs. (5)-(8)
        camera_points = predict_camera_points(A, b, self.image_index, self.points)  # eq. (5)
        if not len(camera_points) or np.any(camera_points[:, 2] <= 0):
            return np.inf
        return float(np.sum(((project(camera_points) - self.observed) / self.sigma) ** 2))  # eq. (9)


def _describe(prefix: tuple[int, ...]) -> str:
    if not prefix:
        return "the root (no mirror placed)"
    return "placement " + ", ".join(f"({l + 1}, {m})" for l, m in enumerate(prefix))


def subtree_dataset(dataset: Dataset, images: list[Image], level: int) -> Dataset:
    """The images under one node at ``level`` (mirrors ``level..Nv`` move) as a dataset of their own.

    The node's ``(A_{l-1}, b_{l-1})`` plays ``(R_cam_base, t_cam_base)``; when it is a reflection
    (``l - 1`` odd) the fiducials are mirrored in y (``A Bp = (A F)(F Bp)``, ``F`` = diag(1, -1, 1)) so it
    becomes a rotation. Mirror ``level`` becomes mirror 1; reconstruction points are left out.
    """
    flip = (level - 1) % 2 == 1
    fiducials = {name: FLIP_Y @ p if flip else p.copy() for name, p in dataset.fiducials.items()}
    sub_images = [im.restricted(im.mirror_configs[level - 1 :], fiducials) for im in images]
    return Dataset(dataset.num_mirrors - level + 1, dataset.camera, dataset.pixel_sigma, fiducials, sub_images,
                   source=dataset.source, point_sigma=dataset.point_sigma)


def subtree_solution(hypothesis: Hypothesis, level: int) -> AnalyticSolution:
    """A node's hypothesis as the solution of its :func:`subtree_dataset`."""
    flip = (level - 1) % 2 == 1
    return AnalyticSolution(
        R_cam_base=hypothesis.A @ FLIP_Y if flip else hypothesis.A.copy(),
        t_cam_base=hypothesis.b.copy(),
        mirror_vectors={(l - level + 1, m): _mean_vector(vs) for (l, m), vs in hypothesis.mirror_vectors.items()},
    )


def hypothesis_of_subtree(solution: AnalyticSolution, hypothesis: Hypothesis, level: int) -> Hypothesis:
    """Back from :func:`subtree_solution` (after refinement) to the node's hypothesis."""
    flip = (level - 1) % 2 == 1
    return Hypothesis(
        A=solution.R_cam_base @ FLIP_Y if flip else solution.R_cam_base,
        b=solution.t_cam_base,
        mirror_vectors={(l + level - 1, m): [v] for (l, m), v in solution.mirror_vectors.items()},
        image_transforms=hypothesis.image_transforms,
    )


def complete_last_mirror(
    hypothesis: Hypothesis, images: list[Image], level: int, candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]]
) -> Hypothesis:
    """``hypothesis`` of a node of the last mirror (``level`` = Nv) with the mirror vectors it lacks for
    the placements of ``images``: each image's PnP candidate ``(A_Nv, b_Nv)`` (``candidates``) most
    consistent with the node's ``(A, b)`` and the reflection between them (eqs. 6-7,
    :func:`peeling.consistent_mirror_vectors`), averaged over a placement's images; the candidates taken
    replace the images' ``image_transforms``."""
    known = hypothesis.mirror_vectors
    missing = [image for image in images if (level, image.mirror_configs[-1]) not in known and image.id in candidates]
    if not missing:
        return hypothesis
    placements, index = np.unique([image.mirror_configs[-1] for image in missing], return_inverse=True)
    image_candidates = [candidates[image.id] for image in missing]
    choice, means = consistent_mirror_vectors(StackedCandidates(image_candidates), index, len(placements),
                                              hypothesis.A, hypothesis.b)
    mirror_vectors = dict(known)
    mirror_vectors.update({(level, int(m)): [v] for m, v in zip(placements, means)})
    image_transforms = dict(hypothesis.image_transforms)
    image_transforms.update({image.id: poses[c] for image, poses, c in zip(missing, image_candidates, choice)})
    return Hypothesis(hypothesis.A, hypothesis.b, mirror_vectors, image_transforms)


_subtree_solution = subtree_solution  # the names tests and older callers use
_hypothesis_of_subtree = hypothesis_of_subtree


@dataclass(eq=False)
class TreeNode:
    """One node of the mirror tree as :meth:`TreeWalk.nodes` proposes it; the caller ranks its proposals.

    ``level``: the mirror whose placements are its children (1 is the root); ``prefix``: the placements
    above it; ``images``: the images under it. ``proposals``: its hypotheses ``(A_{level-1}, b_{level-1})``
    with their subtrees' mirror vectors, best algebraic residual first. Set ``scores`` to one
    ``(cost, hypothesis)`` per proposal (lower is better; the hypothesis may be a refined one) before
    asking for the next node.
    """

    level: int
    prefix: tuple[int, ...]
    images: list[Image]
    proposals: list[Hypothesis]
    degenerate: list[bool]
    dataset: Dataset = field(repr=False)
    normalized: dict[str, dict[str, np.ndarray]] = field(repr=False)
    scores: list[tuple[float, Hypothesis]] | None = None
    #: every image's PnP candidates ``(A_Nv, b_Nv)`` (Sect. 4.1)
    leaf_candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict, repr=False)

    @cached_property
    def _fiducials(self) -> _FiducialObservations:
        return _FiducialObservations(self.dataset, self.images, self.normalized)

    def closed_form_scores(self, images: list[Image] | None = None) -> list[tuple[float, Hypothesis]]:
        """Each proposal's half whitened squared reprojection error of the fiducials of the node's images
        (or of ``images``, some of them)."""
        fiducials = self._fiducials if images is None else _FiducialObservations(self.dataset, images, self.normalized)
        needed = fiducials.placements(self.level)
        scores = []
        for hypothesis in self.proposals:
            vectors = {key: _mean_vector(vs) for key, vs in hypothesis.mirror_vectors.items() if key in needed}
            scores.append((0.5 * fiducials.cost(hypothesis.A, hypothesis.b, vectors, self.level), hypothesis))
        return scores

    def subtree(self, images: list[Image] | None = None) -> Dataset:
        """The node's images (or some of them) as a dataset of their own (:func:`subtree_dataset`)."""
        return subtree_dataset(self.dataset, self.images if images is None else images, self.level)

    def subtree_solution(self, hypothesis: Hypothesis) -> AnalyticSolution:
        """A proposal as the solution of :meth:`subtree`."""
        return subtree_solution(hypothesis, self.level)

    def hypothesis_of(self, solution: AnalyticSolution, proposal: Hypothesis) -> Hypothesis:
        """A solution of :meth:`subtree` (e.g. a refined :meth:`subtree_solution`) back as a hypothesis."""
        return hypothesis_of_subtree(solution, proposal, self.level)

    def kept(self) -> list[Hypothesis]:
        """The scored proposals, best first, each optimum once; none when the best is degenerate."""
        if self.scores is None or len(self.scores) != len(self.proposals):
            raise RuntimeError("TreeWalk: score every proposal of a node (TreeNode.scores) before the next node")
        ranked = sorted(
            ((cost, rank, hypothesis, self.degenerate[rank]) for rank, (cost, hypothesis) in enumerate(self.scores)),
            key=lambda item: item[:2],
        )
        if ranked[0][3]:
            return []
        distinct: list[Hypothesis] = []  # refined starts often meet in one optimum: keep it once
        for _, _, hypothesis, degenerate in ranked:
            if not degenerate and not any(_same_transform(hypothesis, kept) for kept in distinct):
                distinct.append(hypothesis)
        return distinct


class TreeWalk:
    """The analytical solution's bottom-up walk over the mirror tree (Sects. 4.1-4.2), ask and tell.

    ::

        walk = TreeWalk(dataset, seed)
        for node in walk.nodes():
            node.scores = [(cost(h), h) for h in node.proposals]
        solution = walk.solution()

    Each node hands its best ``NODE_HYPOTHESES_KEPT`` hypotheses to the level above; the root's
    solutions, ranked by their scores, give the solution and its alternatives.

    Raises ``DatasetError`` when the mirror schedule cannot support a solution (a placement with fewer
    than three child placements, a configuration only seen without three fiducials, a point seen in
    fewer than two images) and ``SolveError`` for degenerate geometry or PnP failure.
    """

    def __init__(
        self, dataset: Dataset, seed: int = 0, pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]] | None = None
    ) -> None:
        self.dataset = dataset
        self._rng = np.random.default_rng(seed)
        self._normalized = {image.id: dataset.normalized(image) for image in dataset.images}
        self._leaf_candidates = self._pnp_per_image(pnp or {})
        self._roots: list[Hypothesis] | None = None

    def _pnp_per_image(
        self, known: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    ) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
        """Sect. 4.1: ``(A_Nv, b_Nv)`` candidates per image from its fiducials (``known``: those already
        computed by ``pnp_candidates`` on the image's fiducials as they are, e.g. by the consensus)."""
        dataset = self.dataset
        leaf_candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        todo: list[tuple[Image, tuple[np.ndarray, np.ndarray]]] = []
        for image in dataset.images:
            names = [n for n in image.observations if n in dataset.fiducials]
            if len(names) < 3 or image.id in known:
                continue
            base_points = np.array([dataset.fiducials[n] for n in names])
            todo.append((image, (base_points, np.array([self._normalized[image.id][n] for n in names]))))
        solved = dict(zip((image.id for image, _ in todo),
                          pnp_candidates_many([problem for _, problem in todo], dataset.num_mirrors)))
        for image in dataset.images:
            if sum(n in dataset.fiducials for n in image.observations) < 3:
                continue
            if image.id in known:
                leaf_candidates[image.id] = known[image.id]
                continue
            candidates = solved[image.id]
            if not candidates:
                raise SolveError(
                    f"{dataset.source}: image '{image.id}': PnP found no pose with every fiducial in front of the camera"
                )
            leaf_candidates[image.id] = candidates
        seen_configs = {(l + 1, m) for im in dataset.images if im.id in leaf_candidates for l, m in enumerate(im.mirror_configs)}
        for l, m in dataset.configurations:
            if (l, m) not in seen_configs:
                raise DatasetError(
                    f"{dataset.source}: mirror {l} placement {m} is only seen in images with fewer than 3 fiducials"
                )
        return leaf_candidates

    def nodes(self) -> Iterator[TreeNode]:
        """Every node, level Nv first, each to be scored before the next is proposed."""
        dataset = self.dataset
        images = [im for im in dataset.images if im.id in self._leaf_candidates]
        # Level Nv: observations are images; the node is the prefix of the first Nv-1 configurations.
        level_obs: dict[tuple[int, ...], list[_Entry]] = defaultdict(list)
        for im in images:
            hypotheses = [Hypothesis(A, b, {}, {im.id: (A, b)}) for A, b in self._leaf_candidates[im.id]]
            level_obs[im.mirror_configs[:-1]].append((im.mirror_configs[-1], hypotheses))
        for level in range(dataset.num_mirrors, 0, -1):
            next_obs: dict[tuple[int, ...], list[_Entry]] = defaultdict(list)
            images_under: dict[tuple[int, ...], list[Image]] = defaultdict(list)
            for im in images:
                images_under[im.mirror_configs[: level - 1]].append(im)
            for prefix in sorted(level_obs):
                entries = level_obs[prefix]
                child_ids = sorted({m for m, _ in entries})
                if len(child_ids) < 3:
                    raise DatasetError(too_few_placements(dataset.source, [im.mirror_configs for im in images], prefix,
                                                          level, child_ids))
                proposals, degenerate = _node_proposals(entries, level, child_ids, self._rng, exhaustive=level == 1)
                node = TreeNode(level, prefix, images_under[prefix], proposals, degenerate, dataset, self._normalized,
                                leaf_candidates=self._leaf_candidates)
                yield node
                solutions = node.kept()
                # the root's solutions are ranked by every fiducial: the best one is the answer
                kept = solutions[:NODE_HYPOTHESES_KEPT] if level > 1 else solutions
                if not kept:
                    listed = ", ".join(f"({level}, {m})" for m in child_ids)
                    raise SolveError(
                        f"{dataset.source}: under {_describe(prefix)}, the normals of mirror {level} placements "
                        f"{listed} are nearly coplanar; move the mirror about a second axis"
                    )
                if level > 1:
                    next_obs[prefix[:-1]].append((prefix[-1], kept))
                else:
                    self._roots = kept
            level_obs = next_obs

    def solution(self) -> AnalyticSolution:
        """The best root solution with its points (eq. 20) and the runner-up roots as alternatives."""
        if self._roots is None:
            raise RuntimeError("TreeWalk: walk every node (TreeWalk.nodes) first")
        solution, *alternatives = [
            AnalyticSolution(
                R_cam_base=project_to_orthogonal(root.A, 1.0),
                t_cam_base=root.b,
                mirror_vectors={key: _mean_vector(vs) for key, vs in root.mirror_vectors.items()},
                image_transforms=root.image_transforms,
            )
            for root in self._roots
        ]
        solution.points = reconstruct_points(self.dataset, solution, self._normalized)
        solution.alternatives = alternatives
        return solution


def solve_analytic(dataset: Dataset, seed: int = 0) -> AnalyticSolution:
    """Closed-form camera-to-base transform, mirror vectors and reconstruction points (Sects. 4-5).

    With three fiducials P3P leaves up to four candidates per image, and a whole subtree of the
    mirror tree can agree on a wrong ("twin") one. Each node therefore hands its best three solutions
    to the level above, ranked by how well they reproject the node's fiducials; the root's
    combinations are each solved and ranked by every fiducial (the cost of eq. 23 without points).
    ``solver.start.initial.initial_estimate`` refines each hypothesis below the root by Levenberg-Marquardt
    instead. Raises as :class:`TreeWalk`.
    """
    walk = TreeWalk(dataset, seed)
    for node in walk.nodes():
        node.scores = node.closed_form_scores()
    return walk.solution()
