"""Least median of squares over the placements of a node of the mirror tree (``consensus.py`` step 3).

At a node of level Nv (its children: the placements of the last mirror), each triple of children gives
the node's ``(A_{Nv-1}, b_{Nv-1})`` (eqs. 13-17), one hypothesis per choice of its images' PnP
candidates (P3P's, a planar target's twins); every image is scored by the reprojection of its fiducials
through the hypothesis and its last mirror fitted to them (:func:`fit_mirrors`, all images and
hypotheses in one Levenberg-Marquardt, from the reflection nearest to each candidate; eqs. 3, 5-9),
the best of its candidates. Where the least-median hypothesis
leaves some images far above its median, the majority's MLE (eq. 23, ``initial.refine_subtree``) judges
each image again, its mirror placement fitted to its pixels where it is not one of the majority's, and
an image still far off once more at the MLE of the majority and itself.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import replace
from itertools import combinations, product
from math import comb

import numpy as np

from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic import Hypothesis, hypothesis_of_subtree, subtree_dataset, subtree_solution
from mirror_fg.solver.result.calibration import Exclusion
from mirror_fg.solver.start.initial import refine_subtree
from mirror_fg.solver.start.peeling import (
    MIN_NORMAL_SPREAD, reflection_fit, smallest_eigenvectors, solve_children, solve_triples, spread_subset,
)

__all__ = ["CONSENSUS_MIN_SIGMAS", "CONSENSUS_FACTOR", "CONSENSUS_TRIPLES", "MIN_CHILDREN_P3P",
           "COMBINATIONS_PER_TRIPLE", "MAX_RANKING_IMAGES", "check_node", "fit_mirrors", "reflected_errors", "mirror_fit",
           "fiducial_names",
           "sample_triples"]

#: PnP candidates ``(A_Nv, b_Nv)`` of each image (by id).
Candidates = dict[str, list[tuple[np.ndarray, np.ndarray]]]

#: An image is inconsistent with its node's majority when the RMS (whitened) reprojection of its
#: fiducials through the node's consensus exceeds this many sigmas ...
CONSENSUS_MIN_SIGMAS = 20.0
#: ... and this many times the median image's.
CONSENSUS_FACTOR = 5.0
#: Triples of children tried per node (all of them when there are fewer).
CONSENSUS_TRIPLES = 40
#: A node is judged with at least four children (three are solved exactly: no majority to compare
#: against); with three-point images or a planar target's twins at least this many: every choice of
#: a triple's candidates fits those three images, so the median must be over a majority outside it.
MIN_CHILDREN_P3P = 7
#: Levenberg-Marquardt iterations at most of :func:`fit_mirrors` (each image's last mirror fitted to its
#: pixels; from the reflection nearest to its PnP pose it converges in a few).
MIRROR_FIT_ITERATIONS = 20
#: ... stopped when no mirror's cost changes by more than this fraction in an iteration (a score to judge
#: by, not an estimate: its RMS to ~1e-4).
MIRROR_FIT_TOLERANCE = 1e-4
#: A node with more images ranks its hypotheses on this many spread over them, through the reflection
#: nearest to each PnP candidate (the least median needs a sample, not every image, nor their mirrors
#: fitted); the best hypothesis then scores every image, fitted: bounds a node of hundreds.
MAX_RANKING_IMAGES = 64
#: Per triple, the choices of its children's PnP candidates (P3P's, a planar target's twins) kept as
#: hypotheses: those with the lowest residual of eqs. (13) and (16).
COMBINATIONS_PER_TRIPLE = 2


def sample_triples(children: Sequence[int], limit: int, rng: np.random.Generator) -> list[tuple[int, ...]]:
    """Every triple of ``children`` when there are at most ``limit``, else ``limit`` distinct ones drawn at
    random (never all of them listed: 300 children have 4.5 million triples)."""
    count = len(children)
    if comb(count, 3) <= limit:
        return list(combinations(children, 3))
    drawn: dict[tuple[int, ...], None] = {}
    while len(drawn) < limit:
        drawn[tuple(children[k] for k in sorted(rng.choice(count, size=3, replace=False)))] = None
    return list(drawn)


def fiducial_names(dataset: Dataset, image: Image) -> list[str]:
    """The image's observations that are of fiducials, in the image's order."""
    return [name for name in image.observations if name in dataset.fiducials]


class _NodeObservations:
    """A node's images flattened once: every PnP candidate of each image with a copy of the image's fiducial
    observations (whitened later). ``owner[c]``: the image (index into ``images``) of candidate ``c``."""

    def __init__(self, dataset: Dataset, images: list[Image], candidates: Candidates):
        self.sigma = dataset.normalized_sigma
        self.num_images = len(images)
        A: list[np.ndarray] = []
        b: list[np.ndarray] = []
        owner: list[int] = []
        first_row: list[int] = []  # per candidate: its image's first fiducial (row of ``points``) and how many
        count: list[int] = []
        points: list[np.ndarray] = []
        observed: list[np.ndarray] = []
        names_of: dict[tuple[str, ...], list[str]] = {}  # the fiducials among an image's observed names
        for k, image in enumerate(images):
            observed_names = tuple(image.observations)
            names = names_of.get(observed_names)
            if names is None:
                names = names_of[observed_names] = fiducial_names(dataset, image)
            normalized = dataset.normalized(image)
            start = len(points)
            points.extend(dataset.fiducials[name] for name in names)
            observed.extend(normalized[name] for name in names)
            for A_c, b_c in candidates[image.id]:
                A.append(A_c)
                b.append(b_c)
                owner.append(k)
                first_row.append(start)
                count.append(len(names))
        self.A, self.b = np.array(A).reshape(-1, 3, 3), np.array(b).reshape(-1, 3)
        self.owner = np.array(owner, dtype=np.intp)
        counts = np.array(count, dtype=np.intp)
        self.index = np.repeat(np.arange(len(counts)), counts)  # each copied fiducial's candidate
        # each candidate's copy of its image's fiducials and observations (one gather: the same values)
        rows = np.repeat(np.array(first_row, dtype=np.intp) - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
        self.points = np.array(points, dtype=float).reshape(-1, 3)[rows]
        self.observed = np.array(observed, dtype=float).reshape(-1, 2)[rows]
        self.counts = np.maximum(np.bincount(self.index, minlength=len(self.A)), 1)
        # candidates sorted by image: the index of each image's first (its best is first after a lexsort)
        self.first_candidate = np.searchsorted(self.owner, np.arange(self.num_images))

    def subset(self, images: np.ndarray) -> _NodeObservations:
        """The same of some of the images (indices into ``images``, increasing), as built from them alone."""
        keep = np.isin(self.owner, images)
        rows = np.isin(self.index, np.flatnonzero(keep))
        out = object.__new__(_NodeObservations)
        out.sigma, out.num_images = self.sigma, len(images)
        out.A, out.b = self.A[keep], self.b[keep]
        out.owner = np.searchsorted(images, self.owner[keep])
        out.index = np.searchsorted(np.flatnonzero(keep), self.index[rows])
        out.points, out.observed = self.points[rows], self.observed[rows]
        out.counts = self.counts[keep]
        out.first_candidate = np.searchsorted(out.owner, np.arange(out.num_images))
        return out

    def scores(self, A_parents: np.ndarray, b_parents: np.ndarray, fit: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """For each of H hypotheses ``(A_{Nv-1}, b_{Nv-1})`` of the node (stacked (H, 3, 3), (H, 3)) and
        each image, the RMS whitened reprojection of its fiducials through the hypothesis and its last
        mirror fitted to them (:func:`fit_mirrors`, from the reflection nearest to each PnP candidate;
        eqs. 6-7, 3, 5, 9; huge behind the camera), the best of its candidates (H, images), and which
        candidate (index into ``self.A``) that is (H, images). All hypotheses in one fit; ``fit=False``:
        through the reflection nearest to each candidate as it is (a ranking, cheaper)."""
        num_hypotheses, num_candidates = len(A_parents), len(self.A)
        starts = reflection_fit(np.tile(self.A, (num_hypotheses, 1, 1)), np.tile(self.b, (num_hypotheses, 1)),
                                np.repeat(A_parents, num_candidates, axis=0), np.repeat(b_parents, num_candidates, axis=0))[1]
        before = (np.einsum("hab,rb->hra", A_parents, self.points) + b_parents[:, None, :]).reshape(-1, 3)  # eq. (5)
        index = (np.arange(num_hypotheses)[:, None] * num_candidates + self.index[None, :]).ravel()
        _, squared = fit_mirrors(before, index, np.tile(self.observed, (num_hypotheses, 1)), self.sigma, starts,
                                 MIRROR_FIT_ITERATIONS if fit else 0)
        counts = np.tile(self.counts, num_hypotheses)
        rms = np.sqrt(np.bincount(index, weights=squared, minlength=num_hypotheses * num_candidates) / counts)
        rms = rms.reshape(num_hypotheses, num_candidates)
        order = np.lexsort((rms, np.broadcast_to(self.owner, rms.shape)), axis=-1)  # by image, then by score
        best = order[:, self.first_candidate]
        return np.take_along_axis(rms, best, axis=1), best


def reflected_errors(
    before: np.ndarray, vectors: np.ndarray, observed: np.ndarray, sigma: np.ndarray, jacobians: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """Whitened reprojection errors (R, 2) of points ``before`` (R, 3, camera frame) reflected by their
    rows' mirror vectors ``vectors`` (R, 3) (eq. 3) and projected (from a depth of at least 1e-9); when
    asked, their Jacobians with respect to the vectors (2, R, 3: the x rows, then the y rows)."""
    vv = np.einsum("ra,ra->r", vectors, vectors)
    vx = np.einsum("ra,ra->r", vectors, before)
    scale = 2.0 * (1.0 - vx / vv)
    seen = before + scale[:, None] * vectors  # x - 2 ((v.x - v.v) / v.v) v, eq. (3)
    depth = seen[:, 2]
    inverse_depth = 1.0 / np.maximum(depth, 1e-9)
    projected = seen[:, :2] * inverse_depth[:, None]
    errors = (projected - observed) / sigma
    if not jacobians:
        return errors, None
    # d seen / d v = scale I + v w^T with w = -(2 / v.v) x + (4 v.x / (v.v)^2) v; the projection's
    # derivative row for u = x / z is (1, 0, -u) / z (and for y alike): row . (scale I + v w^T).
    w = (-2.0 / vv)[:, None] * before + (4.0 * vx / vv**2)[:, None] * vectors
    jacobian = np.empty((2, len(seen), 3))
    for e in range(2):
        row = np.zeros((len(seen), 3))
        row[:, e] = inverse_depth
        row[:, 2] = -projected[:, e] * inverse_depth
        row_v = np.einsum("ra,ra->r", row, vectors)
        jacobian[e] = (scale[:, None] * row + row_v[:, None] * w) / sigma[e]
    return errors, jacobian


#: The upper triangle of a symmetric 3x3 matrix (its rows and columns), and where each of its nine
#: entries is in it.
_UPPER_A, _UPPER_B = np.triu_indices(3)
_SYMMETRIC = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])


def fit_mirrors(
    before: np.ndarray, index: np.ndarray, observed: np.ndarray, sigma: np.ndarray, vectors: np.ndarray,
    iterations: int = MIRROR_FIT_ITERATIONS,
) -> tuple[np.ndarray, np.ndarray]:
    """Each mirror vector (K, 3, camera frame, metres) fitted by Levenberg-Marquardt, all at once, so that
    its points reflect onto their observations: point r (``before`` (R, 3): camera-frame position before
    the mirror) belongs to mirror ``index[r]`` and is seen at ``observed[r]`` (normalized, sigma (2,)).
    Returns the fitted vectors and each point's squared whitened error (a point behind the camera is
    projected from a depth of 1e-9: its error is huge, and finite)."""
    vectors = np.array(vectors, dtype=float)
    count = len(vectors)

    def squared_of(errors: np.ndarray) -> np.ndarray:
        return errors[:, 0] ** 2 + errors[:, 1] ** 2  # behind the camera: at a clamped depth, huge but finite

    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        squared = squared_of(reflected_errors(before, vectors[index], observed, sigma, False)[0])
        cost = np.bincount(index, weights=squared, minlength=count)
        damping = np.full(count, 1e-3)
        active = np.ones(count, dtype=bool)  # the mirrors still moving: only their points are evaluated
        for _ in range(iterations):
            mirrors = np.flatnonzero(active)
            rows = np.flatnonzero(active[index])
            local = np.empty(count, dtype=np.intp)
            local[mirrors] = np.arange(len(mirrors))
            owner = local[index[rows]]

            def per_mirror(values: np.ndarray) -> np.ndarray:  # (rows, n) summed per active mirror
                return np.stack([np.bincount(owner, weights=values[:, k], minlength=len(mirrors))
                                 for k in range(values.shape[1])], axis=1)

            errors, jacobian = reflected_errors(before[rows], vectors[index[rows]], observed[rows], sigma, True)
            assert jacobian is not None
            jx, jy = jacobian
            upper = per_mirror(jx[:, _UPPER_A] * jx[:, _UPPER_B] + jy[:, _UPPER_A] * jy[:, _UPPER_B])  # J^T J, 6 of 9
            hessian = upper[:, _SYMMETRIC].reshape(-1, 3, 3)
            gradient = per_mirror(jx * errors[:, :1] + jy * errors[:, 1:])
            diagonal = np.maximum(np.einsum("kaa->ka", hessian), 1e-30)
            damped = hessian + (damping[mirrors, None] * diagonal)[:, :, None] * np.eye(3)
            try:
                step = np.linalg.solve(damped, -gradient[..., None])[..., 0]
            except np.linalg.LinAlgError:  # a singular system somewhere (a mirror through its points)
                step = np.einsum("kab,kb->ka", np.linalg.pinv(np.nan_to_num(damped)), -np.nan_to_num(gradient))
            trial = vectors[mirrors] + np.where(np.isfinite(step), step, 0.0)
            trial_squared = squared_of(reflected_errors(before[rows], trial[owner], observed[rows], sigma, False)[0])
            trial_cost = np.bincount(owner, weights=trial_squared, minlength=len(mirrors))
            better = trial_cost < cost[mirrors]
            vectors[mirrors[better]] = trial[better]
            taken = better[owner]
            squared[rows[taken]] = trial_squared[taken]
            active[mirrors] = np.abs(trial_cost - cost[mirrors]) > MIRROR_FIT_TOLERANCE * cost[mirrors]
            cost[mirrors[better]] = trial_cost[better]
            damping[mirrors] = np.where(better, damping[mirrors] * 0.1, damping[mirrors] * 10.0)
            if not active.any():
                break
    return vectors, squared


def _hypotheses(
    images: list[Image], candidates: Candidates, triples: Sequence[tuple[int, ...]],
    parent_det: float, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """The node's ``(A_{Nv-1}, b_{Nv-1})`` (stacked) from each triple of children (eqs. 13-17), one image of
    each child picked at random, solved at once for every choice of their PnP candidates; per triple the
    ``COMBINATIONS_PER_TRIPLE`` choices with the lowest residual, where the three mirrors' normals are not
    nearly coplanar."""
    by_child: dict[int, list[Image]] = defaultdict(list)
    for image in images:
        by_child[image.mirror_configs[-1]].append(image)
    poses: dict[str, int] = {}  # each image drawn: the row of its first candidate in the stacks below
    stacked_A: list[np.ndarray] = []
    stacked_b: list[np.ndarray] = []
    combos: list[tuple[int, ...]] = []  # per hypothesis: the rows of its three children's candidates
    owner: list[int] = []
    for t, triple in enumerate(triples):
        picks = []
        for c in triple:
            image_id = by_child[c][int(rng.integers(len(by_child[c])))].id
            if image_id not in poses:
                poses[image_id] = len(stacked_A)
                stacked_A.extend(A for A, _ in candidates[image_id])
                stacked_b.extend(b for _, b in candidates[image_id])
            picks.append(range(poses[image_id], poses[image_id] + len(candidates[image_id])))
        for choice in product(*picks):
            combos.append(choice)
            owner.append(t)
    if not combos:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    chosen = np.array(combos, dtype=np.intp)
    rotations_array: np.ndarray = np.array(stacked_A)[chosen]
    offsets_array: np.ndarray = np.array(stacked_b)[chosen]
    A_parent, b_parent, residual = solve_triples(rotations_array, offsets_array, parent_det)
    owner_array = np.array(owner)
    order = np.lexsort((residual, owner_array))
    rank = np.empty(len(order), dtype=int)
    firsts = np.searchsorted(owner_array[order], owner_array[order])
    rank[order] = np.arange(len(order)) - firsts
    keep = np.flatnonzero(rank < COMBINATIONS_PER_TRIPLE)
    # the three mirrors' normals (eq. 13: the -1 eigenvector of A_l A_{l-1}^T) must not be nearly coplanar
    M = rotations_array[keep] @ np.swapaxes(A_parent[keep], -1, -2)[:, None]
    normals = smallest_eigenvectors(0.5 * (M + np.swapaxes(M, -1, -2)).reshape(-1, 3, 3)).reshape(-1, 3, 3)
    spread = np.linalg.svd(normals, compute_uv=False)[:, 2] if len(keep) else np.zeros(0)
    keep = keep[spread >= MIN_NORMAL_SPREAD]
    return A_parent[keep], b_parent[keep]


def check_node(
    dataset: Dataset, prefix: tuple[int, ...], images: list[Image], candidates: Candidates,
    rng: np.random.Generator,
) -> tuple[list[Exclusion], dict[str, int]]:
    """Least median of squares over triples of a level-Nv node's children: the images inconsistent with it,
    and the candidate (index into the image's) each image is best explained by."""
    children = sorted({im.mirror_configs[-1] for im in images})
    three_point = any(len(candidates[im.id]) > 1 or len(fiducial_names(dataset, im)) == 3 for im in images)
    if len(children) < (MIN_CHILDREN_P3P if three_point else 4):  # no majority to compare against
        return [], {}
    parent_det = (-1.0) ** (dataset.num_mirrors - 1)
    triples = sample_triples(children, CONSENSUS_TRIPLES, rng)
    A_parents, b_parents = _hypotheses(images, candidates, triples, parent_det, rng)
    if len(A_parents) == 0:
        return [], {}
    observations = _NodeObservations(dataset, images, candidates)
    if len(images) > MAX_RANKING_IMAGES:  # the hypotheses ranked on spread images, the best one judges all
        ranked = observations.subset(spread_subset(len(images), MAX_RANKING_IMAGES)).scores(A_parents, b_parents,
                                                                                             fit=False)[0]
        best = int(np.argmin(np.median(ranked, axis=1)))
        A_parents, b_parents = A_parents[best:best + 1], b_parents[best:best + 1]
    all_scores, all_chosen = observations.scores(A_parents, b_parents)
    medians = np.median(all_scores, axis=1)
    best = int(np.argmin(medians))  # the first of equal medians, as one at a time
    median, scores, chosen = float(medians[best]), all_scores[best], all_chosen[best]
    first = observations.first_candidate
    choice = {im.id: int(chosen[k] - first[k]) for k, im in enumerate(images)}
    inliers = scores <= max(CONSENSUS_MIN_SIGMAS, CONSENSUS_FACTOR * median)
    if np.all(inliers):
        return [], choice
    # The closed form of a few placements is too coarse to judge an image by (real photographs: tens of
    # sigma); the majority's MLE (eq. 23) judges each image, the others with their mirror fitted alone.
    chosen_poses = {im.id: candidates[im.id][choice[im.id]] for im in images}
    refined = _refined_scores(dataset, images, chosen_poses, candidates, inliers)
    if refined is None:
        return [], choice
    scores, median, threshold = refined
    where = "" if not prefix else " under " + ", ".join(f"mirror {l + 1} placement {m}" for l, m in enumerate(prefix))
    return [
        Exclusion(im.id, f"inconsistent with the other placements of mirror {dataset.num_mirrors}{where} "
                         f"({_sigmas(score)}, the majority {median:.3g} sigma)", None,
                  float(score) if np.isfinite(score) else None)
        for im, score in zip(images, scores) if not score <= threshold
    ], choice


def _refined_scores(
    dataset: Dataset, images: list[Image], poses: dict[str, tuple[np.ndarray, np.ndarray]],
    candidates: Candidates, inliers: np.ndarray,
) -> tuple[np.ndarray, float, float] | None:
    """RMS whitened reprojection of each image's fiducials at the MLE of the inlier images' subtree
    (``initial.refine_subtree``, started from their ``poses``), an outlier image's mirror placement fitted
    alone (from each of its PnP ``candidates``) on that node; the inliers' median and the threshold above
    which an image is inconsistent. An outlier above it is scored again at the MLE of the inliers and
    itself: a node of a few placements is too loosely determined to judge an image by its fit to them
    alone, and an image the model fits is never left out. None when the inliers do not determine the node."""
    level = dataset.num_mirrors
    kept = [im for im, ok in zip(images, inliers) if ok]
    children = sorted({im.mirror_configs[-1] for im in kept})
    if len(children) < 3:
        return None
    parent_det = (-1.0) ** (level - 1)
    index_of = {m: k for k, m in enumerate(children)}
    node = solve_children([(index_of[im.mirror_configs[-1]], *poses[im.id]) for im in kept], len(children), parent_det)
    hypothesis = Hypothesis(node.A_parent, node.b_parent, {(level, m): [v] for m, v in zip(children, node.mirror_vectors)}, {})
    refined = refine_subtree(subtree_dataset(dataset, kept, level), subtree_solution(hypothesis, level))
    if refined is None:
        return None
    back = hypothesis_of_subtree(refined[1], hypothesis, level)
    mirror = {m: back.mirror_vectors[(level, m)][0] for m in children}
    fits = [mirror_fit(dataset, image, [poses[image.id]] if ok else candidates[image.id], back.A, back.b,
                        mirror.get(image.mirror_configs[-1]))
            for image, ok in zip(images, inliers)]
    scores = np.array([score for score, _ in fits])
    median = float(np.median(scores[inliers]))
    threshold = max(CONSENSUS_MIN_SIGMAS, CONSENSUS_FACTOR * median)
    for k, (image, ok) in enumerate(zip(images, inliers)):
        if ok or scores[k] <= threshold or not np.all(np.isfinite(fits[k][1])):
            continue
        start = replace(refined[1], mirror_vectors={**refined[1].mirror_vectors, (1, image.mirror_configs[-1]): fits[k][1]})
        joint = refine_subtree(subtree_dataset(dataset, [*kept, image], level), start)
        if joint is not None:
            together = hypothesis_of_subtree(joint[1], hypothesis, level)
            scores[k] = mirror_fit(dataset, image, [], together.A, together.b,
                                    together.mirror_vectors[(level, image.mirror_configs[-1])][0])[0]
    return scores, median, threshold


def _sigmas(rms: float) -> str:
    return f"{rms:.3g} sigma RMS" if rms < 1e6 else "its fiducials fall behind the camera or a mirror"


def mirror_fit(
    dataset: Dataset, image: Image, poses: list[tuple[np.ndarray, np.ndarray]], A_parent: np.ndarray,
    b_parent: np.ndarray, mirror_vector: np.ndarray | None,
) -> tuple[float, np.ndarray]:
    """``consensus.misfit_sigmas`` and the mirror vector it is at (the given one, or the best fit)."""
    names = fiducial_names(dataset, image)
    points = np.array([dataset.fiducials[n] for n in names])
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])

    before = points @ A_parent.T + b_parent  # before the last mirror (eq. 5)
    if mirror_vector is not None:
        starts = np.asarray(mirror_vector, dtype=float).reshape(1, 3)
        iterations = 0
    else:
        starts = reflection_fit(np.array([A for A, _ in poses]).reshape(-1, 3, 3),
                                np.array([b for _, b in poses]).reshape(-1, 3), A_parent, b_parent)[1]
        iterations = MIRROR_FIT_ITERATIONS
    if len(starts) == 0:
        return float("inf"), np.full(3, np.nan)
    index = np.repeat(np.arange(len(starts)), len(points))
    vectors, squared = fit_mirrors(np.tile(before, (len(starts), 1)), index, np.tile(observed, (len(starts), 1)),
                                   dataset.normalized_sigma, starts, iterations)
    rms = np.sqrt(np.bincount(index, weights=squared, minlength=len(starts)) / len(points))
    best = int(np.argmin(rms))
    return float(rms[best]), vectors[best]
