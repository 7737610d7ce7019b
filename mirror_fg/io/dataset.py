"""Dataset (``mirror-fg/dataset@1``) and result (``mirror-fg/result@1``) files, validation, DatasetError.

Coordinates: fiducials in the base frame {B}, metres; observations in pixels when the dataset has a
camera (undistorted and normalized here with OpenCV), else normalized image coordinates.
"""
from __future__ import annotations

import difflib
import json
import math
import numbers
import os
import re
import reprlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError, OutputError
from pathlib import Path

DATASET_FORMAT = "mirror-fg/dataset@1"
RESULT_FORMAT = "mirror-fg/result@1"

__all__ = [
    "DATASET_FORMAT",
    "RESULT_FORMAT",
    "DatasetError",
    "OutputError",
    "Camera",
    "Image",
    "Dataset",
    "load_dataset",
    "dataset_from_dict",
    "dataset_to_dict",
    "save_dataset",
    "validate_image",
    "write_result",
    "result_text",
    "dataset_text",
    "load_result",
]

#: Lengths of OpenCV distortion vectors ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])``.
DIST_LENGTHS = (4, 5, 8, 12, 14)
#: Fiducials all within this fraction of their extent from one line are collinear.
COLLINEAR_TOL = 1e-6
# cv2.undistortPoints stops after 5 fixed-point iterations by default (errors ~1e-5 on a wide-angle
# lens); iterate until the reprojection error is below 1e-12 px (at most 100 times) instead.
_UNDISTORT_CRITERIA = (100, 1e-12)  # (max iterations, epsilon in pixels)
#: Pixel observations may lie this fraction of the image size outside it (detections at the border).
PIXEL_MARGIN_FRACTION = 0.02
#: Intrinsics that ``camera.estimate`` may name (OpenCV's model).
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_DATASET_KEYS = ("format", "num_mirrors", "camera", "pixel_sigma", "fiducials", "images")
_CAMERA_KEYS = ("model", "width", "height", "fx", "fy", "cx", "cy", "dist", "estimate", "prior_sigma")
_IMAGE_KEYS = ("id", "mirror_configs", "observations")




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
    #: Intrinsics to estimate through the mirrors (``camera.estimate``), and their prior sigmas.
    estimate: tuple[str, ...] = ()
    prior_sigma: tuple[tuple[str, float], ...] = ()

    def contains(self, pixels: np.ndarray) -> np.ndarray:
        """Whether each pixel (N, 2) lies in the image, extended by PIXEL_MARGIN_FRACTION of its size."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        margin = PIXEL_MARGIN_FRACTION * np.array([self.width, self.height])
        low, high = -0.5 - margin, np.array([self.width, self.height]) - 0.5 + margin
        return np.all((pixels >= low) & (pixels <= high), axis=1)

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
        dist = np.asarray(self.dist, dtype=np.float64)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, *_UNDISTORT_CRITERIA)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x spelling; 5.x takes criteria directly
            out = cv2.undistortPointsIter(pixels, self.K, dist, None, None, criteria)
        else:
            out = cv2.undistortPoints(pixels, self.K, dist, criteria=criteria)
        return out.reshape(-1, 2)

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
    # The pixel observations each cache entry was computed from: an image id alone does not identify
    # the data (another image with the same id, or an edited one, must not get stale coordinates).
    _normalized_inputs: dict[str, tuple[list[str], np.ndarray]] = field(
        default_factory=dict, repr=False, compare=False
    )

    @property
    def normalized_sigma(self) -> np.ndarray:
        """Measurement standard deviation (2,) in normalized image coordinates (x, y)."""
        if self.camera is None:
            return np.array([self.pixel_sigma, self.pixel_sigma])
        return np.array([self.pixel_sigma / self.camera.fx, self.pixel_sigma / self.camera.fy])

    def normalized(self, image: Image) -> dict[str, np.ndarray]:
        """Observations of ``image`` in normalized image coordinates (undistorted when there is a camera)."""
        names = list(image.observations)
        raw = np.array([image.observations[n] for n in names], dtype=float).reshape(-1, 2)
        cached = self._normalized_cache.get(image.id)
        seen = self._normalized_inputs.get(image.id)
        if cached is not None and seen is not None and seen[0] == names and np.array_equal(seen[1], raw):
            return cached
        coords = self.camera.normalize(raw) if self.camera is not None else raw.copy()
        result = {name: coords[i] for i, name in enumerate(names)}
        self._normalized_cache[image.id] = result
        self._normalized_inputs[image.id] = (names, raw)
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


# --------------------------------------------------------------------------------------------------
# Reading and validating dataset@1
# --------------------------------------------------------------------------------------------------

PathLike = str | os.PathLike[str]


def load_dataset(path: PathLike) -> Dataset:
    """Read and validate a ``mirror-fg/dataset@1`` JSON file.

    Raises DatasetError (one line naming the file, the image or point and the problem) on an unreadable
    file, invalid JSON (with line and column) or any content that :func:`dataset_from_dict` rejects.
    """
    from mirror_fg.io.fileio import parse_json, read_text

    source = os.fspath(path)
    return dataset_from_dict(parse_json(read_text(source), source), source=source)


def dataset_from_dict(d: Mapping[str, Any], source: str = "<dataset>") -> Dataset:
    """Validate a dataset@1 dictionary (the JSON shape) and build a :class:`Dataset`.

    Fiducials become float arrays (3,) in metres in {B}; observations float arrays (2,), pixels with a
    camera or normalized image coordinates without one; ``mirror_configs`` tuples of ints.
    ``source`` names the data in every error message (a file name for :func:`load_dataset`).
    """
    check_format(d, DATASET_FORMAT, source)
    check_keys(d, _DATASET_KEYS, source)

    num_mirrors = d.get("num_mirrors")
    if not _is_int(num_mirrors) or num_mirrors < 1:
        raise DatasetError(f"{source}: num_mirrors must be an integer >= 1, got {_short(num_mirrors)}")

    camera = _camera_from_dict(d.get("camera"), source)

    if "pixel_sigma" not in d:
        raise DatasetError(f"{source}: missing 'pixel_sigma' (measurement noise, pixels)")
    pixel_sigma = d["pixel_sigma"]
    if not _is_number(pixel_sigma) or not math.isfinite(pixel_sigma) or pixel_sigma <= 0:
        raise DatasetError(f"{source}: pixel_sigma must be a finite number > 0, got {_short(pixel_sigma)}")

    ds = Dataset(
        num_mirrors=int(num_mirrors),
        camera=camera,
        pixel_sigma=float(pixel_sigma),
        fiducials=_fiducials_from_dict(d.get("fiducials"), source),
        images=[],
        source=source,
    )

    images = d.get("images")
    if images is None or (isinstance(images, list) and not images):
        raise DatasetError(f"{source}: no images ('images' is missing or empty)")
    if not isinstance(images, list):
        raise DatasetError(f"{source}: 'images' must be a list, got {_kind(images)}")
    first_index: dict[str, int] = {}
    for index, entry in enumerate(images):
        image = validate_image(entry, ds, index)
        if image.id in first_index:
            raise DatasetError(
                f"{source}: image {image.id!r}: duplicate image id (images[{first_index[image.id]}] "
                f"and images[{index}])"
            )
        first_index[image.id] = index
        ds.images.append(image)
    return ds


def validate_image(
    image: Image | Mapping[str, Any],
    ds: Dataset,
    index: int | None = None,
    *,
    known_points: set[str] | None = None,
) -> Image:
    """Check one image against ``ds`` and return it as a new :class:`Image` of plain types.

    ``image`` is an :class:`Image` or a dict in the dataset@1 shape (``id``, ``mirror_configs``,
    ``observations``). Checks: the id is a non-empty string; ``mirror_configs`` has ``ds.num_mirrors``
    non-negative integer entries; there is at least one observation; every observation is two finite
    numbers (pixels with a camera, normalized coordinates without one). Names outside ``ds.fiducials``
    are reconstruction points and allowed, unless ``known_points`` is given: then a name outside
    ``ds.fiducials`` and ``known_points`` is an error. ``index`` (position in the file) names the image
    in messages when its id is unusable. Raises DatasetError.
    """
    source = ds.source
    where = f"images[{index}]" if index is not None else "image"
    if isinstance(image, Image):
        image_id: Any = image.id
        configs: Any = image.mirror_configs
        observations: Any = image.observations
    elif isinstance(image, Mapping):
        check_keys(image, _IMAGE_KEYS, f"{source}: {where}")
        image_id = image.get("id")
        configs = image.get("mirror_configs")
        observations = image.get("observations")
    else:
        raise DatasetError(
            f"{source}: {where}: expected an object with id, mirror_configs and observations, "
            f"got {_kind(image)}"
        )

    if not isinstance(image_id, str) or not image_id:
        raise DatasetError(f"{source}: {where}: image id must be a non-empty string, got {_short(image_id)}")
    prefix = f"{source}: image {image_id!r}"

    if configs is None:
        raise DatasetError(f"{prefix}: missing 'mirror_configs'")
    if isinstance(configs, (str, bytes, Mapping)) or not isinstance(configs, Iterable):
        raise DatasetError(f"{prefix}: mirror_configs must be a list of integers, got {_short(configs)}")
    configs = list(configs)
    if len(configs) != ds.num_mirrors:
        raise DatasetError(
            f"{prefix}: mirror_configs has {len(configs)} entries, expected {ds.num_mirrors} (num_mirrors)"
        )
    for l, m in enumerate(configs):
        if not _is_int(m) or m < 0:
            raise DatasetError(
                f"{prefix}: mirror_configs[{l}] (mirror {l + 1}) must be a non-negative integer, "
                f"got {_short(m)}"
            )

    if observations is None:
        raise DatasetError(f"{prefix}: missing 'observations'")
    if not isinstance(observations, Mapping):
        raise DatasetError(
            f"{prefix}: observations must be an object {{name: [u, v]}}, got {_kind(observations)}"
        )
    if not observations:
        raise DatasetError(f"{prefix}: has no observations")
    obs: dict[str, np.ndarray] = {}
    for name, value in observations.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{prefix}: point name must be a non-empty string, got {_short(name)}")
        if known_points is not None and name not in ds.fiducials and name not in known_points:
            raise DatasetError(f"{prefix}: unknown point {name!r} (neither a fiducial nor a known point)")
        obs[name] = _coordinates(value, 2, "[u, v]", f"{prefix}: point {name!r}")
    if ds.camera is not None:
        names = list(obs)
        inside = ds.camera.contains(np.array([obs[n] for n in names]))
        if not inside.all():
            name = names[int(np.argmin(inside))]
            raise DatasetError(
                f"{prefix}: point {_short(name)} at {_short([round(float(x), 2) for x in obs[name]])} px is "
                f"outside the {ds.camera.width}x{ds.camera.height} image"
            )
    return Image(id=image_id, mirror_configs=tuple(int(m) for m in configs), observations=obs)


def _camera_from_dict(camera: Any, source: str) -> Camera | None:
    """The camera of a dataset (``None`` when absent: observations are then normalized coordinates)."""
    if camera is None:
        return None
    prefix = f"{source}: camera"
    if not isinstance(camera, Mapping):
        raise DatasetError(f"{prefix}: expected an object or null, got {_kind(camera)}")
    check_keys(camera, _CAMERA_KEYS, prefix)
    estimate, prior_sigma = _estimated_intrinsics(camera, prefix)
    model = camera.get("model", "pinhole")
    if model != "pinhole":
        raise DatasetError(f"{prefix}: unsupported model {_short(model)} (only 'pinhole')")
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in camera]
    unstarted = [k for k in missing if k in estimate]
    if unstarted:
        raise DatasetError(f"{prefix}: {', '.join(unstarted)} absent: starting intrinsics from the photographs "
                           "is not supported by this version; give a starting value")
    if missing:
        raise DatasetError(f"{prefix}: missing {', '.join(repr(k) for k in missing)}")
    for key in ("width", "height"):
        if not _is_int(camera[key]) or camera[key] < 1:
            raise DatasetError(
                f"{prefix}: {key} must be a positive integer (pixels), got {_short(camera[key])}"
            )
    for key in ("fx", "fy", "cx", "cy"):
        value = camera[key]
        if not _is_number(value) or not math.isfinite(value):
            raise DatasetError(f"{prefix}: {key} must be a finite number (pixels), got {_short(value)}")
        if key in ("fx", "fy") and value <= 0:
            raise DatasetError(f"{prefix}: {key} must be > 0, got {_short(value)}")
    dist = camera.get("dist", [0.0] * 5)
    if (
        not isinstance(dist, (list, tuple))
        or len(dist) not in DIST_LENGTHS
        or not all(_is_number(x) and math.isfinite(x) for x in dist)
    ):
        raise DatasetError(
            f"{prefix}: dist must be 4, 5, 8, 12 or 14 finite numbers (OpenCV k1, k2, p1, p2[, k3, ...]), "
            f"got {_short(dist)}"
        )
    return Camera(
        width=int(camera["width"]),
        height=int(camera["height"]),
        fx=float(camera["fx"]),
        fy=float(camera["fy"]),
        cx=float(camera["cx"]),
        cy=float(camera["cy"]),
        dist=tuple(float(x) for x in dist),
        estimate=estimate,
        prior_sigma=prior_sigma,
    )


def _estimated_intrinsics(camera: Mapping[str, Any], prefix: str) -> tuple[tuple[str, ...], tuple[tuple[str, float], ...]]:
    """``camera.estimate`` (names of intrinsics) and ``camera.prior_sigma`` ({name: sigma > 0}), checked."""
    estimate = camera.get("estimate", [])
    if not isinstance(estimate, list) or not all(isinstance(n, str) for n in estimate):
        raise DatasetError(f"{prefix}: estimate must be a list of intrinsic names, got {_short(estimate)}")
    for name in estimate:
        _check_name(name, INTRINSIC_NAMES, f"{prefix}: estimate", "intrinsic")
    if len(set(estimate)) != len(estimate):
        raise DatasetError(f"{prefix}: estimate names an intrinsic twice: {_short(estimate)}")
    prior = camera.get("prior_sigma", {})
    if not isinstance(prior, Mapping):
        raise DatasetError(f"{prefix}: prior_sigma must be an object {{name: sigma}}, got {_kind(prior)}")
    for name, sigma in prior.items():
        _check_name(name, INTRINSIC_NAMES, f"{prefix}: prior_sigma", "intrinsic")
        if not _is_number(sigma) or not math.isfinite(sigma) or sigma <= 0:
            raise DatasetError(f"{prefix}: prior_sigma {name}: must be a finite number > 0, got {_short(sigma)}")
    return tuple(estimate), tuple((str(n), float(s)) for n, s in prior.items())


def check_format(d: Any, expected: str, source: str) -> None:
    """Refuse anything but an object whose ``format`` is ``expected`` (one line naming ``source``)."""
    if not isinstance(d, Mapping):
        raise DatasetError(f"{source}: expected an object at the top level, got {_kind(d)}")
    fmt = d.get("format")
    if fmt != expected:
        what = "missing 'format'" if fmt is None else f"unknown format {_short(fmt)}"
        raise DatasetError(f"{source}: {what} (expected {expected!r})")


def check_keys(mapping: Mapping[Any, Any], allowed: Iterable[str], where: str) -> None:
    """Refuse a key of ``mapping`` outside ``allowed``, naming the key meant where one is close."""
    allowed = tuple(allowed)
    for key in mapping:
        if key not in allowed:
            _check_name(key, allowed, where, "key")


def _check_name(name: Any, allowed: tuple[str, ...], where: str, what: str) -> None:
    if name in allowed:
        return
    close = difflib.get_close_matches(str(name), allowed, n=1, cutoff=0.5) if isinstance(name, str) else []
    if not close and isinstance(name, str):  # "distortion" -> "dist": a known name that starts it
        close = [a for a in allowed if len(a) >= 3 and str(name).lower().startswith(a)][:1]
    hint = f" (did you mean {close[0]!r}?)" if close else f" (expected one of {', '.join(allowed)})"
    raise DatasetError(f"{where}: unknown {what} {_short(name)}{hint}")


def _fiducials_from_dict(fiducials: Any, source: str) -> dict[str, np.ndarray]:
    """Fiducials ``{name: (3,) metres in {B}}``: at least three, not all on one line."""
    if fiducials is None:
        raise DatasetError(f"{source}: missing 'fiducials' (at least 3 non-collinear points)")
    if not isinstance(fiducials, Mapping):
        raise DatasetError(
            f"{source}: fiducials must be an object {{name: [x, y, z]}}, got {_kind(fiducials)}"
        )
    result: dict[str, np.ndarray] = {}
    for name, value in fiducials.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{source}: fiducial name must be a non-empty string, got {_short(name)}")
        result[name] = _coordinates(value, 3, "[x, y, z]", f"{source}: fiducial {name!r}")
    if len(result) < 3:
        raise DatasetError(f"{source}: {len(result)} fiducials, need at least 3 (non-collinear)")
    if _collinear(np.array(list(result.values()))):
        raise DatasetError(
            f"{source}: the {len(result)} fiducials are collinear (all on one line); "
            "need at least 3 non-collinear"
        )
    return result


def _collinear(points: np.ndarray, tol: float = COLLINEAR_TOL) -> bool:
    """True when every point (N, 3) lies within ``tol`` times the points' extent of one line."""
    centred = points - points.mean(axis=0)
    extent = float(np.max(np.linalg.norm(centred, axis=1)))
    if extent == 0.0:
        return True  # all coincide
    direction = np.linalg.svd(centred)[2][0]
    off_line = centred - np.outer(centred @ direction, direction)
    return float(np.max(np.linalg.norm(off_line, axis=1))) <= tol * extent


def _coordinates(value: Any, n: int, shape: str, what: str) -> np.ndarray:
    """``value`` as a float array (n,) of finite numbers, else DatasetError starting with ``what``."""
    if value is None:
        raise DatasetError(f"{what}: missing coordinates, expected {shape}")
    if isinstance(value, np.ndarray):
        items = list(value.ravel()) if value.ndim == 1 else None
    elif isinstance(value, (list, tuple)):
        items = list(value)
    else:
        items = None
    if items is None or len(items) != n:
        got = f"{len(items)} values" if items is not None else _short(value)
        raise DatasetError(f"{what}: expected {n} coordinates {shape}, got {got}")
    for k, x in enumerate(items):
        if not _is_number(x):
            raise DatasetError(f"{what}: coordinate {k} is not a number: {_short(x)}")
    try:
        coords = np.array([float(x) for x in items], dtype=np.float64)
    except OverflowError:
        coords = np.full(n, np.inf)
    if not np.all(np.isfinite(coords)):
        raise DatasetError(f"{what}: coordinates are not finite: {_short(items)}")
    return coords


def _is_int(x: Any) -> bool:
    """An integer that is not a bool (JSON ``true`` is not a count)."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _is_number(x: Any) -> bool:
    """A real number that is not a bool."""
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def _kind(x: Any) -> str:
    """JSON-ish name of a value's type, for messages."""
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    for t, name in names.items():
        if isinstance(x, t):
            return name
    return "a number" if _is_number(x) else type(x).__name__


class _Quoter(reprlib.Repr):
    """reprlib with small limits, and without expanding huge integers (str() of one can raise)."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 2, 6, 6, 3
        self.maxstring, self.maxother, self.maxlong = 40, 40, 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:
            return f"<integer of {int(x.bit_length() * 0.30103) + 1} digits>"
        return super().repr_int(x, level)


_QUOTER = _Quoter()


def _short(x: Any, limit: int = 60) -> str:
    """One-line repr of user data for messages, bounded in length and in work (an aliased or deeply
    nested value is not expanded)."""
    if isinstance(x, np.ndarray):
        x = x.tolist() if x.size <= 8 else f"<array of shape {x.shape}>"
    text = " ".join(_QUOTER.repr(x).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --------------------------------------------------------------------------------------------------
# Writing dataset@1
# --------------------------------------------------------------------------------------------------


def dataset_to_dict(ds: Dataset) -> dict[str, Any]:
    """The dataset@1 dictionary of ``ds`` (plain lists and floats; ``camera`` is null without one)."""
    camera: dict[str, Any] | None = None
    if ds.camera is not None:
        c = ds.camera
        camera = {
            "model": "pinhole",
            "width": int(c.width),
            "height": int(c.height),
            "fx": float(c.fx),
            "fy": float(c.fy),
            "cx": float(c.cx),
            "cy": float(c.cy),
            "dist": [float(x) for x in c.dist],
        }
        if c.estimate:
            camera["estimate"] = list(c.estimate)
        if c.prior_sigma:
            camera["prior_sigma"] = dict(c.prior_sigma)
    return {
        "format": DATASET_FORMAT,
        "num_mirrors": int(ds.num_mirrors),
        "camera": camera,
        "pixel_sigma": float(ds.pixel_sigma),
        "fiducials": {name: [float(x) for x in p] for name, p in ds.fiducials.items()},
        "images": [
            {
                "id": image.id,
                "mirror_configs": [int(m) for m in image.mirror_configs],
                "observations": {name: [float(x) for x in z] for name, z in image.observations.items()},
            }
            for image in ds.images
        ],
    }


def save_dataset(path: PathLike, ds: Dataset) -> None:
    """Write ``ds`` as a dataset@1 JSON file, atomically (an existing file is replaced only on success)."""
    atomic_write(os.fspath(path), dataset_text(ds))


# --------------------------------------------------------------------------------------------------
# result@1 files
# --------------------------------------------------------------------------------------------------


def write_result(path: PathLike, result: Mapping[str, Any]) -> None:
    """Write a ``mirror-fg/result@1`` dictionary: JSON (indent 2), or YAML where ``path`` ends in .yaml/.yml.

    numpy arrays and scalars become lists and plain numbers first. The write is atomic: the text goes
    to a temporary file in the same directory that replaces ``path`` only when complete, so any
    failure (a value that cannot be serialised, a full disk) leaves an existing file as it was and no
    temporary file behind. Raises TypeError naming the key of a value that cannot be written.
    """
    target = os.fspath(path)
    atomic_write(target, result_text(result, target))


def result_text(result: Mapping[str, Any], path: PathLike) -> str:
    """The text of a result@1 file: YAML where ``path`` ends in .yaml/.yml, else JSON (indent 2)."""
    plain = _plain(result, "result")
    if _is_yaml(os.fspath(path)):
        import yaml

        return yaml.safe_dump(plain, default_flow_style=None, sort_keys=False, allow_unicode=True)
    return _json_text(plain, allow_nan=True)


def dataset_text(ds: Dataset) -> str:
    """The dataset@1 JSON text of ``ds``."""
    return _json_text(dataset_to_dict(ds), allow_nan=False)


def load_result(path: PathLike) -> dict[str, Any]:
    """Read a result@1 file (JSON, or YAML where the name ends in .yaml/.yml). Raises DatasetError."""
    from mirror_fg.io.fileio import parse_json, parse_yaml, read_text
    from mirror_fg.io.result import validate_result

    source = os.fspath(path)
    text = read_text(source)
    data = parse_yaml(text, source) if _is_yaml(source) else parse_json(text, source)
    return validate_result(data, source)


def _plain(value: Any, where: str) -> Any:
    """``value`` with numpy arrays/scalars and tuples turned into lists, floats, ints, bools."""
    if isinstance(value, np.ndarray):
        if value.ndim == 0:
            return _plain(value[()], where)
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Mapping):
        out: dict[Any, Any] = {}
        for key, v in value.items():
            k = key.item() if isinstance(key, np.generic) else key
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"{where}: cannot write a key of type {type(key).__name__}: {_short(key)}")
            out[k] = _plain(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where}: cannot write a value of type {type(value).__name__}")


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------

# An innermost list of numbers as json.dumps(indent=...) lays it out, one number a line. Strings
# cannot match: JSON escapes newlines inside them.
_NUMBER_LIST = re.compile(r"\[\n\s*(-?[0-9][-+0-9.eE]*(?:,\n\s*-?[0-9][-+0-9.eE]*)*)\n\s*\]")


def _json_text(data: Any, allow_nan: bool) -> str:
    """JSON with indent 2, innermost lists of numbers kept on one line (``[x, y, z]``)."""
    text = json.dumps(data, indent=2, allow_nan=allow_nan, ensure_ascii=False)
    return _NUMBER_LIST.sub(_one_line, text) + "\n"


def _one_line(match: re.Match[str]) -> str:
    return "[" + ", ".join(number.strip() for number in match.group(1).split(",")) + "]"


def _is_yaml(path: str) -> bool:
    return path.lower().endswith((".yaml", ".yml"))


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write ``data`` (text is UTF-8) to ``path`` all-or-nothing (:class:`mirror_fg.io.fileio.OutputPlan`):
    a temporary file in the same directory replaces an existing file only once complete; on any
    failure the old file stays as it was. DatasetError (one line) where ``path`` cannot be written."""
    from mirror_fg.io.fileio import OutputPlan

    plan = OutputPlan()
    plan.add(path)
    plan.commit({os.fspath(path): data})
    return Path(path)
