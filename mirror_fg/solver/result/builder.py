"""The one builder of a solve's :class:`~mirror_fg.solver.result.calibration.Calibration`.

Every solve (the tree's batch and its incremental graph, the view model's batch and incremental, the
joint solve with intrinsics, the arm) hands its estimate here, so that the residuals' units, the outlier
list and the expected cost are worked out once. Frames and units are the result's
(``calibration.Calibration``): camera <- base, metres, covariances in docs/formats.md's convention.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.fit import expected_cost
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Calibration
from mirror_fg.solver.model.residuals import outliers_of

__all__ = ["build_calibration", "Label"]


class Label:
    """A measurement's ``(image_id, point)``: what the outlier list names."""

    __slots__ = ("image_id", "point")

    def __init__(self, image_id: str, point: str):
        self.image_id, self.point = image_id, point


def build_calibration(
    dataset: Dataset, pose: tuple[np.ndarray, np.ndarray], covariance: np.ndarray | None, *,
    mirror_vectors: Mapping, mirror_covariances: Mapping, points: Mapping, point_covariances: Mapping,
    residuals: np.ndarray, whitened: np.ndarray, labels: Iterable[tuple[str, str]], unknowns: int | None,
    iterations: int, initial_error: float, final_error: float, converged: bool,
    timings: Mapping[str, float] | None = None, excluded: Iterable = (), in_pixels: bool | None = None,
    **more: Any,
) -> Calibration:
    """The :class:`Calibration` of an estimate: ``pose`` ``(R_cam_base, t_cam_base)`` of the first camera with
    its 6x6 ``covariance``; ``residuals`` (N, 2), their whitened norms ``whitened`` (N) and ``labels``
    ``(image_id, point)`` per measurement; ``unknowns`` the scalar unknowns the solve fitted (the expected
    cost is half of ``2 N - unknowns``; None: not known, e.g. an incremental estimate without residuals);
    ``in_pixels``: residuals in pixels (None: where the dataset has a camera). ``more``: the result's other
    fields (``analytic``, ``camera``, ``cameras``, ``rig``, ``robot``, ...). Nothing is copied: a caller that
    goes on changing its dictionaries passes copies."""
    labels = [(image_id, point) for image_id, point in labels]
    in_pixels = dataset.camera is not None if in_pixels is None else in_pixels
    expected = expected_cost(2 * len(labels), unknowns) if unknowns is not None else float("nan")
    R, t = pose
    return Calibration(
        R_cam_base=R, t_cam_base=t, covariance=covariance,
        mirror_vectors=mirror_vectors, mirror_covariances=mirror_covariances,  # type: ignore[arg-type]
        points=points, point_covariances=point_covariances,  # type: ignore[arg-type]
        analytic=more.pop("analytic", None), iterations=int(iterations), initial_error=float(initial_error),
        final_error=float(final_error), converged=bool(converged), residuals=residuals,
        residual_labels=labels,
        residual_units="px" if in_pixels else "normalized",
        outliers=outliers_of([Label(i, p) for i, p in labels], whitened),
        timings=timings if timings is not None else {},  # type: ignore[arg-type]
        expected_final_error=expected, excluded=list(excluded), **more,
    )
