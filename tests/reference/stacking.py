"""Which measurements each stacked factor of ``batched.py`` holds, and what the factors need of the
solver's objects (as Protocols, so that the factors do not import the solver).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np

__all__ = [
    "Fiducials", "KeyLayout", "Observation", "MAX_POINTS_PER_FACTOR", "TARGET_MEASUREMENTS_PER_FACTOR",
    "MAX_IMAGES_PER_FACTOR", "auto_images_per_factor", "group_measurements", "sigma_rows",
]

#: Default grouping (measured, see :func:`auto_images_per_factor`): landmarks per factor, about how many
#: measurements a factor holds when ``images_per_factor`` is automatic, and at most how many images.
MAX_POINTS_PER_FACTOR = 16
TARGET_MEASUREMENTS_PER_FACTOR = 72
MAX_IMAGES_PER_FACTOR = 12


class Fiducials(Protocol):
    """Known base-frame points (metres) by name: e.g. a ``Dataset``."""

    @property
    def fiducials(self) -> Mapping[str, np.ndarray]: ...


class KeyLayout(Protocol):
    """Which GTSAM key holds which unknown: e.g. a ``GraphLayout``."""

    @property
    def pose_key(self) -> int: ...  # Pose3 of T_cam_base
    @property
    def mirror_keys(self) -> Mapping[tuple[int, int], int]: ...  # Point3 per mirror configuration (l, m)
    @property
    def point_keys(self) -> Mapping[str, int]: ...  # Point3 per reconstruction point


class Observation(Protocol):
    """One measurement: e.g. a ``Measurement``. ``normalized``: (2,) normalized image coordinates;
    ``mirror_configs``: the image's placement of each mirror (mirror 1 first)."""

    @property
    def image_id(self) -> str: ...
    @property
    def point(self) -> str: ...
    @property
    def normalized(self) -> np.ndarray: ...
    @property
    def mirror_configs(self) -> Sequence[int]: ...


def auto_images_per_factor(measurements: Sequence[Observation], landmark_of: list[int], max_points_per_factor: int | None) -> int:
    """Images per factor so that a factor holds about ``TARGET_MEASUREMENTS_PER_FACTOR`` measurements.

    Measured (scripts/benchmark.py problems): bigger factors amortise the ~5-25 us fixed cost of a
    Python factor call (more inside GTSAM's optimizers, which copy the whole ``Values`` per call), but
    their zero-padded dense Jacobians make elimination and per-key ``Marginals`` slower.
    """
    per_image: dict[str, list[int]] = {}
    for i, meas in enumerate(measurements):
        per_image.setdefault(meas.image_id, [0, 0])[landmark_of[i] >= 0] += 1
    chunk = [f + (min(p, max_points_per_factor) if max_points_per_factor else p) for f, p in per_image.values()]
    typical = max(float(np.median(chunk)), 1.0)
    return int(np.clip(round(TARGET_MEASUREMENTS_PER_FACTOR / typical), 1, MAX_IMAGES_PER_FACTOR))


def group_measurements(
    measurements: Sequence[Observation], landmark_of: list[int], images_per_factor: int, max_points_per_factor: int | None
) -> list[list[int]]:
    """Measurement indices of each factor: by image (file order), consecutive images under the same
    parent placements merged up to ``images_per_factor``, landmarks split into chunks of at most
    ``max_points_per_factor`` (an image's fiducials go with its first chunk)."""
    images: dict[str, list[int]] = {}
    for i, meas in enumerate(measurements):
        images.setdefault(meas.image_id, []).append(i)
    merged: list[list[int]] = []
    parent = None
    count = 0
    for indices in images.values():
        configs = tuple(measurements[indices[0]].mirror_configs)
        if merged and count < images_per_factor and configs[:-1] == parent:
            merged[-1].extend(indices)
            count += 1
        else:
            merged.append(list(indices))
            parent, count = configs[:-1], 1
    if max_points_per_factor is None:
        return merged
    groups = []
    for indices in merged:
        fiducial = [i for i in indices if landmark_of[i] < 0]
        landmarks = list(dict.fromkeys(landmark_of[i] for i in indices if landmark_of[i] >= 0))
        chunks = [landmarks[c : c + max_points_per_factor] for c in range(0, len(landmarks), max_points_per_factor)]
        if not chunks:
            groups.append(fiducial)
            continue
        for c, chunk in enumerate(chunks):
            members = set(chunk)
            rows = [i for i in indices if landmark_of[i] in members]
            groups.append((fiducial if c == 0 else []) + rows)
    return [g for g in groups if g]


def sigma_rows(noise_sigma: np.ndarray, count: int) -> np.ndarray:
    """Measurement noise as one row (x, y) per measurement, (count, 2), normalized coordinates: a
    (2,) sigma shared by all (repeated) or already (count, 2) (copied). Refuses other shapes and sigmas
    that are not finite and > 0."""
    sigma = np.asarray(noise_sigma, dtype=float)
    if sigma.shape == (2,):
        sigma = np.broadcast_to(sigma, (count, 2))
    elif sigma.shape != (count, 2):
        raise ValueError(f"noise sigma: expected shape (2,) or ({count}, 2), got {sigma.shape}")
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0.0)):
        raise ValueError("noise sigma: every sigma must be finite and > 0")
    return np.array(sigma)
