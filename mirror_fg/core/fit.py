"""The fit test's statistics: the cost a solve should end at, and whether the one it reached is plausible.

Costs are the factor graph's ``0.5 * chi^2`` of whitened residuals (pixels over ``pixel_sigma``, unitless).
With ``rows`` scalar residuals (two per measured image point) and ``unknowns`` scalar unknowns at a
least-squares optimum, ``chi^2`` has ``rows - unknowns`` degrees of freedom, so the cost's mean is half
that and its spread ``sqrt(dof / 2)``. Every solve (batch, incremental, screen, verify, arm) asks here.
"""
from __future__ import annotations

import math

__all__ = ["expected_cost", "plausible", "PLAUSIBLE_SPREADS"]

#: How many spreads ``sqrt(dof / 2)`` above its mean a final cost may lie and still be plausible.
PLAUSIBLE_SPREADS = 10.0


def expected_cost(rows: int, unknowns: int, min_dof: int = 0) -> float:
    """Mean of the final cost ``0.5 chi^2`` at the optimum: half the degrees of freedom ``rows - unknowns``,
    taken as at least ``min_dof`` (0: none left; a caller that divides by the cost asks for 1)."""
    return 0.5 * max(rows - unknowns, min_dof)


def plausible(final_error: float, expected_final_error: float) -> bool:
    """Whether a final cost 0.5 chi^2 is within :data:`PLAUSIBLE_SPREADS` spreads (sqrt(dof / 2)) above its
    mean dof / 2."""
    spread = math.sqrt(max(expected_final_error, 1.0))
    return not final_error > expected_final_error + PLAUSIBLE_SPREADS * spread
