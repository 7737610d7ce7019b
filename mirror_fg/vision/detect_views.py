"""Detection in a kaleidoscope photograph's views, and the dataset@1 dictionary of a detected capture.

A photograph with ``views`` (:mod:`mirror_fg.io.capture_views`) holds several views of one target: each
view's region of interest ``roi = [x, y, w, h]`` is cropped, the target is detected in the crop with
that view's parity (an odd number of reflections shows the target mirror-imaged: the detectors flip
the crop, :mod:`mirror_fg.vision.detectors`) and a camera whose principal point is shifted by the
crop's origin (``cx - x``, ``cy - y``: the same pinhole and distortion, so the plane-fit check of a
detection is unchanged), and the corners are shifted back to full-image pixels (``u + x``, ``v + y``).
Each view becomes one dataset image (id ``<image id>#<k>``, or the view's own ``id``) with the view's
``reflections``.

The dataset@1 dictionary keeps the form each image gave: ``mirror_configs`` where the capture gave
``mirror_configs``, ``reflections`` (``[[mirror, config], ...]``) where it gave ``reflections`` or
``views``; a rig's dictionary has ``cameras`` and a ``camera`` per image instead of ``camera``.
``each`` becomes a fresh integer per mirror, above every integer the capture uses for that mirror, one
per photograph (or video frame): the views of one photograph share it.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.capture import Capture, ImageEntry
from mirror_fg.io.capture_views import EACH, Placement, ViewEntry, check_roi, is_mirrored
from mirror_fg.io.dataset import DATASET_FORMAT
from mirror_fg.vision.detectors import FOUND, Detection

__all__ = ["Output", "view_camera", "detect_in_views", "expand_each", "dataset_dict"]

#: A detector on one grayscale image: ``detect(gray, mirrored, camera)``.
DetectOne = Callable[[np.ndarray, bool, dict[str, Any]], Detection]


@dataclass
class Output:
    """A kept image (or view) before its ``each`` placements get their integers.

    ``configs``: its ``mirror_configs`` (``()`` when it gave ``reflections``); ``reflections``: the
    general form; ``group``: the photograph (or frame) it comes from, within which an ``each`` of one
    mirror is one placement; ``camera``: the rig camera that took it (None: the capture's one camera).
    """

    id: str
    configs: tuple[Any, ...]
    points: dict[str, np.ndarray]
    reflections: tuple[Placement, ...] = ()
    camera: str | None = None
    group: str = ""

    def __post_init__(self) -> None:
        if not self.reflections and self.configs:
            self.reflections = tuple((l + 1, m) for l, m in enumerate(self.configs))
        self.group = self.group or self.id


def view_camera(camera: Mapping[str, Any], roi: tuple[int, int, int, int]) -> dict[str, Any]:
    """``camera`` for the crop ``roi``: principal point moved by the crop's origin, size the crop's
    (a crop pixel ``(u, v)`` is the image pixel ``(u + x, v + y)``)."""
    x, y, w, h = roi
    shifted = {**camera, "width": w, "height": h}
    if camera.get("cx") is not None:
        shifted["cx"] = float(camera["cx"]) - x
    if camera.get("cy") is not None:
        shifted["cy"] = float(camera["cy"]) - y
    return shifted


def detect_in_views(entry: ImageEntry, gray: np.ndarray, detect: DetectOne, camera: Mapping[str, Any]
                    ) -> list[tuple[ViewEntry, Detection]]:
    """Every view of ``entry`` detected in its own region of ``gray`` (already checked to be of the
    camera's size), corners in full-image pixels. A roi outside the image is a DatasetError."""
    assert entry.views is not None
    height, width = gray.shape[:2]
    results = []
    for view in entry.views:
        check_roi(view.roi, (width, height), f"{entry.where}: {view.label.rsplit(' ', 1)[-1]}")
        x, y, w, h = view.roi
        crop = np.ascontiguousarray(gray[y:y + h, x:x + w])
        det = detect(crop, is_mirrored(view.reflections), view_camera(camera, view.roi))
        if det.status == FOUND:
            offset = np.array([x, y], dtype=np.float64)
            det.points = {name: np.asarray(p, dtype=np.float64) + offset for name, p in det.points.items()}
        results.append((view, det))
    return results


def _declared_placements(capture: Capture) -> list[tuple[Placement, ...]]:
    """Every placement sequence the capture lists (images, their views, or video segments)."""
    if capture.images is None:
        return [s.reflections for s in capture.video.segments] if capture.video is not None else []
    out: list[tuple[Placement, ...]] = []
    for e in capture.images:
        out += [v.reflections for v in e.views] if e.views is not None else [e.reflections]
    return out


def expand_each(capture: Capture, outputs: list[Output]) -> list[dict[str, list[Any]]]:
    """Per output its placement key for the dataset: ``{"mirror_configs": [...]}`` or ``{"reflections":
    [[mirror, config], ...]}``, ``each`` replaced by a fresh integer per (photograph, mirror)."""
    next_free = {l: 0 for l in range(1, capture.num_mirrors + 1)}
    for placements in _declared_placements(capture):
        for l, m in placements:
            if m != EACH:
                next_free[l] = max(next_free[l], int(m) + 1)
    fresh: dict[tuple[str, int], int] = {}
    result = []
    for out in outputs:
        pairs = []
        for l, m in out.reflections:
            if m == EACH:
                if (out.group, l) not in fresh:
                    fresh[(out.group, l)] = next_free[l]
                    next_free[l] += 1
                m = fresh[(out.group, l)]
            pairs.append([int(l), int(m)])
        result.append({"mirror_configs": [m for _, m in pairs]} if out.configs else {"reflections": pairs})
    return result


@dataclass
class DatasetParts:
    """What :func:`dataset_dict` needs beside the capture: the cameras (filled in from the images),
    the kept outputs, and the per-point sigmas of tracked points."""

    cameras: dict[str | None, dict[str, Any]]
    outputs: list[Output]
    point_sigma: dict[str, float] = field(default_factory=dict)


def dataset_dict(capture: Capture, parts: DatasetParts) -> dict[str, Any]:
    """The dataset@1 dictionary of a detected capture (validated afterwards by ``dataset_from_dict``).

    ``parts.cameras``: ``{None: camera}`` for one camera, ``{name: camera}`` for a rig (sizes filled in
    from the images read); a camera still without a size is a DatasetError.
    """
    for name, camera in parts.cameras.items():
        if camera.get("width") is None or camera.get("height") is None:
            which = "camera" if name is None else f"cameras: {name}"
            raise DatasetError(f"{capture.source}: {which}: no image size (give width and height)")
    rig = capture.cameras is not None
    images = []
    for out, placement in zip(parts.outputs, expand_each(capture, parts.outputs)):
        image: dict[str, Any] = {"id": out.id, **placement}
        if rig:
            image["camera"] = out.camera
        image["observations"] = {name: [float(p[0]), float(p[1])] for name, p in out.points.items()}
        images.append(image)
    cameras = {"cameras": {str(n): c for n, c in parts.cameras.items()}} if rig else {"camera": parts.cameras[None]}
    return {
        "format": DATASET_FORMAT,
        "num_mirrors": capture.num_mirrors,
        **cameras,
        "pixel_sigma": capture.pixel_sigma,
        **({"point_sigma": parts.point_sigma} if parts.point_sigma else {}),
        "fiducials": {name: [float(x) for x in p] for name, p in capture.fiducials().items()},
        "images": images,
    }
