"""Dataset files (``mirror-fg/dataset@1``): reading, validation, writing of the :class:`~mirror_fg.data.Dataset`
and :class:`~mirror_fg.data.Image` values (:mod:`mirror_fg.data.dataset`) they hold.

Coordinates: fiducials in the base frame {B}, metres; observations in pixels with a camera (undistorted and
normalized once, where an image is validated, with :class:`~mirror_fg.core.camera.Camera`'s OpenCV model),
else normalized. result@1 is :mod:`mirror_fg.io.result`'s; value checks :mod:`mirror_fg.core.values`'.
"""
from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.camera import Camera, camera_from_dict, camera_to_dict, check_camera, initial_intrinsics
from mirror_fg.core.errors import DatasetError
from mirror_fg.data.dataset import Dataset, Image, Scale, normalize_observations, observation_array
from mirror_fg.io.dataset_fields import (
    COLLINEAR_TOL, check_scale, image_camera, cameras_from_dict, check_reflections, fiducials_from_dict, reflections_to_list, scale_from_dict,
    scale_to_dict, tree_configs,
)
from mirror_fg.io.output import atomic_write, json_text
from mirror_fg.io.robot_fields import image_joints, joints_to_dict, robot_from_dict, robot_to_dict
from mirror_fg.io.point_sigma import measurement_sigma, point_sigma_from_dict, point_sigma_to_dict
from mirror_fg.core.values import (
    MAX_INDEX, check_format, check_keys, coordinates, is_index, is_int, short, type_name,
)

DATASET_FORMAT = "mirror-fg/dataset@1"
#: Library messages (a dataset loaded, at INFO); a child of the ``mirror_fg`` logger.
_log = logging.getLogger(__name__)

__all__ = [
    "DATASET_FORMAT",
    "Image",
    "Dataset",
    "load_dataset",
    "dataset_from_dict",
    "dataset_to_dict",
    "save_dataset",
    "validate_image",
    "dataset_text",
    "fiducials_from_dict",
    "COLLINEAR_TOL",
]

_DATASET_KEYS = ("format", "num_mirrors", "camera", "cameras", "pixel_sigma", "point_sigma", "fiducials", "scale",
                 "images", "robot", "mounts")
_IMAGE_KEYS = ("id", "mirror_configs", "reflections", "camera", "observations", "joints")


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
    text = read_text(source)
    if re.search(r"[\"']?\bformat[\"']?\s*:\s*[\"']?mirror-fg/capture@", text[:100_000]):  # YAML or JSON
        raise DatasetError(f"{source}: a capture file (mirror-fg/capture@1), not a dataset: detect it with "
                           "mirror_fg.load_capture (or `mirror-fg detect`), which returns the Dataset")
    ds = dataset_from_dict(parse_json(text, source), source=source)
    _log.info("%s: dataset loaded: %s", source, ds)
    return ds


def dataset_from_dict(d: Mapping[str, Any], source: str = "<dataset>") -> Dataset:
    """Validate a dataset@1 dictionary (the JSON shape) and build a :class:`Dataset`.

    Fiducials become float arrays (3,) in metres in {B}; observations float arrays (2,), pixels with a
    camera or normalized image coordinates without one; ``mirror_configs`` tuples of ints.
    ``source`` names the data in every error message (a file name for :func:`load_dataset`).
    """
    check_format(d, DATASET_FORMAT, source)
    check_keys(d, _DATASET_KEYS, source)

    num_mirrors = d.get("num_mirrors")
    if not is_int(num_mirrors) or num_mirrors < 1:
        raise DatasetError(f"{source}: num_mirrors must be an integer >= 1, got {short(num_mirrors)}")

    given: Any = d.get("camera")
    camera: Camera | None = None
    cameras = None
    if "cameras" in d:
        if given is not None:
            raise DatasetError(f"{source}: camera and cameras are both given: give one of them (cameras for several)")
        cameras = cameras_from_dict(d["cameras"], source)
        camera = next(iter(cameras.values()))
    elif isinstance(given, str) or (isinstance(given, Mapping) and "file" in given):  # capture@1 only (docs/formats.md)
        raise DatasetError(f"{source}: camera: a dataset@1 holds the camera inline ({{model, width, height, fx, fy, "
                           f"cx, cy, dist}}); a calibration file such as {short(given)} can be named in a capture@1")
    if cameras is None and given is not None and not isinstance(given, Mapping):
        raise DatasetError(f"{source}: camera: expected an object or null, got {type_name(given)}")
    unstarted: dict[str, Any] | None = None  # the checked camera whose fx, fy, cx or cy is to start from the images
    if cameras is None and given is not None:
        checked = check_camera(given, f"{source}: camera", allow_unstarted=True)
        if any(checked[k] is None for k in _STARTED):
            unstarted = checked
        else:
            camera = camera_from_dict(given, f"{source}: camera")
    if "pixel_sigma" not in d:
        raise DatasetError(f"{source}: missing 'pixel_sigma' (measurement noise, pixels)")
    image_size = None if camera is None else (camera.width, camera.height)
    pixel_sigma = measurement_sigma(d["pixel_sigma"], image_size, f"{source}: pixel_sigma")

    scale = None
    if d.get("scale") is not None:
        distance, placement, scale_points = scale_from_dict(d["scale"], source)
        scale = Scale(distance, placement, scale_points)
    ds = Dataset(
        num_mirrors=int(num_mirrors),
        camera=camera,
        pixel_sigma=float(pixel_sigma),
        fiducials=fiducials_from_dict(d.get("fiducials"), source, allow_empty=scale is not None),
        images=[],
        source=source,
        cameras=cameras,
        scale=scale,
        robot=robot_from_dict(d, source),
    )
    if scale is not None and ds.fiducials:
        raise DatasetError(f"{source}: scale is for data without a known target (fiducials: {{}}); the fiducials "
                           "fix the scale here")

    images = d.get("images")
    if images is None or (isinstance(images, list) and not images):
        raise DatasetError(f"{source}: no images ('images' is missing or empty)")
    if not isinstance(images, list):
        raise DatasetError(f"{source}: 'images' must be a list, got {type_name(images)}")
    first_index: dict[str, int] = {}
    for index, entry in enumerate(images):
        image = validate_image(entry, ds, index)
        if image.id in first_index:
            raise DatasetError(
                f"{source}: image {image.id!r}: duplicate image id (images[{first_index[image.id]}] "
                f"and images[{index}])"
            )
        first_index[image.id] = index
        image.joints = image_joints(ds.robot, entry.get("joints") if isinstance(entry, Mapping) else entry.joints,
                                    f"{source}: image {image.id!r}")
        ds.images.append(image)
    if unstarted is not None:
        _start_camera(ds, unstarted)
    if scale is not None:
        check_scale(ds, scale)
    ds.point_sigma = point_sigma_from_dict(d.get("point_sigma"), (n for im in ds.images for n in im.observations), source,
                                           image_size)
    return ds


#: Intrinsics that a dataset@1 camera may leave absent when ``estimate`` names them.
_STARTED = ("fx", "fy", "cx", "cy")


def _parity(ds: Dataset, where: str) -> bool:
    """Whether every image is mirror-imaged (an odd number of reflections), for intrinsics started from the
    photographs; refused where images of both parities mix (give fx, fy, cx, cy then)."""
    odd = {len(image.reflections) % 2 == 1 for image in ds.images}
    if len(odd) > 1:
        raise DatasetError(f"{where}: give fx, fy, cx and cy: they are started from the photographs only when every "
                           "image sees the target through an even number of reflections, or every one through an odd")
    return odd.pop()


def _start_camera(ds: Dataset, checked: dict[str, Any]) -> None:
    """Give ``ds`` its camera with fx, fy, cx, cy started from its pixel observations, then
    validate its images again with it (image bounds, normalization).

    Until then the dataset has no camera, so nothing can normalize with an unset focal length.
    """
    where = f"{ds.source}: camera"
    start = initial_intrinsics(
        checked["width"], checked["height"], ds.fiducials, [image.observations for image in ds.images],
        mirrored=_parity(ds, where), given={k: checked[k] for k in _STARTED}, dist=tuple(checked["dist"]),
        where=where, free_k1="k1" in checked.get("estimate", ()),
    )
    ds.camera = Camera(
        width=checked["width"], height=checked["height"], fx=start["fx"], fy=start["fy"], cx=start["cx"],
        cy=start["cy"], dist=tuple(checked["dist"]), estimate=tuple(checked.get("estimate", ())),
        prior_sigma=tuple(checked.get("prior_sigma", {}).items()), model=checked["model"],
    )
    _log.info("%s: %s started from the photographs: %s", where,
              ", ".join(k for k in _STARTED if checked[k] is None),
              ", ".join(f"{k}={start[k]:.6g}" for k in _STARTED))
    ds.images = [validate_image(image, ds, index) for index, image in enumerate(ds.images)]


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
        configs: Any = image.mirror_configs or None  # else its reflections ([] = a direct view)
        reflections: Any = None if configs is not None else [list(p) for p in image.reflections]
        camera_name: Any = image.camera
        observations: Any = image.observations
    elif isinstance(image, Mapping):
        check_keys(image, _IMAGE_KEYS, f"{source}: {where}")
        image_id = image.get("id")
        configs = image.get("mirror_configs")
        reflections = image.get("reflections")
        camera_name = image.get("camera")
        observations = image.get("observations")
    else:
        raise DatasetError(
            f"{source}: {where}: expected an object with id, mirror_configs and observations, "
            f"got {type_name(image)}"
        )

    if not isinstance(image_id, str) or not image_id:
        raise DatasetError(f"{source}: {where}: image id must be a non-empty string, got {short(image_id)}")
    prefix = f"{source}: image {image_id!r}"

    camera = image_camera(ds, camera_name, prefix)
    if configs is not None and reflections is not None:
        raise DatasetError(f"{prefix}: give either mirror_configs or reflections, not both")
    if reflections is not None:
        placements = check_reflections(reflections, ds.num_mirrors, prefix)
        configs = list(tree_configs(placements, ds.num_mirrors))
    elif configs is None:
        raise DatasetError(f"{prefix}: missing 'mirror_configs' (or 'reflections')")
    if isinstance(configs, (str, bytes, Mapping)) or not isinstance(configs, Iterable):
        raise DatasetError(f"{prefix}: mirror_configs must be a list of integers, got {short(configs)}")
    configs = list(configs)
    if reflections is None and len(configs) != ds.num_mirrors:
        raise DatasetError(
            f"{prefix}: mirror_configs has {len(configs)} entries, expected {ds.num_mirrors} (num_mirrors)"
        )
    for l, m in enumerate(configs):
        if not is_index(m):
            raise DatasetError(
                f"{prefix}: mirror_configs[{l}] (mirror {l + 1}) must be a non-negative integer "
                f"(at most {MAX_INDEX}), got {short(m)}"
            )

    if observations is None:
        raise DatasetError(f"{prefix}: missing 'observations'")
    if not isinstance(observations, Mapping):
        raise DatasetError(
            f"{prefix}: observations must be an object {{name: [u, v]}}, got {type_name(observations)}"
        )
    if not observations:
        raise DatasetError(f"{prefix}: has no observations")
    obs: dict[str, np.ndarray] = {}
    for name, value in observations.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{prefix}: point name must be a non-empty string, got {short(name)}")
        if known_points is not None and name not in ds.fiducials and name not in known_points:
            raise DatasetError(f"{prefix}: unknown point {name!r} (neither a fiducial nor a known point)")
        obs[name] = coordinates(value, 2, "[u, v]", f"{prefix}: point {name!r}")
    if camera is not None:
        names = list(obs)
        inside = camera.contains(np.array([obs[n] for n in names]))
        if not inside.all():
            name = names[int(np.argmin(inside))]
            raise DatasetError(
                f"{prefix}: point {short(name)} at {short([round(float(x), 2) for x in obs[name]])} px is "
                f"outside the {camera.width}x{camera.height} image"
            )
    checked = Image(id=image_id, mirror_configs=tuple(int(m) for m in configs), observations=obs,
                    reflections=placements if reflections is not None else (), camera=camera_name)
    raw = observation_array(obs, list(obs))
    checked.normalized = normalize_observations(camera, list(obs), raw)  # once, here
    for name, z in checked.normalized.items():
        if not np.all(np.isfinite(z)):
            assert camera is not None  # normalized coordinates are checked finite above
            raise DatasetError(
                f"{prefix}: point {short(name)} at {short([round(float(x), 2) for x in obs[name]])} px cannot be "
                f"undistorted with the {camera.model} camera model (beyond the lens's field of view)"
            )
    checked.normalized_from = (camera, raw)
    return checked


# --------------------------------------------------------------------------------------------------
# Writing dataset@1
# --------------------------------------------------------------------------------------------------


def dataset_to_dict(ds: Dataset) -> dict[str, Any]:
    """The dataset@1 dictionary of ``ds`` (plain lists and floats; ``camera`` is null without one;
    ``point_sigma`` only when some observed point has one)."""
    point_sigma = point_sigma_to_dict(ds.point_sigma, (n for image in ds.images for n in image.observations))
    cameras = ({"cameras": {name: camera_to_dict(c) for name, c in ds.cameras.items()}} if ds.cameras is not None
               else {"camera": None if ds.camera is None else camera_to_dict(ds.camera)})
    scale = ds.scale
    return {
        "format": DATASET_FORMAT,
        "num_mirrors": int(ds.num_mirrors),
        **cameras,
        "pixel_sigma": float(ds.pixel_sigma),
        **({"point_sigma": point_sigma} if point_sigma else {}),
        "fiducials": {name: [float(x) for x in p] for name, p in ds.fiducials.items()},
        **({"scale": scale_to_dict(scale.distance, scale.placement, scale.points)} if scale is not None else {}),
        **robot_to_dict(ds.robot),
        "images": [_image_dict(image, ds.num_mirrors) for image in ds.images],
    }


def _image_dict(image: Image, num_mirrors: int) -> dict[str, Any]:
    """One image's dataset@1 shape: ``mirror_configs`` where it follows the tree, else ``reflections``."""
    placements: dict[str, Any] = (
        {"mirror_configs": [int(m) for m in image.mirror_configs]} if len(image.mirror_configs) == num_mirrors
        else {"reflections": reflections_to_list(image.reflections)})
    return {
        "id": image.id,
        **({"camera": image.camera} if image.camera is not None else {}),
        **placements,
        "observations": {name: [float(x) for x in z] for name, z in image.observations.items()},
        **joints_to_dict(image.joints),
    }


def save_dataset(path: PathLike, ds: Dataset) -> None:
    """Write ``ds`` as a dataset@1 JSON file, atomically (an existing file is replaced only on success)."""
    atomic_write(os.fspath(path), dataset_text(ds))


def dataset_text(ds: Dataset) -> str:
    """The dataset@1 JSON text of ``ds``."""
    return json_text(dataset_to_dict(ds), allow_nan=False)
