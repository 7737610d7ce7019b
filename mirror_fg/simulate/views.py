"""Synthetic views of any reflection order (docs/formats.md "Views of any reflection order, and several cameras").

Kinds (numpy only; the tree of the paper's Sect. 7 stays in :mod:`mirror_fg.simulate.tree`):

- **kaleidoscope**: two or three fixed mirrors (one placement each, config 0) around the target. A
  two-mirror kaleidoscope is a wedge of dihedral angle about 72 deg (five chambers: the direct view,
  two first-order and two second-order ones); a three-mirror one a near-equilateral prism. The camera
  looks along the mirrors, inside them. Each view is one image: the direct view ``[]``, every
  first-order ``[[l, 0]]`` and every second-order ``[[i, 0], [j, 0]]`` (i != j; light meets i first).
- **mixed**: two hand-held mirrors in that wedge arrangement, moved between photographs; each
  photograph gives the views ``[[1, m]]``, ``[[2, k]]``, ``[[1, m], [2, k]]``, ``[[2, k], [1, m]]``
  (and ``[]`` in the first ``direct`` photographs).
- without a known target (``fiducials: {}``): unknown points only, base frame = camera frame, and
  ``scale`` = the length of mirror 1's vector (Takahashi, Nobuhara & Matsuyama, CVPR 2017).

A point is observed in a view only where the light really takes that path: the mirror planes (infinite)
are traced from the camera (the first plane the ray meets must be the view's last mirror, and so on, and
no plane may block the last leg to the point), the point lies on the reflective side (the camera's) of
each mirror in turn, and its image is at positive depth and inside the image with
VISIBILITY_MARGIN_PX to spare. Mirror vectors follow eq. (3): ``x -> M x + 2 v``.
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mirror_fg.core.camera import Camera, camera_to_dict
from mirror_fg.core.geometry import apply_transform, project, reflect
from mirror_fg.io.dataset import DATASET_FORMAT
from mirror_fg.io.output import OutputPlan, json_text
from mirror_fg.simulate.views_truth import Camera_name, ViewsTruth, load_views_truth, plane_in_camera, views_truth_from_dict
from mirror_fg.simulate.tree import (
    NOISE_FREE_NOMINAL_SIGMA_PX,
    VISIBILITY_MARGIN_PX,
    default_camera,
    default_fiducials,
    default_T_cam_base,
    normal_spread,
    simulation_outputs,
    truth_path,
)

__all__ = [
    "ViewsTruth",
    "views_truth_from_dict",
    "load_views_truth",
    "plane_in_camera",
    "observe",
    "kaleidoscope_fiducials",
    "simulate_kaleidoscope",
    "simulate_mixed",
    "write_views_simulation",
    "MIN_FIDUCIALS_PER_VIEW",
]

#: A view of a known target is kept only where at least this many fiducials are seen (a unique PnP).
MIN_FIDUCIALS_PER_VIEW = 4
#: Distance (metres) from the camera to the centre of the target or of the unknown points.
SCENE_DEPTH = 1.0
#: Radius (metres) of the ball around the scene centre in which unknown points are drawn.
KALEIDOSCOPE_POINT_RADIUS = 0.03
_SCENE_TRIES = 500  # kaleidoscopes / placement sets drawn before giving up

# --------------------------------------------------------------------------------------------------
# What a camera sees through a sequence of mirrors


def _pixels(camera: Camera, camera_points: np.ndarray) -> np.ndarray:
    """Pinhole pixels (N, 2) of camera-frame points; simulated cameras have no distortion."""
    if camera.model != "pinhole" or any(float(k) != 0.0 for k in camera.dist):
        raise ValueError("simulate: only distortion-free pinhole cameras are simulated")
    z = project(camera_points)  # eq. (9)
    return np.column_stack([camera.fx * z[:, 0] + camera.cx, camera.fy * z[:, 1] + camera.cy])


def _traced(virtual: np.ndarray, path: Sequence[np.ndarray], planes: Sequence[np.ndarray]) -> bool:
    """Whether the ray from the camera to ``virtual`` meets the planes of ``path`` (light order) from the
    last to the first, each the nearest plane of ``planes`` on its way, and then reaches ``point`` with
    no plane in between (every plane infinite, reflective on the camera's side)."""
    origin, length = np.zeros(3), float(np.linalg.norm(virtual))
    direction = virtual / length
    normals = [v / np.linalg.norm(v) for v in planes]
    distances = [float(np.linalg.norm(v)) for v in planes]
    target_index = [next(i for i, w in enumerate(planes) if w is v) for v in path]
    left = None
    for step in [*reversed(target_index), None]:
        hits = []
        for i, (n, d) in enumerate(zip(normals, distances)):
            towards = float(n @ direction)
            if i == left or towards <= 1e-12:
                continue
            hits.append(((d - float(n @ origin)) / towards, i))
        nearest = min(hits) if hits else (np.inf, None)
        if step is None:
            return nearest[0] > length - 1e-9
        if nearest[1] != step or nearest[0] >= length:
            return False
        origin = origin + nearest[0] * direction
        direction = direction - 2.0 * float(normals[step] @ direction) * normals[step]  # eq. (3) on a ray
        length -= nearest[0]
        left = step
    return False  # not reached


def observe(camera: Camera, camera_points: np.ndarray, path: Sequence[np.ndarray],
            planes: Sequence[np.ndarray] | None = None, margin_px: float = VISIBILITY_MARGIN_PX
            ) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free pixels (N, 2) of camera-frame points seen through ``path`` (mirror vectors in the
    order the light meets them) and which of them are seen (N,) bool.

    Seen: before each mirror the (virtual) point is on its reflective side, the camera's
    (``v . x < v . v``); the final image is at positive depth and inside the image with ``margin_px``;
    and, where ``planes`` (every mirror in the photograph, ``path``'s among them, by identity) are
    given, the traced light path takes exactly ``path`` (:func:`_traced`).
    """
    x = np.asarray(camera_points, dtype=float).reshape(-1, 3)
    seen = np.ones(len(x), dtype=bool)
    for v in path:
        v = np.asarray(v, dtype=float)
        seen &= x @ v < float(v @ v)
        x = reflect(x, v)  # eq. (3)
    seen &= x[:, 2] > 1e-6
    pixels = np.full((len(x), 2), np.nan)
    pixels[seen] = _pixels(camera, x[seen])
    inside = np.zeros(len(x), dtype=bool)
    inside[seen] = ((pixels[seen] >= margin_px) & (pixels[seen] <= [camera.width - margin_px, camera.height - margin_px])).all(axis=1)
    seen &= inside
    if planes is not None:
        for i in np.flatnonzero(seen):
            seen[i] = _traced(x[i], path, planes)
    return pixels, seen


# --------------------------------------------------------------------------------------------------
# Scenes


def kaleidoscope_fiducials() -> dict[str, np.ndarray]:
    """The four default fiducials at half size (a 10 cm right triangle and a point 7.5 cm off it), so
    that the target fits between mirrors a decimetre from it."""
    return {name: 0.5 * p for name, p in default_fiducials(4).items()}


def _scene_pose(fiducials: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_base putting the fiducials' centroid SCENE_DEPTH in front of the camera (rotation: the
    simulator's default), or the identity without fiducials (base frame = camera frame)."""
    if not fiducials:
        return np.eye(3), np.zeros(3)
    R, _ = default_T_cam_base()
    centroid = np.mean(list(fiducials.values()), axis=0)
    return R, np.array([0.0, 0.0, SCENE_DEPTH]) - R @ centroid


def _scene_points(rng: np.random.Generator, fiducials: Mapping[str, np.ndarray], pose, num_points: int) -> dict[str, np.ndarray]:
    """Unknown points P0.. (base frame) in a ball of KALEIDOSCOPE_POINT_RADIUS around the scene centre."""
    R, t = pose
    centre = R.T @ (np.array([0.0, 0.0, SCENE_DEPTH]) - t)
    points = {}
    for i in range(num_points):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        points[f"P{i}"] = centre + KALEIDOSCOPE_POINT_RADIUS * rng.uniform() ** (1.0 / 3.0) * direction
    return points


def _wall(rng: np.random.Generator, angle_deg: float, offset: float, tilt_deg: float, jitter_deg: float,
          spread: float) -> np.ndarray:
    """Mirror vector (camera frame) of a wall ``offset`` metres from the scene centre (0, 0, SCENE_DEPTH)
    with outward normal at ``angle_deg`` in the image plane, jittered by up to ``jitter_deg``, tilted
    toward or away from the camera by up to ``tilt_deg``, the offset by +/- ``spread`` (relative)."""
    phi = np.deg2rad(angle_deg + jitter_deg * rng.uniform(-1.0, 1.0))
    tilt = np.deg2rad(tilt_deg * rng.uniform(-1.0, 1.0))
    normal = np.array([np.cos(phi) * np.cos(tilt), np.sin(phi) * np.cos(tilt), np.sin(tilt)])
    distance = float(normal @ [0.0, 0.0, SCENE_DEPTH]) + offset * (1.0 + spread * rng.uniform(-1.0, 1.0))
    return distance * normal


#: Two-mirror wedge: outward normals at +/-(90 + WEDGE_DEG / 2) deg from the bisector (image up, -y;
#: the apex is below the target);
#: the apex WEDGE_APEX metres from the scene centre along it.
WEDGE_DEG, WEDGE_APEX = 72.0, 0.2
#: Three-mirror prism: walls PRISM_INRADIUS metres from the scene centre, normals 120 deg apart.
PRISM_INRADIUS = 0.1


def _kaleidoscope_walls(rng: np.random.Generator, num_mirrors: int, tilt_deg: float, jitter_deg: float,
                        spread: float) -> list[np.ndarray]:
    if num_mirrors == 2:
        half = 90.0 + WEDGE_DEG / 2.0
        offset = WEDGE_APEX * np.sin(np.deg2rad(WEDGE_DEG / 2.0))
        return [_wall(rng, -90.0 + s * half, offset, tilt_deg, jitter_deg, spread) for s in (1.0, -1.0)]
    return [_wall(rng, -90.0 + 120.0 * k, PRISM_INRADIUS, tilt_deg, jitter_deg, spread) for k in range(3)]


# --------------------------------------------------------------------------------------------------
# Images of views


def _image(camera: Camera, image_id: str, reflections, camera_points: np.ndarray, names: Sequence[str],
           fiducial_names, vectors: Mapping[tuple[int, int], np.ndarray], present: Sequence[tuple[int, int]],
           need_fiducials: int) -> dict | None:
    """The dataset@1 image of one view (noise-free pixels of the points seen), or None when too few
    fiducials (a known target) or no point at all is seen."""
    planes = [vectors[p] for p in present]
    path = [vectors[tuple(p)] for p in reflections]
    pixels, seen = observe(camera, camera_points, path, planes)
    fiducials_seen = sum(1 for i, n in enumerate(names) if seen[i] and n in fiducial_names)
    if not seen.any() or (fiducial_names and fiducials_seen < need_fiducials):
        return None
    return {"id": image_id, "reflections": [[int(l), int(m)] for l, m in reflections],
            "observations": {n: pixels[i] for i, n in enumerate(names) if seen[i]}}


def _add_noise(images: list[dict], pixel_sigma: float, rng: np.random.Generator) -> None:
    for image in images:
        for name, z in image["observations"].items():
            noisy = z + (rng.normal(scale=pixel_sigma, size=2) if pixel_sigma > 0.0 else 0.0)
            image["observations"][name] = [float(c) for c in noisy]


def _dataset(num_mirrors: int, cameras: Mapping[Camera_name, Camera], pixel_sigma: float,
             fiducials: Mapping[str, np.ndarray], images: list[dict], scale: dict | None) -> dict:
    """The dataset@1 dictionary (``camera`` or ``cameras``; ``scale`` without fiducials)."""
    single = list(cameras) == [None]
    data = {"format": DATASET_FORMAT, "num_mirrors": int(num_mirrors)}
    if single:
        data["camera"] = camera_to_dict(cameras[None])
    else:
        data["cameras"] = {name: camera_to_dict(c) for name, c in cameras.items()}
    data["pixel_sigma"] = float(pixel_sigma) if pixel_sigma > 0.0 else NOISE_FREE_NOMINAL_SIGMA_PX
    data["fiducials"] = {name: np.asarray(p, dtype=float).tolist() for name, p in fiducials.items()}
    if scale is not None:
        data["scale"] = scale
    data["images"] = images
    return data


def _owners(images: Sequence[dict], cameras: Sequence[Camera_name]) -> dict[tuple[int, int], Camera_name]:
    """The first camera (in ``cameras`` order) with an image of each placement."""
    order = {name: i for i, name in enumerate(cameras)}
    owners: dict[tuple[int, int], Camera_name] = {}
    for image in images:
        camera = image.get("camera")
        for l, m in image.get("reflections", []) or [(l + 1, m) for l, m in enumerate(image.get("mirror_configs", []))]:
            key = (int(l), int(m))
            if key not in owners or order[camera] < order[owners[key]]:
                owners[key] = camera
    return owners


def _check_common(pixel_sigma: float, num_points: int, target: bool) -> None:
    if pixel_sigma < 0.0:
        raise ValueError(f"pixel_sigma must be >= 0, got {pixel_sigma}")
    if num_points < 0:
        raise ValueError(f"the number of points must be >= 0, got {num_points}")
    if not target and num_points < 1:
        raise ValueError("without a known target (no fiducials) at least one unknown point is needed")


def simulate_kaleidoscope(num_mirrors: int = 2, target: bool = True, num_points: int | None = None,
                          pixel_sigma: float = 1.0, seed: int = 0, tilt_deg: float = 3.0,
                          jitter_deg: float = 4.0) -> tuple[dict, ViewsTruth]:
    """A kaleidoscope of ``num_mirrors`` (2 or 3) fixed mirrors: (dataset@1 dict, truth).

    One image per view seen: ``[]``, ``[[l, 0]]``, ``[[i, 0], [j, 0]]`` (i != j). With ``target`` the
    fiducials are :func:`kaleidoscope_fiducials` and a view needs MIN_FIDUCIALS_PER_VIEW of them;
    ``num_points`` unknown points (default 0 with a target, 1 without) lie within 3 cm of the scene
    centre. Without a target: ``fiducials: {}``, base frame = camera frame and ``scale`` = mirror 1's
    distance. The kaleidoscope is re-drawn until the direct view, every first-order view and at least two
    second-order views are seen. ``pixel_sigma`` pixels (0: noise-free).
    """
    if num_mirrors not in (2, 3):
        raise ValueError(f"a kaleidoscope has 2 or 3 mirrors, got {num_mirrors}")
    num_points = (0 if target else 1) if num_points is None else num_points
    _check_common(pixel_sigma, num_points, target)
    rng = np.random.default_rng(seed)
    camera = default_camera()
    fiducials = kaleidoscope_fiducials() if target else {}
    pose = _scene_pose(fiducials)
    points = _scene_points(rng, fiducials, pose, num_points)
    names = [*fiducials, *points]
    camera_points = apply_transform(*pose, np.array([*fiducials.values(), *points.values()]).reshape(-1, 3))  # eq. (2)
    mirrors = list(range(1, num_mirrors + 1))
    views: list[list[tuple[int, int]]] = [[]] + [[(l, 0)] for l in mirrors]
    views += [[(i, 0), (j, 0)] for i in mirrors for j in mirrors if i != j]
    for _ in range(_SCENE_TRIES):
        walls = _kaleidoscope_walls(rng, num_mirrors, tilt_deg, jitter_deg, spread=0.1)
        vectors = {(l, 0): walls[l - 1] for l in mirrors}
        images = []
        for view in views:
            tag = "".join(str(l) for l, _ in view) or "d"
            image = _image(camera, f"view_{tag}", view, camera_points, names, set(fiducials), vectors,
                           list(vectors), MIN_FIDUCIALS_PER_VIEW)
            if image is not None:
                images.append(image)
        orders = [len(image["reflections"]) for image in images]
        if orders.count(0) == 1 and orders.count(1) == num_mirrors and orders.count(2) >= 2:
            break
    else:
        raise RuntimeError("simulate: found no kaleidoscope showing the direct, every first-order and two "
                           "second-order views")
    _add_noise(images, pixel_sigma, rng)
    scale = None if target else {"mirror": 1, "config": 0, "distance": float(np.linalg.norm(vectors[(1, 0)]))}
    truth = ViewsTruth(poses={None: pose}, mirror_vectors=vectors, mirror_cameras={p: None for p in vectors},
                       points=points)
    return _dataset(num_mirrors, {None: camera}, pixel_sigma, fiducials, images, scale), truth


def simulate_mixed(placements: Sequence[int] = (4, 4), direct: int = 0, num_points: int = 0,
                   pixel_sigma: float = 1.0, seed: int = 0, tilt_deg: float = 6.0, jitter_deg: float = 8.0,
                   min_normal_spread_deg: float = 2.0) -> tuple[dict, ViewsTruth]:
    """Two hand-held mirrors: (dataset@1 dict, truth).

    Mirror l has ``placements[l-1]`` placements; photograph i (of max(placements)) holds placement
    ``i % n1`` of mirror 1 and ``i % n2`` of mirror 2, in a wedge around the target like
    :func:`simulate_kaleidoscope`'s, and gives the images ``[[1, m]]``, ``[[2, k]]``, ``[[1, m], [2, k]]``
    and ``[[2, k], [1, m]]``; the first ``direct`` photographs also the direct view ``[]``. Placements
    are re-drawn until every one of these views is seen and the placements of a mirror with three or
    more are ``min_normal_spread_deg`` from coplanar (eqs. 14-15). The analytical solution then follows
    from a mirror with >= 3 placements (or a direct view) by propagation.
    """
    n1, n2 = (int(n) for n in placements)
    if min(n1, n2) < 1:
        raise ValueError(f"each mirror needs at least one placement, got {n1} and {n2}")
    if max(n1, n2) < 3 and direct < 1:
        raise ValueError(f"placements {n1} and {n2}: the pose needs a mirror with at least 3 placements seen "
                         "alone, or a direct view")
    if direct < 0 or direct > max(n1, n2):
        raise ValueError(f"direct views must be between 0 and the {max(n1, n2)} photographs, got {direct}")
    _check_common(pixel_sigma, num_points, True)
    rng = np.random.default_rng(seed)
    camera = default_camera()
    fiducials = kaleidoscope_fiducials()
    pose = _scene_pose(fiducials)
    points = _scene_points(rng, fiducials, pose, num_points)
    names = [*fiducials, *points]
    camera_points = apply_transform(*pose, np.array([*fiducials.values(), *points.values()]).reshape(-1, 3))
    photos = [((1, i % n1), (2, i % n2)) for i in range(max(n1, n2))]
    spread = np.sin(np.deg2rad(min_normal_spread_deg))
    for _ in range(_SCENE_TRIES):
        vectors: dict[tuple[int, int], np.ndarray] = {}
        for l, count in ((1, n1), (2, n2)):
            for m in range(count):
                vectors[(l, m)] = _kaleidoscope_walls(rng, 2, tilt_deg, jitter_deg, spread=0.15)[l - 1]
        if any(count >= 3 and normal_spread([vectors[(l, m)] for m in range(count)]) < spread
               for l, count in ((1, n1), (2, n2))):
            continue
        images = _photograph_images(camera, photos, direct, camera_points, names, set(fiducials), vectors)
        if images is not None:
            break
    else:
        raise RuntimeError("simulate: found no hand-held mirror placements that show every view")
    _add_noise(images, pixel_sigma, rng)
    truth = ViewsTruth(poses={None: pose}, mirror_vectors=vectors, mirror_cameras={p: None for p in vectors},
                       points=points)
    return _dataset(2, {None: camera}, pixel_sigma, fiducials, images, None), truth


def _photograph_images(camera: Camera, photos, direct: int, camera_points, names, fiducial_names,
                       vectors) -> list[dict] | None:
    """Every view of every two-mirror photograph, or None when one of them is not seen."""
    images = []
    for i, (a, b) in enumerate(photos):
        for view in ([[]] if i < direct else []) + [[a], [b], [a, b], [b, a]]:
            tag = "".join(str(l) for l, _ in view) or "d"
            image = _image(camera, f"img{i:03d}_{tag}", view, camera_points, names, fiducial_names, vectors,
                           [a, b], MIN_FIDUCIALS_PER_VIEW)
            if image is None:
                return None
            images.append(image)
    return images


# --------------------------------------------------------------------------------------------------
# Files


def write_views_simulation(path: str | Path, dataset: dict, truth: ViewsTruth, plan: OutputPlan | None = None) -> Path:
    """Write the dataset@1 dict to ``path`` and its truth to ``<stem>.truth.json``, all-or-nothing
    (``plan``: :func:`mirror_fg.simulate.tree.simulation_outputs`, checked before the work). Returns
    the truth file's path."""
    plan = plan if plan is not None else simulation_outputs(path)
    out = truth_path(path)
    plan.commit({path: json_text(dataset, allow_nan=False), out: json.dumps(truth.to_dict(), indent=1) + "\n"})
    return out

