"""Consensus before the solve and a final check after it: images or measurements that do not
agree with the rest are left out, each named with its reason, instead of sinking the calibration.

Before the solve (:func:`screen`), on images with >= 3 fiducials:

1. Per image with >= 4 fiducials: the PnP of its fiducials (Sect. 4.1, eq. 10) must reproject them within
   ``PNP_POINT_SIGMAS``. Where it does not, RANSAC PnP (cv2) finds the fiducials that agree; a few
   gross ones are left out as measurements, and an image where many disagree (a shuffled row, a wrong
   corner order) is left out whole. A small planar target far away has a twin pose that fits about as
   well (``TWIN_COST_GAP``): both are the image's candidates, as P3P's are for three fiducials.
2. Planar fiducials (a board): the images that see it from the other side than most. That alone leaves
   nothing out (a dataset's points may be seen from either side, and it does not say which side of a
   board is printed); an image that step 3 leaves out is told so (``BEHIND``): a chessboard labelled
   with its rows (or columns) in reverse order fits PnP exactly, seen from behind.
3. Per node of the mirror tree at level Nv (its children: the placements of the last mirror): least
   median of squares over triples of children. Each triple gives the node's ``(A_{Nv-1}, b_{Nv-1})``
   (eqs. 13-17), for each choice of its images' candidates (the best ``COMBINATIONS_PER_TRIPLE``);
   every image is scored by the reprojection of its fiducials through the reflection nearest to its
   best candidate (eqs. 5-9). Where some are far above the least-median hypothesis's median, the
   majority's MLE judges again, an image it does not fit once more at the MLE of the majority and
   itself: only an image the model cannot fit is left out (a half-turned board fits PnP but no mirror
   placement; random pixels fit nothing). With three-fiducial images every triple fits its own three,
   so a node is judged from ``MIN_CHILDREN_P3P`` children on.

After LM (:func:`final_check`): measurements above ``FINAL_SIGMAS``, or whole images where many of
their measurements are, are left out and the caller solves again.

Nothing left out is dropped silently: every image or measurement is an
:class:`~mirror_fg.solver.result.calibration.Exclusion` with its reason and residual.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np

from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.core.geometry import apply_transform
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.result.calibration import Exclusion
from mirror_fg.solver.model.graph import Labelled
from mirror_fg.solver.screen.placement_consensus import (  # noqa: F401 (the node's constants: public here too)
    CONSENSUS_FACTOR,
    CONSENSUS_MIN_SIGMAS,
    CONSENSUS_TRIPLES,
    check_node,
    fiducial_names,
    fit_mirrors,
    mirror_fit,
    reflected_errors,
)
from mirror_fg.solver.start.pnp import pnp_candidates, pnp_candidates_many, pnp_minima
from mirror_fg.solver.start.pnp_screen import screen_minima_many

__all__ = [
    "PNP_POINT_SIGMAS", "MAX_BAD_POINT_FRACTION", "CONSENSUS_MIN_SIGMAS", "CONSENSUS_FACTOR", "FINAL_SIGMAS",
    "screen", "check_images", "ImageChecks", "final_check", "without", "check_image", "board_side", "misfit_sigmas",
    "fit_last_mirror",
]

logger = logging.getLogger("mirror_fg")

#: A fiducial further than this (whitened norm) from its image's PnP fit is a gross error.
PNP_POINT_SIGMAS = 10.0
#: An image with more than this fraction of gross fiducials is left out whole (its labelling is wrong).
MAX_BAD_POINT_FRACTION = 0.1
#: A planar target's twin PnP pose is kept as a candidate when its whitened squared reprojection cost is
#: above the best's by less than this (a likelihood ratio of about 5 sigma): the image cannot tell them apart.
TWIN_COST_GAP = 25.0
#: What an image left out as inconsistent is told when it also sees the board from the other side.
BEHIND = "board seen from behind, unlike the other images (rows or columns in reverse order?)"
#: After LM, a measurement above this whitened residual is left out and the solve repeated.
FINAL_SIGMAS = 10.0
#: The final check leaves nothing out when more than this fraction of the measurements are above
#: ``FINAL_SIGMAS``: that is a wrong minimum or a wrong sigma, not a few outliers.
FINAL_MAX_FRACTION = 0.2


def _unit(dataset: Dataset) -> str:
    return "px" if dataset.camera is not None else "(normalized)"


def _whitened_errors(dataset: Dataset, A: np.ndarray, b: np.ndarray, points: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Whitened reprojection error norm of each point under ``(A, b)`` (eqs. 5, 9); inf behind the camera."""
    camera_points = apply_transform(A, b, points)
    depth = camera_points[:, 2]
    predicted = camera_points[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
    errors = np.linalg.norm((predicted - observed) / dataset.normalized_sigma, axis=1)
    return np.where(depth > 0, errors, np.inf)


def _ransac_inliers(points: np.ndarray, observed: np.ndarray, num_mirrors: int, threshold: float) -> np.ndarray | None:
    """Indices of the fiducials that agree with cv2's RANSAC PnP (normalized coordinates), or None."""
    import cv2  # imported where used: OpenCV is slow to load

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
    dataset: Dataset, image: Image, names: list[str], minima: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[Exclusion], Exclusion | None, list[tuple[np.ndarray, np.ndarray]]]:
    """Per-image check: its PnP candidates (empty if left out: the best fit first, then a planar target's
    twin where the image cannot tell them apart), the fiducials left out, or the image left out, and the
    PnP minima it judged (``minima``: those, when already found for these fiducials and observations)."""
    points = np.array([dataset.fiducials[n] for n in names])
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])
    parity = len(image.reflections)  # eq. (11): an odd number of reflections flips the image
    if minima is None:
        minima = pnp_minima(points, observed, parity)
    found = minima
    errors = _whitened_errors(dataset, *minima[0], points, observed) if minima else np.full(len(names), np.inf)
    if np.all(errors <= PNP_POINT_SIGMAS):
        best_cost = float(np.sum(errors**2))
        twins = []
        for twin in minima[1:]:
            twin_errors = _whitened_errors(dataset, *twin, points, observed)
            if np.all(twin_errors <= PNP_POINT_SIGMAS) and float(np.sum(twin_errors**2)) - best_cost < TWIN_COST_GAP:
                twins.append(twin)
        return [minima[0], *twins], [], None, found
    finite = errors[np.isfinite(errors)]
    rms = float(np.sqrt(np.mean(finite**2))) if len(finite) else float("inf")
    threshold = PNP_POINT_SIGMAS * float(np.mean(dataset.normalized_sigma))
    inliers = _ransac_inliers(points, observed, parity, threshold)
    pose: tuple[np.ndarray, np.ndarray] | None = None
    if inliers is not None and len(inliers) >= max(4, len(names) // 2):  # then judged by the refit's errors
        refit = pnp_candidates(points[inliers], observed[inliers], parity)
        if refit:
            pose = refit[0]
            errors = _whitened_errors(dataset, *pose, points, observed)
    bad = np.flatnonzero(~(errors <= PNP_POINT_SIGMAS))
    if pose is None or len(bad) > MAX_BAD_POINT_FRACTION * len(names):
        reason = (f"PnP reprojection {rms * dataset.pixel_sigma:.3g} {_unit(dataset)} RMS over its {len(names)} "
                  "fiducials (board order wrong?)" if np.isfinite(rms)
                  else "PnP found no pose with every fiducial in front of the camera")
        return [], [], Exclusion(image.id, reason, None, rms), found
    points_out = [
        Exclusion(image.id, f"{errors[i] * dataset.pixel_sigma:.3g} {_unit(dataset)} from the PnP fit of the image's "
                            "other fiducials (wrong detection?)", names[i], float(errors[i]))
        for i in bad
    ]
    return [pose], points_out, None, found


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


def _seen_from_behind(
    dataset: Dataset, candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]], normal: np.ndarray
) -> set[str]:
    """Images whose PnP pose sees the board (coplanar fiducials) from the other side than most images do.

    Not a reason to leave an image out on its own: a dataset's points may be seen from either side (LEDs,
    markers on a glass plate, a board whose sides the dataset does not say). It names the likely cause
    (rows or columns in reverse order) when an image also fits no placement consistent with the others.
    """
    centre = np.mean(np.array(list(dataset.fiducials.values())), axis=0)
    sides = {image_id: float(np.sign((poses[0][0] @ normal) @ (poses[0][0] @ centre + poses[0][1])))
             for image_id, poses in candidates.items()}
    majority = np.sign(sum(sides.values()))
    return set() if majority == 0 else {image_id for image_id, side in sides.items() if side != majority}


#: PnP candidates ``(A_Nv, b_Nv)`` per image id, as ``pnp.pnp_candidates`` gives them.
PnPCandidates = dict[str, list[tuple[np.ndarray, np.ndarray]]]


@dataclass
class ImageChecks:
    """Step 1 of :func:`screen` on every image: the PnP candidates of each image kept (Sect. 4.1, eqs.
    10-12; what the analytical solution starts from) and what the per-image check left out."""

    candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    excluded: list[Exclusion]
    #: ``{image_id: (fiducial names, PnP minima)}`` of the images with >= 4 fiducials (those the check can
    #: keep: ``pnp_screen.screen_minima_many``, before the check judged them): another check of the same
    #: photographs (the same cameras and parity) takes them instead of solving again (:func:`check_images`'
    #: ``known``).
    minima: dict[str, tuple[tuple[str, ...], list[tuple[np.ndarray, np.ndarray]]]] = field(default_factory=dict)


def check_images(dataset: Dataset, known: dict[str, tuple[tuple[str, ...], list[tuple[np.ndarray, np.ndarray]]]] | None = None
                 ) -> ImageChecks:
    """Each image's PnP and its check (module docstring, step 1): with >= 4 fiducials the PnP fit (gross
    fiducials, wrong corner orders left out; a planar target's twin kept as a candidate), with three
    P3P's candidates (all images at once, nothing to check), with fewer nothing. The PnP minima of all
    images are found at once (``pnp_screen.screen_minima_many``: the minima the check can keep, the lowest
    and its twins within ``TWIN_COST_GAP``, from fewer refinements than ``pnp.pnp_minima``), and the images
    whose one minimum fits every fiducial are judged at once too. ``known``: another check's
    :attr:`ImageChecks.minima` of the same photographs seen by the same cameras with the same parity: an
    image with those very fiducials is judged from them instead of solving its PnP again."""
    known = known or {}
    minima: dict[str, tuple[tuple[str, ...], list[tuple[np.ndarray, np.ndarray]]]] = {}
    excluded: list[Exclusion] = []
    candidates: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    three: list[tuple[str, tuple[np.ndarray, np.ndarray]]] = []
    tree = dataset.is_tree  # once: it looks at every image
    names_of = {image.id: fiducial_names(dataset, image) for image in dataset.images}
    solve = []  # the images with >= 4 fiducials whose minima are not known: all solved at once
    for image in dataset.images:
        names = names_of[image.id]
        found = known.get(image.id)
        if len(names) >= 4 and (found is None or found[0] != tuple(names)):
            solve.append(image)
    problems = []
    for image in solve:
        normalized = dataset.normalized(image)
        problems.append((np.array([dataset.fiducials[n] for n in names_of[image.id]]),
                         np.array([normalized[n] for n in names_of[image.id]])))
    # the lowest minimum alone where nothing else could be kept as a twin (TWIN_COST_GAP), else every one
    solved = dict(zip((image.id for image in solve), screen_minima_many(
        problems, [len(image.reflections) for image in solve], dataset.normalized_sigma, TWIN_COST_GAP)))
    fits = _lone_minimum_fits(dataset, solve, problems, [solved[image.id] for image in solve])
    for image in dataset.images:
        names = names_of[image.id]
        if len(names) == 3:
            if not tree:  # P3P's candidates feed only the tree's analytical solution
                continue
            normalized = dataset.normalized(image)
            three.append((image.id, (np.array([dataset.fiducials[n] for n in names]),
                                     np.array([normalized[n] for n in names]))))
            continue
        if len(names) < 3:
            continue
        if image.id in fits:  # one minimum, every fiducial within PNP_POINT_SIGMAS: _check_pnp's answer
            minima[image.id] = (tuple(names), solved[image.id])
            candidates[image.id] = solved[image.id][:1]
            continue
        found = known.get(image.id)
        poses, points_out, image_out, minima_of_image = _check_pnp(
            dataset, image, names, found[1] if found is not None and found[0] == tuple(names) else solved[image.id])
        minima[image.id] = (tuple(names), minima_of_image)
        if image_out is not None:
            excluded.append(image_out)
            continue
        excluded.extend(points_out)
        candidates[image.id] = poses
    for (image_id, _), poses in zip(three, pnp_candidates_many([problem for _, problem in three], dataset.num_mirrors)):
        if poses:
            candidates[image_id] = poses
    return ImageChecks(candidates, excluded, minima)


def _lone_minimum_fits(dataset: Dataset, images: list[Image], problems: list[tuple[np.ndarray, np.ndarray]],
                       found: list[list[tuple[np.ndarray, np.ndarray]]]) -> set[str]:
    """The images (of ``images``, their fiducials and observations ``problems``) whose PnP has one minimum
    that reprojects every fiducial within ``PNP_POINT_SIGMAS`` (eqs. 5, 9), judged all at once; one near
    the bound is left to :func:`_check_pnp`."""
    groups: dict[int, list[int]] = defaultdict(list)
    for k, minima in enumerate(found):
        if len(minima) == 1:
            groups[len(problems[k][0])].append(k)
    fitting: set[str] = set()
    for members in groups.values():
        points = np.array([problems[k][0] for k in members])
        observed = np.array([problems[k][1] for k in members])
        A = np.array([found[k][0][0] for k in members])
        b = np.array([found[k][0][1] for k in members])
        camera_points = np.einsum("mab,mnb->mna", A, points) + b[:, None, :]
        depth = camera_points[..., 2]
        predicted = camera_points[..., :2] / np.where(depth > 0, depth, 1.0)[..., None]
        errors = np.linalg.norm((predicted - observed) / dataset.normalized_sigma, axis=2)
        clear = np.all((depth > 0) & (errors <= PNP_POINT_SIGMAS * (1.0 - 1e-9)), axis=1)
        fitting.update(images[k].id for k, ok in zip(members, clear.tolist()) if ok)
    return fitting


def screen(dataset: Dataset, seed: int = 0, checked: ImageChecks | None = None) -> tuple[Dataset, list[Exclusion], PnPCandidates]:
    """``dataset`` without the images and fiducial observations that disagree with the rest, those left
    out with their reasons (module docstring, steps 1-3), and the PnP candidates of every image kept
    unchanged (for ``initial_estimate``, which would compute the same again). ``checked``: step 1's
    :func:`check_images` of ``dataset`` when already done (``calibrate`` times it as the PnP). Images
    with fewer than 3 fiducials are not checked. With nothing left out, ``dataset`` itself is returned
    (the same object)."""
    checked = checked if checked is not None else check_images(dataset)
    excluded = list(checked.excluded)
    candidates = dict(checked.candidates)
    normal = _board_normal(dataset)
    behind = _seen_from_behind(dataset, candidates, normal) if normal is not None and candidates else set()
    reduced = without(dataset, excluded) if excluded else dataset
    nodes: dict[tuple[int, ...], list[Image]] = defaultdict(list)
    for image in reduced.images if dataset.is_tree else ():  # steps 2-3 compare placements of the tree
        if image.id in candidates:
            nodes[image.mirror_configs[:-1]].append(image)
    rng = np.random.default_rng(seed)
    node_excluded: list[Exclusion] = []
    for prefix in sorted(nodes):
        out, choice = check_node(reduced, prefix, nodes[prefix], candidates, rng)
        node_excluded.extend(out)
        for image_id, k in choice.items():  # the candidate the node explains the image by, first
            poses = candidates[image_id]
            candidates[image_id] = [poses[k], *poses[:k], *poses[k + 1:]]
    if node_excluded:
        excluded.extend(replace(e, reason=f"{BEHIND}; {e.reason}") if e.image in behind else e for e in node_excluded)
        reduced = without(dataset, excluded)
    for exclusion in excluded:
        logger.warning("%s: image '%s'%s left out: %s", dataset.source, exclusion.image,
                       f" point '{exclusion.point}'" if exclusion.point else "", exclusion.reason)
    untouched = {e.image for e in excluded}
    return reduced, excluded, {image_id: poses for image_id, poses in candidates.items() if image_id not in untouched}


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
            image = replace(image, observations={n: z for n, z in image.observations.items()
                                                 if n not in points_out[image.id]})
        images.append(image)
    return replace(dataset, images=images)


def final_check(
    dataset: Dataset, measurements: Sequence[Labelled], whitened: np.ndarray, dimension: int
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
    if not plausible(0.5 * float(np.sum(rest**2)), expected_cost(2 * len(rest), dimension)):
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
) -> tuple[Image | None, list[tuple[np.ndarray, np.ndarray]], list[Exclusion]]:
    """Step 1 on one image: the image to use (None when it is left out; a copy without its gross
    fiducials where it has some), its PnP candidates (as :func:`screen` gives them: P3P's with three
    fiducials, unchecked; none with fewer) and what was left out."""
    names = fiducial_names(dataset, image)
    if len(names) < 3:
        return image, [], []
    if len(names) == 3:
        normalized = dataset.normalized(image)
        return image, pnp_candidates(np.array([dataset.fiducials[n] for n in names]),
                                     np.array([normalized[n] for n in names]), dataset.num_mirrors), []
    poses, points_out, image_out, _ = _check_pnp(dataset, image, names)
    if image_out is not None:
        return None, [], [image_out]
    if points_out:
        image = without(replace(dataset, images=[image]), points_out).images[0]
    return image, poses, points_out


def board_side(dataset: Dataset, pose: tuple[np.ndarray, np.ndarray]) -> float | None:
    """+1 or -1: the side of the board (coplanar fiducials) an image's PnP pose sees; None without a board."""
    normal = _board_normal(dataset)
    if normal is None:
        return None
    A, b = pose
    centre = np.mean(np.array(list(dataset.fiducials.values())), axis=0)
    return float(np.sign((A @ normal) @ (A @ centre + b)))


def misfit_sigmas(
    dataset: Dataset, image: Image, pose: tuple[np.ndarray, np.ndarray] | list[tuple[np.ndarray, np.ndarray]],
    A_parent: np.ndarray, b_parent: np.ndarray, mirror_vector: np.ndarray | None,
) -> float:
    """RMS whitened reprojection of an image's fiducials through its parent ``(A_{Nv-1}, b_{Nv-1})`` (from an
    estimate) and its last mirror: ``mirror_vector`` where known, else the one fitting them best
    (``placement_consensus.fit_mirrors`` from the reflection nearest to its PnP ``pose``, eqs. 6-7, 5, 9;
    given a list of PnP candidates, from each: the best fit)."""
    return mirror_fit(dataset, image, pose if isinstance(pose, list) else [pose], A_parent, b_parent, mirror_vector)[0]


def fit_last_mirror(
    dataset: Dataset, image: Image, A_parent: np.ndarray, b_parent: np.ndarray, start: np.ndarray
) -> SimpleNamespace:
    """The last mirror vector (camera frame, metres) that fits an image's fiducials best with its parent
    ``(A_{Nv-1}, b_{Nv-1})`` held, from ``start`` (``placement_consensus.fit_mirrors``): ``x`` the vector,
    ``fun`` the whitened errors (x, y of each fiducial in turn, eqs. 6-7, 5, 9) and ``jac`` their Jacobian
    (2N, 3) there, as scipy's least-squares result names them."""
    names = fiducial_names(dataset, image)
    before = np.array([dataset.fiducials[n] for n in names]) @ A_parent.T + b_parent  # eq. (5)
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])
    sigma = dataset.normalized_sigma
    vectors, _ = fit_mirrors(before, np.zeros(len(names), dtype=np.intp), observed, sigma,
                             np.asarray(start, dtype=float).reshape(1, 3))
    errors, jacobian = reflected_errors(before, np.repeat(vectors, len(names), axis=0), observed, sigma, True)
    assert jacobian is not None
    return SimpleNamespace(x=vectors[0], fun=errors.ravel(), jac=np.swapaxes(jacobian, 0, 1).reshape(-1, 3))
