"""Per-point measurement noise of dataset@1 (``point_sigma``) and every measurement's sigma in normalized units.

``point_sigma: {name: sigma}`` (optional, same units as ``pixel_sigma``: pixels with a camera, else
normalized image coordinates) gives every observation of that point this standard deviation (per
axis) instead of ``pixel_sigma``: e.g. a point followed through a video by the tracker, whose pixel is
noisier (and biased along the track) than a detected fiducial's corner. The solver whitens
each measurement with its own sigma (:func:`normalized_sigmas`).
"""
from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import finite, short, type_name

__all__ = ["measurement_sigma", "point_sigma_from_dict", "point_sigma_to_dict", "normalized_sigmas"]

#: A measurement standard deviation (``pixel_sigma``, ``point_sigma``) lies in [``SIGMA_MIN_PX``, the
#: image diagonal] pixels with a camera, [``SIGMA_MIN_NORMALIZED``, ``SIGMA_MAX_NORMALIZED``] normalized
#: units without one: a point known to a millionth of a pixel, or known less well than the image is
#: wide, is no measurement (and whitened errors overflow or vanish in floating point).
SIGMA_MIN_PX = 1e-6
SIGMA_MIN_NORMALIZED = 1e-9
SIGMA_MAX_NORMALIZED = 10.0


def measurement_sigma(value: Any, image_size: tuple[int, int] | None, where: str) -> float:
    """``value`` as a measurement standard deviation (pixels when ``image_size`` = (width, height) of
    the camera is given, else normalized units), or DatasetError naming ``where`` and the range."""
    number = finite(value)
    if number is None or number <= 0.0:
        raise DatasetError(f"{where} must be a finite number > 0, got {short(value)}")
    if image_size is not None:
        smallest, largest, unit = SIGMA_MIN_PX, float(np.hypot(*image_size)), " px (the image diagonal)"
    else:
        smallest, largest, unit = SIGMA_MIN_NORMALIZED, SIGMA_MAX_NORMALIZED, " (normalized units)"
    if not smallest <= number <= largest:
        raise DatasetError(f"{where} must be between {smallest:g} and {largest:g}{unit}, got {short(value)}")
    return number


def point_sigma_from_dict(
    value: Any, observed: Iterable[str], source: str, image_size: tuple[int, int] | None = None
) -> dict[str, float]:
    """Validate dataset@1's ``point_sigma`` (``None``: absent) against the ``observed`` point names.

    Returns ``{name: sigma}`` (floats > 0, finite, in the range of :func:`measurement_sigma` for the
    camera's ``image_size``, or normalized units without one). Raises DatasetError (one line naming
    ``source`` and the point) on anything but an object of such numbers keyed by names some image
    observes (a name no image observes is refused with the name probably meant).
    """
    if value is None:
        return {}
    where = f"{source}: point_sigma"
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected an object {{point name: sigma}}, got {type_name(value)}")
    names = tuple(sorted(set(observed)))
    result: dict[str, float] = {}
    for name, sigma in value.items():
        if not isinstance(name, str) or name not in names:
            close = difflib.get_close_matches(name, names, n=1, cutoff=0.5) if isinstance(name, str) else []
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise DatasetError(f"{where}: point {short(name)} is observed by no image{hint}")
        result[name] = measurement_sigma(sigma, image_size, f"{where}: point {short(name)}: sigma")
    return result


def point_sigma_to_dict(point_sigma: Mapping[str, float], observed: Iterable[str]) -> dict[str, float]:
    """The JSON shape of ``point_sigma`` (plain floats, file order kept) for the ``observed`` names only:
    a dataset whose images lost a point's observations (left out as outliers, ...) is still written as a
    file :func:`point_sigma_from_dict` accepts."""
    seen = set(observed)
    return {name: float(sigma) for name, sigma in point_sigma.items() if name in seen}


def normalized_sigmas(
    camera: Camera | None, pixel_sigma: float, point_sigma: Mapping[str, float], points: Sequence[str]
) -> np.ndarray:
    """Standard deviation (N, 2) in normalized image coordinates (x, y) of one measurement of each of
    ``points``: its ``point_sigma`` where given, else ``pixel_sigma``, over the focal lengths with a
    camera (exact without distortion, the value at the image centre otherwise) and as it is without one.
    With no ``point_sigma`` every row is ``Dataset.normalized_sigma`` bit for bit."""
    sigma = np.array([point_sigma.get(name, pixel_sigma) for name in points], dtype=float).reshape(-1, 1)
    if camera is None:
        return np.repeat(sigma, 2, axis=1)
    return sigma / np.array([camera.fx, camera.fy])  # as ``pixel_sigma / fx``, elementwise
