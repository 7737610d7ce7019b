"""``SolveOptions``: how ``calibrate`` solves, in one frozen value (as GTSAM's ``SmartProjectionParams``).

The factor kind is a :class:`Linearization` of the one measurement model: one ``reference`` view factor per
image (``factors/views.py``), the ``stacked`` vectorised ones (``factors/view_stack.py``, same model and
Jacobians) or ``eliminated``: the stacked factors with each photograph's own placement eliminated inside
them (``factors/view_eliminated.py``) where the data allow it, else stacked (see :meth:`SolveOptions.eliminates`).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any
from dataclasses import dataclass, replace
from enum import Enum

from mirror_fg.factors.robust import check_kernel

__all__ = ["Linearization", "Progress", "SolveOptions", "IncrementalOptions", "STAGES"]

#: ``progress(stage, done, total)``: called as each stage of ``calibrate`` advances (``total`` None
#: where it is not known in advance).
Progress = Callable[[str, int, "int | None"], None]
#: The stages ``calibrate`` reports, in order.
STAGES = ("initial estimate", "Levenberg-Marquardt", "marginals")


class Linearization(str, Enum):
    """The factors the MLE (eq. 23) is linearised with; every kind gives the same estimates."""

    REFERENCE = "reference"  # one view factor per image (factors/views.py)
    STACKED = "stacked"  # the views stacked into vectorised factors (factors/view_stack.py)
    ELIMINATED = "eliminated"  # stacked, each photograph's own placement eliminated inside (factors/view_eliminated.py)


@dataclass(frozen=True)
class SolveOptions:
    """The settings of one ``calibrate`` (arguments as :func:`mirror_fg.solver.calibrate.calibrate`).

    robust: ``None``, ``"huber"`` or ``"cauchy"`` (another name: ValueError). linearization: a
    :class:`Linearization` or its value. on_iteration: ``(iteration, error_before, error_after)`` after
    each LM iteration. progress: ``progress(stage, done, total)`` per stage of :data:`STAGES`.
    """

    robust: str | None = None
    linearization: Linearization = Linearization.ELIMINATED
    max_iterations: int = 100
    compute_covariance: bool = True
    on_iteration: Callable[[int, float, float], None] | None = None
    progress: Progress | None = None
    diagnose: bool = True

    def __post_init__(self) -> None:
        check_kernel(self.robust)
        # a string ("stacked") is taken as its Linearization; another value: ValueError
        object.__setattr__(self, "linearization", Linearization(self.linearization))

    @property
    def stacked(self) -> bool:
        """Whether the graph uses the stacked factors (``graph.build_graph(fast=...)``) rather than the reference ones."""
        return self.linearization is not Linearization.REFERENCE

    def report(self, stage: str, done: int, total: int | None) -> None:
        """``progress(stage, done, total)`` where there is a progress callback."""
        if self.progress is not None:
            self.progress(stage, done, total)

    def iteration(self, number: int, error_before: float, error_after: float) -> None:
        """The LM iteration hook: the Levenberg-Marquardt stage's progress, then ``on_iteration``."""
        self.report(STAGES[1], number, self.max_iterations)
        if self.on_iteration is not None:
            self.on_iteration(number, error_before, error_after)

    def nested(self) -> "SolveOptions":
        """These options for a solve run inside another (a start, a consistency check): the user's kernel,
        linearisation and iteration limit, without covariances, diagnosis, progress or iteration hook
        (those belong to the solve the user asked for)."""
        return replace(self, compute_covariance=False, diagnose=False, on_iteration=None, progress=None)

    def eliminates(self, allowed: bool = True) -> bool:
        """Whether to build the eliminated graph: asked for, no robust kernel (the elimination solves
        the placements by least squares) and ``allowed`` (``lm.ELIMINATE``, the switch tests turn off)."""
        return self.linearization is Linearization.ELIMINATED and self.robust is None and allowed


@dataclass(frozen=True)
class IncrementalOptions:
    """The settings of the incremental path (iSAM2: :class:`~mirror_fg.solver.incremental.IncrementalCalibrator`,
    :func:`~mirror_fg.solver.incremental.calibrate_incremental`), one value as :class:`SolveOptions` is
    for the batch.

    robust: ``None``, ``"huber"`` or ``"cauchy"`` (another name: ValueError). points: the reconstruction
    points to estimate (None: those the dataset names). thresholds: iSAM2's relinearisation thresholds
    (``incremental.state.RelinearizeThresholds``; None: its defaults, the one place they are set). seed:
    the consensus's random choices. accept_poor_fit: a final estimate that fits worse than the noise model
    allows is kept (``calibrate_incremental``).
    """

    robust: str | None = None
    points: tuple[str, ...] | None = None
    thresholds: Any = None
    seed: int = 0
    accept_poor_fit: bool = False

    def __post_init__(self) -> None:
        check_kernel(self.robust)
        if self.points is not None:
            object.__setattr__(self, "points", tuple(self.points))

    def backend_options(self) -> dict[str, Any]:
        """The keywords the incremental backends take."""
        return {"points": self.points, "robust": self.robust, "thresholds": self.thresholds, "seed": self.seed}

    def solve_options(self) -> SolveOptions:
        """The batch settings of the checks the incremental path runs (consistency, splits)."""
        return SolveOptions(robust=self.robust)
