"""Consensus before the solve and a final check after it (issue 15): images or measurements that do not
agree with the rest are left out, each named with its reason, instead of sinking the calibration.

Before the solve (:func:`screen`), on images with >= 4 fiducials (three leave P3P twins and no check):

1. Per image: the PnP of its fiducials (Sect. 4.1, eq. 10) must reproject them within
   ``PNP_POINT_SIGMAS``. Where it does not, RANSAC PnP (cv2) finds the fiducials that agree; a few
   gross ones are left out as measurements, and an image where many disagree (a shuffled row, a wrong
   corner order) is left out whole.
2. Planar fiducials (a board): every image must see the board from the side most images see it from.
   A chessboard labelled with its rows (or columns) in reverse order fits PnP exactly, seen from behind.
3. Per node of the mirror tree at level Nv (its children: the placements of the last mirror): least
   median of squares over triples of children. Each triple gives the node's ``(A_{Nv-1}, b_{Nv-1})``
   (eqs. 13-17); every image is scored by the reprojection of its fiducials through the reflection
   nearest to its PnP pose (eqs. 5-9); images far above the least-median triple's median are left out
   (a half-turned board fits PnP but no mirror placement).

After LM (:func:`final_check`): measurements above ``FINAL_SIGMAS``, or whole images where many of
their measurements are, are left out and the caller solves again.

Nothing left out is dropped silently: every image or measurement is an
:class:`~mirror_fg.solver.calibration.Exclusion` with its reason and residual.
"""
from __future__ import annotations

from dataclasses import replace

import logging
from collections import defaultdict
from itertools import combinations

import numpy as np

from mirror_fg.core.geometry import apply_transform, predict_camera_points, reflect_transforms
from mirror_fg.io.dataset import Dataset, Image
from mirror_fg.solver.analytic import Hypothesis, hypothesis_of_subtree, subtree_dataset, subtree_solution
from mirror_fg.solver.calibration import Exclusion
from mirror_fg.solver.graph import Measurement
from mirror_fg.solver.peeling import MIN_NORMAL_SPREAD, reflection_fit, solve_children
from mirror_fg.solver.initial import refine_subtree
from mirror_fg.solver.lm import plausible
from mirror_fg.solver.pnp import pnp_candidates

__all__ = [
    "PNP_POINT_SIGMAS", "MAX_BAD_POINT_FRACTION", "CONSENSUS_MIN_SIGMAS", "CONSENSUS_FACTOR", "FINAL_SIGMAS",
    "screen", "final_check", "without", "check_image", "board_side", "misfit_sigmas", "fit_last_mirror",
]

logger = logging.getLogger("mirror_fg")

#: A fiducial further than this (whitened norm) from its image's PnP fit is a gross error.
PNP_POINT_SIGMAS = 10.0
#: An image with more than this fraction of gross fiducials is left out whole (its labelling is wrong).
MAX_BAD_POINT_FRACTION = 0.1
#: An image is inconsistent with its node's majority when the RMS (whitened) reprojection of its
#: fiducials through the node's consensus exceeds this many sigmas ...
CONSENSUS_MIN_SIGMAS = 20.0
#: ... and this many times the median image's.
CONSENSUS_FACTOR = 5.0
#: Triples of children tried per node (all of them when there are fewer).
CONSENSUS_TRIPLES = 40
#: After LM, a measurement above this whitened residual is left out and the solve repeated.
FINAL_SIGMAS = 10.0
#: The final check leaves nothing out when more than this fraction of the measurements are above
#: ``FINAL_SIGMAS``: that is a wrong minimum or a wrong sigma, not a few outliers.
FINAL_MAX_FRACTION = 0.2


def _unit(dataset: Dataset) -> str:
    return "px" if dataset.camera is not None else "(normalized)"


def _fiducial_names(dataset: Dataset, image: Image) -> list[str]:
    return [name for name in image.observations if name in dataset.fiducials]


def _whitened_errors(dataset: Dataset, A: np.ndarray, b: np.ndarray, points: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Whitened reprojection error norm of each point under ``(A, b)`` (eqs. 5, 9); inf behind the camera."""
    camera_points = apply_transform(A, b, points)
    depth = camera_points[:, 2]
    predicted = camera_points[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
    errors = np.linalg.norm((predicted - observed) / dataset.normalized_sigma, axis=1)
    return np.where(depth > 0, errors, np.inf)


def _ransac_inliers(points: np.ndarray, observed: np.ndarray, num_mirrors: int, threshold: float) -> np.ndarray | None:
    """Indices of the fiducials that agree with cv2's RANSAC PnP (normalized coordinates), or None."""
    import cv2  # imported where used: OpenCV is slow to load (issue 27)

    image_points = np.array(observed, dtype=np.float64)
    if num_mirrors % 2 == 1:
        image_points[:, 1] *= -1.0  # eq. (11): PnP sees a rotation
    cv2.setRNGSeed(0)
    try:
        ok, _, _, inliers = cv2.solvePnPRansac(
            np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3), image_points.reshape(-1, 1, 2),
            np.eye(3), None, iterationsCount=500, reprojectionError=threshold, confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error:
        return None
    if not ok or inliers is None or len(inliers) < 4:
        return None
    return np.sort(inliers.reshape(-1))


def _check_pnp(
    dataset: Dataset, image: Image, names: list[str]
) -> tuple[tuple[np.ndarray, np.ndarray] | None, list[Exclusion], Exclusion | None]:
    """Per-image check: its PnP pose (None if left out), the fiducials left out, or the image left out."""
    points = np.array([dataset.fiducials[n] for n in names])
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])
    candidates = pnp_candidates(points, observed, dataset.num_mirrors)
    errors = _whitened_errors(dataset, *candidates[0], points, observed) if candidates else np.full(len(names), np.inf)
    if np.all(errors <= PNP_POINT_SIGMAS):
        return candidates[0], [], None
    finite = errors[np.isfinite(errors)]
    rms = float(np.sqrt(np.mean(finite**2))) if len(finite) else float("inf")
    threshold = PNP_POINT_SIGMAS * float(np.mean(dataset.normalized_sigma))
    inliers = _ransac_inliers(points, observed, dataset.num_mirrors, threshold)
    pose = None
    if inliers is not None and len(inliers) >= max(4, len(names) // 2):  # then judged by the refit's errors
        refit = pnp_candidates(points[inliers], observed[inliers], dataset.num_mirrors)
        if refit:
            pose = refit[0]
            errors = _whitened_errors(dataset, *pose, points, observed)
    bad = np.flatnonzero(~(errors <= PNP_POINT_SIGMAS))
    if pose is None or len(bad) > MAX_BAD_POINT_FRACTION * len(names):
        reason = (f"PnP reprojection {rms * dataset.pixel_sigma:.3g} {_unit(dataset)} RMS over its {len(names)} "
                  "fiducials (board order wrong?)" if np.isfinite(rms)
                  else "PnP found no pose with every fiducial in front of the camera")
        return None, [], Exclusion(image.id, reason, None, rms)
    points_out = [
        Exclusion(image.id, f"{errors[i] * dataset.pixel_sigma:.3g} {_unit(dataset)} from the PnP fit of the image's "
                            "other fiducials (wrong detection?)", names[i], float(errors[i]))
        for i in bad
    ]
    return pose, points_out, None


def _board_normal(dataset: Dataset) -> np.ndarray | None:
    """Unit normal (base frame) of the fiducials' plane when they are coplanar (a board), else None."""
    points = np.array(list(dataset.fiducials.values()))
    if len(points) < 4:
        return None
    centered = points - points.mean(axis=0)
    _, singular, vt = np.linalg.svd(centered)
    if singular[2] > 1e-6 * max(singular[0], 1e-12):
        return None
    return vt[2]


def _check_sides(
    dataset: Dataset, poses: dict[str, tuple[np.ndarray, np.ndarray]], normal: np.ndarray
) -> list[Exclusion]:
    """Images that see the board from the other side than the majority (reversed rows or columns)."""
    centre = np.mean(np.array(list(dataset.fiducials.values())), axis=0)
    sides = {}
    for image_id, (A, b) in poses.items():
        sides[image_id] = float(np.sign((A @ normal) @ (A @ centre + b)))
    total = sum(sides.values())
    if total == 0:  # no majority: nothing to decide
        return []
    majority = np.sign(total)
    return [Exclusion(image_id, "board seen from behind, unlike the other images (rows or columns in reverse order?)")
            for image_id, side in sides.items() if side != majority]


class _NodeObservations:
    """A node's images flattened once: their PnP poses and every fiducial observation (whitened later)."""

    def __init__(self, dataset: Dataset, images: list[Image], poses: dict[str, tuple[np.ndarray, np.ndarray]]):
        self.sigma = dataset.normalized_sigma
        self.A = np.array([poses[im.id][0] for im in images])
        self.b = np.array([poses[im.id][1] for im in images])
        index, points, observed = [], [], []
        for k, image in enumerate(images):
            normalized = dataset.normalized(image)
            for name in _fiducial_names(dataset, image):
                index.append(k)
                points.append(dataset.fiducials[name])
                observed.append(normalized[name])
        self.index = np.array(index, dtype=np.intp)
        self.points = np.array(points, dtype=float).reshape(-1, 3)
        self.observed = np.array(observed, dtype=float).reshape(-1, 2)
        self.counts = np.maximum(np.bincount(self.index, minlength=len(images)), 1)

    def scores(self, A_parent: np.ndarray, b_parent: np.ndarray) -> np.ndarray:
        """RMS whitened reprojection of each image's fiducials through the node's ``(A_{Nv-1}, b_{Nv-1})``
        and the reflection nearest to the image's PnP pose (eqs. 6-7, 5, 9); inf behind the camera."""
        _, vectors = reflection_fit(self.A, self.b, A_parent, b_parent)
        A_pred, b_pred = reflect_transforms(A_parent, b_parent, vectors)  # eqs. (6)-(7)
        camera_points = predict_camera_points(A_pred, b_pred, self.index, self.points)  # eq. (5)
        depth = camera_points[:, 2]
        predicted = camera_points[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
        squared = np.sum(((predicted - self.observed) / self.sigma) ** 2, axis=1)  # eq. (9)
        squared = np.where(depth > 0, squared, np.inf)
        return np.sqrt(np.bincount(self.index, weights=squared, minlength=len(self.counts)) / self.counts)


def _solve_node(
    images: list[Image], poses: dict[str, tuple[np.ndarray, np.ndarray]], children: list[int], parent_det: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The node's ``(A_{Nv-1}, b_{Nv-1})`` from the images of ``children`` (eqs. 13-17), or None when
    their mirror normals are nearly coplanar."""
    index_of = {m: k for k, m in enumerate(children)}
    observations = [(index_of[im.mirror_configs[-1]], *poses[im.id]) for im in images
                    if im.mirror_configs[-1] in index_of]
    node = solve_children(observations, len(children), parent_det)
    normals = np.array([v / max(np.linalg.norm(v), 1e-300) for v in node.mirror_vectors])
    if np.linalg.svd(normals, compute_uv=False)[2] < MIN_NORMAL_SPREAD:
        return None
    return node.A_parent, node.b_parent


def _check_node(
    dataset: Dataset, prefix: tuple[int, ...], images: list[Image], poses: dict[str, tuple[np.ndarray, np.ndarray]],
    rng: np.random.Generator,
) -> list[Exclusion]:
    """Least median of squares over triples of a level-Nv node's children: the images inconsistent with it."""
    children = sorted({im.mirror_configs[-1] for im in images})
    if len(children) < 4:  # three placements are solved exactly: no majority to compare against
        return []
    parent_det = (-1.0) ** (dataset.num_mirrors - 1)
    triples = list(combinations(children, 3))
    if len(triples) > CONSENSUS_TRIPLES:
        triples = [triples[i] for i in rng.choice(len(triples), size=CONSENSUS_TRIPLES, replace=False)]
    observations = _NodeObservations(dataset, images, poses)
    best: tuple[float, np.ndarray] | None = None
    for triple in triples:
        parent = _solve_node(images, poses, list(triple), parent_det)
        if parent is None:
            continue
        scores = observations.scores(*parent)
        median = float(np.median(scores))
        if best is None or median < best[0]:
            best = (median, scores)
    if best is None:
        return []
    median, scores = best
    inliers = scores <= max(CONSENSUS_MIN_SIGMAS, CONSENSUS_FACTOR * median)
    if np.all(inliers):
        return []
    # The closed form of a few placements is too coarse to judge an image by (real photographs: tens of
    # sigma); the majority's MLE (eq. 23) judges each image, the others with their mirror fitted alone.
    refined = _refined_scores(dataset, images, poses, inliers)
    if refined is None:
        return []
    scores = refined
    median = float(np.median(scores[inliers]))
    threshold = max(CONSENSUS_MIN_SIGMAS, CONSENSUS_FACTOR * median)
    where = "" if not prefix else " under " + ", ".join(f"mirror {l + 1} placement {m}" for l, m in enumerate(prefix))
    return [
        Exclusion(im.id, f"inconsistent with the other placements of mirror {dataset.num_mirrors}{where} "
                         f"({_sigmas(score)}, the majority {median:.3g} sigma)", None, float(score))
        for im, score in zip(images, scores) if not score <= threshold
    ]


def _refined_scores(
    dataset: Dataset, images: list[Image], poses: dict[str, tuple[np.ndarray, np.ndarray]], inliers: np.ndarray
) -> np.ndarray | None:
    """RMS whitened reprojection of each image's fiducials at the MLE of the inlier images' subtree
    (``initial.refine_subtree``); an outlier image's mirror placement fitted alone (scipy least squares)
    on that node. None when the inliers do not determine the node."""
    level = dataset.num_mirrors
    kept = [im for im, ok in zip(images, inliers) if ok]
    children = sorted({im.mirror_configs[-1] for im in kept})
    if len(children) < 3:
        return None
    parent_det = (-1.0) ** (level - 1)
    index_of = {m: k for k, m in enumerate(children)}
    node = solve_children([(index_of[im.mirror_configs[-1]], *poses[im.id]) for im in kept], len(children), parent_det)
    hypothesis = Hypothesis(node.A_parent, node.b_parent, {(level, m): [v] for m, v in zip(children, node.mirror_vectors)}, {})
    start = subtree_solution(hypothesis, level)
    refined = refine_subtree(subtree_dataset(dataset, kept, level), start)
    if refined is None:
        return None
    back = hypothesis_of_subtree(refined[1], hypothesis, level)
    A_parent, b_parent = back.A, back.b
    mirror = {m: back.mirror_vectors[(level, m)][0] for m in children}
    scores = np.array([
        misfit_sigmas(dataset, image, poses[image.id], A_parent, b_parent, mirror[image.mirror_configs[-1]] if ok else None)
        for image, ok in zip(images, inliers)
    ])
    return scores


#: PnP candidates ``(A_Nv, b_Nv)`` per image id, as ``pnp.pnp_candidates`` gives them.
PnPCandidates = dict[str, list[tuple[np.ndarray, np.ndarray]]]


def _sigmas(rms: float) -> str:
    return f"{rms:.3g} sigma RMS" if rms < 1e6 else "its fiducials fall behind the camera or a mirror"


def screen(dataset: Dataset, seed: int = 0) -> tuple[Dataset, list[Exclusion], PnPCandidates]:
    """``dataset`` without the images and fiducial observations that disagree with the rest, those left
    out with their reasons (module docstring, steps 1-3), and the PnP of every image kept unchanged (for
    ``initial_estimate``, which would compute the same again). Images with fewer than 4 fiducials are not
    checked. With nothing left out, ``dataset`` itself is returned (the same object)."""
    excluded: list[Exclusion] = []
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for image in dataset.images:
        names = _fiducial_names(dataset, image)
        if len(names) < 4:
            continue
        pose, points_out, image_out = _check_pnp(dataset, image, names)
        if image_out is not None:
            excluded.append(image_out)
            continue
        excluded.extend(points_out)
        if pose is not None:
            poses[image.id] = pose
    normal = _board_normal(dataset)
    if normal is not None and poses:
        for exclusion in _check_sides(dataset, poses, normal):
            excluded.append(exclusion)
            del poses[exclusion.image]
    reduced = without(dataset, excluded) if excluded else dataset
    nodes: dict[tuple[int, ...], list[Image]] = defaultdict(list)
    for image in reduced.images:
        nodes[image.mirror_configs[:-1]].append(image)
    rng = np.random.default_rng(seed)
    node_excluded: list[Exclusion] = []
    for prefix in sorted(nodes):
        images = nodes[prefix]
        if all(im.id in poses for im in images):
            node_excluded.extend(_check_node(reduced, prefix, images, poses, rng))
    if node_excluded:
        excluded.extend(node_excluded)
        reduced = without(dataset, excluded)
    for exclusion in excluded:
        logger.warning("%s: image '%s'%s left out: %s", dataset.source, exclusion.image,
                       f" point '{exclusion.point}'" if exclusion.point else "", exclusion.reason)
    untouched = {e.image for e in excluded}
    return reduced, excluded, {image_id: [pose] for image_id, pose in poses.items() if image_id not in untouched}


def without(dataset: Dataset, excluded: list[Exclusion]) -> Dataset:
    """``dataset`` without the excluded images and measurements; untouched images are the same objects."""
    images_out = {e.image for e in excluded if e.point is None}
    points_out: dict[str, set[str]] = defaultdict(set)
    for e in excluded:
        if e.point is not None:
            points_out[e.image].add(e.point)
    images = []
    for image in dataset.images:
        if image.id in images_out:
            continue
        if image.id in points_out:
            image = Image(image.id, image.mirror_configs,
                          {n: z for n, z in image.observations.items() if n not in points_out[image.id]})
        images.append(image)
    return replace(dataset, images=images)


def final_check(
    dataset: Dataset, measurements: list[Measurement], whitened: np.ndarray, dimension: int
) -> list[Exclusion]:
    """After LM: the measurements above ``FINAL_SIGMAS`` to leave out, or their whole image where more than
    two and more than ``MAX_BAD_POINT_FRACTION`` of its measurements are. None when too many are (a wrong minimum), or when
    the other images do not fit either (their cost 0.5 chi^2 implausible for ``dimension`` unknowns,
    ``lm.plausible``): then the model, not a few measurements, is at fault (a camera that moved).
    """
    bad = whitened > FINAL_SIGMAS
    if not np.any(bad) or np.mean(bad) > FINAL_MAX_FRACTION:
        return []
    flagged_images = {m.image_id for m, b in zip(measurements, bad) if b}  # their other residuals are pulled too
    rest = whitened[[m.image_id not in flagged_images for m in measurements]]
    if not plausible(0.5 * float(np.sum(rest**2)), 0.5 * max(2 * len(rest) - dimension, 0)):
        return []
    per_image: dict[str, list[int]] = defaultdict(list)
    for i, m in enumerate(measurements):
        per_image[m.image_id].append(i)
    excluded = []
    for image_id, indices in per_image.items():
        flagged = [i for i in indices if bad[i]]
        if not flagged:
            continue
        if len(flagged) > max(2, MAX_BAD_POINT_FRACTION * len(indices)):
            rms = float(np.sqrt(np.mean(whitened[indices] ** 2)))
            excluded.append(Exclusion(image_id, f"{len(flagged)} of its {len(indices)} measurements above "
                                                f"{FINAL_SIGMAS:g} sigma after the solve ({rms:.3g} sigma RMS)", None, rms))
        else:
            excluded.extend(
                Exclusion(image_id, f"{whitened[i] * dataset.pixel_sigma:.3g} {_unit(dataset)} from the solution "
                                    f"({whitened[i]:.3g} sigma)", measurements[i].point, float(whitened[i]))
                for i in flagged
            )
    return excluded


# --------------------------------------------------------------------------------------------------
# One image at a time (``IncrementalCalibrator``): the same checks against the images and estimate so far


def check_image(
    dataset: Dataset, image: Image
) -> tuple[Image | None, tuple[np.ndarray, np.ndarray] | None, list[Exclusion]]:
    """Step 1 on one image: the image to use (None when it is left out; a copy without its gross
    fiducials where it has some), its PnP pose (None with fewer than 4 fiducials) and what was left out."""
    names = _fiducial_names(dataset, image)
    if len(names) < 4:
        return image, None, []
    pose, points_out, image_out = _check_pnp(dataset, image, names)
    if image_out is not None:
        return None, None, [image_out]
    if points_out:
        image = without(replace(dataset, images=[image]), points_out).images[0]
    return image, pose, points_out


def board_side(dataset: Dataset, pose: tuple[np.ndarray, np.ndarray]) -> float | None:
    """+1 or -1: the side of the board (coplanar fiducials) an image's PnP pose sees; None without a board."""
    normal = _board_normal(dataset)
    if normal is None:
        return None
    A, b = pose
    centre = np.mean(np.array(list(dataset.fiducials.values())), axis=0)
    return float(np.sign((A @ normal) @ (A @ centre + b)))


def misfit_sigmas(
    dataset: Dataset, image: Image, pose: tuple[np.ndarray, np.ndarray], A_parent: np.ndarray, b_parent: np.ndarray,
    mirror_vector: np.ndarray | None,
) -> float:
    """RMS whitened reprojection of an image's fiducials through its parent ``(A_{Nv-1}, b_{Nv-1})`` (from an
    estimate) and its last mirror: ``mirror_vector`` where known, else the one fitting them best
    (:func:`fit_last_mirror` from the reflection nearest to its PnP ``pose``, eqs. 6-7)."""
    errors = _last_mirror_errors(dataset, image, A_parent, b_parent)
    if mirror_vector is None:
        v0 = reflection_fit(pose[0][None], pose[1][None], A_parent, b_parent)[1][0]
        mirror_vector = fit_last_mirror(dataset, image, A_parent, b_parent, v0).x
    return float(np.sqrt(2.0 * np.mean(errors(np.asarray(mirror_vector)) ** 2)))


def _last_mirror_errors(dataset: Dataset, image: Image, A_parent: np.ndarray, b_parent: np.ndarray):
    """Whitened reprojection errors of an image's fiducials as a function of its last mirror vector
    (eqs. 6-7, 5, 9), the parent ``(A_{Nv-1}, b_{Nv-1})`` held."""
    names = _fiducial_names(dataset, image)
    points = np.array([dataset.fiducials[n] for n in names])
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])

    def errors(v: np.ndarray) -> np.ndarray:
        A, b = reflect_transforms(A_parent, b_parent, v[None])  # eqs. (6)-(7)
        camera_points = apply_transform(A[0], b[0], points)
        depth = np.maximum(camera_points[:, 2], 1e-9)
        return ((camera_points[:, :2] / depth[:, None] - observed) / dataset.normalized_sigma).ravel()  # eq. (9)

    return errors


def fit_last_mirror(dataset: Dataset, image: Image, A_parent: np.ndarray, b_parent: np.ndarray, start: np.ndarray):
    """The last mirror vector (camera frame, metres) that fits an image's fiducials best with its parent
    ``(A_{Nv-1}, b_{Nv-1})`` held: scipy's least-squares result from ``start`` (``x`` the vector, ``fun``
    the whitened errors, ``jac`` their Jacobian)."""
    from scipy.optimize import least_squares  # imported where used: SciPy is slow to load (issue 27)

    errors = _last_mirror_errors(dataset, image, A_parent, b_parent)
    return least_squares(errors, start, x_scale=np.full(3, 1e-3 + 1e-2 * np.linalg.norm(start)), method="lm")
