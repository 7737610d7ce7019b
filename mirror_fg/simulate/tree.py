"""Synthetic mirror scenes of the paper's Sect. 7 (Hesch et al., ECCV 2010). numpy only.

Scene: the base frame {B} sits around the camera; its fiducials and reconstruction points are never
seen directly, only through Nv planar mirrors that alternate in front of (+z) and behind (-z) the
camera, the last one (mirror Nv) in front, so light goes point -> mirror 1 -> ... -> mirror Nv ->
camera (docs/formats.md's nested transform ``A_k = M_k A_{k-1}``). With nominal mirrors at distance ``d`` the
camera sees a point at camera depth ``z`` at depth ``2 Nv d + z`` (even Nv) or ``2 Nv d - z`` (odd
Nv): about 2 m for the base case's two mirrors at 0.5 m.

Each mirror placement is drawn by rejection: normal = nominal normal rotated by a random angle up to
``tilt_deg`` about a random axis perpendicular to it, distance = ``mirror_distance * (1 +/- 10%)``; a
placement is kept only if, with its ancestors, every fiducial and reconstruction point of every image
below it is at positive depth, in front of every mirror's reflective face, and inside the image with a
20 px margin; the placements under one parent are re-drawn until their normals are not nearly
coplanar (by default 2 deg; the analytical solution needs non-coplanar normals, eqs. 14-15).
Observations are pixels with iid Gaussian noise ``pixel_sigma`` (pixels).
"""
from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.geometry import apply_transform, nested_transform, project, reflect, so3_exp
from mirror_fg.data import Dataset, Image
from mirror_fg.io.output import OutputPlan

__all__ = [
    "GroundTruth",
    "ground_truth_from_dict",
    "default_camera",
    "default_fiducials",
    "default_T_cam_base",
    "simulate_base_case",
    "simulate_tree",
    "visible",
    "normal_spread",
    "measure",
    "write_simulation",
    "truth_path",
    "TRUTH_FORMAT",
    "VISIBILITY_MARGIN_PX",
]

TRUTH_FORMAT = "mirror-fg/truth@1"
#: Every simulated point projects at least this far inside the image border (pixels).
VISIBILITY_MARGIN_PX = 20.0
#: Relative spread of a placement's distance around ``mirror_distance``.
DISTANCE_SPREAD = 0.10
#: Radius (metres) of the ball around a fiducial in which a reconstruction point is drawn.
POINT_RADIUS = 0.10
#: Dataset.pixel_sigma stored for a noise-free simulation (the file format needs sigma > 0).
NOISE_FREE_NOMINAL_SIGMA_PX = 1.0

_LEAF_TRIES = 2000  # placements of the last mirror tried before its parent is re-drawn
_INNER_TRIES = 50  # placements of an inner mirror tried before its parent is re-drawn
_GROUP_TRIES = 50  # draws of a whole set of sibling placements tried for a non-coplanar set
_DRAW_BUDGET_BASE = 20_000  # total placements drawn before giving up: base + per image
_DRAW_BUDGET_PER_IMAGE = 1_000


@dataclass
class GroundTruth:
    """True unknowns of a simulation.

    ``R_cam_base`` (3x3), ``t_cam_base`` (3,) metres: ``Cp = R @ Bp + t`` (eq. 2).
    ``mirror_vectors[(l, m)]``: mirror vector (metres, camera frame) of configuration m of mirror l
    (1-based l, m as in the images' ``mirror_configs``). ``points``: base-frame positions (metres)
    of the reconstruction points.
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray] = field(default_factory=dict)

    def vectors(self, mirror_configs: Sequence[int]) -> list[np.ndarray]:
        """The mirror vectors of an image with these mirror configurations, mirror 1 first."""
        return [self.mirror_vectors[(l + 1, m)] for l, m in enumerate(mirror_configs)]

    def transform(self, mirror_configs: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """``(A_Nv, b_Nv)`` of an image with these mirror configurations (eqs. 5-8)."""
        return nested_transform(self.R_cam_base, self.t_cam_base, self.vectors(mirror_configs))

    def to_dict(self) -> dict:
        """JSON-able dictionary (``mirror-fg/truth@1``)."""
        return {
            "format": TRUTH_FORMAT,
            "T_cam_base": {
                "R": np.asarray(self.R_cam_base, dtype=float).tolist(),
                "t": np.asarray(self.t_cam_base, dtype=float).tolist(),
            },
            "mirrors": [
                {"mirror": int(l), "config": int(m), "v": np.asarray(v, dtype=float).tolist()}
                for (l, m), v in sorted(self.mirror_vectors.items())
            ],
            "points": {name: np.asarray(p, dtype=float).tolist() for name, p in self.points.items()},
        }


def ground_truth_from_dict(data: dict) -> GroundTruth:
    """Inverse of :meth:`GroundTruth.to_dict`."""
    fmt = data.get("format", TRUTH_FORMAT)
    if fmt != TRUTH_FORMAT:
        raise ValueError(f"ground truth: format is {fmt!r}, expected {TRUTH_FORMAT!r}")
    T = data["T_cam_base"]
    return GroundTruth(
        R_cam_base=np.array(T["R"], dtype=float).reshape(3, 3),
        t_cam_base=np.array(T["t"], dtype=float).reshape(3),
        mirror_vectors={
            (int(e["mirror"]), int(e["config"])): np.array(e["v"], dtype=float).reshape(3)
            for e in data.get("mirrors", [])
        },
        points={name: np.array(p, dtype=float).reshape(3) for name, p in data.get("points", {}).items()},
    )


# --------------------------------------------------------------------------------------------------
# Scene


def default_camera() -> Camera:
    """The simulated camera: 1024x768, fx = fy = 800, principal point at the centre, no distortion."""
    return Camera(width=1024, height=768, fx=800.0, fy=800.0, cx=512.0, cy=384.0)


def default_fiducials(num_fiducials: int = 3) -> dict[str, np.ndarray]:
    """Sect. 7 fiducials (metres, base frame): a 20 x 20 x 20*sqrt(2) cm right triangle, F0 at the origin.

    ``num_fiducials=4`` adds F3 = (0.1, 0.1, 0.15), off the triangle's plane (unique PnP).
    """
    if num_fiducials not in (3, 4):
        raise ValueError(f"num_fiducials must be 3 or 4, got {num_fiducials}")
    fiducials = {
        "F0": np.array([0.0, 0.0, 0.0]),
        "F1": np.array([0.2, 0.0, 0.0]),
        "F2": np.array([0.0, 0.2, 0.0]),
    }
    if num_fiducials == 4:
        fiducials["F3"] = np.array([0.1, 0.1, 0.15])
    return fiducials


def default_T_cam_base() -> tuple[np.ndarray, np.ndarray]:
    """True camera-to-base transform of every simulation.

    ``R`` is 30 deg about (1, -2, 1)/sqrt(6); ``t`` puts the base point (0.1, 0.1, 0) (about the centre
    of the fiducials and reconstruction points) near (0, 0.1, 0) in the camera frame: 10 cm below the
    camera centre, level with it, so the mirrors show the robot near the image centre.
    """
    axis = np.array([1.0, -2.0, 1.0]) / np.sqrt(6.0)
    R = so3_exp(np.deg2rad(30.0) * axis)
    t = np.array([-0.065, -0.010, -0.060])
    return R, t


def _random_points(
    rng: np.random.Generator, fiducials: dict[str, np.ndarray], num_points: int
) -> dict[str, np.ndarray]:
    """Reconstruction points P0.. uniformly in balls of radius POINT_RADIUS around random fiducials."""
    anchors = np.array(list(fiducials.values()))
    points = {}
    for i in range(num_points):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        radius = POINT_RADIUS * rng.uniform() ** (1.0 / 3.0)
        points[f"P{i}"] = anchors[rng.integers(len(anchors))] + radius * direction
    return points


def _nominal_normal(level: int, num_mirrors: int) -> np.ndarray:
    """Unit normal (camera frame, camera to mirror) of mirror ``level``: the last in front, alternating."""
    return np.array([0.0, 0.0, 1.0 if (num_mirrors - level) % 2 == 0 else -1.0])


def _random_mirror_vector(
    rng: np.random.Generator, nominal_normal: np.ndarray, mirror_distance: float, tilt_deg: float
) -> np.ndarray:
    """Nominal normal tilted up to ``tilt_deg`` about a random perpendicular axis, distance +/- 10%."""
    axis = rng.normal(size=3)
    axis -= (axis @ nominal_normal) * nominal_normal
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(tilt_deg) * rng.uniform()
    normal = so3_exp(angle * axis) @ nominal_normal
    distance = mirror_distance * (1.0 + DISTANCE_SPREAD * rng.uniform(-1.0, 1.0))
    return distance * normal


# --------------------------------------------------------------------------------------------------
# Visibility and measurement


def visible(
    camera: Camera,
    camera_points: np.ndarray,
    mirror_vectors: Sequence[np.ndarray],
    margin_px: float = VISIBILITY_MARGIN_PX,
) -> bool:
    """Whether camera-frame points (N, 3) seen through ``mirror_vectors`` (mirror 1 first) are all visible.

    Visible: before each mirror the (virtual) point lies on the mirror's reflective side, the side of
    the camera (``v . x < v . v``), and its final image is at positive depth and projects inside the
    image with ``margin_px`` pixels to spare.
    """
    x = np.asarray(camera_points, dtype=float)
    for v in mirror_vectors:
        v = np.asarray(v, dtype=float)
        vv = float(v @ v)
        if np.any(x @ v >= vv):
            return False
        x = reflect(x, v)  # eq. (3)
    if np.any(x[:, 2] <= 1e-6):
        return False
    pixels = _to_pixels(camera, project(x))
    return bool(
        np.all(pixels[:, 0] >= margin_px)
        and np.all(pixels[:, 0] <= camera.width - margin_px)
        and np.all(pixels[:, 1] >= margin_px)
        and np.all(pixels[:, 1] <= camera.height - margin_px)
    )


def _to_pixels(camera: Camera, normalized: np.ndarray) -> np.ndarray:
    """Pinhole pixels (N, 2) of normalized coordinates; the simulated camera has no distortion."""
    if camera.model != "pinhole" or any(float(k) != 0.0 for k in camera.dist):
        raise ValueError("simulate: only distortion-free pinhole cameras are simulated")
    return np.column_stack(
        [camera.fx * normalized[:, 0] + camera.cx, camera.fy * normalized[:, 1] + camera.cy]
    )


def measure(
    truth: GroundTruth,
    camera: Camera,
    fiducials: dict[str, np.ndarray],
    mirror_configs: Sequence[int],
    pixel_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> dict[str, np.ndarray]:
    """Pixel observations of every fiducial and reconstruction point in one image (eqs. 5, 9).

    Noise: iid Gaussian, ``pixel_sigma`` pixels per coordinate (none when 0).
    """
    names = list(fiducials) + list(truth.points)
    base = np.array([*fiducials.values(), *truth.points.values()], dtype=float).reshape(-1, 3)
    A, b = truth.transform(mirror_configs)
    pixels = _to_pixels(camera, project(apply_transform(A, b, base)))
    if pixel_sigma > 0.0:
        if rng is None:
            raise ValueError("measure: pixel_sigma > 0 needs an rng")
        pixels = pixels + rng.normal(scale=pixel_sigma, size=pixels.shape)
    return {name: pixels[i] for i, name in enumerate(names)}


# --------------------------------------------------------------------------------------------------
# Mirror placements by rejection down the configuration tree (Fig. 3)


def normal_spread(mirror_vectors: Sequence[np.ndarray]) -> float:
    """Smallest singular value of the stacked unit normals: 0 when they are coplanar (eqs. 14-15 fail)."""
    normals = np.array([np.asarray(v, dtype=float) / np.linalg.norm(v) for v in mirror_vectors])
    if len(normals) < 3:
        return 0.0
    return float(np.linalg.svd(normals, compute_uv=False)[2])


def _place_mirrors(
    leaves: list[tuple[int, ...]],
    draw: Callable[[int], np.ndarray],
    is_visible: Callable[[list[np.ndarray]], bool],
    min_spread: float = 0.0,
) -> dict[tuple[int, int], np.ndarray]:
    """Mirror vectors for every configuration of ``leaves`` (one tuple of mirror configs per image).

    Configurations form a tree (configuration m of mirror l has one parent path). Each is drawn with
    ``draw(l)`` until every image below it can be completed visibly; a configuration whose children
    cannot be placed is re-drawn. The placements under one parent (three or more) are re-drawn
    together until :func:`normal_spread` of their normals is at least ``min_spread``.
    """
    num_mirrors = len(leaves[0])
    budget = [_DRAW_BUDGET_BASE + _DRAW_BUDGET_PER_IMAGE * len(leaves)]  # bounds the nested retries

    def place(level: int, prefix: list[np.ndarray], group: list[tuple[int, ...]]):
        by_config: dict[int, list[tuple[int, ...]]] = {}
        for leaf in group:
            by_config.setdefault(leaf[level - 1], []).append(leaf)
        for _ in range(_GROUP_TRIES):
            placed: dict[tuple[int, int], np.ndarray] = {}
            for m, sub in by_config.items():
                for _ in range(_LEAF_TRIES if level == num_mirrors else _INNER_TRIES):
                    budget[0] -= 1
                    if budget[0] < 0:
                        return None
                    v = draw(level)
                    below: dict | None
                    if level == num_mirrors:
                        below = {} if is_visible(prefix + [v]) else None
                    else:
                        below = place(level + 1, prefix + [v], sub)
                    if below is not None:
                        placed[(level, m)] = v
                        placed.update(below)
                        break
                else:
                    return None
            siblings = [placed[(level, m)] for m in by_config]
            if len(siblings) < 3 or normal_spread(siblings) >= min_spread:
                return placed
        return None

    placed = place(1, [], leaves)
    if placed is None:
        raise RuntimeError(
            "simulate: found no mirror placements that show every point inside the image with "
            "non-coplanar sibling normals; the points must lie between the mirrors (mirror_distance "
            "of a few decimetres or more), and tilt_deg must allow min_normal_spread_deg"
        )
    return placed


def _simulate(
    leaves: list[tuple[int, ...]],
    num_fiducials: int,
    num_points: int,
    pixel_sigma: float,
    mirror_distance: float,
    tilt_deg: float,
    seed: int,
    min_normal_spread_deg: float,
) -> tuple[Dataset, GroundTruth]:
    if pixel_sigma < 0.0:
        raise ValueError(f"pixel_sigma must be >= 0, got {pixel_sigma}")
    if mirror_distance <= 0.0:
        raise ValueError(f"mirror_distance must be > 0, got {mirror_distance}")
    rng = np.random.default_rng(seed)
    camera = default_camera()
    fiducials = default_fiducials(num_fiducials)
    R, t = default_T_cam_base()
    points = _random_points(rng, fiducials, num_points)
    base = np.array([*fiducials.values(), *points.values()])
    camera_points = apply_transform(R, t, base)  # eq. (2)
    num_mirrors = len(leaves[0])
    normals = {l: _nominal_normal(l, num_mirrors) for l in range(1, num_mirrors + 1)}
    mirror_vectors = _place_mirrors(
        leaves,
        draw=lambda l: _random_mirror_vector(rng, normals[l], mirror_distance, tilt_deg),
        is_visible=lambda vectors: visible(camera, camera_points, vectors),
        min_spread=np.sin(np.deg2rad(min_normal_spread_deg)),
    )
    truth = GroundTruth(R_cam_base=R, t_cam_base=t, mirror_vectors=mirror_vectors, points=points)
    images = [
        Image(
            id=f"img{i:05d}",
            mirror_configs=tuple(int(m) for m in configs),
            observations=measure(truth, camera, fiducials, configs, pixel_sigma, rng),
        )
        for i, configs in enumerate(leaves)
    ]
    ds = Dataset(
        num_mirrors=num_mirrors,
        camera=camera,
        pixel_sigma=float(pixel_sigma) if pixel_sigma > 0.0 else NOISE_FREE_NOMINAL_SIGMA_PX,
        fiducials=fiducials,
        images=images,
        source="<simulation>",
    )
    return ds, truth


def simulate_base_case(
    num_images: int = 200,
    num_points: int = 0,
    pixel_sigma: float = 1.0,
    mirror_distance: float = 0.5,
    tilt_deg: float = 30.0,
    mirror1_placements: int = 3,
    seed: int = 0,
    num_mirrors: int = 2,
    num_fiducials: int = 3,
    min_normal_spread_deg: float = 2.0,
) -> tuple[Dataset, GroundTruth]:
    """The paper's Sect. 7 base case: Nc images of a 20 cm right triangle through two mirrors.

    Mirror 2 (in front of the camera, ``mirror_distance`` metres) moves in every image (configuration
    index = image index); mirror 1 (behind the camera) has ``mirror1_placements`` = k configurations
    0..k-1, the images split evenly among them in order. ``num_mirrors=1``: only the front mirror,
    moving in every image. ``num_mirrors > 2``: mirrors 1..Nv-1 form a k-ary tree (mirror l has
    configurations 0..k**l - 1, as in :func:`simulate_tree`) whose k**(Nv-1) leaves split the images
    evenly in order; mirrors alternate behind/in front of the camera, mirror Nv in front.

    ``pixel_sigma`` in pixels; 0 gives noise-free observations and the dataset then stores
    ``pixel_sigma = 1.0`` (NOISE_FREE_NOMINAL_SIGMA_PX), as the file needs a positive value.
    ``num_points`` reconstruction points P0.. lie within 10 cm of the fiducials.
    ``min_normal_spread_deg``: the placements of a mirror under one parent are re-drawn until their
    normals are this far from coplanar (:func:`normal_spread` >= its sine), so the analytical
    solution's eqs. (14)-(15) are solvable; 0 turns the check off (to simulate degenerate motion).
    """
    if num_mirrors < 1:
        raise ValueError(f"num_mirrors must be >= 1, got {num_mirrors}")
    if num_images < 1:
        raise ValueError(f"num_images must be >= 1, got {num_images}")
    k = mirror1_placements
    blocks_needed = k ** (num_mirrors - 1)
    if k < 1 or blocks_needed > num_images:
        raise ValueError(
            f"mirror1_placements={k} with {num_mirrors} mirrors needs at least {blocks_needed} images, "
            f"got {num_images}"
        )
    # Mirrors 1..Nv-1: a k-ary tree whose k**(Nv-1) leaves split the images evenly, in order.
    blocks = np.array_split(np.arange(num_images), blocks_needed)
    leaves = [
        tuple(j // k ** (num_mirrors - 1 - l) for l in range(1, num_mirrors)) + (int(i),)
        for j, block in enumerate(blocks)
        for i in block
    ]
    return _simulate(
        leaves, num_fiducials, num_points, pixel_sigma, mirror_distance, tilt_deg, seed, min_normal_spread_deg
    )


def simulate_tree(
    num_mirrors: int,
    children: int = 3,
    images_per_leaf: int = 1,
    num_fiducials: int = 3,
    num_points: int = 0,
    pixel_sigma: float = 0.0,
    seed: int = 0,
    mirror_distance: float = 0.5,
    tilt_deg: float = 25.0,
    min_normal_spread_deg: float = 2.0,
) -> tuple[Dataset, GroundTruth]:
    """The paper's Fig. 3 configuration tree for any Nv.

    Every configuration of mirror l has ``children`` configurations of mirror l+1 under it; mirror l's
    configurations are numbered 0..children**l - 1 across the tree (children of configuration j are
    j*children .. j*children + children-1). Each leaf (configuration of mirror Nv) is seen in
    ``images_per_leaf`` images (same mirrors, independent noise): children**Nv * images_per_leaf images.
    Mirrors alternate: Nv in front of the camera, Nv-1 behind, ... Odd Nv gives mirror-imaged views.
    ``min_normal_spread_deg`` as in :func:`simulate_base_case`.
    """
    if num_mirrors < 1:
        raise ValueError(f"num_mirrors must be >= 1, got {num_mirrors}")
    if children < 1 or images_per_leaf < 1:
        raise ValueError("children and images_per_leaf must be >= 1")
    leaves = []
    for leaf in range(children**num_mirrors):
        configs = tuple(leaf // children ** (num_mirrors - l) for l in range(1, num_mirrors + 1))
        leaves.extend([configs] * images_per_leaf)
    return _simulate(
        leaves, num_fiducials, num_points, pixel_sigma, mirror_distance, tilt_deg, seed, min_normal_spread_deg
    )


# --------------------------------------------------------------------------------------------------
# Files


def truth_path(dataset_path: str | Path) -> Path:
    """Where the ground truth of a simulated dataset is written: ``<stem>.truth.json`` beside it."""
    path = Path(dataset_path)
    return path.with_name(path.stem + ".truth.json")


def simulation_outputs(path: str | Path) -> OutputPlan:
    """The checked outputs of :func:`write_simulation` (DatasetError before any work if one cannot be
    written): the dataset at ``path`` and its ground truth at ``<stem>.truth.json``."""
    plan = OutputPlan()
    plan.add(path, "dataset")
    plan.add(truth_path(path), "ground truth")
    return plan


def write_simulation(path: str | Path, dataset: Dataset, truth: GroundTruth, plan: OutputPlan | None = None) -> Path:
    """Write ``dataset`` (dataset@1 JSON) to ``path`` and its ground truth to ``<stem>.truth.json``,
    all-or-nothing (``plan``: from :func:`simulation_outputs`, checked before the simulation).

    Returns the path of the ground-truth file.
    """
    from mirror_fg.io.dataset import dataset_text

    plan = plan if plan is not None else simulation_outputs(path)
    out = truth_path(path)
    plan.commit({path: dataset_text(dataset), out: json.dumps(truth.to_dict(), indent=1) + "\n"})
    return out
