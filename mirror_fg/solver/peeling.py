"""Mirror peeling at one node of the mirror tree (Hesch et al., Sect. 4.2, eqs. 13-18).

A node's children are the placements of the next mirror; from each child's ``(A_l, b_l)`` (camera frame,
metres) the node's ``(A_{l-1}, b_{l-1})`` and the children's mirror vectors follow. With P3P several
candidates per observation are possible: the search picks one each (:func:`solve_node`).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, product

import numpy as np

from mirror_fg.core.geometry import householders, project_to_orthogonal

__all__ = ["MIN_NORMAL_SPREAD", "NodeSolution", "choose_candidates", "reflection_fit", "solve_children", "solve_node"]

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
#: Partners per child when its normal is started from pairwise axes (eqs. 14-15); more add nothing.
MAX_AXIS_PARTNERS = 24


@dataclass
class NodeSolution:
    """A node's ``(A_{l-1}, b_{l-1})`` (camera frame, metres) and its children's mirror vectors."""

    A_parent: np.ndarray
    b_parent: np.ndarray
    mirror_vectors: list[np.ndarray]  # per child
    residual: float  # combined residual of eqs. (13) and (16), unitless


#: From this many matrices on, :func:`smallest_eigenvectors` is computed in closed form.
CLOSED_FORM_EIGEN_MIN = 16


def smallest_eigenvectors(S: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (K, 3) of the smallest eigenvalue of symmetric matrices ``S`` (K, 3, 3).

    ``np.linalg.eigh`` on a stack of 3x3 matrices costs ~2 us each and the mirror peeling asks for
    thousands per node; in closed form instead: the smallest eigenvalue by the trigonometric solution
    of the characteristic cubic, the eigenvector as the longest cross product of two rows of
    ``S - lambda I``, then one inverse-free power step on ``||S|| I - S``. Accurate to rounding when the
    smallest eigenvalue is apart from the others (a mirror's ``-1`` against ``+1, +1``, eq. 13); the sign
    is arbitrary, as ``eigh``'s.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 3 or len(S) < CLOSED_FORM_EIGEN_MIN:  # a few matrices: eigh's fixed cost is lower
        return np.linalg.eigh(S)[1][..., 0]
    a00, a11, a22 = S[..., 0, 0], S[..., 1, 1], S[..., 2, 2]
    a01, a02, a12 = S[..., 0, 1], S[..., 0, 2], S[..., 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    p = np.sqrt(p2 / 6.0)
    safe = np.where(p > 0.0, p, 1.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = np.clip(det / (2.0 * safe**3), -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    d0, d1, d2 = a00 - smallest, a11 - smallest, a22 - smallest  # rows of S - lambda I
    crosses = np.stack([
        np.stack([a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - a01 * a01], axis=-1),  # row 0 x row 1
        np.stack([a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d0 * a12 - a01 * a02], axis=-1),  # row 0 x row 2
        np.stack([d1 * d2 - a12 * a12, a12 * a02 - a01 * d2, a01 * a12 - d1 * a02], axis=-1),  # row 1 x row 2
    ], axis=-2)
    lengths = np.einsum("...ka,...ka->...k", crosses, crosses)
    best = np.argmax(lengths, axis=-1)
    v = np.where((np.max(lengths, axis=-1) > 0.0)[..., None],
                 np.take_along_axis(crosses, best[..., None, None], axis=-2)[..., 0, :], np.array([1.0, 0.0, 0.0]))
    v = v / np.sqrt(np.einsum("...a,...a->...", v, v))[..., None]
    shift = np.sqrt(np.einsum("...ab,...ab->...", S, S))  # >= |eigenvalues|: ||S|| I - S is positive semi-definite
    v = shift[..., None] * v - np.einsum("...ab,...b->...a", S, v)
    return v / np.sqrt(np.einsum("...a,...a->...", v, v))[..., None]


def _normals_from_pairwise_axes(child_A: np.ndarray) -> np.ndarray:
    """Unit normals (K, 3) of K mirror placements from the axes of ``A_m A_m'^T`` (eqs. 14-15).

    Eq. (15) crosses two axes; with more children each normal is the direction most perpendicular
    to all of its axes (least squares, weighted by how well each axis is defined).
    """
    A = np.asarray(child_A)
    # Only a start for the alternation in solve_children: a few partners spread over the children will do.
    partners = np.unique(np.linspace(0, len(A) - 1, min(len(A), MAX_AXIS_PARTNERS)).round().astype(int))
    Q = np.matmul(A[:, None], np.swapaxes(A[partners], 1, 2)[None])  # A_m A_m'^T, eq. (14)
    axes = np.stack(
        [Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1
    )
    # the smallest right singular vector of each child's stacked axes (its own axis is zero)
    scatter = np.matmul(np.swapaxes(axes, 1, 2), axes)
    return np.linalg.eigh(scatter)[1][:, :, 0]


def solve_children(
    observations: list[tuple[int, np.ndarray, np.ndarray]], num_children: int, parent_det: float
) -> NodeSolution:
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
        reflections = householders(normals[children], unit=True)
        A_parent = project_to_orthogonal(np.einsum("iab,ibc->ac", reflections, rotations), parent_det)
        # eq. (13): each child's M_m = A_l(m) A_{l-1}^T; its normal is the -1 eigenvector.
        estimates = child_sums @ A_parent.T
        new_normals = smallest_eigenvectors(0.5 * (estimates + estimates.transpose(0, 2, 1)))
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
    reflections = householders(normals[children], unit=True)
    rotation_residual = float(np.sum((rotations - reflections @ A_parent) ** 2))  # eq. (13)
    return NodeSolution(A_parent, b_parent, mirror_vectors, rotation_residual + translation_residual)


def reflection_fit(
    A: np.ndarray, b: np.ndarray, A_parent: np.ndarray, b_parent: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The reflection nearest to each candidate ``(A_l, b_l)`` (stacked (n, 3, 3), (n, 3)) of a known
    parent ``(A_{l-1}, b_{l-1})`` (eqs. 6-7): misfits (n,), squared and unitless, and mirror vectors (n, 3).

    ``A_l A_{l-1}^T`` must be a Householder matrix (normal: eigenvector of its -1 eigenvalue) and
    ``b_l - M b_{l-1}`` must be ``2 v``, parallel to that normal; the misfit is how far both are off.
    """
    M = A @ A_parent.T
    normals = smallest_eigenvectors(0.5 * (M + M.transpose(0, 2, 1)))
    H = householders(normals, unit=True)
    offsets = b - H @ b_parent  # must be 2 v, parallel to the normal (eq. 7)
    along = np.einsum("ia,ia->i", normals, offsets)
    perpendicular = offsets - normals * along[:, None]
    scale = np.maximum(np.linalg.norm(b, axis=1), 1e-9)
    misfits = np.sum((M - H) ** 2, axis=(1, 2)) + np.sum(perpendicular**2, axis=1) / scale**2
    return misfits, 0.5 * along[:, None] * normals


def choose_candidates(
    image_children: list[int],
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]],
    num_children: int,
    parent_det: float,
    rng: np.random.Generator,
) -> list[tuple[list[int], NodeSolution]]:
    """Ranked choices of one candidate per observation of a node, each with its node solution.

    Without enumerating all combinations: minimal triples of children are solved over every
    candidate combination; each triple's best two solutions (lowest residual of eqs. 13 and 16) pick
    every observation's candidate by consistency (robustly capped score). A distant target's P3P
    "twin" can be consistent across many images on its own, so the best few of these choices are
    re-solved over every child (candidates re-picked by consistency with that full solution) and
    returned best residual first.
    """
    if all(len(c) == 1 for c in image_candidates):
        only = [0] * len(image_candidates)
        observations = [(k, *candidates[0]) for k, candidates in zip(image_children, image_candidates)]
        return [(only, solve_children(observations, num_children, parent_det))]
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
            ranked.append(solve_children(observations, 3, parent_det))
        for node in sorted(ranked, key=lambda n: n.residual)[:2]:
            choice, score = _consistent_choice(image_candidates, node)
            hypotheses[choice] = min(score, hypotheses.get(choice, np.inf))
    results: dict[tuple[int, ...], NodeSolution] = {}
    # full solves and re-picks of one choice, computed once: distinct choices often re-pick the same one
    solved: dict[tuple[int, ...], tuple[NodeSolution, tuple[int, ...]]] = {}
    for choice in sorted(hypotheses, key=lambda c: hypotheses[c])[:NUM_FULL_HYPOTHESES]:
        for _ in range(2):
            if choice not in solved:
                observations = [(k, *candidates[c]) for k, candidates, c in zip(image_children, image_candidates, choice)]
                node = solve_children(observations, num_children, parent_det)
                solved[choice] = (node, _consistent_choice(image_candidates, node)[0])
            node, choice = solved[choice]
        if choice not in results or node.residual < results[choice].residual:
            results[choice] = node
    return sorted(((list(c), n) for c, n in results.items()), key=lambda item: item[1].residual)


def _consistent_choice(
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]], node: NodeSolution
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
) -> tuple[list[int], NodeSolution]:
    """One tree node (Sect. 4.2, eqs. 13-18): pick a candidate ``(A_l, b_l)`` per observation, then
    solve the children's mirror vectors and the parent's ``(A_{l-1}, b_{l-1})``.

    children: child index (0..num_children-1) of each observation; candidates: its candidates
    (several for P3P); parent_det: ``det A_{l-1} = (-1)^(l-1)``. Returns the best picks (lowest
    residual) and their solution (``A_parent``, ``b_parent``, ``mirror_vectors`` per child, ``residual``).
    """
    return choose_candidates(children, candidates, num_children, parent_det, rng)[0]
