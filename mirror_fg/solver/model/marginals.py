"""What to say when the data leave an unknown unconstrained: GTSAM's indeterminant linear system named as
the unknown it stopped at, and raised as a :class:`~mirror_fg.core.errors.SolveError` (the marginal
covariances themselves: ``views.ViewProblem.covariances``).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import gtsam

from mirror_fg.core.errors import SolveError
from mirror_fg.solver.model.graph import GraphLayout

__all__ = ["unconstrained_as_solve_error", "unconstrained_message"]


def unconstrained_message(error: Exception, layout: GraphLayout | Any) -> str:
    """Name the unknown GTSAM found unconstrained in an indeterminant linear system. ``layout``: anything
    with its unknowns' ``keys`` and ``name_of(key)`` (a GraphLayout, the general model's ViewProblem)."""
    text = str(error)
    for key in layout.keys:
        if gtsam.DefaultKeyFormatter(key) in text:
            return f"the data do not constrain {layout.name_of(key)} (indeterminant system near it)"
    return "the data leave some unknowns unconstrained (indeterminant linear system)"


@contextmanager
def unconstrained_as_solve_error(source: str, unconstrained: Callable[[Exception], str]) -> Iterator[None]:
    """Turn GTSAM's ``IndeterminantLinearSystemException`` (a ``RuntimeError`` in Python) raised inside the
    block into a :class:`SolveError` ``"SOURCE: ..."`` naming, through ``unconstrained(error)`` (e.g.
    :func:`unconstrained_message` of the graph's layout), the unknown GTSAM found unconstrained."""
    try:
        yield
    except RuntimeError as error:
        raise SolveError(f"{source}: {unconstrained(error)}") from None
