"""The data a calibration works on, as plain values: :class:`Dataset` (a validated ``mirror-fg/dataset@1``:
the known target, the cameras, the images and what each observed) and :class:`Image`. No parsing here: reading
and writing dataset@1 is :mod:`mirror_fg.io.dataset`'s, which builds these.

Coordinates: fiducials in the base frame {B}, metres; observations in pixels with a camera (undistorted and
normalized once, where an image is validated, with :class:`~mirror_fg.core.camera.Camera`'s OpenCV model),
else normalized.
"""
from __future__ import annotations

import html
from collections.abc import Container, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.values import clip, short

if TYPE_CHECKING:
    from mirror_fg.io.robot_fields import RobotSetup

__all__ = ["Image", "Scale", "Dataset", "dataset_summary", "names_text", "observation_array", "normalize_observations"]


@dataclass
class Image:
    """One image: the placement index of every mirror and what it observed.

    ``mirror_configs[l-1]`` is the configuration index of mirror l. ``observations`` maps a point name to
    its measured coordinates as in the file (pixels with a camera, normalized without one).
    """

    id: str
    mirror_configs: tuple[int, ...]
    observations: dict[str, np.ndarray]
    #: The placements ``(mirror, config)`` the light meets from the points to the camera, in that order
    #: (docs/formats.md, "Views of any reflection order"); ``()`` is a direct view. Derived from
    #: ``mirror_configs`` when not given: ``((1, m1), ..., (Nv, mNv))``. An image whose reflections are
    #: not of that form has ``mirror_configs == ()``.
    reflections: tuple[tuple[int, int], ...] = ()
    #: The name of the camera that took it (a dataset with ``cameras``), else None.
    camera: str | None = None
    #: The arm's joint values in this image (a dataset with a ``robot``; ``io/robot_fields.py``), else None.
    joints: dict[str, float] | None = None
    #: ``observations`` in normalized image coordinates, computed once where the image is validated for
    #: a dataset (:func:`validate_image`); None for an image built by hand. Read through
    #: :meth:`Dataset.normalized`, which also checks that they still belong to ``observations``.
    normalized: dict[str, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)
    #: The camera and the observations (N, 2) ``normalized`` was computed from.
    normalized_from: tuple[Camera | None, np.ndarray] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if not self.reflections and self.mirror_configs:
            self.reflections = tuple((l + 1, int(m)) for l, m in enumerate(self.mirror_configs))

    def restricted(self, mirror_configs: tuple[int, ...], names: Container[str]) -> Image:
        """This image with ``mirror_configs`` and only its observations of ``names`` (in its order), e.g.
        as a subtree of the mirror tree sees it; its normalized observations come along with the raw
        ones they were computed from (so :meth:`Dataset.normalized` still checks them)."""
        kept = [n for n in self.observations if n in names]
        image = Image(self.id, mirror_configs, {n: self.observations[n] for n in kept},
                      reflections=() if mirror_configs else self.reflections, camera=self.camera, joints=self.joints)
        if self.normalized is not None and self.normalized_from is not None and list(self.normalized) == list(self.observations):
            rows = [k for k, n in enumerate(self.normalized) if n in names]
            image.normalized = {n: self.normalized[n] for n in kept}
            image.normalized_from = (self.normalized_from[0], self.normalized_from[1][rows])
        return image


@dataclass(frozen=True)
class Scale:
    """What fixes the scale without a known target (docs/formats.md, "Without a known target"): the
    length of placement ``(mirror, config)``'s mirror vector, or the distance between two ``points``,
    ``distance`` metres."""

    distance: float
    placement: tuple[int, int] | None = None
    points: tuple[str, str] | None = None


@dataclass
class Dataset:
    """A validated ``mirror-fg/dataset@1``.

    ``fiducials``: known base-frame points, metres. ``pixel_sigma``: measurement noise (pixels with a
    camera, else normalized units). ``source``: the file it came from, for messages. ``point_sigma``:
    ``{name: sigma}`` noise of every observation of that point instead of ``pixel_sigma``
    (:mod:`mirror_fg.io.point_sigma`).
    """

    num_mirrors: int
    camera: Camera | None
    pixel_sigma: float
    fiducials: dict[str, np.ndarray]
    images: list[Image]
    source: str = "<dataset>"
    point_sigma: dict[str, float] = field(default_factory=dict)
    #: ``{name: camera}`` of a dataset with several cameras (``cameras``), in the file's order; None for
    #: one ``camera``. ``camera`` is then the first of them.
    cameras: dict[str, Camera] | None = None
    #: What fixes the scale of a dataset without fiducials (``scale``), else None.
    scale: Scale | None = None
    #: The robot the camera or the target rides (``robot``, ``mounts``: ``io/robot_fields.py``), else None.
    robot: RobotSetup | None = None

    def __repr__(self) -> str:
        """One bounded line (a dataclass repr would print every observation)."""
        return f"Dataset({', '.join(f'{k}={v}' for k, v in dataset_summary(self))})"

    def _repr_html_(self) -> str:
        """A summary table for notebooks, bounded like :meth:`__repr__`."""
        rows = "".join(
            f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
            for k, v in dataset_summary(self)
        )
        return f"<table><caption>mirror_fg Dataset</caption>{rows}</table>"

    @property
    def normalized_sigma(self) -> np.ndarray:
        """Measurement standard deviation (2,) in normalized image coordinates (x, y).

        ``pixel_sigma`` over the focal lengths: exact for a distortion-free camera, the value at the image
        centre otherwise (a fisheye lens compresses the edges, where a pixel spans more normalized units).
        """
        if self.camera is None:
            return np.array([self.pixel_sigma, self.pixel_sigma])
        return np.array([self.pixel_sigma / self.camera.fx, self.pixel_sigma / self.camera.fy])

    def normalized(self, image: Image) -> dict[str, np.ndarray]:
        """Observations of ``image`` in normalized image coordinates (undistorted when there is a camera).

        Those computed when the image was validated (``image.normalized``), as long as they were computed
        with this dataset's camera from the observations as they are now; else (an image built by hand, or
        edited since) they are computed here and stored on the image the same way.
        """
        names = list(image.observations)
        raw = observation_array(image.observations, names)
        stored = image.normalized_from
        camera = self.camera_of(image)
        if (image.normalized is None or stored is None or (stored[0] is not camera and stored[0] != camera)
                or list(image.normalized) != names or not np.array_equal(stored[1], raw)):
            image.normalized = normalize_observations(camera, names, raw)
            image.normalized_from = (camera, raw)
        return image.normalized

    def camera_of(self, image: Image) -> Camera | None:
        """The camera that took ``image``: its named one of :attr:`cameras`, else :attr:`camera`."""
        if self.cameras is not None and image.camera is not None:
            return self.cameras[image.camera]
        return self.camera

    @property
    def is_tree(self) -> bool:
        """Whether this is the paper's problem: one camera, a known target, and every image seeing the
        points through mirrors 1..num_mirrors in that order (``mirror_configs``). Anything else is solved
        by the general view model (:mod:`mirror_fg.solver.model.views`)."""
        return (self.cameras is None and bool(self.fiducials) and self.scale is None and self.robot is None
                and all(len(image.mirror_configs) == self.num_mirrors for image in self.images))

    @property
    def reconstruction_point_names(self) -> list[str]:
        """Sorted names of observed points that are not fiducials (their positions are estimated)."""
        names = {n for image in self.images for n in image.observations if n not in self.fiducials}
        return sorted(names)

    @property
    def configurations(self) -> list[tuple[int, int]]:
        """Sorted mirror configurations ``(l, m)`` (mirror l is 1-based) seen in the images."""
        return sorted({placement for image in self.images for placement in image.reflections})


def dataset_summary(ds: Any) -> list[tuple[str, str]]:
    """(label, value) pairs describing the dataset in bounded text."""
    per_mirror = [sorted({m for l, m in ds.configurations if l == k + 1}) for k in range(ds.num_mirrors)]
    points = ds.reconstruction_point_names
    camera = "none (normalized coordinates)"
    if ds.camera is not None:
        c = ds.camera
        camera = f"{c.model} {c.width}x{c.height} fx={c.fx:.6g} fy={c.fy:.6g} cx={c.cx:.6g} cy={c.cy:.6g}"
        if any(k != 0.0 for k in c.dist):
            camera += f" dist={short([round(k, 6) for k in c.dist], 70)}"
    return [
        ("source", short(ds.source)),
        ("num_mirrors", f"{ds.num_mirrors} (placements: {', '.join(str(len(p)) for p in per_mirror[:8])})"),
        ("camera", camera if ds.cameras is None else f"{len(ds.cameras)} cameras ({', '.join(clip(n, 20) for n in ds.cameras)})"),
        ("pixel_sigma", f"{ds.pixel_sigma:.6g}{' px' if ds.camera is not None else ' (normalized)'}"),
        ("fiducials", names_text(list(ds.fiducials))),
        ("images", str(len(ds.images))),
        ("observations", str(sum(len(image.observations) for image in ds.images))),
        ("points", names_text(points)),
    ]


def names_text(names: list[str], limit: int = 6) -> str:
    """``count (a, b, ...)`` with at most ``limit`` names, each bounded."""
    shown = ", ".join(clip(n, 20) for n in names[:limit])
    more = ", ..." if len(names) > limit else ""
    return f"{len(names)} ({shown}{more})" if names else "0"


def observation_array(observations: Mapping[str, np.ndarray], names: list[str]) -> np.ndarray:
    """The observations of ``names`` as an array (N, 2), in that order."""
    return np.array([observations[n] for n in names], dtype=float).reshape(-1, 2)


def normalize_observations(camera: Camera | None, names: list[str], raw: np.ndarray) -> dict[str, np.ndarray]:
    """``{name: normalized (2,)}`` of the observations ``raw`` (N, 2) of ``names`` (undistorted with ``camera``)."""
    coords = camera.normalize(raw) if camera is not None else raw.copy()
    return {name: coords[i] for i, name in enumerate(names)}
