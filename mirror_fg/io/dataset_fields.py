"""The dataset@1 keys of the general view model (docs/formats.md, "Views of any reflection order, and
several cameras"): an image's ``reflections`` and ``camera``, the dataset's ``cameras`` and ``scale``.

Checked here, used by :mod:`mirror_fg.io.dataset` (the format's one reader and writer).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from mirror_fg.core.camera import Camera, camera_from_dict, check_camera
from mirror_fg.core.errors import DatasetError
import numpy as np

from mirror_fg.core.values import (
    MAX_INDEX, MAX_TARGET_EXTENT_M, MIN_LENGTH_M, check_extent, check_keys, clip, coordinates, is_index, is_int, is_number, short, type_name,
)

__all__ = ["fiducials_from_dict", "check_scale", "image_camera", "named_camera", "check_cameras_named", "Placement", "check_reflections", "tree_configs", "cameras_from_dict", "scale_from_dict",
           "scale_to_dict", "reflections_to_list"]

#: Fiducials all within this fraction of their extent from one line are collinear.
COLLINEAR_TOL = 1e-6

#: One mirror placement ``(mirror, config)``: mirror l (1-based) at its configuration m.
Placement = tuple[int, int]

#: Longest sequence of reflections of one view (a light path through more mirrors is no measurement).
MAX_REFLECTIONS = 16


def check_reflections(value: Any, num_mirrors: int, prefix: str,
                      config: Callable[[Any, str], Any] | None = None) -> tuple[tuple[int, Any], ...]:
    """An image's ``reflections`` as a tuple of placements: each ``[mirror, config]`` with mirror in
    1..num_mirrors, two consecutive pairs naming different mirrors (a light path meets another mirror
    between two reflections in one). ``prefix`` names the image. ``config(value, where)`` checks one
    config (default: a non-negative integer; a capture's also takes ``each``)."""
    if not isinstance(value, (list, tuple)):
        raise DatasetError(f"{prefix}: reflections must be a list of [mirror, config] pairs ([] for a direct view), "
                           f"got {short(value)}")
    if len(value) > MAX_REFLECTIONS:
        raise DatasetError(f"{prefix}: reflections has {len(value)} pairs, at most {MAX_REFLECTIONS} are taken")
    result: list[tuple[int, Any]] = []
    for k, pair in enumerate(value):
        where = f"{prefix}: reflections[{k}]"
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise DatasetError(f"{where} must be a [mirror, config] pair, got {short(pair)}")
        mirror, m = pair
        if not is_int(mirror) or not 1 <= mirror <= num_mirrors:
            raise DatasetError(f"{where}: mirror {short(mirror)} is not one of 1..{num_mirrors} (num_mirrors)")
        if result and result[-1][0] == mirror:
            raise DatasetError(f"{where}: mirror {int(mirror)} twice in a row (reflections[{k - 1}] is also mirror "
                               f"{int(mirror)}); light cannot meet the same mirror twice in a row")
        result.append((int(mirror), (config or _index)(m, f"{where}: config")))
    return tuple(result)


def _index(value: Any, where: str) -> int:
    """A placement's config: a non-negative integer."""
    if not is_index(value):
        raise DatasetError(f"{where} must be a non-negative integer (at most {MAX_INDEX}), got {short(value)}")
    return int(value)


def tree_configs(reflections: tuple[Placement, ...], num_mirrors: int) -> tuple[int, ...]:
    """The ``mirror_configs`` equivalent to ``reflections`` (mirrors 1..num_mirrors in order, each once),
    or ``()`` where the reflections are not of that form."""
    if len(reflections) == num_mirrors and all(l == k + 1 for k, (l, _) in enumerate(reflections)):
        return tuple(m for _, m in reflections)
    return ()


def reflections_to_list(reflections: tuple[Placement, ...]) -> list[list[int]]:
    """The JSON shape of ``reflections``."""
    return [[int(l), int(m)] for l, m in reflections]


def cameras_from_dict(value: Any, source: str) -> dict[str, Camera]:
    """``cameras: {name: camera}`` as Cameras in the file's order: at least one, every name a non-empty
    string, every camera a full camera object (fx, fy, cx, cy given: intrinsics started from the
    photographs are taken for one ``camera`` only in this version)."""
    if not isinstance(value, Mapping) or not value:
        raise DatasetError(f"{source}: cameras must be an object {{name: camera}} with at least one camera, "
                           f"got {short(value) if not isinstance(value, Mapping) else '{}'}")
    cameras: dict[str, Camera] = {}
    for name, camera in value.items():
        where = f"{source}: cameras[{short(name)}]"
        if not isinstance(name, str) or not name.strip():
            raise DatasetError(f"{source}: cameras: a camera name must be a non-empty string, got {short(name)}")
        if not isinstance(camera, Mapping):
            raise DatasetError(f"{where}: expected a camera object, got {type_name(camera)}")
        checked = check_camera(camera, where, allow_unstarted=True)
        missing = [k for k in ("fx", "fy", "cx", "cy") if checked[k] is None]
        if missing:
            raise DatasetError(f"{where}: give {', '.join(missing)}: with several cameras every camera needs its "
                               "start intrinsics (estimate may still name them)")
        cameras[name] = camera_from_dict(camera, where)
    return cameras


def scale_from_dict(value: Any, source: str) -> tuple[float, Placement | None, tuple[str, str] | None]:
    """``scale`` as ``(distance, placement, points)``: ``{mirror, config, distance}`` (the length of that
    placement's mirror vector) or ``{points: [a, b], distance}``, distance metres from
    :data:`MIN_LENGTH_M` to :data:`MAX_TARGET_EXTENT_M` (a mirror or two points the camera sees are within a
    few metres of it: a distance typed in millimetres or centimetres would put them hundreds of metres away)."""
    where = f"{source}: scale"
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected {{mirror, config, distance}} or {{points: [a, b], distance}}, "
                           f"got {short(value)}")
    check_keys(value, ("mirror", "config", "points", "distance"), where)
    distance: Any = value.get("distance")
    if not is_number(distance) or not MIN_LENGTH_M <= float(distance) <= MAX_TARGET_EXTENT_M:
        raise DatasetError(f"{where}: distance must be a length in metres (from {MIN_LENGTH_M:g} to "
                           f"{MAX_TARGET_EXTENT_M:g}), got {short(distance)}{_unit_hint(distance)}")
    if "points" in value:
        if "mirror" in value or "config" in value:
            raise DatasetError(f"{where}: give either points or mirror and config, not both")
        points = value["points"]
        if (not isinstance(points, list) or len(points) != 2 or not all(isinstance(p, str) and p for p in points)
                or points[0] == points[1]):
            raise DatasetError(f"{where}: points must be two different point names, got {short(points)}")
        return float(distance), None, (points[0], points[1])
    mirror: Any = value.get("mirror")
    config: Any = value.get("config")
    if not is_index(mirror, 1) or not is_index(config):
        raise DatasetError(f"{where}: give mirror (from 1) and config (from 0) of the placement whose mirror "
                           f"distance is known, or points; got mirror {short(mirror)}, config {short(config)}")
    return float(distance), (int(mirror), int(config)), None


def _unit_hint(value: Any) -> str:
    """``" (millimetres? 21.9 mm = 0.0219 m)"`` for a length too large to be metres, else ``""``."""
    if not is_number(value) or not MAX_TARGET_EXTENT_M < float(value) < 1e7:
        return ""
    return (f": lengths are in metres ({float(value):g} mm = {float(value) / 1000:g} m, "
            f"{float(value):g} cm = {float(value) / 100:g} m)")


def scale_to_dict(distance: float, placement: Placement | None, points: tuple[str, str] | None) -> dict[str, Any]:
    """The JSON shape of a scale."""
    if placement is not None:
        return {"mirror": placement[0], "config": placement[1], "distance": float(distance)}
    assert points is not None
    return {"points": list(points), "distance": float(distance)}


def fiducials_from_dict(fiducials: Any, source: str, allow_empty: bool = False) -> dict[str, np.ndarray]:
    """Fiducials ``{name: (3,) metres in {B}}``: at least three, not all on one line, at most 5 m across;
    or none (``{}``) where ``allow_empty`` (a dataset with ``scale``: no known target)."""
    if fiducials is None:
        raise DatasetError(f"{source}: missing 'fiducials' (at least 3 non-collinear points)")
    if not isinstance(fiducials, Mapping):
        raise DatasetError(
            f"{source}: fiducials must be an object {{name: [x, y, z]}}, got {type_name(fiducials)}"
        )
    result: dict[str, np.ndarray] = {}
    if not fiducials and allow_empty:
        return result
    for name, value in fiducials.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{source}: fiducial name must be a non-empty string, got {short(name)}")
        result[name] = coordinates(value, 3, "[x, y, z]", f"{source}: fiducial {name!r}")
    if len(result) < 3:
        empty = " (without a known target give fiducials: {} and a scale)" if not result else ""
        raise DatasetError(f"{source}: {len(result)} fiducials, need at least 3 (non-collinear){empty}")
    check_extent(result.values(), f"{source}: fiducials", "fiducial layout")  # millimetres typed as metres
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


def check_scale(ds: Any, scale: Any) -> None:
    """The scale names a placement or points that the images see."""
    if scale.placement is not None and scale.placement not in set(ds.configurations):
        raise DatasetError(f"{ds.source}: scale: no image sees mirror {scale.placement[0]} at config "
                           f"{scale.placement[1]}")
    seen = {n for image in ds.images for n in image.observations}
    for name in scale.points or ():
        if name not in seen:
            raise DatasetError(f"{ds.source}: scale: no image observes point {short(name)}")


def named_camera(name: Any, cameras: Mapping[str, Any] | None, where: str, what: str = "dataset") -> str | None:
    """The camera an image of a dataset or capture (``what``) names: required and declared with ``cameras``,
    refused without; None for one ``camera``."""
    if cameras is None:
        if name is not None:
            raise DatasetError(f"{where}: camera {short(name)}: an image names its camera only when the {what} "
                               "declares 'cameras: {name: camera}' (a rig); with one 'camera' leave it out")
        return None
    declared = ", ".join(cameras)
    if name is None:
        raise DatasetError(f"{where}: missing 'camera' (which camera took it: one of {declared})")
    if not isinstance(name, str) or name not in cameras:
        raise DatasetError(f"{where}: camera {short(name)} is not declared under 'cameras' ({declared})")
    return name


def check_cameras_named(cameras: Mapping[str, Any] | None, named: Any, source: str, why: str = "") -> None:
    """Refuse a camera declared under ``cameras`` that no image names (``named``: the images' camera names):
    it has no data, so its pose cannot be estimated. ``why`` adds where its images may have gone."""
    if cameras is None:
        return
    used = set(named)
    unused = [name for name in cameras if name not in used]
    if unused:
        which = ", ".join(repr(clip(n, 30)) for n in unused[:4]) + (" ..." if len(unused) > 4 else "")
        camera = "camera" if len(unused) == 1 else "cameras"
        raise DatasetError(f"{source}: {camera} {which} declared under 'cameras' but no image names it{why}: "
                           "remove it from 'cameras' or add its images")


def image_camera(ds: Any, name: Any, prefix: str) -> Camera | None:
    """The camera that took an image of ``ds`` naming ``name`` (:func:`named_camera`)."""
    named = named_camera(name, ds.cameras, prefix)
    return ds.camera if named is None else ds.cameras[named]
