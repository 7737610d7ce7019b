"""Analytical solution (Hesch et al., Sects. 4-5, eqs. 10-20): PnP per image, mirror peeling, points.

Everything is in the camera frame {C} (metres) except base-frame points. Configuration ``(l, m)`` is
placement ``m`` of mirror ``l`` (1-based). A *node* at level ``l`` is a prefix ``(c_1, ..., c_{l-1})`` of
mirror configurations; its children are the configurations of mirror ``l`` seen under it.
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import combinations, product

import cv2
import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import Dataset, Image
from mirror_fg.core.geometry import FLIP_Y, apply_transform, nested_transform, project, project_to_orthogonal

__all__ = ["AnalyticSolution", "SolveError", "pnp_candidates", "reflection_fit", "solve_analytic", "solve_node", "triangulate_point"]

#: Smallest out-of-plane spread (third singular value of the unit normals, ~radians) of a node's mirrors.
MIN_NORMAL_SPREAD = np.sin(np.deg2rad(0.5))
#: Robust cap on a P3P candidate's inconsistency with a node hypothesis (squared, unitless).
CONSISTENCY_CAP = 0.05
#: Number of child triples tried as hypotheses when P3P leaves several candidates per image.
NUM_TRIPLE_HYPOTHESES = 12
#: Best distinct hypotheses re-solved over all of a node's children.
NUM_FULL_HYPOTHESES = 4
#: Alternations between mirror normals and the parent transform per node.
NODE_ALTERNATIONS = 30
#: Best solutions of an inner node handed to the level above (a subtree's P3P "twin" is only told
#: apart from the truth by the images of the other subtrees).
NODE_HYPOTHESES_KEPT = 3
#: At most this many combinations of the root's child hypotheses are each solved and scored.
MAX_ROOT_COMBINATIONS = 64
#: Partners per child when its normal is started from pairwise axes (eqs. 14-15); more add nothing.
MAX_AXIS_PARTNERS = 24




@dataclass
class AnalyticSolution:
    """Closed-form estimate of every unknown.

    ``R_cam_base``, ``t_cam_base``: camera <- base (``Cp = R Bp + t``, metres). ``mirror_vectors``:
    ``(l, m) -> v`` (camera frame, metres). ``points``: reconstruction points, base frame, metres.
    ``image_transforms``: the PnP ``(A_Nv, b_Nv)`` chosen for each image that had one.
    ``alternatives``: the root's runner-up hypotheses (other P3P choices), best first, without points.
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray] = field(default_factory=dict)
    image_transforms: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    alternatives: list[AnalyticSolution] = field(default_factory=list, repr=False)


# --- PnP per image (Sect. 4.1) -------------------------------------------------------------------

_PNP_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def _reprojection_rms(R: np.ndarray, t: np.ndarray, base_points: np.ndarray, normalized: np.ndarray) -> float:
    camera_points = apply_transform(R, t, base_points)
    if np.any(camera_points[:, 2] <= 0):
        return np.inf
    return float(np.sqrt(np.mean(np.sum((project(camera_points) - normalized) ** 2, axis=1))))


def _pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0], np.asarray(tvec, dtype=np.float64).reshape(3)


def _pnp_rotation_candidates(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """All admissible rigid poses (R, t) explaining normalized observations of base points (eq. 10)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    K = np.eye(3)
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    if len(base_points) == 3:
        # Up to four P3P solutions (Fischler & Bolles); every admissible one is a candidate.
        for flag in (cv2.SOLVEPNP_P3P, cv2.SOLVEPNP_AP3P):
            try:
                count, rvecs, tvecs = cv2.solveP3P(obj, img, K, None, flags=flag)
            except cv2.error:
                continue
            for i in range(count):
                poses.append(_pose_from_rvec(rvecs[i], tvecs[i]))
        admissible = [(R, t) for R, t in poses if _reprojection_rms(R, t, base_points, normalized) < 1e-3]
        unique: list[tuple[np.ndarray, np.ndarray]] = []
        for R, t in admissible:
            if all(np.linalg.norm(R - R2) + np.linalg.norm(t - t2) > 1e-6 for R2, t2 in unique):
                unique.append((R, t))
        return unique
    # >= 4 points: one pose. SQPnP alone can be wrong (STYLE.md), so refine the candidates of several
    # solvers with LM and keep the one with the lowest reprojection error.
    flags = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE]
    centered = base_points - base_points.mean(axis=0)
    if np.linalg.svd(centered, compute_uv=False)[2] < 1e-9 * max(1.0, np.abs(centered).max()):
        flags.append(cv2.SOLVEPNP_IPPE)
    for flag in flags:
        try:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=flag)
        except cv2.error:
            continue
        if ok:
            poses.extend(_pose_from_rvec(r, t) for r, t in zip(rvecs, tvecs))
    for triple in list(combinations(range(len(base_points)), 3))[:4]:
        try:
            count, rvecs, tvecs = cv2.solveP3P(obj[list(triple)], img[list(triple)], K, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        poses.extend(_pose_from_rvec(rvecs[i], tvecs[i]) for i in range(count))
    best, best_error = None, np.inf
    for R, t in poses:
        rvec = cv2.Rodrigues(R)[0]
        tvec = t.reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, criteria=_PNP_CRITERIA)
        except cv2.error:
            pass
        R_ref, t_ref = _pose_from_rvec(rvec, tvec)
        error = _reprojection_rms(R_ref, t_ref, base_points, normalized)
        if error < best_error:
            best, best_error = (R_ref, t_ref), error
    return [] if best is None or not np.isfinite(best_error) else [best]


def pnp_candidates(base_points: np.ndarray, normalized: np.ndarray, num_mirrors: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate composite transforms ``(A_Nv, b_Nv)`` of one image (eqs. 5, 10-12).

    base_points: (N, 3) fiducials, base frame, metres; normalized: (N, 2) their normalized image
    coordinates. For odd Nv the image is flipped in y so PnP sees a rotation (eq. 11), then
    ``A = F R``, ``b = F t`` (eq. 12). Three points give up to four candidates, four or more give one.
    """
    flip = num_mirrors % 2 == 1
    observed = np.array(normalized, dtype=float)
    if flip:
        observed[:, 1] *= -1.0  # eq. (11)
    candidates = _pnp_rotation_candidates(np.asarray(base_points, dtype=float), observed)
    if flip:
        candidates = [(FLIP_Y @ R, FLIP_Y @ t) for R, t in candidates]  # eq. (12)
    return candidates


# --- Mirror peeling (Sect. 4.2, eqs. 13-18) ------------------------------------------------------


@dataclass
class _NodeSolution:
    A_parent: np.ndarray
    b_parent: np.ndarray
    mirror_vectors: list[np.ndarray]  # per child
    residual: float  # combined residual of eqs. (13) and (16), unitless


def _normals_from_pairwise_axes(child_A: np.ndarray) -> np.ndarray:
    """Unit normals (K, 3) of K mirror placements from the axes of ``A_m A_m'^T`` (eqs. 14-15).

    Eq. (15) crosses two axes; with more children each normal is the direction most perpendicular
    to all of its axes (least squares, weighted by how well each axis is defined).
    """
    A = np.asarray(child_A)
    # Only a start for the alternation in _solve_node: a few partners spread over the children will do.
    partners = np.unique(np.linspace(0, len(A) - 1, min(len(A), MAX_AXIS_PARTNERS)).round().astype(int))
    Q = np.matmul(A[:, None], np.swapaxes(A[partners], 1, 2)[None])  # A_m A_m'^T, eq. (14)
    axes = np.stack(
        [Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1
    )
    # the smallest right singular vector of each child's stacked axes (its own axis is zero)
    scatter = np.matmul(np.swapaxes(axes, 1, 2), axes)
    return np.linalg.eigh(scatter)[1][:, :, 0]


def _solve_node(
    observations: list[tuple[int, np.ndarray, np.ndarray]], num_children: int, parent_det: float
) -> _NodeSolution:
    """Mirror vectors of a node's children and the parent's ``(A, b)`` from children's ``(A, b)``.

    observations: ``(child index, A_l, b_l)``; several observations may share a child. Normals start
    from eqs. (14)-(15), then alternate with the parent's O(3) average (eq. 17); offsets and parent
    translation come from the linear system of eq. (16), which also gives the residual.
    """
    children = np.array([k for k, _, _ in observations])
    rotations = np.array([A for _, A, _ in observations])
    child_sums = np.zeros((num_children, 3, 3))
    np.add.at(child_sums, children, rotations)
    child_A = project_to_orthogonal(child_sums, -parent_det)
    normals = _normals_from_pairwise_axes(child_A)  # eqs. (14)-(15)
    A_parent = np.eye(3)
    for _ in range(NODE_ALTERNATIONS):
        # eq. (17): A_{l-1} = M_m^{-1} A_l(m), averaged over all children on O(3).
        obs_normals = normals[children]
        reflections = np.eye(3) - 2.0 * np.einsum("ia,ib->iab", obs_normals, obs_normals)
        A_parent = project_to_orthogonal(np.einsum("iab,ibc->ac", reflections, rotations), parent_det)
        # eq. (13): each child's M_m = A_l(m) A_{l-1}^T; its normal is the -1 eigenvector.
        estimates = child_sums @ A_parent.T
        new_normals = np.linalg.eigh(0.5 * (estimates + estimates.transpose(0, 2, 1)))[1][:, :, 0]
        # keep the sign of each normal stable between iterations
        new_normals *= np.where(np.sum(new_normals * normals, axis=1) < 0, -1.0, 1.0)[:, None]
        converged = np.max(np.abs(new_normals - normals)) < 1e-13
        normals = new_normals
        if converged:
            break
    # eq. (16): [M_m, 2 n_m] [b_{l-1}; d_m] = b_l(m), stacked over every observation, solved with the
    # offsets d_m eliminated (exactly): across n_m it reads P_m (b_{l-1} - b_l) = 0 with P_m = I - n n^T
    # (P_m M_m = P_m), along n_m it gives d_m = (n_m . b_l + n_m . b_{l-1}) / 2, averaged per child.
    offsets = np.array([b for _, _, b in observations])
    children = np.array([k for k, _, _ in observations])
    obs_normals = normals[children]
    projectors = np.eye(3) - np.einsum("ia,ib->iab", obs_normals, obs_normals)
    normal_matrix, rhs = projectors.sum(axis=0), np.einsum("iab,ib->a", projectors, offsets)
    try:
        b_parent = np.linalg.solve(normal_matrix, rhs)
    except np.linalg.LinAlgError:  # parallel normals: the caller's spread check names the degenerate motion
        b_parent = np.linalg.lstsq(normal_matrix, rhs, rcond=None)[0]
    along = np.einsum("ia,ia->i", obs_normals, offsets) + obs_normals @ b_parent
    counts = np.bincount(children, minlength=num_children)
    distances = np.bincount(children, weights=along, minlength=num_children) / (2.0 * np.maximum(counts, 1))
    mirror_vectors = [distances[k] * normals[k] for k in range(num_children)]
    across = np.einsum("iab,ib->ia", projectors, b_parent - offsets)
    along_residual = along - 2.0 * distances[children]
    scale = max(float(np.mean(np.linalg.norm(offsets, axis=1))), 1e-9)
    translation_residual = float(np.sum(across**2) + np.sum(along_residual**2)) / scale**2
    obs_normals = normals[children]
    reflections = np.eye(3) - 2.0 * np.einsum("ia,ib->iab", obs_normals, obs_normals)
    rotation_residual = float(np.sum((rotations - reflections @ A_parent) ** 2))  # eq. (13)
    return _NodeSolution(A_parent, b_parent, mirror_vectors, rotation_residual + translation_residual)


def reflection_fit(
    A: np.ndarray, b: np.ndarray, A_parent: np.ndarray, b_parent: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The reflection nearest to each candidate ``(A_l, b_l)`` (stacked (n, 3, 3), (n, 3)) of a known
    parent ``(A_{l-1}, b_{l-1})`` (eqs. 6-7): misfits (n,), squared and unitless, and mirror vectors (n, 3).

    ``A_l A_{l-1}^T`` must be a Householder matrix (normal: eigenvector of its -1 eigenvalue) and
    ``b_l - M b_{l-1}`` must be ``2 v``, parallel to that normal; the misfit is how far both are off.
    """
    M = A @ A_parent.T
    normals = np.linalg.eigh(0.5 * (M + M.transpose(0, 2, 1)))[1][:, :, 0]
    H = np.eye(3) - 2.0 * np.einsum("ia,ib->iab", normals, normals)
    offsets = b - H @ b_parent  # must be 2 v, parallel to the normal (eq. 7)
    along = np.einsum("ia,ia->i", normals, offsets)
    perpendicular = offsets - normals * along[:, None]
    scale = np.maximum(np.linalg.norm(b, axis=1), 1e-9)
    misfits = np.sum((M - H) ** 2, axis=(1, 2)) + np.sum(perpendicular**2, axis=1) / scale**2
    return misfits, 0.5 * along[:, None] * normals


def _choose_candidates(
    image_children: list[int],
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]],
    num_children: int,
    parent_det: float,
    rng: np.random.Generator,
) -> list[tuple[list[int], _NodeSolution]]:
    """Ranked choices of one candidate per observation of a node, each with its node solution.

    Without enumerating all combinations: minimal triples of children are solved over every
    candidate combination; each triple's best two solutions (lowest residual of eqs. 13 and 16) pick
    every observation's candidate by consistency (robustly capped score). A distant target's P3P
    "twin" can be consistent across many images on its own, so the best few of these choices are
    re-solved over every child (candidates re-picked by consistency with that full solution) and
    returned best residual first.
    """
    if all(len(c) == 1 for c in image_candidates):
        choice = [0] * len(image_candidates)
        observations = [(k, *candidates[0]) for k, candidates in zip(image_children, image_candidates)]
        return [(choice, _solve_node(observations, num_children, parent_det))]
    first_image_of_child: dict[int, int] = {}
    for i, k in enumerate(image_children):
        first_image_of_child.setdefault(k, i)
    children = sorted(first_image_of_child)
    if len(children) <= 5:  # at most 10 triples: take them all
        triples = list(combinations(children, 3))
    else:
        triples = [tuple(sorted(rng.choice(children, size=3, replace=False))) for _ in range(NUM_TRIPLE_HYPOTHESES)]
    hypotheses: dict[tuple[int, ...], float] = {}
    for triple in triples:
        images = [first_image_of_child[k] for k in triple]
        ranked = []
        for combo in product(*(range(len(image_candidates[i])) for i in images)):
            observations = [(j, *image_candidates[i][c]) for j, (i, c) in enumerate(zip(images, combo))]
            ranked.append(_solve_node(observations, 3, parent_det))
        for node in sorted(ranked, key=lambda n: n.residual)[:2]:
            choice, score = _consistent_choice(image_candidates, node)
            hypotheses[choice] = min(score, hypotheses.get(choice, np.inf))
    results: dict[tuple[int, ...], _NodeSolution] = {}
    for choice in sorted(hypotheses, key=hypotheses.get)[:NUM_FULL_HYPOTHESES]:
        for _ in range(2):
            observations = [(k, *candidates[c]) for k, candidates, c in zip(image_children, image_candidates, choice)]
            node = _solve_node(observations, num_children, parent_det)
            choice, _ = _consistent_choice(image_candidates, node)
        if choice not in results or node.residual < results[choice].residual:
            results[choice] = node
    return sorted(((list(c), n) for c, n in results.items()), key=lambda item: item[1].residual)


def _consistent_choice(
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]], node: _NodeSolution
) -> tuple[tuple[int, ...], float]:
    """Each image's candidate most consistent with a node's parent, and the capped total inconsistency."""
    counts = np.array([len(candidates) for candidates in image_candidates])
    A = np.array([A for candidates in image_candidates for A, _ in candidates])
    b = np.array([b for candidates in image_candidates for _, b in candidates])
    costs = np.full((len(counts), counts.max()), np.inf)
    image_of = np.repeat(np.arange(len(counts)), counts)
    slot = np.arange(len(A)) - np.repeat(np.cumsum(counts) - counts, counts)
    costs[image_of, slot] = reflection_fit(A, b, node.A_parent, node.b_parent)[0]
    choice = tuple(np.argmin(costs, axis=1).tolist())
    score = float(np.sum(np.minimum(costs.min(axis=1), CONSISTENCY_CAP)))
    return choice, score


def solve_node(
    children: list[int],
    candidates: list[list[tuple[np.ndarray, np.ndarray]]],
    num_children: int,
    parent_det: float,
    rng: np.random.Generator,
) -> tuple[list[int], _NodeSolution]:
    """One tree node (Sect. 4.2, eqs. 13-18): pick a candidate ``(A_l, b_l)`` per observation, then
    solve the children's mirror vectors and the parent's ``(A_{l-1}, b_{l-1})``.

    children: child index (0..num_children-1) of each observation; candidates: its candidates
    (several for P3P); parent_det: ``det A_{l-1} = (-1)^(l-1)``. Returns the best picks (lowest
    residual) and their solution (``A_parent``, ``b_parent``, ``mirror_vectors`` per child, ``residual``).
    """
    return _choose_candidates(children, candidates, num_children, parent_det, rng)[0]


@dataclass
class _Hypothesis:
    """One candidate ``(A_l, b_l)`` of a tree node with what its subtree chose to get there."""

    A: np.ndarray
    b: np.ndarray
    mirror_vectors: dict[tuple[int, int], list[np.ndarray]]
    image_transforms: dict[str, tuple[np.ndarray, np.ndarray]]


def _node_hypotheses(
    entries: list[tuple[int, list[_Hypothesis]]],
    level: int,
    child_ids: list[int],
    score: Callable[[_Hypothesis], tuple[float, _Hypothesis]],
    rng: np.random.Generator,
    exhaustive: bool,
) -> list[_Hypothesis]:
    """Solutions of one node from its observations' hypotheses, best first, without those whose mirror
    normals are nearly coplanar (eqs. 14-15 cannot be trusted); none at all when the best one is (then
    the motion itself is degenerate).

    The search proposes solutions by the algebraic residual of eqs. (13) and (16), but under noise a
    wrong P3P pick can lower that residual, so they are ranked by ``score``: the reprojection cost of
    the node's fiducials, after refining the hypothesis when a refiner is given.
    ``exhaustive``: solve every combination of the observations' hypotheses (when there are at most
    ``MAX_ROOT_COMBINATIONS``) instead of the sampled search of ``_choose_candidates``.
    """
    index_of = {m: k for k, m in enumerate(child_ids)}
    children = [index_of[m] for m, _ in entries]
    candidates = [[(h.A, h.b) for h in hyps] for _, hyps in entries]
    parent_det = (-1.0) ** (level - 1)
    if exhaustive and math.prod(len(c) for c in candidates) <= MAX_ROOT_COMBINATIONS:  # no int64 overflow
        ranked = []
        for combo in product(*(range(len(c)) for c in candidates)):
            observations = [(k, *cands[c]) for k, cands, c in zip(children, candidates, combo)]
            ranked.append((list(combo), _solve_node(observations, len(child_ids), parent_det)))
        ranked.sort(key=lambda item: item[1].residual)
    else:
        ranked = _choose_candidates(children, candidates, len(child_ids), parent_det, rng)
    solutions: list[tuple[float, int, _Hypothesis, bool]] = []
    for rank, (picks, node) in enumerate(ranked):
        normals = np.stack([v / np.linalg.norm(v) for v in node.mirror_vectors])
        degenerate = bool(np.linalg.svd(normals, compute_uv=False)[2] < MIN_NORMAL_SPREAD)
        hypothesis = _Hypothesis(node.A_parent, node.b_parent, defaultdict(list), {})
        for (_, hyps), p in zip(entries, picks):
            for config, vectors in hyps[p].mirror_vectors.items():
                hypothesis.mirror_vectors[config].extend(vectors)
            hypothesis.image_transforms.update(hyps[p].image_transforms)
        for m, v in zip(child_ids, node.mirror_vectors):
            hypothesis.mirror_vectors[(level, m)].append(v)
        cost, hypothesis = score(hypothesis)
        solutions.append((cost, rank, hypothesis, degenerate))
    solutions.sort(key=lambda item: item[:2])
    if solutions[0][3]:
        return []
    distinct: list[_Hypothesis] = []  # refined starts often meet in one optimum: keep it once
    for _, _, hypothesis, degenerate in solutions:
        if not degenerate and not any(_same_transform(hypothesis, kept) for kept in distinct):
            distinct.append(hypothesis)
    return distinct


def _same_transform(first: _Hypothesis, second: _Hypothesis, tolerance: float = 1e-3) -> bool:
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

    def cost(
        self, A_start: np.ndarray, b_start: np.ndarray, mirror_vectors: dict[tuple[int, int], np.ndarray],
        first_mirror: int = 1,
    ) -> float:
        """Sum of squared whitened reprojection errors of every fiducial (eq. 23 without the points),
        given ``(A, b)`` before mirror ``first_mirror`` (``R_cam_base, t_cam_base`` for mirror 1) and the
        vectors of that mirror's and every later mirror's placements."""
        A = np.broadcast_to(A_start, (len(self.configs), 3, 3)).copy()
        b = np.broadcast_to(b_start, (len(self.configs), 3)).copy()
        for level in range(first_mirror - 1, len(self.configs[0]) if self.configs else 0):
            v = np.array([mirror_vectors[(level + 1, configs[level])] for configs in self.configs])
            n = v / np.linalg.norm(v, axis=1, keepdims=True)
            M = np.eye(3) - 2.0 * np.einsum("ia,ib->iab", n, n)  # eq. (3)
            A = M @ A  # eq. (6)
            b = np.einsum("iab,ib->ia", M, b) + 2.0 * v  # eq. (7)
        camera_points = np.einsum("iab,ib->ia", A[self.image_index], self.points) + b[self.image_index]  # eq. (5)
        if not len(camera_points) or np.any(camera_points[:, 2] <= 0):
            return np.inf
        return float(np.sum(((project(camera_points) - self.observed) / self.sigma) ** 2))  # eq. (9)


def _describe(prefix: tuple[int, ...]) -> str:
    if not prefix:
        return "the root (no mirror placed)"
    return "placement " + ", ".join(f"({l + 1}, {m})" for l, m in enumerate(prefix))


#: Refines a subtree's solution: ``(sub-dataset, its closed-form solution) -> (cost, refined solution)``
#: or ``None`` when it fails. The sub-dataset is a :func:`subtree_dataset`; the cost is comparable with
#: that of the other hypotheses of the same subtree (e.g. half the whitened squared reprojection error).
SubtreeRefiner = Callable[[Dataset, AnalyticSolution], "tuple[float, AnalyticSolution] | None"]


def subtree_dataset(dataset: Dataset, images: list[Image], level: int) -> Dataset:
    """The images under one node at ``level`` (mirrors ``level..Nv`` move) as a dataset of their own.

    The node's ``(A_{l-1}, b_{l-1})`` plays ``(R_cam_base, t_cam_base)``; when it is a reflection
    (``l - 1`` odd) the fiducials are mirrored in y (``A Bp = (A F)(F Bp)``, ``F`` = diag(1, -1, 1)) so it
    becomes a rotation. Mirror ``level`` becomes mirror 1; reconstruction points are left out.
    """
    flip = (level - 1) % 2 == 1
    fiducials = {name: FLIP_Y @ p if flip else p.copy() for name, p in dataset.fiducials.items()}
    sub_images = [
        Image(im.id, im.mirror_configs[level - 1 :], {n: z for n, z in im.observations.items() if n in fiducials})
        for im in images
    ]
    return Dataset(dataset.num_mirrors - level + 1, dataset.camera, dataset.pixel_sigma, fiducials, sub_images,
                   source=dataset.source)


def _subtree_solution(hypothesis: _Hypothesis, level: int) -> AnalyticSolution:
    """A node's hypothesis as the solution of its :func:`subtree_dataset`."""
    flip = (level - 1) % 2 == 1
    return AnalyticSolution(
        R_cam_base=hypothesis.A @ FLIP_Y if flip else hypothesis.A.copy(),
        t_cam_base=hypothesis.b.copy(),
        mirror_vectors={(l - level + 1, m): np.mean(vs, axis=0) for (l, m), vs in hypothesis.mirror_vectors.items()},
    )


def _hypothesis_of_subtree(solution: AnalyticSolution, hypothesis: _Hypothesis, level: int) -> _Hypothesis:
    """Back from :func:`_subtree_solution` (after refinement) to the node's hypothesis."""
    flip = (level - 1) % 2 == 1
    return _Hypothesis(
        A=solution.R_cam_base @ FLIP_Y if flip else solution.R_cam_base,
        b=solution.t_cam_base,
        mirror_vectors={(l + level - 1, m): [v] for (l, m), v in solution.mirror_vectors.items()},
        image_transforms=hypothesis.image_transforms,
    )


def solve_analytic(dataset: Dataset, seed: int = 0, refine_subtree: SubtreeRefiner | None = None) -> AnalyticSolution:
    """Closed-form camera-to-base transform, mirror vectors and reconstruction points (Sects. 4-5).

    With three fiducials P3P leaves up to four candidates per image, and a whole subtree of the
    mirror tree can agree on a wrong ("twin") one. Each node therefore hands its best three solutions
    to the level above, ranked by how well they reproject the node's fiducials; the root's
    combinations are each solved and ranked by every fiducial (the cost of eq. 23 without points).
    ``refine_subtree``: refine each hypothesis of every node below the root on its own images first
    (e.g. by Levenberg-Marquardt, ``graph.initial_estimate``); without it the solution is closed-form.

    Raises ``DatasetError`` when the mirror schedule cannot support a solution (a placement with fewer
    than three child placements, a configuration only seen without three fiducials, a point seen in
    fewer than two images) and ``SolveError`` for degenerate geometry or PnP failure.
    """
    rng = np.random.default_rng(seed)
    Nv = dataset.num_mirrors
    normalized = {image.id: dataset.normalized(image) for image in dataset.images}
    # Sect. 4.1: (A_Nv, b_Nv) candidates per image from its fiducials.
    leaf_candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for image in dataset.images:
        names = [n for n in image.observations if n in dataset.fiducials]
        if len(names) < 3:
            continue
        base_points = np.array([dataset.fiducials[n] for n in names])
        observed = np.array([normalized[image.id][n] for n in names])
        candidates = pnp_candidates(base_points, observed, Nv)
        if not candidates:
            raise SolveError(
                f"{dataset.source}: image '{image.id}': PnP found no pose with every fiducial in front of the camera"
            )
        leaf_candidates[image.id] = candidates
    images = [im for im in dataset.images if im.id in leaf_candidates]
    seen_configs = {(l + 1, m) for im in images for l, m in enumerate(im.mirror_configs)}
    for l, m in dataset.configurations:
        if (l, m) not in seen_configs:
            raise DatasetError(
                f"{dataset.source}: mirror {l} placement {m} is only seen in images with fewer than 3 fiducials"
            )

    # Level Nv: observations are images; the node is the prefix of the first Nv-1 configurations.
    level_obs: dict[tuple[int, ...], list[tuple[int, list[_Hypothesis]]]] = defaultdict(list)
    for im in images:
        hypotheses = [_Hypothesis(A, b, {}, {im.id: (A, b)}) for A, b in leaf_candidates[im.id]]
        level_obs[im.mirror_configs[:-1]].append((im.mirror_configs[-1], hypotheses))
    for level in range(Nv, 0, -1):
        next_obs: dict[tuple[int, ...], list[tuple[int, list[_Hypothesis]]]] = defaultdict(list)
        images_under: dict[tuple[int, ...], list[Image]] = defaultdict(list)
        for im in images:
            images_under[im.mirror_configs[: level - 1]].append(im)
        for prefix in sorted(level_obs):
            entries = level_obs[prefix]
            child_ids = sorted({m for m, _ in entries})
            if len(child_ids) < 3:
                raise DatasetError(
                    f"{dataset.source}: {_describe(prefix)} has {len(child_ids)} placement(s) of mirror {level} "
                    f"under it ({', '.join(str(m) for m in child_ids)}); the analytical solution needs >= 3"
                )
            refine = refine_subtree is not None and level > 1
            # Built once per node: the subtree a refiner works on, or the fiducials that score closed forms.
            subtree = subtree_dataset(dataset, images_under[prefix], level) if refine else None
            fiducials = None if refine else _FiducialObservations(dataset, images_under[prefix], normalized)

            def score(hypothesis: _Hypothesis, level: int = level, subtree: Dataset | None = subtree,
                      fiducials: _FiducialObservations | None = fiducials) -> tuple[float, _Hypothesis]:
                if fiducials is not None:
                    vectors = {key: np.mean(vs, axis=0) for key, vs in hypothesis.mirror_vectors.items()}
                    return 0.5 * fiducials.cost(hypothesis.A, hypothesis.b, vectors, level), hypothesis
                refined = refine_subtree(subtree, _subtree_solution(hypothesis, level))
                if refined is None or not np.isfinite(refined[0]):
                    return np.inf, hypothesis
                return refined[0], _hypothesis_of_subtree(refined[1], hypothesis, level)

            solutions = _node_hypotheses(entries, level, child_ids, score, rng, exhaustive=level == 1)
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
                roots = kept
        level_obs = next_obs
    solution, *alternatives = [
        AnalyticSolution(
            R_cam_base=project_to_orthogonal(root.A, 1.0),
            t_cam_base=root.b,
            mirror_vectors={key: np.mean(vs, axis=0) for key, vs in root.mirror_vectors.items()},
            image_transforms=root.image_transforms,
        )
        for root in roots
    ]
    solution.points = reconstruct_points(dataset, solution, normalized)
    solution.alternatives = alternatives
    return solution


# --- Reconstruction points (Sect. 5, eqs. 19-20) --------------------------------------------------


def triangulate_point(transforms: list[tuple[np.ndarray, np.ndarray]], normalized: list[np.ndarray]) -> np.ndarray:
    """Base-frame point from >= 2 images: ``s_j u_j = A_j Bp + b_j`` solved in least squares (eq. 20).

    The depths ``s_j`` are eliminated exactly: for a unit ray ``u_j`` the least-squares residual of
    image j is ``(I - u_j u_j^T)(A_j Bp + b_j)``, so eq. (20) reduces to a 3x3 normal equation.
    """
    A = np.array([A for A, _ in transforms])
    b = np.array([b for _, b in transforms])
    rays = np.column_stack([np.asarray(normalized, dtype=float).reshape(-1, 2), np.ones(len(transforms))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)  # eq. (19)
    projectors = np.eye(3) - np.einsum("ia,ib->iab", rays, rays)
    weighted = np.swapaxes(A, 1, 2) @ projectors  # A_j^T (I - u_j u_j^T)
    normal_matrix = np.sum(weighted @ A, axis=0)
    rhs = -np.einsum("iab,ib->a", weighted, b)
    return np.linalg.solve(normal_matrix, rhs)


def image_transform(solution: AnalyticSolution, image: Image) -> tuple[np.ndarray, np.ndarray]:
    """``(A_Nv, b_Nv)`` of an image from the solved pose and mirror vectors (eqs. 6-7)."""
    vectors = [solution.mirror_vectors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)]
    return nested_transform(solution.R_cam_base, solution.t_cam_base, vectors)


def reconstruct_points(
    dataset: Dataset, solution: AnalyticSolution, normalized: dict[str, dict[str, np.ndarray]] | None = None
) -> dict[str, np.ndarray]:
    """Every reconstruction point by eq. (20) from all images that see it.

    ``normalized``: each image's normalized observations (``Dataset.normalized``) when already at hand.
    """
    seen: dict[str, list[Image]] = defaultdict(list)
    for image in dataset.images:
        for name in image.observations:
            if name not in dataset.fiducials:
                seen[name].append(image)
    if not seen:
        return {}
    if normalized is None:
        normalized = {}
    transforms: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    points = {}
    for name in sorted(seen):
        images = seen[name]
        if len(images) < 2:
            raise DatasetError(
                f"{dataset.source}: point '{name}' is seen only in image '{images[0].id}'; "
                "a reconstruction point needs >= 2 images"
            )
        for im in images:
            if im.id not in transforms:
                transforms[im.id] = image_transform(solution, im)
            if im.id not in normalized:
                normalized[im.id] = dataset.normalized(im)
        rays = [normalized[im.id][name] for im in images]
        points[name] = triangulate_point([transforms[im.id] for im in images], rays)
    return points
