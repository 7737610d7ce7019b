"""Inconsistent captures diagnosed: when the images do not fit one ``T_cam_base``, do they split
into groups that each fit one? A camera (or a board) that moved mid-capture shows as images before and
after some index in capture order that are each consistent alone but disagree with each other.

Each group is solved on its own (analytical solution, then the MLE of eq. 23 without covariances); a
split is named when both groups are plausible alone (their final cost within its chi-square range,
``lm.plausible``) and the whole is not (:func:`diagnose_split`).

A move need not make the cost implausible: a mirror placement absorbs most of it. So the
splits at the boundaries between placements of mirror 1 in capture order, where each side is solvable
alone, are tested whatever the cost (:func:`moved_camera_split`, at most ``MAX_MOVE_SPLITS`` of them):
the two sides' ``T_cam_base`` with their covariances, and a chi-square test on their difference.

Two images labelled as one placement of the last mirror must see one plane: with the pose and the
parent mirrors held at the estimate, each image's own mirror vector is fitted to its fiducials
(``consensus.fit_last_mirror``) and two that differ beyond their covariances are named
(:func:`placement_disagreement`).
"""
from __future__ import annotations

from dataclasses import replace
from itertools import combinations

import logging

import gtsam
import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.geometry import nested_transform
from mirror_fg.core.transform import rotation_angle
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.result.calibration import Calibration, Inconsistency
from mirror_fg.solver.screen.consensus import PnPCandidates, fit_last_mirror
from mirror_fg.solver.start.initial import initial_estimate
from mirror_fg.solver.model.lm import levenberg_marquardt
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.start.peeling import spread_subset
from mirror_fg.solver.start.placement_tree import complete_tree

__all__ = [
    "MAX_SPLITS_TRIED", "MAX_MOVE_SPLITS", "MOVE_SIGNIFICANCE", "LABEL_SIGNIFICANCE", "GroupFit", "fit_group",
    "diagnose_inconsistency", "diagnose_split", "describe_split", "split_in_capture_order", "moved_camera_split", "placement_disagreement", "misfits_split",
]

logger = logging.getLogger("mirror_fg")

#: At most this many split indices in capture order are solved in a first pass (evenly spaced);
#: the best one's neighbourhood is then searched index by index.
MAX_SPLITS_TRIED = 12
#: At most this many boundaries between placements of mirror 1 (evenly spread over those where each
#: side is solvable alone) are tested for a moved camera: two solves with covariances each.
MAX_MOVE_SPLITS = 3
#: Probability of naming a split of a consistent capture (all boundaries tested together, Bonferroni).
MOVE_SIGNIFICANCE = 1e-4
#: ... and of naming two images of one placement that do see one plane (all pairs together).
LABEL_SIGNIFICANCE = 1e-4
#: Images of one placement whose mirrors are compared pairwise (the first this many in capture order).
MAX_IMAGES_PER_PLACEMENT = 8


class GroupFit:
    """One group of images solved alone: its ``T_cam_base``, final cost and whether the cost is plausible;
    ``covariance``: of the pose (docs/formats.md's ``[dtheta, dt]``) where asked for, scaled up by the group's own
    cost over its expected value when that is above 1 (a model that fits less well than its sigma)."""

    def __init__(self, R: np.ndarray, t: np.ndarray, final_error: float, plausible: bool,
                 covariance: np.ndarray | None = None):
        self.R, self.t, self.final_error, self.plausible = R, t, final_error, plausible
        self.covariance = covariance

    @property
    def camera_centre(self) -> np.ndarray:
        """Camera centre in the base frame (``T_base_cam``'s translation), metres."""
        return -self.R.T @ self.t


def fit_group(
    dataset: Dataset, images: list[Image], pnp: PnPCandidates | None = None, covariance: bool = False,
    options: SolveOptions | None = None,
) -> GroupFit | None:
    """``images`` of ``dataset`` solved alone, or None where they cannot be (too few placements, ...).
    ``pnp``: PnP candidates already computed for some of the images (``consensus.screen``);
    ``covariance``: also the pose covariance (:class:`GroupFit`); ``options``: the calibration's
    (``SolveOptions.nested``: its kernel and iteration limit; the defaults where None)."""
    group = replace(dataset, images=images)
    try:
        start = initial_estimate(group, pnp=pnp)
        run = levenberg_marquardt(group, start, (options or SolveOptions()).nested(), None, {})
        pose_covariance = run.covariances(group)[0] if covariance and run.converged else None
    except (DatasetError, SolveError, RuntimeError, np.linalg.LinAlgError):
        return None
    if pose_covariance is not None and run.expected_final_error > 0:
        pose_covariance = pose_covariance * max(1.0, run.final_error / run.expected_final_error)
    R, t, _, _ = run.estimate()
    return GroupFit(R, t, run.final_error, run.plausible, pose_covariance)


def describe_split(dataset: Dataset, groups: list[list[int]], fits: list[GroupFit], why: str = "") -> Inconsistency:
    """The :class:`Inconsistency` of two groups (indices in capture order) and their fits; ``why``: the
    evidence, in parentheses after the figures."""
    rotation_deg = float(np.degrees(rotation_angle(fits[0].R, fits[1].R)))
    position_mm = float(1000.0 * np.linalg.norm(fits[0].camera_centre - fits[1].camera_centre))

    def span(indices: list[int]) -> str:
        """Capture-order indices as runs: ``0–4, 9``."""
        runs: list[list[int]] = []
        for index in indices:
            if runs and index == runs[-1][-1] + 1:
                runs[-1].append(index)
            else:
                runs.append([index])
        return ", ".join(f"{run[0]}" if len(run) == 1 else f"{run[0]}–{run[-1]}" for run in runs)

    evidence = f" ({why})" if why else ""
    message = (f"images {span(groups[0])} and {span(groups[1])} disagree by {rotation_deg:.1f}° / {position_mm:.0f} mm"
               f"{evidence}: did the camera or the board move?")
    ids = tuple(tuple(dataset.images[i].id for i in group) for group in groups)
    return Inconsistency(ids, rotation_deg, position_mm, message)


def _split_at(dataset: Dataset, k: int, pnp: PnPCandidates | None,
              options: SolveOptions | None) -> tuple[float, list[GroupFit]] | None:
    fits = [fit_group(dataset, dataset.images[:k], pnp, options=options),
            fit_group(dataset, dataset.images[k:], pnp, options=options)]
    if fits[0] is None or fits[1] is None:
        return None
    return fits[0].final_error + fits[1].final_error, [fits[0], fits[1]]


def diagnose_inconsistency(
    dataset: Dataset, calibration: Calibration, pnp: PnPCandidates | None = None,
    options: SolveOptions | None = None,
) -> Inconsistency | None:
    """What the data contradict, most specific first: where the final cost is implausible, a split in
    capture order into groups each consistent alone (:func:`diagnose_split`), else two images of one
    placement that see different mirrors (:func:`placement_disagreement`); whatever the cost, a camera
    that moved between placements of mirror 1 (:func:`moved_camera_split`). One rule for batch and
    incremental results. ``options``: the calibration's, for the groups' solves (:func:`fit_group`)."""
    found = None
    if not calibration.cost_plausible:
        found = diagnose_split(dataset, calibration, pnp, options) or placement_disagreement(dataset, calibration)
    return found or moved_camera_split(dataset, calibration.R_cam_base, pnp, options)


def diagnose_split(dataset: Dataset, calibration: Calibration, pnp: PnPCandidates | None = None,
                   options: SolveOptions | None = None) -> Inconsistency | None:
    """Where the calibration's final cost is implausible: the split of the images in capture order into
    two groups each consistent alone (the lowest total cost of the two solves), or None when there is
    no such split."""
    if calibration.cost_plausible:
        return None
    return split_in_capture_order(dataset, calibration.final_error, pnp, options)


def split_in_capture_order(
    dataset: Dataset, whole_error: float = float("nan"), pnp: PnPCandidates | None = None,
    options: SolveOptions | None = None,
) -> Inconsistency | None:
    """The split of the images in capture order into two groups each consistent alone (the lowest total
    cost of the two solves), or None when there is no such split. ``whole_error``: the whole capture's
    final cost, for the log."""
    n = len(dataset.images)
    if n < 2:
        return None
    tried: dict[int, tuple[float, list[GroupFit]] | None] = {}

    def best_of(indices) -> int | None:
        for k in indices:
            if k not in tried:
                tried[k] = _split_at(dataset, int(k), pnp, options)
        solved = [k for k in tried if tried[k] is not None]
        return min(solved, key=lambda k: tried[k][0]) if solved else None  # type: ignore[index]

    # Coarse to fine: MAX_SPLITS_TRIED indices spread over the capture, then ever narrower brackets
    # around the best (the total cost is lowest at the true split and grows away from it).
    step = max(1, int(np.ceil((n - 1) / MAX_SPLITS_TRIED)))
    best = best_of(range(1, n, step))
    while best is not None and step > 1:
        step = max(1, step // 3)
        best = best_of(range(max(1, best - 3 * step), min(n, best + 3 * step + 1), step))
    if best is None:
        return None
    cost_and_fits = tried[best]
    assert cost_and_fits is not None
    _, fits = cost_and_fits
    logger.info("%s: best split in capture order before image %d: cost %.6g + %.6g (whole %.6g)", dataset.source, best,
                fits[0].final_error, fits[1].final_error, whole_error)
    if not (fits[0].plausible and fits[1].plausible):
        return None
    return describe_split(dataset, [list(range(best)), list(range(best, n))], fits)


def misfits_split(dataset: Dataset, in_graph: list[Image], misfits: list[Image],
                  options: SolveOptions | None = None) -> Inconsistency | None:
    """Where the images an incremental calibration refused as inconsistent with its estimate (``misfits``,
    at least three) fit one ``T_cam_base`` of their own, and those in its graph (``in_graph``) theirs, the
    two groups named as the batch names a split."""
    if len(misfits) < 3:
        return None
    index = {image.id: i for i, image in enumerate(dataset.images)}
    fits = [fit_group(dataset, in_graph, options=options), fit_group(dataset, misfits, options=options)]
    if fits[0] is None or fits[1] is None or not (fits[0].plausible and fits[1].plausible):
        return None
    groups = [sorted(index[image.id] for image in in_graph), sorted(index[image.id] for image in misfits)]
    return describe_split(dataset, groups, [fits[0], fits[1]])


def _pose_mahalanobis(fits: list[GroupFit], R_reference: np.ndarray) -> float:
    """Squared Mahalanobis distance of two independent fits' ``T_cam_base`` (docs/formats.md's ``[dtheta, dt]``, their
    covariances added): chi-square with 6 degrees of freedom where both see one pose.

    Each rotation is taken as ``R_k = Exp(dtheta_k) R_reference`` (the whole capture's estimate) and the
    two ``dtheta_k`` subtracted: ``Log(R_1 R_0^T)`` itself would mix the rotations about the weakly
    determined axes into the well determined one (its second-order term, degrees where that axis is
    known to a fraction of one).
    """
    covariances = [fit.covariance for fit in fits]
    if covariances[0] is None or covariances[1] is None:
        raise ValueError("_pose_mahalanobis: fits without a covariance")
    dtheta = [gtsam.Rot3.Logmap(gtsam.Rot3(fit.R @ R_reference.T)) for fit in fits]
    difference = np.r_[dtheta[1] - dtheta[0], fits[1].t - fits[0].t]
    return float(difference @ np.linalg.solve(covariances[0] + covariances[1], difference))


def _solvable_boundaries(dataset: Dataset) -> list[int]:
    """Indices ``k`` in capture order where image ``k`` starts a new placement of mirror 1 and both
    ``images[:k]`` and ``images[k:]`` hold a complete configuration tree (Fig. 3) alone.

    More images never make a tree incomplete, so the first images form one from some ``k`` on and the
    last from some ``k`` down: two bisections (``complete_tree`` is linear in the images), not one test
    per boundary (a video of 10,000 placements)."""
    images, Nv = dataset.images, dataset.num_mirrors

    def first(test, low: int, high: int) -> int:
        """The least k in [low, high] with test(k) (test monotone: False ... True), else high + 1."""
        while low <= high:
            middle = (low + high) // 2
            if test(middle):
                high = middle - 1
            else:
                low = middle + 1
        return low

    start = first(lambda k: bool(complete_tree(images[:k], Nv)), 1, len(images) - 1)
    stop = first(lambda k: not complete_tree(images[k:], Nv), 1, len(images) - 1) - 1  # last k with a tree after
    return [k for k in range(start, stop + 1) if images[k].mirror_configs[0] != images[k - 1].mirror_configs[0]]


def moved_camera_split(
    dataset: Dataset, R_reference: np.ndarray, pnp: PnPCandidates | None = None,
    options: SolveOptions | None = None,
) -> Inconsistency | None:
    """A split of the images in capture order at a boundary between placements of mirror 1 whose two
    sides, each solved alone with its covariance, disagree beyond chance: the largest chi-square of
    their ``T_cam_base`` difference above its 1 - MOVE_SIGNIFICANCE quantile (Bonferroni over the
    boundaries tested; at most ``MAX_MOVE_SPLITS``, evenly spread over the solvable ones). None when no
    boundary splits the capture into two solvable sides, or they agree. ``R_reference``: the whole
    capture's ``R_cam_base`` (:func:`_pose_mahalanobis`)."""
    boundaries = _solvable_boundaries(dataset)
    if not boundaries:
        return None
    tested = [boundaries[i] for i in spread_subset(len(boundaries), MAX_MOVE_SPLITS).tolist()]
    from scipy.stats import chi2  # imported where used: SciPy is slow to load

    threshold = chi2.isf(MOVE_SIGNIFICANCE / len(tested), 6)
    worst: tuple[float, int, list[GroupFit]] | None = None
    for k in tested:
        sides = [complete_tree(dataset.images[:k], dataset.num_mirrors), complete_tree(dataset.images[k:], dataset.num_mirrors)]
        fits = [fit for fit in (fit_group(dataset, side, pnp, covariance=True, options=options) for side in sides)
                if fit is not None and fit.covariance is not None]
        if len(fits) < 2:
            continue
        try:
            distance = _pose_mahalanobis(fits, R_reference)
        except np.linalg.LinAlgError:
            continue
        logger.info("%s: split before image %d: Mahalanobis distance %.3g of the two sides' T_cam_base",
                    dataset.source, k, np.sqrt(distance))
        if worst is None or distance > worst[0]:
            worst = (distance, k, fits)
    if worst is None or not worst[0] > threshold:
        return None
    distance, k, fits = worst
    why = (f"Mahalanobis distance {np.sqrt(distance):.1f} with their covariances, chi-square(6) p = "
           f"{chi2.sf(distance, 6):.2g}")
    return describe_split(dataset, [list(range(k)), list(range(k, len(dataset.images)))], fits, why)


def placement_disagreement(dataset: Dataset, calibration: Calibration) -> Inconsistency | None:
    """Two images labelled as one placement of the last mirror whose own mirrors (each fitted to the
    image's fiducials with ``T_cam_base`` and the mirrors before it held at ``calibration``) differ
    beyond their covariances: the pair with the largest chi-square (3 degrees of freedom) above its
    1 - LABEL_SIGNIFICANCE quantile (Bonferroni over the pairs), or None."""
    Nv = dataset.num_mirrors
    by_placement: dict[int, list[Image]] = {}
    for image in dataset.images:
        if sum(1 for name in image.observations if name in dataset.fiducials) >= 3:
            by_placement.setdefault(image.mirror_configs[-1], []).append(image)
    pairs: list[tuple[float, Image, Image, np.ndarray, np.ndarray]] = []
    for placement, images in by_placement.items():
        start = calibration.mirror_vectors.get((Nv, placement))
        if len(images) < 2 or start is None:
            continue
        fitted = []
        for image in images[:MAX_IMAGES_PER_PLACEMENT]:
            keys = [(level + 1, m) for level, m in enumerate(image.mirror_configs[:-1])]
            if any(key not in calibration.mirror_vectors for key in keys):
                continue
            above = [calibration.mirror_vectors[key] for key in keys]
            A_parent, b_parent = nested_transform(calibration.R_cam_base, calibration.t_cam_base, above)  # eqs. (6)-(8)
            fit = fit_last_mirror(dataset, image, A_parent, b_parent, np.asarray(start, dtype=float))
            dof = fit.fun.size - 3
            try:
                covariance = np.linalg.inv(fit.jac.T @ fit.jac)  # whitened errors: m^2
            except np.linalg.LinAlgError:
                continue
            if dof > 0:
                covariance *= max(1.0, float(fit.fun @ fit.fun) / dof)
            fitted.append((image, fit.x, covariance))
        for (a, v_a, C_a), (b, v_b, C_b) in combinations(fitted, 2):
            difference = v_a - v_b
            try:
                pairs.append((float(difference @ np.linalg.solve(C_a + C_b, difference)), a, b, v_a, v_b))
            except np.linalg.LinAlgError:
                continue
    if not pairs:
        return None
    distance, a, b, v_a, v_b = max(pairs, key=lambda pair: pair[0])
    from scipy.stats import chi2  # imported where used: SciPy is slow to load

    if not distance > chi2.isf(LABEL_SIGNIFICANCE / len(pairs), 3):
        return None
    cosine = float(v_a @ v_b / (np.linalg.norm(v_a) * np.linalg.norm(v_b)))
    rotation_deg = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    position_mm = float(1000.0 * abs(np.linalg.norm(v_a) - np.linalg.norm(v_b)))  # the planes' distances from the camera
    message = (f"{a.id} and {b.id} are labelled placement {a.mirror_configs[-1]} of mirror {Nv} but their mirrors "
               f"differ by {rotation_deg:.1f}° / {position_mm:.0f} mm (Mahalanobis distance {np.sqrt(distance):.1f}): "
               "check their mirror_configs")
    return Inconsistency(((a.id,), (b.id,)), rotation_deg, position_mm, message)
