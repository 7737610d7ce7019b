"""Labelling a symmetric target's images by consistency across the images.

A symmetric chessboard (``cols + rows`` even) looks the same after a half turn (a square one with an
even count also after a quarter turn), so one image gives its corners only up to the board's
symmetries (:class:`mirror_fg.io.target.Symmetry`). Every labelling fits its own image equally well;
only one ``T_cam_base`` shared by all images tells them apart. Per image and candidate labelling ``s``
the PnP composite transform ``(A, b)`` (Sect. 4.1, eqs. 10-12, :func:`mirror_fg.solver.start.pnp.pnp_candidates`);
the candidates of one image differ by the board's turn ``G_s`` in the base frame: ``(A, b) o G_s``.

The mirror tree is walked bottom-up as by the analytical solution (Sect. 4.2). At each node, a
RANSAC over triples of child placements with one labelling each (the first's fixed: a hypothesis
turned as a whole by ``G_s`` is its twin): the node's ``(A_{l-1}, b_{l-1})`` solved from the triple
(eqs. 13-17, :func:`mirror_fg.solver.start.peeling.solve_children`), every child's candidates scored by how
far ``A_l A_{l-1}^T`` is from a Householder matrix and ``b_l - M b_{l-1}`` from ``2 v`` (eqs. 3, 6-7,
:func:`~mirror_fg.solver.start.peeling.reflection_fit`), the hypothesis with the lowest capped misfit kept
and re-solved from its inliers. At the deepest nodes each image then has its mirror vector fitted by
least squares to its fiducials' pixels with the node's transform held fixed (eqs. 3-9), once per
labelling: the best labelling is chosen when the runner-up fits clearly worse
(:data:`AMBIGUITY_COST_RATIO`, :data:`AMBIGUITY_COST_GAP`), otherwise the image is left out as ambiguous.
A node is one candidate per symmetry (its ``(A, b)`` turned by ``G_s``) at the level above.

Which of the whole capture and its turned twin is meant the images cannot tell (the same board seen
the same way); :func:`choose_labellings` takes the one that shows the board upright in most images
(the target's first row above its last, ``upright``).
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import product

import numpy as np

from mirror_fg.core.geometry import reflect
from mirror_fg.data import Dataset, Image
from mirror_fg.io.target import Symmetry
from mirror_fg.solver.start.peeling import reflection_fit, solve_children
from mirror_fg.solver.screen.placement_consensus import fit_mirrors, sample_triples
from mirror_fg.solver.start.pnp import pnp_candidates

__all__ = ["LabelReport", "choose_labellings", "AMBIGUITY_COST_RATIO", "AMBIGUITY_COST_GAP"]

#: An image's labelling is chosen only when the runner-up's whitened squared reprojection cost is at
#: least this many times the best's (an RMS ratio of 3) ...
AMBIGUITY_COST_RATIO = 9.0
#: ... and above it by at least this much (a likelihood ratio of about 5 sigma).
AMBIGUITY_COST_GAP = 25.0
#: An undecided image whose best labelling is off by more than this many pixel sigmas (RMS) fits none.
MISFIT_SIGMAS = 10.0
#: A child's misfit of eqs. (3), (6)-(7) (squared, unitless) above which it is an outlier of a hypothesis.
MISFIT_CAP = 0.05
#: A node's own labelling (level above the images) is chosen when the runner-up's misfit is at least
#: this many times the best's and above MISFIT_CAP.
NODE_MISFIT_RATIO = 9.0
#: Child triples tried per node (all of them when there are fewer).
MAX_TRIPLES = 40
#: Re-solves of a node's best hypothesis from its inliers.
REFINEMENTS = 3
#: Fewest fiducials of an image whose labelling is checked (PnP with one solution).
MIN_FIDUCIALS = 4

_Transform = tuple[np.ndarray, np.ndarray]


@dataclass
class LabelReport:
    """The labelling chosen for one image, or why it was left out.

    ``symmetry``: the chosen labelling as the turn from the detector's (``identity``: as detected), None
    when left out; ``rms_px`` / ``runner_up_px``: RMS reprojection error (pixels, or normalized units
    without a camera) of the best and second-best labelling with the transform the other images give;
    ``reason``: why the image was left out ('' when kept).
    """

    image: str
    symmetry: str | None
    rms_px: float = float("nan")
    runner_up_px: float = float("nan")
    reason: str = ""

    @property
    def excluded(self) -> bool:
        return self.symmetry is None

    def line(self) -> str:
        """How the image was labelled, for a detection report."""
        if self.excluded:
            return self.reason
        fit = f"{self.rms_px:.2g} px against the other images"
        if np.isfinite(self.runner_up_px):
            fit += f", next labelling {self.runner_up_px:.3g} px"
        return f"labelling {self.symmetry} ({fit})"


class _Group:
    """The symmetries as a group: composition table and each turn in the base frame."""

    def __init__(self, symmetries: Sequence[Symmetry], fiducials: dict[str, np.ndarray]):
        self.symmetries = list(symmetries)
        perms = [s.permutation for s in self.symmetries]
        self.size = len(perms)
        self.compose = np.zeros((self.size, self.size), dtype=int)  # index of pi_a o pi_b
        for a, b in product(range(self.size), repeat=2):
            product_ab = {n: perms[a][perms[b][n]] for n in perms[b]}
            matches = [k for k, p in enumerate(perms) if p == product_ab]
            if len(matches) != 1:
                raise ValueError("choose_labellings: the symmetries do not form a group")
            self.compose[a, b] = matches[0]
        names = [n for n in perms[0] if n in fiducials]
        self.motions = [_rigid_fit(np.array([fiducials[n] for n in names]),
                                   np.array([fiducials[p[n]] for n in names])) for p in perms]

    def turned(self, transform: _Transform, g: int) -> _Transform:
        """``(A, b) o G_g``: the transform of a labelling turned by symmetry ``g``."""
        A, b = transform
        R, t = self.motions[g]
        return A @ R, A @ t + b


def _rigid_fit(source: np.ndarray, target: np.ndarray) -> _Transform:
    """The rotation and translation (metres) taking points ``source`` (N, 3) onto ``target`` (Kabsch)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((target - ct).T @ (source - cs))
    d = np.sign(np.linalg.det(u @ vt))
    R = u @ np.diag([1.0, 1.0, d]) @ vt
    return R, ct - R @ cs


@dataclass
class _Item:
    """A child of a node: an image, or a solved node of the level below.

    ``transforms[g]``: its ``(A_l, b_l)`` when its images take labellings ``compose[c_i, g]`` (None
    where PnP found none); ``members``: image id -> its labelling ``c_i`` in the item's candidate 0.
    """

    child: int
    transforms: list[_Transform | None]
    members: dict[str, int]


@dataclass
class _NodeFit:
    A: np.ndarray
    b: np.ndarray
    misfits: np.ndarray  # (items, symmetries), inf where a candidate has no transform


def _fit_node(items: list[_Item], parent_det: float, rng: np.random.Generator) -> _NodeFit | None:
    """RANSAC over child triples with a labelling each; None with fewer than 3 child placements."""
    by_child: dict[int, list[int]] = defaultdict(list)
    for i, item in enumerate(items):
        if any(t is not None for t in item.transforms):
            by_child[item.child].append(i)
    children = sorted(by_child)
    if len(children) < 3:
        return None
    triples = sample_triples(children, MAX_TRIPLES, rng)
    size = len(items[0].transforms)
    best: tuple[float, _NodeFit] | None = None
    for triple in triples:
        picks = [items[int(rng.choice(by_child[c]))] for c in triple]
        first = next(g for g, t in enumerate(picks[0].transforms) if t is not None)  # twins: fix the first's
        for combo in product(range(size), repeat=2):
            chosen = [picks[0].transforms[first], picks[1].transforms[combo[0]], picks[2].transforms[combo[1]]]
            observations = [(k, t[0], t[1]) for k, t in enumerate(chosen) if t is not None]
            if len(observations) < 3:
                continue
            node = solve_children(observations, 3, parent_det)
            fit = _score(items, node.A_parent, node.b_parent)
            score = float(np.sum(np.minimum(fit.misfits.min(axis=1), MISFIT_CAP)))
            if best is None or score < best[0]:
                best = (score, fit)
    if best is None:
        return None
    fit = best[1]
    for _ in range(REFINEMENTS):  # re-solve from every inlier's best candidate
        choice = np.argmin(fit.misfits, axis=1)
        inliers = [i for i in range(len(items)) if fit.misfits[i, choice[i]] < MISFIT_CAP]
        inlier_children = sorted({items[i].child for i in inliers})
        if len(inlier_children) < 3:
            break
        index = {c: k for k, c in enumerate(inlier_children)}
        observations = [(index[items[i].child], *items[i].transforms[choice[i]]) for i in inliers]
        node = solve_children(observations, len(inlier_children), parent_det)
        fit = _score(items, node.A_parent, node.b_parent)
    return fit


def _score(items: list[_Item], A_parent: np.ndarray, b_parent: np.ndarray) -> _NodeFit:
    """Misfit (eqs. 3, 6-7) of every item's every candidate with one parent transform."""
    size = len(items[0].transforms)
    misfits = np.full((len(items), size), np.inf)
    slots = [(i, g, t) for i, item in enumerate(items) for g, t in enumerate(item.transforms) if t is not None]
    if slots:
        A = np.array([t[0] for _, _, t in slots])
        b = np.array([t[1] for _, _, t in slots])
        values = reflection_fit(A, b, A_parent, b_parent)[0]
        for (i, g, _), value in zip(slots, values):
            misfits[i, g] = value
    return _NodeFit(A_parent, b_parent, misfits)


class _Images:
    """Per image: its fiducials, and per labelling its normalized observations and PnP transform."""

    def __init__(self, dataset: Dataset, group: _Group):
        self.dataset = dataset
        self.points: dict[str, np.ndarray] = {}
        self.observed: dict[str, list[np.ndarray]] = {}
        self.transforms: dict[str, list[_Transform | None]] = {}
        self.too_few: list[str] = []
        for image in dataset.images:
            normalized = dataset.normalized(image)
            names = [n for n in image.observations if n in dataset.fiducials and n in group.symmetries[0].permutation]
            if len(names) < MIN_FIDUCIALS or any(s.permutation[n] not in normalized for s in group.symmetries for n in names):
                self.too_few.append(image.id)
                continue
            base = np.array([dataset.fiducials[n] for n in names])
            self.points[image.id] = base
            self.observed[image.id] = []
            self.transforms[image.id] = []
            for symmetry in group.symmetries:
                observed = np.array([normalized[symmetry.permutation[n]] for n in names])
                candidates = pnp_candidates(base, observed, dataset.num_mirrors)  # eqs. (10)-(12)
                self.observed[image.id].append(observed)
                self.transforms[image.id].append(candidates[0] if candidates else None)

    def costs(self, image_id: str, A_parent: np.ndarray, b_parent: np.ndarray) -> np.ndarray:
        """Whitened squared reprojection cost of each labelling of an image seen through one more
        mirror than ``(A_parent, b_parent)``, its mirror vector fitted (eqs. 3, 5, 9; all labellings in one
        :func:`~mirror_fg.solver.screen.placement_consensus.fit_mirrors`); inf where a point ends behind the camera."""
        sigma = self.dataset.normalized_sigma
        before = self.points[image_id] @ A_parent.T + b_parent  # the points before the image's last mirror
        costs = np.full(len(self.transforms[image_id]), np.inf)
        present = [(g, transform) for g, transform in enumerate(self.transforms[image_id]) if transform is not None]
        if not present:
            return costs
        labellings = [g for g, _ in present]
        starts = reflection_fit(np.array([A for _, (A, _) in present]), np.array([b for _, (_, b) in present]),
                                A_parent, b_parent)[1]
        usable = np.all(np.isfinite(starts), axis=1) & (np.linalg.norm(starts, axis=1) >= 1e-12)
        labellings = [g for g, ok in zip(labellings, usable) if ok]
        if not labellings:
            return costs
        count = len(before)
        index = np.repeat(np.arange(len(labellings)), count)
        observed = np.concatenate([self.observed[image_id][g] for g in labellings])
        fitted, squared = fit_mirrors(np.tile(before, (len(labellings), 1)), index, observed, sigma, starts[usable])
        for k, g in enumerate(labellings):
            if np.all(reflect(before, fitted[k])[:, 2] > 0):
                costs[g] = float(np.sum(squared[k * count:(k + 1) * count]))
        return costs

    def rms(self, image_id: str, cost: float) -> float:
        """An image's RMS reprojection error (pixels with a camera) from its whitened squared cost."""
        return float(np.sqrt(cost / len(self.points[image_id])) * self.dataset.pixel_sigma)


def choose_labellings(
    dataset: Dataset,
    symmetries: Sequence[Symmetry],
    upright: tuple[Sequence[str], Sequence[str]] | None = None,
    seed: int = 0,
) -> tuple[Dataset, list[LabelReport]]:
    """Each image's labelling among ``symmetries`` (the target's, identity first) by consistency across
    the images; returns the relabelled dataset (images left out removed) and one report per image.

    ``dataset``: the images in the detector's labelling (pixels or normalized coordinates, fiducials in
    the base frame); ``upright``: names of the target's first and last rows. Of the capture and its twin
    turned by a symmetry (which fit equally well) the one whose last row lies below its first in most
    images is returned; without ``upright`` the labelling of the first image decided anchors it. With
    one symmetry (an asymmetric target) the dataset is returned as it is, with no reports.
    """
    if len(symmetries) <= 1:
        return dataset, []
    group = _Group(symmetries, dataset.fiducials)
    images = _Images(dataset, group)
    rng = np.random.default_rng(seed)
    reports: dict[str, LabelReport] = {}
    for image_id in images.too_few:
        reports[image_id] = LabelReport(
            image_id, None, reason=f"fewer than {MIN_FIDUCIALS} fiducials of the symmetric target: its labelling cannot be checked")
    choices: dict[str, int] = {}  # image id -> labelling relative to its item's candidate 0
    num_mirrors = dataset.num_mirrors
    by_id = {im.id: im for im in dataset.images}

    # Level Nv: the images under each node (the first Nv-1 placements), one item each.
    level_items: dict[tuple[int, ...], list[_Item]] = defaultdict(list)
    for image in dataset.images:
        if image.id in images.transforms:
            level_items[image.mirror_configs[:-1]].append(
                _Item(image.mirror_configs[-1], images.transforms[image.id], {image.id: 0}))
    for level in range(num_mirrors, 0, -1):
        parent_det = (-1.0) ** (level - 1)
        next_items: dict[tuple[int, ...], list[_Item]] = defaultdict(list)
        for prefix in sorted(level_items):
            items = level_items[prefix]
            fit = _fit_node(items, parent_det, rng)
            where = _describe(prefix, level)
            if fit is None:
                for item in items:
                    for image_id in item.members:
                        reports[image_id] = LabelReport(
                            image_id, None, reason=f"labelling undecided: {where} has fewer than 3 placements of mirror "
                                                   f"{level} with a detection, too few to compare labellings")
                continue
            kept: dict[str, int] = {}
            for i, item in enumerate(items):
                if level == num_mirrors:  # an image: decided by its pixels
                    (image_id,) = item.members
                    decided = _decide_image(images, image_id, fit, reports, where)
                    if decided is not None:
                        kept[image_id] = decided
                    continue
                order = np.argsort(fit.misfits[i])
                best, second = fit.misfits[i, order[0]], fit.misfits[i, order[1]]
                if np.isfinite(best) and second >= max(NODE_MISFIT_RATIO * best, MISFIT_CAP):
                    kept.update({image_id: int(group.compose[c, order[0]]) for image_id, c in item.members.items()})
                else:
                    for image_id in item.members:
                        reports[image_id] = LabelReport(
                            image_id, None, reason=f"labelling ambiguous: the images under mirror {level + 1}'s node "
                                                   f"{_describe(prefix + (item.child,), level + 1)} fit {where} "
                                                   f"about as well turned as not (misfit {best:.2g} vs {second:.2g})")
            if level > 1 and kept:
                transforms: list[_Transform | None] = [group.turned((fit.A, fit.b), g) for g in range(group.size)]
                next_items[prefix[:-1]].append(_Item(prefix[-1], transforms, kept))
            elif level == 1:
                choices.update(kept)
        level_items = next_items

    turn = _upright_turn(choices, group, by_id, upright)
    out_images = []
    for image in dataset.images:
        if image.id in choices:
            g = int(group.compose[choices[image.id], turn])
            symmetry = group.symmetries[g]
            out_images.append(Image(image.id, image.mirror_configs, symmetry.relabel(image.observations)))
            report = reports.get(image.id, LabelReport(image.id, None))
            report.symmetry = symmetry.name
            reports[image.id] = report
        elif image.id not in reports:
            reports[image.id] = LabelReport(image.id, None, reason="labelling undecided")
    relabelled = replace(dataset, fiducials=dict(dataset.fiducials), images=out_images)
    return relabelled, [reports[image.id] for image in dataset.images]


def _decide_image(images: _Images, image_id: str, fit: _NodeFit, reports: dict[str, LabelReport], where: str) -> int | None:
    """The labelling of one image (index into its candidates) when its pixels decide it, else None
    (its report says why)."""
    costs = images.costs(image_id, fit.A, fit.b)
    order = np.argsort(costs)
    best, second = costs[order[0]], costs[order[1]]
    rms_best, rms_second = images.rms(image_id, best), images.rms(image_id, second)
    if np.isfinite(best) and second >= AMBIGUITY_COST_RATIO * best and second - best >= AMBIGUITY_COST_GAP:
        reports[image_id] = LabelReport(image_id, None, rms_best, rms_second)
        return int(order[0])
    if not np.isfinite(best):
        reason = "labelling undecided: no labelling of it is a mirror reflection of the other images"
    elif rms_best > MISFIT_SIGMAS * images.dataset.pixel_sigma:
        reason = (f"labelling undecided: no labelling fits the other images of {where} (best {rms_best:.3g} px, "
                  f"next {rms_second:.3g} px; a wrong corner order, or a camera or board that moved?)")
    else:
        reason = (f"labelling ambiguous: turned or not it fits the other images of {where} about as well "
                  f"({rms_best:.3g} px vs {rms_second:.3g} px)")
    reports[image_id] = LabelReport(image_id, None, rms_best, rms_second, reason=reason)
    return None


def _upright_turn(
    choices: dict[str, int], group: _Group, by_id: dict[str, Image], upright: tuple[Sequence[str], Sequence[str]] | None
) -> int:
    """The symmetry that turns the whole capture so that the target's last row lies below its first in
    most images (summed cosine of the rows' direction with the image's down); 0 without ``upright``."""
    if upright is None or not choices:
        return 0
    top, bottom = upright
    scores = np.zeros(group.size)
    for image_id, c in choices.items():
        observations = by_id[image_id].observations
        for h in range(group.size):
            turned = group.symmetries[int(group.compose[c, h])].relabel(observations)
            if not all(n in turned for n in (*top, *bottom)):
                continue
            down = np.mean([turned[n] for n in bottom], axis=0) - np.mean([turned[n] for n in top], axis=0)
            scores[h] += down[1] / max(float(np.linalg.norm(down)), 1e-12)
    return int(np.argmax(scores))


def _describe(prefix: tuple[int, ...], level: int) -> str:
    if not prefix:
        return "the capture"
    return "placement " + ", ".join(f"(mirror {l + 1}, {m})" for l, m in enumerate(prefix))
