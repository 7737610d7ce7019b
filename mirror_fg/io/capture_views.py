"""Per-image reflections, kaleidoscope views and rig cameras of a capture@1 (docs/capture_guide.md, "4c.
Direct views, fixed mirrors, kaleidoscopes and rigs"; docs/formats.md "Views of any reflection order, and several
cameras").

An image gives either ``mirror_configs: [m1, ..., mNv]`` (the paper's tree: it means ``reflections:
[[1, m1], ..., [Nv, mNv]]``) or ``reflections: [[mirror, config], ...]`` (the placements the light meets
from the target to the camera, in that order; ``[]`` is a direct view), never both. A kaleidoscope
photograph instead lists its ``views: [{roi: [x, y, w, h], reflections: [...], id?}, ...]``: the target
is detected in each region of interest (pixels, inside the image; rois may overlap) on its own, and each
view becomes a dataset image ``<image id>#<k>`` (k its 0-based index in ``views``, unless the view gives
its own ``id``).

``each`` as a config is a placement of its own *for that photograph*: in ``mirror_configs`` as before
(a fresh integer per image or video frame), and in ``reflections`` too (``[1, each]``); the views of
one photograph that give ``each`` for the same mirror share that fresh placement (they were taken at
one instant). Placements shared between photographs (a fixed mirror, the cameras of a rig triggered
together) must be given as integers.

A rig gives ``cameras: {name: camera}`` (each what ``camera`` takes: intrinsics, a calibration file
path, or ``{file, name}``) instead of ``camera``, and every image names its ``camera``.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mirror_fg.core.camera import check_camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import MAX_INDEX, check_keys, is_index, is_int, short, short_path, type_name
from mirror_fg.io.camera_files import camera_from_file
from mirror_fg.io.dataset_fields import check_reflections, named_camera
from mirror_fg.io.fileio import MAX_IMAGE_PIXELS, resolve_path

__all__ = [
    "EACH",
    "Config",
    "Placement",
    "ViewEntry",
    "camera_entry",
    "rig_cameras",
    "mirror_configs_from",
    "reflections_from",
    "image_placements",
    "image_views",
    "check_roi",
    "is_mirrored",
]

#: A config meaning "a placement of its own in this photograph / frame".
EACH = "each"
Config = int | str  # an integer placement or EACH
Placement = tuple[int, Config]  # (mirror, config)


@dataclass
class ViewEntry:
    """One view of a kaleidoscope photograph: the target seen in ``roi`` (x, y, w, h pixels, OpenCV
    convention) through ``reflections``; ``mirror_configs`` is set (and ``reflections`` its general
    form) when the view gave ``mirror_configs``. ``label``: ``images[3] (k.png) views[1]``."""

    id: str
    roi: tuple[int, int, int, int]
    reflections: tuple[Placement, ...]
    mirror_configs: tuple[Config, ...] | None = None
    label: str = "views[0]"


def is_mirrored(reflections: Sequence[Any]) -> bool:
    """True when the target is seen through an odd number of reflections (the view is mirror-imaged:
    det A = (-1)^len, eqs. 5-8)."""
    return len(reflections) % 2 == 1


# --- cameras ----------------------------------------------------------------------------------------


def camera_entry(value: Any, where: str, base_dir: str) -> tuple[dict[str, Any], str | None]:
    """A capture camera (intrinsics, a calibration file path or ``{file, name}``): the dataset@1 camera
    dictionary and the calibration file it was read from (None for inline intrinsics)."""
    if isinstance(value, str) or (isinstance(value, Mapping) and "file" in value):
        name = None
        if isinstance(value, Mapping):
            extra = sorted(str(k) for k in value if k not in ("file", "name"))
            if extra:
                raise DatasetError(f"{where}: unknown key {short(extra[0])} next to 'file' (expected 'name')")
            name = value.get("name")
            if name is not None and not isinstance(name, str):
                raise DatasetError(f"{where}: name must be a camera name such as 'cam0', got {short(name)}")
            value = value["file"]
            if not isinstance(value, str) or not value:
                raise DatasetError(f"{where}: file must be a path, got {short(value)}")
        path = resolve_path(value, base_dir)
        if not os.path.isfile(path):
            raise DatasetError(f"{where}: calibration file {short_path(value)!r} not found")
        return camera_from_file(path, name, f"{where} ({short_path(value)})"), path
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected intrinsics or a path to a calibration file, got {type_name(value)}")
    return check_camera(value, where, max_pixels=MAX_IMAGE_PIXELS, allow_unstarted=True), None


def rig_cameras(value: Any, source: str, base_dir: str) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """``cameras: {name: camera}``: the camera dictionaries in the file's order, and the calibration file
    of each camera read from one."""
    where = f"{source}: cameras"
    if not isinstance(value, Mapping) or not value:
        raise DatasetError(f"{where}: expected {{name: camera}} with at least one camera, got {short(value)}")
    cameras: dict[str, dict[str, Any]] = {}
    files: dict[str, str] = {}
    for name, spec in value.items():
        if not isinstance(name, str) or not name or "#" in name:
            raise DatasetError(f"{where}: camera names must be non-empty strings such as 'left' (no '#'), got {short(name)}")
        camera, file = camera_entry(spec, f"{where}: {name}", base_dir)
        cameras[name] = camera
        if file is not None:
            files[name] = file
    return cameras, files


def image_camera(e: Mapping[str, Any], cameras: Mapping[str, Any] | None, where: str) -> str | None:
    """The camera an image names: required and declared with ``cameras``, refused without."""
    return named_camera(e.get("camera"), cameras, where, "capture")


# --- placements ---------------------------------------------------------------------------------------


def _config(m: Any, where: str) -> Config:
    if m == EACH:
        return EACH
    if is_index(m):
        return int(m)
    raise DatasetError(f"{where} must be a non-negative integer (at most {MAX_INDEX}) or 'each', got {short(m)}")


def mirror_configs_from(value: Any, num_mirrors: int, where: str) -> tuple[Config, ...]:
    """``mirror_configs``: one config per mirror, 1..num_mirrors in order."""
    if not isinstance(value, (list, tuple)):
        raise DatasetError(f"{where}: mirror_configs must be a list of {num_mirrors} integers or 'each', got {short(value)}")
    if len(value) != num_mirrors:
        raise DatasetError(f"{where}: mirror_configs has {len(value)} entries, expected {num_mirrors} (num_mirrors)")
    return tuple(_config(m, f"{where}: mirror_configs[{l}] (mirror {l + 1})") for l, m in enumerate(value))


def reflections_from(value: Any, num_mirrors: int, where: str) -> tuple[Placement, ...]:
    """``reflections``: ``[mirror, config]`` pairs in the order the light meets them, checked as a
    dataset's are (``dataset_fields.check_reflections``), a config also ``each``."""
    return check_reflections(value, num_mirrors, where, _config)


def image_placements(e: Mapping[str, Any], num_mirrors: int, where: str
                     ) -> tuple[tuple[Config, ...] | None, tuple[Placement, ...]]:
    """``(mirror_configs or None, reflections)`` of an image, video segment or view: exactly one of
    ``mirror_configs`` and ``reflections``; ``reflections`` is always the general form."""
    has_configs, has_reflections = e.get("mirror_configs") is not None, e.get("reflections") is not None
    if has_configs and has_reflections:
        raise DatasetError(f"{where}: give mirror_configs or reflections, not both "
                           "(mirror_configs [m1, m2] means reflections [[1, m1], [2, m2]])")
    if has_configs:
        configs = mirror_configs_from(e["mirror_configs"], num_mirrors, where)
        return configs, tuple((l + 1, m) for l, m in enumerate(configs))
    if has_reflections:
        return None, reflections_from(e["reflections"], num_mirrors, where)
    raise DatasetError(f"{where}: missing 'mirror_configs' (or 'reflections': the [mirror, config] placements the light meets)")


# --- views -------------------------------------------------------------------------------------------


def check_roi(roi: tuple[int, int, int, int], size: tuple[Any, Any], where: str) -> None:
    """Refuse a roi that is not inside an image of ``size`` (width, height; nothing checked while unknown)."""
    width, height = size
    if width is None or height is None:
        return
    x, y, w, h = roi
    if x + w > width or y + h > height:
        raise DatasetError(f"{where}: roi {list(roi)} reaches outside the {width} x {height} image "
                           f"(x + w <= {width}, y + h <= {height})")


def image_views(value: Any, image_id: str, num_mirrors: int, size: tuple[Any, Any], where: str) -> list[ViewEntry]:
    """``views``: a non-empty list of ``{roi: [x, y, w, h], reflections | mirror_configs, id?}``; rois
    (integers, pixels) inside the image when its size is known (else checked once it is read)."""
    if not isinstance(value, list) or not value:
        raise DatasetError(f"{where}: views must be a non-empty list of {{roi: [x, y, w, h], reflections}}, got {short(value)}")
    label_of = where.split(": ", 1)[-1] if ": " in where else where
    views: list[ViewEntry] = []
    seen: set[str] = set()
    for k, v in enumerate(value):
        vw = f"{where}: views[{k}]"
        if not isinstance(v, Mapping):
            raise DatasetError(f"{vw}: expected {{roi: [x, y, w, h], reflections}}, got {type_name(v)}")
        check_keys(v, ("roi", "reflections", "mirror_configs", "id"), vw)
        roi = v.get("roi")
        if roi is None:
            raise DatasetError(f"{vw}: missing 'roi' ([x, y, w, h] pixels: the region where this view of the target is)")
        if (not isinstance(roi, (list, tuple)) or len(roi) != 4 or not all(is_int(c) for c in roi)
                or roi[0] < 0 or roi[1] < 0 or roi[2] < 1 or roi[3] < 1):
            raise DatasetError(f"{vw}: roi must be [x, y, w, h], integer pixels with x, y >= 0 and w, h >= 1, got {short(roi)}")
        box = (int(roi[0]), int(roi[1]), int(roi[2]), int(roi[3]))
        check_roi(box, size, vw)
        configs, reflections = image_placements(v, num_mirrors, vw)
        view_id = v.get("id", f"{image_id}#{k}")
        if not isinstance(view_id, str) or not view_id:
            raise DatasetError(f"{vw}: id must be a non-empty string, got {short(view_id)}")
        if view_id in seen:
            raise DatasetError(f"{vw}: view id {short(view_id)} is given twice in this image")
        seen.add(view_id)
        views.append(ViewEntry(view_id, box, reflections, configs, f"{label_of} views[{k}]"))
    return views
