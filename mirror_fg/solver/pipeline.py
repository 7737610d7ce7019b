"""The one batch pipeline of ``calibrate()``, whatever the problem: screen (consensus: what disagrees
with the rest left out, named) -> solve (the start, then the MLE by Levenberg-Marquardt with its restarts,
eq. 23) -> final check (``rechecks.py``: what ends far off the solution left out, solved again) ->
finish (marginals, what the data contradict, the :class:`~mirror_fg.solver.result.calibration.Calibration`).

A *problem* says how each step is done for its kind of data; three implement it:
``tree_problem.TreeProblem`` (the paper's tree, normalized measurements, stacked or eliminated factors),
``pixel_problem.PixelProblem`` (the same with intrinsics estimated: pixel factors, its screen the
fixed-intrinsics start) and ``views_solve.ViewsProblem`` (the general view model: any reflections,
several cameras, no known target; normalized or, with intrinsics, pixel factors).
"""
from __future__ import annotations

from typing import Protocol, TypeVar

from mirror_fg.core.errors import SolveError
from mirror_fg.core.values import clip
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.screen.rechecks import Checked, Rechecked, solve_with_rechecks

__all__ = ["Problem", "run_pipeline"]

Run = TypeVar("Run")


class Problem(Protocol[Run]):
    """How one kind of data goes through the pipeline (module docstring)."""

    def screen(self, dataset: Dataset) -> tuple[Dataset, list[Exclusion]]:
        """The data to solve and what was left out before any solve, each with its reason."""
        ...

    def solve(self, solved: Dataset, excluded: list[Exclusion]) -> Run:
        """One solve of ``solved`` (``excluded``: what is left out so far, for messages)."""
        ...

    def check(self, run: Run) -> Checked:
        """What the final check reads of a solve."""
        ...

    def finish(self, rechecked: Rechecked[Run]) -> Calibration:
        """The calibration of the last solve."""
        ...


def run_pipeline(problem: Problem[Run], dataset: Dataset) -> Calibration:
    """screen -> solve -> final check (solve again without what ends far off) -> finish. SolveError where the
    screen leaves every image out: nothing is left to solve."""
    screened, excluded = problem.screen(dataset)
    if dataset.images and not screened.images:
        raise SolveError(_nothing_left(dataset, excluded))
    return problem.finish(solve_with_rechecks(screened, problem.solve, problem.check, excluded))


def _nothing_left(dataset: Dataset, excluded: list[Exclusion]) -> str:
    """Why nothing is left to solve, in the user's words: the screen left every image out. Where every image
    disagrees with its own PnP fit, the noise model or the target is more likely at fault than every image."""
    first = next((e for e in excluded if e.point is None), excluded[0] if excluded else None)
    example = f" (image {clip(first.image, 40)!r}: {first.reason})" if first is not None else ""
    return (f"{dataset.source}: every image was left out before the solve{example}: when all of them disagree, "
            f"check pixel_sigma ({dataset.pixel_sigma:g}: too small for these images?), the fiducials' "
            "coordinates and the camera's intrinsics")
