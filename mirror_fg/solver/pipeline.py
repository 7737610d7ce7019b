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

from mirror_fg.io.dataset import Dataset
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
    """screen -> solve -> final check (solve again without what ends far off) -> finish."""
    screened, excluded = problem.screen(dataset)
    return problem.finish(solve_with_rechecks(screened, problem.solve, problem.check, excluded))
