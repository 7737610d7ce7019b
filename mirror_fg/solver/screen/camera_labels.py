"""Camera labels of a rig's images checked before the solve (docs/formats.md "Several cameras").

A rig is fixed on its body and a placement is one mirror plane, so two images that name the same camera
and the same reflections (placements, in order) see every point at the same pixels, up to the noise:
the light path from the point to that camera is the same. Where they disagree by far more than the noise
allows, one of them names the wrong camera (an image of another camera relabelled) or the wrong
placements; the solve could only report a plane it cannot start, or leave both images out. Pixels
throughout; ``pixel_sigma`` (or the largest ``point_sigma`` of the points compared) the noise.
"""
from __future__ import annotations

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import clip

__all__ = ["check_camera_labels", "lone_image_hint", "LABEL_CONFLICT_SIGMAS"]

#: Two images of one camera and one placement sequence disagree when the RMS distance between their
#: pixels of the same points exceeds this many noise sigmas (the difference of two measurements has
#: sigma sqrt(2) pixel_sigma per coordinate; 10 of those is never noise).
LABEL_CONFLICT_SIGMAS = 10.0


def check_camera_labels(dataset) -> None:
    """DatasetError (exit 2) naming the first two images of one rig camera with the same reflections whose
    pixels disagree far beyond the noise, and the cameras that have no image at those placements (the
    camera one of them was likely taken by). Nothing for one camera (its placement checks are the
    solver's, ``consistency.placement_disagreement``)."""
    if dataset.cameras is None or len(dataset.cameras) < 2:
        return
    groups: dict[tuple, list] = {}
    for image in dataset.images:
        groups.setdefault((image.camera, tuple(image.reflections)), []).append(image)
    placements_of: dict[str, set[tuple]] = {name: set() for name in dataset.cameras}
    for camera, reflections in groups:
        placements_of[camera].add(reflections)
    for (camera, reflections), images in groups.items():
        for k, first in enumerate(images):
            for second in images[k + 1:]:
                rms, sigma = _pixel_disagreement(dataset, first, second)
                if rms is not None and rms > LABEL_CONFLICT_SIGMAS * np.sqrt(2.0) * sigma:
                    _refuse(dataset, camera, reflections, first, second, rms, placements_of)


def _pixel_disagreement(dataset, first, second) -> tuple[float | None, float]:
    """RMS pixel distance between two images' common points, and the noise sigma of those points."""
    common = [n for n in first.observations if n in second.observations]
    if not common:
        return None, 0.0
    a = np.array([first.observations[n] for n in common], dtype=float)
    b = np.array([second.observations[n] for n in common], dtype=float)
    point_sigma = dataset.point_sigma or {}
    sigma = max([float(dataset.pixel_sigma)] + [float(np.max(point_sigma[n])) for n in common if n in point_sigma])
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1)))), sigma


def _refuse(dataset, camera: str, reflections: tuple, first, second, rms: float, placements_of: dict) -> None:
    where = ", ".join(f"mirror {l} placement {m}" for l, m in reflections) or "no mirror (a direct view)"
    others = [name for name, seen in placements_of.items() if name != camera and reflections not in seen]
    hint = (f"; camera {', '.join(repr(clip(n, 30)) for n in others[:3])} has no image there: was one of them taken "
            "by it?" if others else "")
    raise DatasetError(
        f"{dataset.source}: images {clip(first.id, 40)!r} and {clip(second.id, 40)!r} look mislabelled: both say camera "
        f"{clip(camera, 30)!r} through {where}, yet see the same points {rms:.3g} px apart (RMS; noise allows a few "
        f"px): one of them names the wrong camera (or placements){hint}")


def lone_image_hint(dataset) -> str:
    """Where a rig cannot be started: the images that look as if they name the wrong camera, as the start
    of a message ("" where none does). An image is suspect when it is its camera's only image through a
    placement that another camera sees in two or more images (a placement is one mirror plane: the
    other camera's images of it were taken with it; this one alone cannot place it)."""
    if dataset.cameras is None or len(dataset.cameras) < 2:
        return ""
    seen: dict[tuple, dict[str, list]] = {}
    for image in dataset.images:
        for placement in set(image.reflections):
            seen.setdefault(placement, {}).setdefault(image.camera, []).append(image)
    suspects: dict[str, tuple] = {}
    for (l, m), by_camera in seen.items():
        for camera, images in by_camera.items():
            others = {name: len(group) for name, group in by_camera.items() if name != camera and len(group) >= 2}
            if len(images) == 1 and others:
                other = max(others, key=lambda name: others[name])
                suspects.setdefault(images[0].id, (camera, l, m, other, others[other]))
    if not suspects:
        return ""
    parts = [f"image {clip(image_id, 40)!r} is the only image of camera {clip(camera, 30)!r} through mirror {l} "
             f"placement {m}, which camera {clip(other, 30)!r} sees in {count}"
             for image_id, (camera, l, m, other, count) in list(suspects.items())[:3]]
    more = f" (and {len(suspects) - 3} more)" if len(suspects) > 3 else ""
    return "; ".join(parts) + more + ": do these images name the wrong camera?"
