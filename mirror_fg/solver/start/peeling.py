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

__all__ = ["MIN_NORMAL_SPREAD", "NodeSolution", "StackedCandidates", "choose_candidates", "consistent_mirror_vectors",
           "reflection_fit", "solve_children", "solve_node", "solve_children_many", "solve_triples"]

#: Smallest out-of-plane spread (third singular value of the unit normals, ~radians) of a node's mirrors.
MIN_NORMAL_SPREAD = np.sin(np.deg2rad(0.5))
#: Robust cap on a P3P candidate's inconsistency with a node hypothesis (squared, unitless).
CONSISTENCY_CAP = 0.05
#: Number of child triples tried as hypotheses when P3P leaves several candidates per image.
NUM_TRIPLE_HYPOTHESES = 12
#: Best distinct hypotheses re-solved over all of a node's children.
NUM_FULL_HYPOTHESES = 4
#: Alternations between mirror normals and the parent transform per node. Under noise the alternation
#: creeps (each step ~3 % shorter than the last): on the 900-image case a node's parent is 5e-3 to 9e-3
#: from the fixed point after 10 steps, 4e-3 to 7e-3 after 30, 2e-3 to 3e-3 after 100 (unitless) - a
#: start that the LM refinement of the node and the MLE take the rest of the way either way; noise-free,
#: the alternation stops at once.
NODE_ALTERNATIONS = 10
#: Partners per child when its normal is started from pairwise axes (eqs. 14-15); more add nothing.
MAX_AXIS_PARTNERS = 24
#: :func:`choose_candidates` searches on the observations of at most this many children, spread over the
#: node's children in their order (capture order); every other observation's candidate and mirror vector
#: then follow from each solution's parent (eqs. 6-7). Bounds the cost of a node with hundreds of
#: placements (a video): the search needs the residual gap between P3P twins, not every child.
MAX_SEARCH_CHILDREN = 48


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
    # the six entries as contiguous rows: every step below is a handful of 1-D operations
    a00, a01, a02, _, a11, a12, _, _, a22 = np.ascontiguousarray(S.reshape(-1, 9).T)
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off
    p = np.sqrt(p2 / 6.0)
    safe = np.where(p > 0.0, p, 1.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = np.clip(det / (2.0 * safe**3), -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    d0, d1, d2 = a00 - smallest, a11 - smallest, a22 - smallest  # rows of S - lambda I
    c0 = (a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - a01 * a01)  # row 0 x row 1
    c1 = (a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d0 * a12 - a01 * a02)  # row 0 x row 2
    c2 = (d1 * d2 - a12 * a12, a12 * a02 - a01 * d2, a01 * a12 - d1 * a02)  # row 1 x row 2
    l0, l1, l2 = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2] for c in (c0, c1, c2))
    first, second = (l0 >= l1) & (l0 >= l2), l1 >= l2  # the longest (the first of equals, as argmax)
    longest = np.maximum(np.maximum(l0, l1), l2)
    x, y, z = (np.where(first, c0[i], np.where(second, c1[i], c2[i])) for i in range(3))
    zero = longest <= 0.0
    if np.any(zero):
        x, y, z = np.where(zero, 1.0, x), np.where(zero, 0.0, y), np.where(zero, 0.0, z)
    norm = np.sqrt(x * x + y * y + z * z)
    x, y, z = x / norm, y / norm, z / norm
    shift = np.sqrt(a00 * a00 + a11 * a11 + a22 * a22 + 2.0 * off)  # >= |eigenvalues|: ||S|| I - S is PSD
    x, y, z = (shift * x - (a00 * x + a01 * y + a02 * z), shift * y - (a01 * x + a11 * y + a12 * z),
               shift * z - (a02 * x + a12 * y + a22 * z))
    v = np.stack([x, y, z], axis=-1)
    return v / np.sqrt(x * x + y * y + z * z)[:, None]


def _normals_from_pairwise_axes(child_A: np.ndarray) -> np.ndarray:
    """Unit normals (..., K, 3) of K mirror placements (``child_A`` (..., K, 3, 3)) from the axes of
    ``A_m A_m'^T`` (eqs. 14-15).

    Eq. (15) crosses two axes; with more children each normal is the direction most perpendicular
    to all of its axes (least squares, weighted by how well each axis is defined).
    """
    A = np.asarray(child_A)
    # Only a start for the alternation in solve_children: a few partners spread over the children will do.
    count = A.shape[-3]
    partners = np.unique(np.linspace(0, count - 1, min(count, MAX_AXIS_PARTNERS)).round().astype(int))
    Q = np.matmul(A[..., :, None, :, :], np.swapaxes(A[..., partners, :, :], -1, -2)[..., None, :, :, :])  # eq. (14)
    axes = np.stack(
        [Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1
    )
    # the smallest right singular vector of each child's stacked axes (its own axis is zero)
    scatter = np.matmul(np.swapaxes(axes, -1, -2), axes)
    return np.linalg.eigh(scatter)[1][..., 0]


def _solve_or_lstsq(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(matrix, rhs)
    except np.linalg.LinAlgError:  # parallel normals: the caller's spread check names the degenerate motion
        return np.linalg.lstsq(matrix, rhs, rcond=None)[0]


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
    offsets = np.array([b for _, _, b in observations])
    return solve_children_many(children, rotations[None], offsets[None], num_children, parent_det)[0]


def _update_normals(normals: np.ndarray, new_normals: np.ndarray, active: np.ndarray) -> bool:
    """One alternation's normals (nodes, children, 3) taken in place for the ``active`` nodes, each sign
    kept as before (so convergence is measured); nodes whose normals moved < 1e-13 leave ``active``.
    Whether any node is still active."""
    new_normals *= np.where(np.sum(new_normals * normals, axis=-1) < 0, -1.0, 1.0)[..., None]
    converged = np.max(np.abs(new_normals - normals), axis=(1, 2)) < 1e-13
    normals[active] = new_normals[active]
    active &= ~converged
    return bool(active.any())


def solve_children_many(
    children: np.ndarray, rotations: np.ndarray, offsets: np.ndarray, num_children: int, parent_det: float
) -> list[NodeSolution]:
    """:func:`solve_children` of C choices of one node's candidates at once (the same observations,
    another ``(A_l, b_l)`` picked for some): children (N,) child index of each observation, rotations
    (C, N, 3, 3) and offsets (C, N, 3) each choice's ``A_l`` and ``b_l``. Each choice's alternation
    stops when its own normals settle, as it would alone."""
    num = len(rotations)
    child_sums = np.zeros((num_children, num, 3, 3))  # children first: np.add.at over the first axis
    np.add.at(child_sums, children, np.swapaxes(rotations, 0, 1))
    child_sums = np.ascontiguousarray(np.swapaxes(child_sums, 0, 1))
    child_A = project_to_orthogonal(child_sums, -parent_det)
    normals = _normals_from_pairwise_axes(child_A)  # eqs. (14)-(15)
    A_parent = np.broadcast_to(np.eye(3), (num, 3, 3)).copy()
    rotation_sum = child_sums.sum(axis=1)
    active = np.ones(num, dtype=bool)
    for _ in range(NODE_ALTERNATIONS):
        # eq. (17): A_{l-1} = M_m^{-1} A_l(m), averaged over all children on O(3). Summed per child, as
        # sum_m (I - 2 n_m n_m^T) S_m = sum_m S_m - 2 sum_m n_m (n_m^T S_m): K products, not K 3x3 ones.
        weighted = np.einsum("cka,ckab->ckb", normals, child_sums)
        new_parent = project_to_orthogonal(rotation_sum - 2.0 * np.swapaxes(normals, 1, 2) @ weighted, parent_det)
        A_parent[active] = new_parent[active]
        # eq. (13): each child's M_m = A_l(m) A_{l-1}^T; its normal is the -1 eigenvector.
        estimates = (child_sums.reshape(num, -1, 3) @ np.swapaxes(A_parent, 1, 2)).reshape(child_sums.shape)
        symmetric = 0.5 * (estimates + np.swapaxes(estimates, -1, -2))
        if num_children < CLOSED_FORM_EIGEN_MIN:  # as smallest_eigenvectors does for one node
            new_normals = np.linalg.eigh(symmetric)[1][..., 0]
        else:
            new_normals = smallest_eigenvectors(symmetric.reshape(-1, 3, 3)).reshape(normals.shape)
        if not _update_normals(normals, new_normals, active):
            break
    # eq. (16): [M_m, 2 n_m] [b_{l-1}; d_m] = b_l(m), stacked over every observation, solved with the
    # offsets d_m eliminated (exactly): across n_m it reads P_m (b_{l-1} - b_l) = 0 with P_m = I - n n^T
    # (P_m M_m = P_m), along n_m it gives d_m = (n_m . b_l + n_m . b_{l-1}) / 2, averaged per child.
    obs_normals = normals[:, children]
    projectors = np.eye(3) - np.einsum("cia,cib->ciab", obs_normals, obs_normals)
    normal_matrix, rhs = projectors.sum(axis=1), np.einsum("ciab,cib->ca", projectors, offsets)
    counts = np.bincount(children, minlength=num_children)
    reflections = householders(obs_normals.reshape(-1, 3), unit=True).reshape(rotations.shape)
    rotation_residuals = np.sum((rotations - reflections @ A_parent[:, None]) ** 2, axis=(1, 2, 3))  # eq. (13)
    solutions = []
    for c in range(num):
        b_parent = _solve_or_lstsq(normal_matrix[c], rhs[c])
        along = np.einsum("ia,ia->i", obs_normals[c], offsets[c]) + obs_normals[c] @ b_parent
        distances = np.bincount(children, weights=along, minlength=num_children) / (2.0 * np.maximum(counts, 1))
        mirror_vectors = [distances[k] * normals[c, k] for k in range(num_children)]
        across = np.einsum("iab,ib->ia", projectors[c], b_parent - offsets[c])
        along_residual = along - 2.0 * distances[children]
        scale = max(float(np.mean(np.linalg.norm(offsets[c], axis=1))), 1e-9)
        translation_residual = float(np.sum(across**2) + np.sum(along_residual**2)) / scale**2
        solutions.append(NodeSolution(A_parent[c], b_parent, mirror_vectors, float(rotation_residuals[c]) + translation_residual))
    return solutions


def solve_triples(
    rotations: np.ndarray, offsets: np.ndarray, parent_det: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`solve_children` of P minimal nodes at once, each with three children seen once.

    rotations (P, 3, 3, 3): the children's ``A_l``; offsets (P, 3, 3): their ``b_l``. Returns each
    node's ``A_{l-1}`` (P, 3, 3), ``b_{l-1}`` (P, 3) and residual of eqs. (13) and (16) (P,), the
    same steps as :func:`solve_children` (eigenvectors by ``eigh``, each node's alternation stopped
    when its own normals settle).
    """
    num = len(rotations)
    if num == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0)
    child_A = project_to_orthogonal(rotations, -parent_det)
    Q = np.matmul(child_A[:, :, None], np.swapaxes(child_A, -1, -2)[:, None])  # A_m A_m'^T, eq. (14)
    axes = np.stack([Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1)
    normals = np.linalg.eigh(np.matmul(np.swapaxes(axes, -1, -2), axes))[1][..., 0]  # eq. (15)
    A_parent = np.broadcast_to(np.eye(3), (num, 3, 3)).copy()
    rotation_sum = rotations.sum(axis=1)
    active = np.ones(num, dtype=bool)
    for _ in range(NODE_ALTERNATIONS):
        weighted = np.einsum("pka,pkab->pkb", normals, rotations)  # eq. (17), as in solve_children
        new_parent = project_to_orthogonal(rotation_sum - 2.0 * np.swapaxes(normals, 1, 2) @ weighted, parent_det)
        A_parent[active] = new_parent[active]
        estimates = rotations @ np.swapaxes(A_parent, 1, 2)[:, None]  # eq. (13)
        new_normals = np.linalg.eigh(0.5 * (estimates + np.swapaxes(estimates, -1, -2)))[1][..., 0]
        if not _update_normals(normals, new_normals, active):
            break
    projectors = np.eye(3) - np.einsum("pia,pib->piab", normals, normals)  # eq. (16), as in solve_children
    normal_matrix, rhs = projectors.sum(axis=1), np.einsum("piab,pib->pa", projectors, offsets)
    try:
        b_parent = np.linalg.solve(normal_matrix, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:  # parallel normals somewhere: each node as solve_children does it
        b_parent = np.array([_solve_or_lstsq(m, r) for m, r in zip(normal_matrix, rhs)])
    across = np.einsum("piab,pib->pia", projectors, b_parent[:, None] - offsets)
    # along n_m each child's own offset d_m fits exactly (one observation each): no residual there
    scale = np.maximum(np.mean(np.linalg.norm(offsets, axis=-1), axis=-1), 1e-9)
    translation_residual = np.sum(across**2, axis=(1, 2)) / scale**2
    reflections = householders(normals.reshape(-1, 3), unit=True).reshape(num, 3, 3, 3)
    rotation_residual = np.sum((rotations - reflections @ A_parent[:, None]) ** 2, axis=(1, 2, 3))
    return A_parent, b_parent, rotation_residual + translation_residual


def reflection_fit(
    A: np.ndarray, b: np.ndarray, A_parent: np.ndarray, b_parent: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The reflection nearest to each candidate ``(A_l, b_l)`` (stacked (n, 3, 3), (n, 3)) of a known
    parent ``(A_{l-1}, b_{l-1})`` (one, or one per candidate: (n, 3, 3), (n, 3)) (eqs. 6-7): misfits (n,),
    squared and unitless, and mirror vectors (n, 3).

    ``A_l A_{l-1}^T`` must be a Householder matrix (normal: eigenvector of its -1 eigenvalue) and
    ``b_l - M b_{l-1}`` must be ``2 v``, parallel to that normal; the misfit is how far both are off.
    """
    M = A @ np.swapaxes(A_parent, -1, -2)  # one parent, or one per candidate (stacked)
    normals = smallest_eigenvectors(0.5 * (M + M.transpose(0, 2, 1)))
    H = householders(normals, unit=True)
    offsets = b - (H @ b_parent if np.ndim(b_parent) == 1 else (H @ b_parent[:, :, None])[:, :, 0])  # 2 v (eq. 7)
    along = np.einsum("ia,ia->i", normals, offsets)
    perpendicular = offsets - normals * along[:, None]
    scale = np.maximum(np.linalg.norm(b, axis=1), 1e-9)
    misfits = np.sum((M - H) ** 2, axis=(1, 2)) + np.sum(perpendicular**2, axis=1) / scale**2
    return misfits, 0.5 * along[:, None] * normals


def spread_subset(count: int, limit: int) -> np.ndarray:
    """Indices of at most ``limit`` of ``count`` items, evenly spread (first and last included)."""
    if count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(int))


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

    With more than ``MAX_SEARCH_CHILDREN`` children the search runs on the observations of that many,
    spread over them; each solution's residual is theirs, and every observation's candidate is then
    re-picked by consistency with its parent, the other children's mirror vectors following from it
    (eqs. 6-7, :func:`reflection_fit`).
    """
    children_index = np.asarray(image_children)
    searched = spread_subset(num_children, MAX_SEARCH_CHILDREN)
    if len(searched) == num_children:
        return _search(image_children, image_candidates, num_children, parent_det, rng)
    observations = np.flatnonzero(np.isin(children_index, searched))
    ranked = _search(
        np.searchsorted(searched, children_index[observations]).tolist(), [image_candidates[i] for i in observations],
        len(searched), parent_det, rng,
    )
    stacked = StackedCandidates(image_candidates)
    results: dict[tuple[int, ...], NodeSolution] = {}
    for _, node in ranked:
        choice, means = consistent_mirror_vectors(stacked, children_index, num_children, node.A_parent, node.b_parent)
        mirror_vectors = list(means)
        for k, vector in zip(searched.tolist(), node.mirror_vectors):
            mirror_vectors[k] = vector
        if choice not in results or node.residual < results[choice].residual:
            results[choice] = NodeSolution(node.A_parent, node.b_parent, mirror_vectors, node.residual)
    return sorted(((list(c), n) for c, n in results.items()), key=lambda item: item[1].residual)


def _search(
    image_children: list[int],
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]],
    num_children: int,
    parent_det: float,
    rng: np.random.Generator,
) -> list[tuple[list[int], NodeSolution]]:
    """:func:`choose_candidates` on every observation given."""
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
    # every candidate combination of every triple solved at once (solve_children of each, vectorised)
    stacked = StackedCandidates(image_candidates)
    combos_of = []  # per triple: each combination of its images' candidates, as rows of ``stacked``
    for triple in triples:
        images = [first_image_of_child[k] for k in triple]
        first_rows = [int(stacked.first[i]) for i in images]
        combos_of.append([tuple(first + c for first, c in zip(first_rows, combo))
                          for combo in product(*(range(len(image_candidates[i])) for i in images))])
    flat = np.array([combo for combos in combos_of for combo in combos], dtype=np.intp).reshape(-1, 3)
    A_parents, b_parents, residuals = solve_triples(stacked.A[flat], stacked.b[flat], parent_det)
    hypotheses: dict[tuple[int, ...], float] = {}
    start = 0
    for combos in combos_of:
        indices = start + np.argsort(residuals[start : start + len(combos)], kind="stable")[:2]
        start += len(combos)
        for k in indices:
            choice, score = _consistent_choice(stacked, A_parents[k], b_parents[k])
            hypotheses[choice] = min(score, hypotheses.get(choice, np.inf))
    # full solves and re-picks of one choice, computed once (distinct choices often re-pick the same
    # one), all choices of a round at once: each best choice solved, re-picked, its re-pick solved
    solved: dict[tuple[int, ...], tuple[NodeSolution, tuple[int, ...]]] = {}
    children_index = np.asarray(image_children)

    def solve(choices: list[tuple[int, ...]]) -> None:
        todo = [choice for choice in dict.fromkeys(choices) if choice not in solved]
        if not todo:
            return
        rows = stacked.first[None, :] + np.array(todo, dtype=np.intp)  # each choice's candidates' rows
        nodes = solve_children_many(children_index, stacked.A[rows], stacked.b[rows], num_children, parent_det)
        for choice, node in zip(todo, nodes):
            solved[choice] = (node, _consistent_choice(stacked, node.A_parent, node.b_parent)[0])

    firsts = sorted(hypotheses, key=lambda c: hypotheses[c])[:NUM_FULL_HYPOTHESES]
    solve(firsts)
    seconds = [solved[choice][1] for choice in firsts]
    solve(seconds)
    results: dict[tuple[int, ...], NodeSolution] = {}
    for second in seconds:
        node, choice = solved[second]
        if choice not in results or node.residual < results[choice].residual:
            results[choice] = node
    return sorted(((list(c), n) for c, n in results.items()), key=lambda item: item[1].residual)


class StackedCandidates:
    """Every observation's candidates ``(A_l, b_l)`` of a node stacked once (for :func:`_consistent_choice`
    and :func:`consistent_mirror_vectors`)."""

    def __init__(self, image_candidates: list[list[tuple[np.ndarray, np.ndarray]]]):
        counts = np.array([len(candidates) for candidates in image_candidates])
        self.A = np.array([A for candidates in image_candidates for A, _ in candidates])
        self.b = np.array([b for candidates in image_candidates for _, b in candidates])
        self.shape = (len(counts), int(counts.max()))
        self.first = np.cumsum(counts) - counts  # row of each observation's first candidate
        self.image_of = np.repeat(np.arange(len(counts)), counts)
        self.slot = np.arange(len(self.A)) - np.repeat(self.first, counts)

    def fit(self, A_parent: np.ndarray, b_parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every candidate's misfit to a parent (observations x slots, inf where an observation has fewer
        candidates) and the mirror vector of its nearest reflection (row of :attr:`A`), by
        :func:`reflection_fit` (eqs. 6-7)."""
        misfits, vectors = reflection_fit(self.A, self.b, A_parent, b_parent)
        costs = np.full(self.shape, np.inf)
        costs[self.image_of, self.slot] = misfits
        return costs, vectors


def _consistent_choice(
    stacked: StackedCandidates, A_parent: np.ndarray, b_parent: np.ndarray
) -> tuple[tuple[int, ...], float]:
    """Each image's candidate most consistent with a node's parent, and the capped total inconsistency."""
    costs, _ = stacked.fit(A_parent, b_parent)
    choice = tuple(np.argmin(costs, axis=1).tolist())
    score = float(np.sum(np.minimum(costs.min(axis=1), CONSISTENCY_CAP)))
    return choice, score


def consistent_mirror_vectors(
    stacked: StackedCandidates, children: np.ndarray, num_children: int, A_parent: np.ndarray, b_parent: np.ndarray
) -> tuple[tuple[int, ...], np.ndarray]:
    """Each observation's candidate most consistent with a parent (as :func:`_consistent_choice`) and each
    child's mirror vector (num_children, 3): the reflection from the parent to its observations' chosen
    candidates (eqs. 6-7), averaged over them (``children``: each observation's child index)."""
    costs, vectors = stacked.fit(A_parent, b_parent)
    chosen = np.argmin(costs, axis=1)
    sums = np.zeros((num_children, 3))
    np.add.at(sums, children, vectors[stacked.first + chosen])
    return tuple(chosen.tolist()), sums / np.maximum(np.bincount(children, minlength=num_children), 1)[:, None]


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
