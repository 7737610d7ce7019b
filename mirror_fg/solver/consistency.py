"""Inconsistent captures diagnosed (issue 15): when the images do not fit one ``T_cam_base``, do they split
into groups that each fit one? A camera (or a board) that moved mid-capture shows as images before and
after some index in capture order that are each consistent alone but disagree with each other.

Each group is solved on its own (analytical solution, then the MLE of eq. 23 without covariances); a
split is named when both groups are plausible alone (their final cost within its chi-square range,
``lm.plausible``) and the whole is not.
"""
from __future__ import annotations

from dataclasses import replace

import logging

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.transform import rotation_angle
from mirror_fg.io.dataset import Dataset, Image
from mirror_fg.solver.calibration import Calibration, Inconsistency
from mirror_fg.solver.consensus import PnPCandidates
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.lm import levenberg_marquardt

__all__ = ["MAX_SPLITS_TRIED", "GroupFit", "fit_group", "diagnose_split", "describe_split", "split_in_capture_order"]

logger = logging.getLogger("mirror_fg")

#: At most this many split indices in capture order are solved in a first pass (evenly spaced);
#: the best one's neighbourhood is then searched index by index.
MAX_SPLITS_TRIED = 12


class GroupFit:
    """One group of images solved alone: its ``T_cam_base``, final cost and whether the cost is plausible."""

    def __init__(self, R: np.ndarray, t: np.ndarray, final_error: float, plausible: bool):
        self.R, self.t, self.final_error, self.plausible = R, t, final_error, plausible

    @property
    def camera_centre(self) -> np.ndarray:
        """Camera centre in the base frame (``T_base_cam``'s translation), metres."""
        return -self.R.T @ self.t


def fit_group(dataset: Dataset, images: list[Image], pnp: PnPCandidates | None = None) -> GroupFit | None:
    """``images`` of ``dataset`` solved alone, or None where they cannot be (too few placements, ...).
    ``pnp``: PnP candidates already computed for some of the images (``consensus.screen``)."""
    group = replace(dataset, images=images)
    try:
        start = initial_estimate(group, pnp=pnp)
        run = levenberg_marquardt(group, start, None, True, 100, None, {})
    except (DatasetError, SolveError, RuntimeError, np.linalg.LinAlgError):
        return None
    R, t, _, _ = run.estimate()
    return GroupFit(R, t, run.final_error, run.plausible)


def describe_split(dataset: Dataset, groups: list[list[int]], fits: list[GroupFit]) -> Inconsistency:
    """The :class:`Inconsistency` of two groups (indices in capture order) and their fits."""
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

    message = (f"images {span(groups[0])} and {span(groups[1])} disagree by {rotation_deg:.1f}° / {position_mm:.0f} mm: "
               "did the camera or the board move?")
    ids = tuple(tuple(dataset.images[i].id for i in group) for group in groups)
    return Inconsistency(ids, rotation_deg, position_mm, message)


def _split_at(dataset: Dataset, k: int, pnp: PnPCandidates | None) -> tuple[float, list[GroupFit]] | None:
    fits = [fit_group(dataset, dataset.images[:k], pnp), fit_group(dataset, dataset.images[k:], pnp)]
    if fits[0] is None or fits[1] is None:
        return None
    return fits[0].final_error + fits[1].final_error, [fits[0], fits[1]]


def diagnose_split(dataset: Dataset, calibration: Calibration, pnp: PnPCandidates | None = None) -> Inconsistency | None:
    """Where the calibration's final cost is implausible: the split of the images in capture order into
    two groups each consistent alone (the lowest total cost of the two solves), or None when there is
    no such split."""
    if calibration.cost_plausible:
        return None
    return split_in_capture_order(dataset, calibration.final_error, pnp)


def split_in_capture_order(
    dataset: Dataset, whole_error: float = float("nan"), pnp: PnPCandidates | None = None
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
                tried[k] = _split_at(dataset, int(k), pnp)
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
