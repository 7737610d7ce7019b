"""Analytical solution (Hesch et al., Sects. 4-5, eqs. 10-20): PnP per image, mirror peeling, points.

Everything is in the camera frame {C} (metres) except base-frame points. Configuration ``(l, m)`` is
placement ``m`` of mirror ``l`` (1-based). A *node* at level ``l`` is a prefix ``(c_1, ..., c_{l-1})`` of
mirror configurations; its children are the configurations of mirror ``l`` seen under it.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from itertools import combinations, product

import cv2
import numpy as np

from mirror_fg.dataset import Dataset, DatasetError, Image
from mirror_fg.geometry import FLIP_Y, apply_transform, nested_transform, project, project_to_orthogonal

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


class SolveError(RuntimeError):
    """The data cannot be solved (degenerate geometry, PnP failure, no convergence): exit status 3."""


@dataclass
class AnalyticSolution:
    """Closed-form estimate of every unknown.

    ``R_cam_base``, ``t_cam_base``: camera <- base (``Cp = R Bp + t``, metres). ``mirror_vectors``:
    ``(l, m) -> v`` (camera frame, metres). ``points``: reconstruction points, base frame, metres.
    ``image_transforms``: the PnP ``(A_Nv, b_Nv)`` chosen for each image that had one.
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray] = field(default_factory=dict)
    image_transforms: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


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


def _normals_from_pairwise_axes(child_A: list[np.ndarray]) -> np.ndarray:
    """Unit normals (K, 3) of K mirror placements from the axes of ``A_m A_m'^T`` (eqs. 14-15).

    Eq. (15) crosses two axes; with more children each normal is the direction most perpendicular
    to all of its axes (least squares, weighted by how well each axis is defined).
    """
    A = np.stack(child_A)
    Q = np.einsum("iab,jcb->ijac", A, A)  # A_m A_m'^T, eq. (14)
    axes = np.stack(
        [Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1
    )
    # the smallest right singular vector of each child's stacked axes (its own axis is zero)
    scatter = np.einsum("mja,mjb->mab", axes, axes)
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
    child_A = [project_to_orthogonal(child_sums[k], -parent_det) for k in range(num_children)]
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
    b_parent = np.linalg.solve(projectors.sum(axis=0), np.einsum("iab,ib->a", projectors, offsets))
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
) -> list[int]:
    """Pick one PnP candidate per image of a node without enumerating all combinations.

    Minimal triples of children are solved over every candidate combination, each keeping the one
    with the lowest residual of eq. (16); each such hypothesis then scores how many images have a
    candidate consistent with it (robustly capped), and the best hypothesis picks every image's
    candidate by consistency.
    """
    if all(len(c) == 1 for c in image_candidates):
        return [0] * len(image_candidates)
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
        best_node, best_residual = None, np.inf
        for combo in product(*(range(len(image_candidates[i])) for i in images)):
            observations = [(j, *image_candidates[i][c]) for j, (i, c) in enumerate(zip(images, combo))]
            node = _solve_node(observations, 3, parent_det)
            if node.residual < best_residual:
                best_node, best_residual = node, node.residual
        if best_node is not None:
            choice, score = _consistent_choice(image_candidates, best_node)
            hypotheses[choice] = min(score, hypotheses.get(choice, np.inf))
    # A distant target's P3P "twin" can be consistent across many images on its own, so the best
    # few hypotheses are judged by the residual of eqs. (13) and (16) over every child, and the
    # winner's candidates are re-picked by consistency with that full solution.
    best_choice, best_residual = None, np.inf
    for choice in sorted(hypotheses, key=hypotheses.get)[:NUM_FULL_HYPOTHESES]:
        for _ in range(2):
            observations = [(k, *candidates[c]) for k, candidates, c in zip(image_children, image_candidates, choice)]
            node = _solve_node(observations, num_children, parent_det)
            choice, _ = _consistent_choice(image_candidates, node)
        if node.residual < best_residual:
            best_choice, best_residual = list(choice), node.residual
    assert best_choice is not None
    return best_choice


def _consistent_choice(
    image_candidates: list[list[tuple[np.ndarray, np.ndarray]]], node: _NodeSolution
) -> tuple[tuple[int, ...], float]:
    """Each image's candidate most consistent with a node's parent, and the capped total inconsistency."""
    counts = [len(candidates) for candidates in image_candidates]
    A = np.array([A for candidates in image_candidates for A, _ in candidates])
    b = np.array([b for candidates in image_candidates for _, b in candidates])
    costs = np.split(reflection_fit(A, b, node.A_parent, node.b_parent)[0], np.cumsum(counts)[:-1])
    choice = tuple(int(np.argmin(c)) for c in costs)
    score = float(sum(min(float(np.min(c)), CONSISTENCY_CAP) for c in costs))
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
    (several for P3P); parent_det: ``det A_{l-1} = (-1)^(l-1)``. Returns the picks and the solution
    (``A_parent``, ``b_parent``, ``mirror_vectors`` per child, ``residual``).
    """
    picks = _choose_candidates(children, candidates, num_children, parent_det, rng)
    observations = [(k, *cands[p]) for k, cands, p in zip(children, candidates, picks)]
    return picks, _solve_node(observations, num_children, parent_det)


def _describe(prefix: tuple[int, ...]) -> str:
    if not prefix:
        return "the root (no mirror placed)"
    return "placement " + ", ".join(f"({l + 1}, {m})" for l, m in enumerate(prefix))


def solve_analytic(dataset: Dataset, seed: int = 0) -> AnalyticSolution:
    """Closed-form camera-to-base transform, mirror vectors and reconstruction points (Sects. 4-5).

    Raises ``DatasetError`` when the mirror schedule cannot support a solution (a placement with fewer
    than three child placements, a configuration only seen without three fiducials, a point seen in
    fewer than two images) and ``SolveError`` for degenerate geometry or PnP failure.
    """
    rng = np.random.default_rng(seed)
    Nv = dataset.num_mirrors
    # Sect. 4.1: (A_Nv, b_Nv) candidates per image from its fiducials.
    leaf_candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for image in dataset.images:
        normalized = dataset.normalized(image)
        names = [n for n in image.observations if n in dataset.fiducials]
        if len(names) < 3:
            continue
        base_points = np.array([dataset.fiducials[n] for n in names])
        observed = np.array([normalized[n] for n in names])
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

    estimates: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
    chosen: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    # Level Nv: observations are images; the node is the prefix of the first Nv-1 configurations.
    level_obs: dict[tuple[int, ...], list[tuple[int, list[tuple[np.ndarray, np.ndarray]], str | None]]] = defaultdict(list)
    for im in images:
        level_obs[im.mirror_configs[:-1]].append((im.mirror_configs[-1], leaf_candidates[im.id], im.id))
    for level in range(Nv, 0, -1):
        parent_det = (-1.0) ** (level - 1)
        next_obs: dict[tuple[int, ...], list] = defaultdict(list)
        for prefix in sorted(level_obs):
            entries = level_obs[prefix]
            child_ids = sorted({m for m, _, _ in entries})
            if len(child_ids) < 3:
                raise DatasetError(
                    f"{dataset.source}: {_describe(prefix)} has {len(child_ids)} placement(s) of mirror {level} "
                    f"under it ({', '.join(str(m) for m in child_ids)}); the analytical solution needs >= 3"
                )
            index_of = {m: k for k, m in enumerate(child_ids)}
            children = [index_of[m] for m, _, _ in entries]
            picks, node = solve_node(children, [c for _, c, _ in entries], len(child_ids), parent_det, rng)
            for entry, p in zip(entries, picks):
                if entry[2] is not None:
                    chosen[entry[2]] = entry[1][p]
            normals = np.stack([v / np.linalg.norm(v) for v in node.mirror_vectors])
            singular = np.linalg.svd(normals, compute_uv=False)
            if singular[2] < MIN_NORMAL_SPREAD:
                listed = ", ".join(f"({level}, {m})" for m in child_ids)
                raise SolveError(
                    f"{dataset.source}: under {_describe(prefix)}, the normals of mirror {level} placements "
                    f"{listed} are nearly coplanar; move the mirror about a second axis"
                )
            for m, v in zip(child_ids, node.mirror_vectors):
                estimates[(level, m)].append(v)
            if level > 1:
                next_obs[prefix[:-1]].append((prefix[-1], [(node.A_parent, node.b_parent)], None))
            else:
                root = node
        level_obs = next_obs
    mirror_vectors = {key: np.mean(vs, axis=0) for key, vs in estimates.items()}
    solution = AnalyticSolution(
        R_cam_base=project_to_orthogonal(root.A_parent, 1.0),
        t_cam_base=root.b_parent,
        mirror_vectors=mirror_vectors,
        image_transforms=chosen,
    )
    solution.points = reconstruct_points(dataset, solution)
    return solution


# --- Reconstruction points (Sect. 5, eqs. 19-20) --------------------------------------------------


def triangulate_point(transforms: list[tuple[np.ndarray, np.ndarray]], normalized: list[np.ndarray]) -> np.ndarray:
    """Base-frame point from >= 2 images: ``s_j u_j = A_j Bp + b_j`` solved in least squares (eq. 20).

    The depths ``s_j`` are eliminated exactly: for a unit ray ``u_j`` the least-squares residual of
    image j is ``(I - u_j u_j^T)(A_j Bp + b_j)``, so eq. (20) reduces to a 3x3 normal equation.
    """
    normal_matrix = np.zeros((3, 3))
    rhs = np.zeros(3)
    for (A, b), z in zip(transforms, normalized):
        ray = np.array([z[0], z[1], 1.0])
        ray /= np.linalg.norm(ray)  # eq. (19)
        projector = np.eye(3) - np.outer(ray, ray)
        normal_matrix += A.T @ projector @ A
        rhs -= A.T @ projector @ b
    return np.linalg.solve(normal_matrix, rhs)


def image_transform(solution: AnalyticSolution, image: Image) -> tuple[np.ndarray, np.ndarray]:
    """``(A_Nv, b_Nv)`` of an image from the solved pose and mirror vectors (eqs. 6-7)."""
    vectors = [solution.mirror_vectors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)]
    return nested_transform(solution.R_cam_base, solution.t_cam_base, vectors)


def reconstruct_points(dataset: Dataset, solution: AnalyticSolution) -> dict[str, np.ndarray]:
    """Every reconstruction point by eq. (20) from all images that see it."""
    seen: dict[str, list[Image]] = defaultdict(list)
    for image in dataset.images:
        for name in image.observations:
            if name not in dataset.fiducials:
                seen[name].append(image)
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
        rays = [dataset.normalized(im)[name] for im in images]
        points[name] = triangulate_point([transforms[im.id] for im in images], rays)
    return points
