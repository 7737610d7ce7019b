"""The final check of every batch solve, in one place: solve, leave out what ends far off the solution
(``consensus.final_check``: measurements above ``FINAL_SIGMAS``, or their whole image), solve again, at
most :data:`MAX_RECHECKS` times. ``calibrate`` runs it for the paper's tree, for the joint solve with
intrinsics and for the general view model, each with its own solve.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Exclusion
from mirror_fg.solver.screen.consensus import final_check, without
from mirror_fg.solver.model.graph import Labelled

__all__ = ["MAX_RECHECKS", "Checked", "Rechecked", "solve_with_rechecks"]

logger = logging.getLogger("mirror_fg")

#: Times the final check may leave measurements out and solve again.
MAX_RECHECKS = 2


@dataclass
class Checked:
    """What the final check reads of one solve: each measurement's ``image_id`` and ``point`` (in
    ``measurements``), its whitened residual norm and the number of unknowns solved for."""

    measurements: Sequence[Labelled]
    whitened: np.ndarray
    dimension: int


Run = TypeVar("Run")


@dataclass
class Rechecked(Generic[Run]):
    """The last solve, the data it was solved on and everything left out (``excluded`` first)."""

    run: Run
    solved: Dataset
    excluded: list[Exclusion]


def solve_with_rechecks(dataset: Dataset, solve: Callable[[Dataset, list[Exclusion]], Run],
                        checked: Callable[[Run], Checked], excluded: Sequence[Exclusion] = ()) -> Rechecked[Run]:
    """``solve(dataset, excluded)``, then ``solve`` again on the data without what ``final_check`` leaves
    out of its result (``checked(run)``), until nothing is left out or MAX_RECHECKS times; each exclusion
    is logged with its reason and added to ``excluded`` (``solve`` gets those so far, for its messages)."""
    solved, left_out = dataset, list(excluded)
    for recheck in range(MAX_RECHECKS + 1):
        run = solve(solved, left_out)
        if recheck == MAX_RECHECKS:
            break
        check = checked(run)
        more = final_check(solved, list(check.measurements), check.whitened, check.dimension)
        if not more:
            break
        logger.warning("%s: %d measurement(s) or image(s) far off the solution left out; solving again",
                       dataset.source, len(more))
        for exclusion in more:
            logger.warning("%s: image '%s'%s left out: %s", dataset.source, exclusion.image,
                           f" point '{exclusion.point}'" if exclusion.point else "", exclusion.reason)
        left_out += more
        solved = without(solved, more)
    return Rechecked(run, solved, left_out)
