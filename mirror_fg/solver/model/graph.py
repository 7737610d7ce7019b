"""The factor graph of a dataset (eq. 23): which key holds which unknown, one factor per measurement.

Unknowns (eq. 21): one ``Pose3`` node ``X(0)`` for ``T_cam_base`` (camera <- base), one ``Point3`` node
``V(i)`` per mirror configuration (mirror vector, camera frame, metres) and one ``Point3`` node ``L(j)``
per reconstruction point (base frame, metres). The pipeline that solves it is ``solver/calibrate.py``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from mirror_fg.data import Dataset
from mirror_fg.io.point_sigma import normalized_sigmas

__all__ = [
    "Estimate", "GraphLayout", "InitialEstimate", "Labelled", "Measurement", "measurement_sigmas", "measurements_of",
    "unknown_name",
]


class Labelled(Protocol):
    """What the outlier checks read of a measurement: its image and point (a :class:`Measurement`, or a
    general view model's label)."""

    image_id: str
    point: str


class InitialEstimate(Protocol):
    """Anything with the unknowns' values: an ``AnalyticSolution`` or a ground truth."""

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]


@dataclass
class Estimate:
    """Plain values of every unknown (an :class:`InitialEstimate`): a guess, a truth, a result read back."""

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]


@dataclass
class GraphLayout:
    """Which key holds which unknown."""

    pose_key: int
    mirror_keys: dict[tuple[int, int], int]
    point_keys: dict[str, int]

    @classmethod
    def for_dataset(cls, dataset: Dataset) -> "GraphLayout":
        return cls(
            pose_key=X(0),
            mirror_keys={config: V(i) for i, config in enumerate(dataset.configurations)},
            point_keys={name: L(j) for j, name in enumerate(dataset.reconstruction_point_names)},
        )

    @property
    def keys(self) -> list[int]:
        """Every unknown's key: the pose, the placements, the points."""
        return [self.pose_key, *self.mirror_keys.values(), *self.point_keys.values()]

    def name_of(self, key: int) -> str:
        """Human name of the unknown behind a key."""
        return unknown_name(key, {self.pose_key: "T_cam_base"}, self.mirror_keys, self.point_keys)


def unknown_name(key: int, poses: dict[int, str], mirror_keys: dict[tuple[int, int], int],
                 point_keys: dict[str, int]) -> str:
    """Human name of the unknown behind a key: ``poses`` names the pose keys, then a mirror placement or a
    point (GTSAM's key formatting for anything else)."""
    if key in poses:
        return poses[key]
    for (l, m), k in mirror_keys.items():
        if k == key:
            return f"mirror {l} placement {m}"
    for name, k in point_keys.items():
        if k == key:
            return f"point '{name}'"
    return gtsam.DefaultKeyFormatter(key)


@dataclass
class Measurement:
    """One observation: image, point name, normalized coordinates (2,), the image's mirror configs."""

    image_id: str
    point: str
    normalized: np.ndarray
    mirror_configs: tuple[int, ...]


def measurements_of(dataset: Dataset) -> list[Measurement]:
    """Every observation of the dataset in normalized coordinates, in file order."""
    result = []
    for image in dataset.images:
        normalized = dataset.normalized(image)
        for name in image.observations:
            result.append(Measurement(image.id, name, normalized[name], image.mirror_configs))
    return result


def measurement_sigmas(dataset: Dataset, measurements: Sequence[Measurement]) -> np.ndarray:
    """Each measurement's standard deviation (N, 2) in normalized coordinates (x, y), in the order of
    ``measurements``: its point's ``point_sigma`` where the dataset gives one, else ``pixel_sigma``, over
    the focal lengths (``io/point_sigma.py``). The one noise model of every factor, the outlier test and
    the incremental graph."""
    return normalized_sigmas(dataset.camera, dataset.pixel_sigma, dataset.point_sigma, [m.point for m in measurements])
