"""Residuals of a ``mirror-fg/result@1`` on its dataset: every measurement predicted (eqs. 5-9) and compared.

Residuals are ``predicted - observed`` in pixels when the dataset has a camera, else in normalized image
coordinates. "RMS" is the root mean square of the measurements' Euclidean residual lengths, as
``residuals.rms_px`` in result@1 (``sqrt(2) pixel_sigma`` expected under the noise model); every
other statistic is named for what it is. :meth:`Residuals.radial_profile` is the RMS against the
distance from the image centre: growth towards the edge is the signature of a wrong distortion model.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.geometry import nested_transforms, predict_camera_points, project
from mirror_fg.io.result import estimated_camera, mirror_vectors, transforms, validate_result
from mirror_fg.io.result import points as reconstruction_points

if TYPE_CHECKING:
    from mirror_fg.data import Dataset

__all__ = ["Residuals", "RadialProfile", "compute_residuals", "residuals_of_valid_result", "OUTLIER_FACTOR",
           "RADIAL_P_VALUE", "RADIAL_RATIO"]

#: An image is flagged when its RMS residual exceeds this many times the median image RMS.
OUTLIER_FACTOR = 3.0
#: The residual grows with the distance from the image centre (a wrong distortion model) when the
#: outer third's RMS is this many times the inner third's and an F test gives a p-value below RADIAL_P_VALUE.
RADIAL_RATIO = 1.3
RADIAL_P_VALUE = 1e-3


@dataclass
class RadialProfile:
    """Residual RMS against the distance from the image centre (principal point; normalized: the axis).

    ``edges`` (bins + 1,) radii; ``rms`` and ``counts`` (bins,) per ring (NaN where empty), RMS as
    result@1's ``rms_px``; ``inner_rms`` / ``outer_rms``: the inner and outer thirds of the measurements
    by radius; ``p_value``: one-sided F test that the outer third's squared lengths are larger
    (2 degrees of freedom per measurement under the noise model; log F taken as normal, numpy only).
    """

    radius: np.ndarray
    length: np.ndarray
    edges: np.ndarray
    rms: np.ndarray
    counts: np.ndarray
    inner_rms: float
    outer_rms: float
    p_value: float

    @property
    def ratio(self) -> float:
        return self.outer_rms / self.inner_rms if self.inner_rms > 0 else float("nan")

    @property
    def significant(self) -> bool:
        """The residual grows towards the edge beyond noise (RADIAL_RATIO and RADIAL_P_VALUE)."""
        return bool(self.ratio > RADIAL_RATIO and self.p_value < RADIAL_P_VALUE)


@dataclass
class Residuals:
    """Per-measurement residuals of a result on a dataset, in dataset order.

    ``predicted``, ``observed`` (N, 2): pixels (``units == "px"``) or normalized image coordinates
    (``units == "normalized"``). ``residual = predicted - observed``. Measurements whose prediction lies
    behind the camera are kept with NaN predictions and left out of every statistic.
    """

    units: str
    image_ids: list[str]
    names: list[str]
    is_fiducial: np.ndarray
    predicted: np.ndarray
    observed: np.ndarray
    sigma: float

    @property
    def residual(self) -> np.ndarray:
        """(N, 2) ``predicted - observed``."""
        return self.predicted - self.observed

    @property
    def valid(self) -> np.ndarray:
        """(N,) measurements with a finite prediction."""
        return np.all(np.isfinite(self.predicted), axis=1)

    @property
    def rms(self) -> float:
        """RMS of the Euclidean residual lengths (result@1's ``rms_px``); expected ``sqrt(2) sigma``."""
        r = self.residual[self.valid]
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if r.size else float("nan")

    @property
    def expected_rms(self) -> float:
        """``sqrt(2) sigma``: the RMS residual length when the residuals are N(0, sigma^2 I)."""
        return math.sqrt(2.0) * self.sigma

    @property
    def largest(self) -> float:
        """Largest Euclidean residual of one measurement."""
        r = self.residual[self.valid]
        return float(np.max(np.linalg.norm(r, axis=1))) if r.size else float("nan")

    def _rms_by(self, keys: Sequence[str]) -> dict[str, float]:
        r = self.residual
        ok = self.valid
        out: dict[str, float] = {}
        for key in dict.fromkeys(keys):  # first-seen order
            sel = ok & (np.asarray(keys) == key)
            if np.any(sel):
                out[key] = float(np.sqrt(np.mean(np.sum(r[sel] ** 2, axis=1))))
        return out

    def per_image_rms(self) -> dict[str, float]:
        """RMS residual of each image (dataset order)."""
        return self._rms_by(self.image_ids)

    def per_point_rms(self) -> dict[str, float]:
        """RMS residual of each point over the images that saw it (first-seen order)."""
        return self._rms_by(self.names)

    def radial_profile(self, centre: Sequence[float], bins: int = 6) -> RadialProfile | None:
        """Residual RMS by distance of the observed point from ``centre`` (pixels, or normalized (0, 0));
        None with fewer than 6 measurements."""
        ok = self.valid
        if int(np.sum(ok)) < 6:
            return None
        radius = np.linalg.norm(self.observed[ok] - np.asarray(centre, dtype=float), axis=1)
        squared = np.sum(self.residual[ok] ** 2, axis=1)
        edges = np.linspace(0.0, float(radius.max()) * (1 + 1e-9), bins + 1)
        ring = np.clip(np.digitize(radius, edges) - 1, 0, bins - 1)
        counts = np.bincount(ring, minlength=bins)
        sums = np.bincount(ring, weights=squared, minlength=bins)
        rms = np.sqrt(np.divide(sums, counts, out=np.full(bins, np.nan), where=counts > 0))
        order = np.argsort(radius)
        third = len(order) // 3
        inner, outer = squared[order[:third]], squared[order[-third:]]
        ms_in, ms_out = float(np.mean(inner)), float(np.mean(outer))
        # One-sided test of ms_out / ms_in ~ F(2n, 2n) through log F ~ N(0, 2/(2n) + 2/(2n)) (n = third).
        z = math.log(ms_out / ms_in) / math.sqrt(2.0 / third) if ms_in > 0 and ms_out > 0 else float("nan")
        p = 0.5 * math.erfc(z / math.sqrt(2.0)) if math.isfinite(z) else float("nan")
        return RadialProfile(radius=radius, length=np.sqrt(squared), edges=edges, rms=rms, counts=counts,
                             inner_rms=math.sqrt(ms_in), outer_rms=math.sqrt(ms_out), p_value=p)

    def flagged_images(self, factor: float = OUTLIER_FACTOR) -> dict[str, float]:
        """Images whose RMS exceeds ``factor`` times the median image RMS."""
        per_image = self.per_image_rms()
        if not per_image:
            return {}
        median = float(np.median(list(per_image.values())))
        return {k: v for k, v in per_image.items() if v > factor * median}


def compute_residuals(result: Mapping[str, Any], dataset: Dataset, *, source: str = "result") -> Residuals:
    """Residuals of every observation in ``dataset`` under the estimates in ``result`` (eqs. 5-9).

    Per image, ``(A, b)`` is the nested transform of ``T_cam_base`` and the image's mirror vectors
    (``geometry.nested_transforms``, all images at once); a point ``Bp`` (a fiducial, or the result's
    reconstruction point) is predicted at ``project(A @ Bp + b)``, distorted to pixels with
    the result's estimated camera where it has one (intrinsics estimated through the mirrors), else
    ``dataset.camera`` when there is one.
    Raises DatasetError naming ``source`` (the result's file) on a malformed result, and naming it
    and the dataset's file when the dataset is not the result's (other mirrors, or a mirror
    configuration or point the result lacks).
    """
    return residuals_of_valid_result(validate_result(result, source), dataset, source)


def residuals_of_valid_result(result: Mapping[str, Any], dataset: Dataset, source: str) -> Residuals:
    """:func:`compute_residuals` of a result already checked by ``validate_result``."""
    (R, t), _ = transforms(result)
    mirrors = mirror_vectors(result)
    points = {name: xyz for name, (xyz, _) in reconstruction_points(result).items()}
    mismatch = f"{source} does not belong to {dataset.source}"
    num_mirrors = max((l for l, _ in mirrors), default=dataset.num_mirrors)
    if num_mirrors != dataset.num_mirrors:
        raise DatasetError(f"{mismatch}: the result has {num_mirrors} mirror(s), the dataset {dataset.num_mirrors}")
    # One pass in dataset order: check each image against the result, gather what to predict.
    vectors: list[list[np.ndarray]] = [[] for _ in range(dataset.num_mirrors)]  # [mirror l-1][image k]
    image_ids: list[str] = []
    names: list[str] = []
    transform_index: list[int] = []
    base: list[np.ndarray] = []
    observed: list[np.ndarray] = []
    for k, image in enumerate(dataset.images):
        if len(image.mirror_configs) != dataset.num_mirrors:
            raise DatasetError(f"{dataset.source}: image {image.id!r} has {len(image.mirror_configs)} mirror configs")
        for l, m in enumerate(image.mirror_configs, start=1):
            if (l, int(m)) not in mirrors:
                raise DatasetError(
                    f"{mismatch}: image {image.id!r} uses mirror {l} configuration {m}, which the "
                    "result has no mirror vector for"
                )
            vectors[l - 1].append(mirrors[(l, int(m))])
        for name, xy in image.observations.items():
            if name in dataset.fiducials:
                base.append(dataset.fiducials[name])
            elif name in points:
                base.append(points[name])
            else:
                raise DatasetError(
                    f"{mismatch}: image {image.id!r} observes {name!r}, which is neither a fiducial "
                    "nor a point of the result"
                )
            image_ids.append(image.id)
            names.append(name)
            transform_index.append(k)
            observed.append(np.asarray(xy, dtype=float))
    A, b = nested_transforms(R, t, [np.array(v).reshape(-1, 3) for v in vectors])  # eqs. (5)-(8)
    camera_points = predict_camera_points(
        A, b, np.asarray(transform_index, dtype=int), np.array(base, dtype=float).reshape(-1, 3)
    )
    predicted = project(camera_points)  # eq. (9)
    predicted[camera_points[:, 2] <= 0.0] = np.nan  # behind the camera: no image
    camera = estimated_camera(result, source, dataset.camera) if dataset.camera is not None else None
    camera = camera if camera is not None else dataset.camera
    if camera is not None:
        pixels = np.full_like(predicted, np.nan)
        ok = np.all(np.isfinite(predicted), axis=1)
        if np.any(ok):
            pixels[ok] = camera.distort(predicted[ok])
        predicted = pixels
    return Residuals(
        units="px" if dataset.camera is not None else "normalized",
        image_ids=image_ids,
        names=names,
        is_fiducial=np.array([name in dataset.fiducials for name in names], dtype=bool),
        predicted=predicted.reshape(-1, 2),
        observed=np.array(observed, dtype=float).reshape(-1, 2),
        sigma=float(dataset.pixel_sigma),
    )
