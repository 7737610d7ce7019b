"""Every measurement's predicted and residual reprojection at an estimate (eqs. 5, 9), and the outliers.

One prediction for batch and incremental results: the core's batched primitives
(:func:`~mirror_fg.core.geometry.nested_transforms`, :func:`~mirror_fg.core.geometry.predict_camera_points`,
:func:`~mirror_fg.core.geometry.project`), one composite ``(A, b)`` per distinct mirror schedule.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mirror_fg.core.geometry import nested_transforms, predict_camera_points, project
from mirror_fg.data import Dataset
from mirror_fg.solver.model.graph import Labelled, Measurement, measurement_sigmas

__all__ = ["OUTLIER_SIGMAS", "predicted_normalized", "residual_statistics", "outliers_of"]

#: Measurements whose whitened residual exceeds this many sigmas after the solve are reported.
OUTLIER_SIGMAS = 5.0


def predicted_normalized(
    dataset: Dataset, measurements: list[Measurement], R: np.ndarray, t: np.ndarray,
    mirror_vectors: dict[tuple[int, int], np.ndarray], points: dict[str, np.ndarray],
) -> np.ndarray:
    """Predicted normalized coordinates (N, 2) of every measurement (eqs. 5, 9), one (A, b) per image
    schedule. ``R``, ``t``: ``T_cam_base``; ``mirror_vectors`` (camera frame) and ``points`` (base frame)
    in metres."""
    base_points = np.array(
        [dataset.fiducials[m.point] if m.point in dataset.fiducials else points[m.point] for m in measurements]
    ).reshape(-1, 3)
    schedules: dict[tuple[int, ...], int] = {}
    index = np.array([schedules.setdefault(m.mirror_configs, len(schedules)) for m in measurements], dtype=int)
    num_mirrors = len(next(iter(schedules), ()))
    vectors = [
        np.array([mirror_vectors[(level + 1, configs[level])] for configs in schedules]).reshape(-1, 3)
        for level in range(num_mirrors)
    ]
    A, b = nested_transforms(R, t, vectors)  # eqs. (5)-(8)
    return project(predict_camera_points(A, b, index, base_points))  # eq. (9)


def residual_statistics(
    dataset: Dataset, measurements: list[Measurement], predicted: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 2) predicted minus observed, in pixels (through the distortion) where the dataset
    has a camera, else normalized; and each measurement's whitened residual norm in its own sigmas
    (``graph.measurement_sigmas``: ``point_sigma`` where given)."""
    observed_normalized = np.array([m.normalized for m in measurements]).reshape(-1, 2)
    whitened = np.linalg.norm((predicted - observed_normalized) / measurement_sigmas(dataset, measurements), axis=1)
    if dataset.camera is None:
        return predicted - observed_normalized, whitened
    by_id = {image.id: image for image in dataset.images}
    observed_pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements]).reshape(-1, 2)
    return dataset.camera.distort(predicted) - observed_pixels, whitened


def outliers_of(measurements: Sequence[Labelled], whitened: np.ndarray) -> list[tuple[str, str, float]]:
    """``(image id, point, sigmas)`` of each measurement whose whitened residual exceeds ``OUTLIER_SIGMAS``."""
    return [(m.image_id, m.point, float(w)) for m, w in zip(measurements, whitened) if w > OUTLIER_SIGMAS]
