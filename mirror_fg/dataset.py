"""Dataset (``mirror-fg/dataset@1``) and result (``mirror-fg/result@1``) files, validation, DatasetError.

Coordinates: fiducials in the base frame {B}, metres; observations in pixels when the dataset has a
camera (undistorted and normalized here with OpenCV), else normalized image coordinates.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DATASET_FORMAT = "mirror-fg/dataset@1"
RESULT_FORMAT = "mirror-fg/result@1"


class DatasetError(ValueError):
    """Bad input: the message names the file, image or point and what is wrong, in one line."""


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with OpenCV distortion ``(k1, k2, p1, p2[, k3])``; focal lengths and centre in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (N, 2) of pixel coordinates (N, 2) (cv2.undistortPoints)."""
        import cv2

        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if pixels.shape[0] == 0:
            return np.zeros((0, 2))
        return cv2.undistortPoints(pixels, self.K, np.asarray(self.dist, dtype=np.float64)).reshape(-1, 2)

    def distort(self, normalized: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of normalized coordinates (N, 2) through the distortion (cv2.projectPoints)."""
        import cv2

        normalized = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
        if normalized.shape[0] == 0:
            return np.zeros((0, 2))
        rays = np.hstack([normalized, np.ones((len(normalized), 1))])
        pixels, _ = cv2.projectPoints(
            rays, np.zeros(3), np.zeros(3), self.K, np.asarray(self.dist, dtype=np.float64)
        )
        return pixels.reshape(-1, 2)


@dataclass
class Image:
    """One image: the placement index of every mirror and what it observed.

    ``mirror_configs[l-1]`` is the configuration index of mirror l. ``observations`` maps a point name to
    its measured coordinates as in the file (pixels with a camera, normalized without one).
    """

    id: str
    mirror_configs: tuple[int, ...]
    observations: dict[str, np.ndarray]


@dataclass
class Dataset:
    """A validated ``mirror-fg/dataset@1``.

    ``fiducials``: known base-frame points, metres. ``pixel_sigma``: measurement noise (pixels with a
    camera, else normalized units). ``source``: the file it came from, for messages.
    """

    num_mirrors: int
    camera: Camera | None
    pixel_sigma: float
    fiducials: dict[str, np.ndarray]
    images: list[Image]
    source: str = "<dataset>"
    _normalized_cache: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False)

    @property
    def normalized_sigma(self) -> np.ndarray:
        """Measurement standard deviation (2,) in normalized image coordinates (x, y)."""
        if self.camera is None:
            return np.array([self.pixel_sigma, self.pixel_sigma])
        return np.array([self.pixel_sigma / self.camera.fx, self.pixel_sigma / self.camera.fy])

    def normalized(self, image: Image) -> dict[str, np.ndarray]:
        """Observations of ``image`` in normalized image coordinates (undistorted when there is a camera)."""
        cached = self._normalized_cache.get(image.id)
        if cached is not None and cached.keys() == image.observations.keys():
            return cached
        names = list(image.observations)
        coords = np.array([image.observations[n] for n in names], dtype=float).reshape(-1, 2)
        if self.camera is not None:
            coords = self.camera.normalize(coords)
        result = {name: coords[i] for i, name in enumerate(names)}
        self._normalized_cache[image.id] = result
        return result

    @property
    def reconstruction_point_names(self) -> list[str]:
        """Sorted names of observed points that are not fiducials (their positions are estimated)."""
        names = {n for image in self.images for n in image.observations if n not in self.fiducials}
        return sorted(names)

    @property
    def configurations(self) -> list[tuple[int, int]]:
        """Sorted mirror configurations ``(l, m)`` (mirror l is 1-based) seen in the images."""
        return sorted({(l + 1, m) for image in self.images for l, m in enumerate(image.mirror_configs)})
