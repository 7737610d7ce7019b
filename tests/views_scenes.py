"""Synthetic scenes for the general view model (docs/formats.md "Views of any reflection order, and several cameras").

Each generator returns ``(dataset_dict, truth)``: a ``mirror-fg/dataset@1`` dictionary (JSON types only,
``reflections`` per image, pixels of pinhole cameras without distortion) and a :class:`Truth`.

The forward model here works with mirror planes in the *base* frame (``n . Bx = d``), reflecting the
base-frame point across each plane in turn and only then mapping it into the camera (reflections and
rigid motions commute: T(Refl(x)) = Refl_in_camera(T(x))). The reference MLE (views_reference.py)
instead reflects in the camera frame with eq. (3) ``x <- M x + 2 v``; the two agree only if both are
right. Nothing here comes from mirror_fg.

Plausibility of every kept observation (checked here, asserted again in test_views_reference.py):
in front of the camera (final depth > MIN_DEPTH_M), inside the image by IMAGE_MARGIN_PX, and for each
reflection in turn the point before it on the same side of that plane as the camera centre.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_DEPTH_M = 0.1
IMAGE_MARGIN_PX = 8.0
#: Where ``seed`` draws the noise, the geometry is drawn from this one (same scene, new noise).
GEOMETRY_SEED = 7


@dataclass
class Truth:
    """``T_cam_base[name] = (R, t)`` (``Cp = R Bp + t``); ``mirrors[(l, m)]``: v in the frame of
    ``owners[(l, m)]`` (docs/formats.md: first camera in ``cameras`` order with an image seeing it);
    ``points[name]``: reconstruction points, base frame; ``planes[(l, m)] = (n, d)``: base frame."""

    T_cam_base: dict[str, tuple[np.ndarray, np.ndarray]]
    mirrors: dict[tuple[int, int], np.ndarray]
    owners: dict[tuple[int, int], str]
    points: dict[str, np.ndarray]
    planes: dict[tuple[int, int], tuple[np.ndarray, float]] = field(default_factory=dict)


def rotation(axis, angle_deg: float) -> np.ndarray:
    """Rotation by ``angle_deg`` about ``axis`` (Rodrigues, real inputs only)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def camera_dict(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> dict:
    return {"model": "pinhole", "width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "dist": [0.0, 0.0, 0.0, 0.0, 0.0]}


def unit(u) -> np.ndarray:
    return np.asarray(u, float) / np.linalg.norm(u)


def plane_through(point, normal) -> tuple[np.ndarray, float]:
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    return n, float(n @ np.asarray(point, float))


def grid(cols: int, rows: int, pitch: float, R=np.eye(3), t=np.zeros(3), prefix: str = "F") -> dict:
    """``cols x rows`` fiducials, centred, in the plane z = 0 of a board placed at ``Bx = R x + t``."""
    names = {}
    for r in range(rows):
        for c in range(cols):
            local = np.array([(c - (cols - 1) / 2) * pitch, (r - (rows - 1) / 2) * pitch, 0.0])
            names[f"{prefix}{r * cols + c:02d}"] = R @ local + t
    return names


def observe(camera: dict, R, t, planes_base: list, X_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of base points ``X_base`` seen by the camera at ``(R, t)`` after the light met
    ``planes_base`` (base frame, in order), and the mask of plausible observations (module docstring)."""
    C = -R.T @ t  # camera centre, base frame
    x = np.array(X_base, float)
    ok = np.ones(len(x), bool)
    for n, d in planes_base:
        camera_side = np.sign(n @ C - d)
        s = x @ n - d
        ok &= (np.sign(s) == camera_side) & (np.abs(s) > 1e-3)
        x = x - 2.0 * s[:, None] * n  # reflection across n . x = d
    xc = x @ R.T + t
    ok &= xc[:, 2] > MIN_DEPTH_M
    z = xc[:, :2] / np.where(ok, xc[:, 2], 1.0)[:, None]
    pix = np.c_[camera["fx"] * z[:, 0] + camera["cx"], camera["fy"] * z[:, 1] + camera["cy"]]
    m = IMAGE_MARGIN_PX
    ok &= (pix[:, 0] > m) & (pix[:, 0] < camera["width"] - m) & (pix[:, 1] > m) & (pix[:, 1] < camera["height"] - m)
    return pix, ok


def plane_in_camera(n_b, d_b, R, t) -> np.ndarray:
    """Mirror vector of base plane ``n_b . Bx = d_b`` in the frame of the camera at (R, t)."""
    n_c = R @ n_b
    return (d_b + n_c @ t) * n_c


def build(cameras: dict, poses: dict, fiducials: dict, points: dict, planes: dict, views: list,
          pixel_sigma: float, seed: int, num_mirrors: int, *, single_camera: bool, min_points: int,
          scale: dict | None = None) -> tuple[dict, Truth]:
    """The dataset of ``views`` = [(image id, camera name, reflections, required)], each keeping its
    plausible observations; a required view with fewer than ``min_points`` raises (a scene design
    error), an optional one is dropped. Noise N(0, pixel_sigma^2) per coordinate from ``seed`` (None: no
    noise; every generator passes its ``seed`` here)."""
    rng = np.random.default_rng(seed)
    names = list(fiducials) + list(points)
    X = np.array([fiducials.get(n, points.get(n)) for n in names], float).reshape(-1, 3)
    images = []
    for image_id, cam, reflections, required in views:
        R, t = poses[cam]
        pix, ok = observe(cameras[cam], R, t, [planes[tuple(p)] for p in reflections], X)
        if ok.sum() < min_points:
            if required:
                raise AssertionError(f"scene: view {image_id} {reflections} sees only {ok.sum()} points")
            continue
        noisy = pix if seed is None else pix + rng.normal(0.0, pixel_sigma, pix.shape)
        obs = {n: [float(u), float(v)] for n, (u, v), k in zip(names, noisy, ok) if k}
        image = {"id": image_id, "reflections": [list(map(int, p)) for p in reflections], "observations": obs}
        if not single_camera:
            image["camera"] = cam
        images.append(image)
    owners: dict = {}
    for cam in cameras:  # docs/formats.md: the first camera in `cameras` order with an image seeing the placement
        for image in images:
            if single_camera or image["camera"] == cam:
                for p in image["reflections"]:
                    owners.setdefault(tuple(p), cam)
    mirrors = {p: plane_in_camera(*planes[p], *poses[owners[p]]) for p in owners}
    d = {"format": "mirror-fg/dataset@1", "num_mirrors": num_mirrors}
    if single_camera:
        d["camera"] = next(iter(cameras.values()))
    else:
        d["cameras"] = cameras
    d["pixel_sigma"] = float(pixel_sigma)
    d["fiducials"] = {n: [float(c) for c in x] for n, x in fiducials.items()}
    d["images"] = images
    if scale is not None:
        d["scale"] = scale
    truth = Truth({c: (np.array(R), np.array(t)) for c, (R, t) in poses.items()}, mirrors, owners,
                  {n: np.array(p, float) for n, p in points.items()}, dict(planes))
    return d, truth


def _to_base(R_cb, t_cb, point_cam=None, normal_cam=None):
    """A camera-frame point or plane normal expressed in the base frame (camera at (R_cb, t_cb))."""
    if point_cam is not None:
        return R_cb.T @ (np.asarray(point_cam, float) - t_cb)
    return R_cb.T @ np.asarray(normal_cam, float)


def _plane_cam_to_base(R_cb, t_cb, point_cam, normal_cam):
    return plane_through(_to_base(R_cb, t_cb, point_cam=point_cam), _to_base(R_cb, t_cb, normal_cam=normal_cam))


def _side_mirror_scene():
    """One camera, a 6 x 5 board 0.75 m ahead (base = board frame), a mirror on the left and one below."""
    camera = camera_dict(1280, 960, 1000.0, 1002.0, 641.5, 478.0)
    R_board = rotation([1, 0.3, 0], 14.0)  # board frame -> camera frame
    t_board = np.array([0.01, -0.02, 0.75])
    fiducials = grid(6, 5, 0.03)
    return camera, (R_board, t_board), fiducials


def _jittered(rng, point, normal, shift_m: float, tilt_deg: float):
    axis = np.cross(normal, rng.normal(size=3))
    return (np.asarray(point, float) + rng.uniform(-shift_m, shift_m, 3),
            rotation(axis, rng.uniform(0.4, 1.0) * tilt_deg) @ np.asarray(normal, float))


LEFT = ([-0.17, 0.0, 0.75], [1.0, 0.08, -0.22])
BELOW = ([0.0, 0.15, 0.75], [0.12, -1.0, -0.25])


def kaleidoscope_two_mirrors(seed: int | None = 0, pixel_sigma: float = 0.5) -> tuple[dict, Truth]:
    """(a) A known board and two fixed mirrors (one placement each): the direct view and every
    plausible view of order 1 and 2 of one photograph."""
    camera, (R, t), fiducials = _side_mirror_scene()
    planes = {(1, 0): _plane_cam_to_base(R, t, *LEFT), (2, 0): _plane_cam_to_base(R, t, *BELOW)}
    views = [("direct", "camera", [], True), ("m1", "camera", [[1, 0]], True), ("m2", "camera", [[2, 0]], True),
             ("m1m2", "camera", [[1, 0], [2, 0]], False), ("m2m1", "camera", [[2, 0], [1, 0]], False)]
    return build({"camera": camera}, {"camera": (R, t)}, fiducials, {}, planes, views, pixel_sigma, seed, 2,
                 single_camera=True, min_points=20)


def _handheld_planes(R, t, counts: tuple[int, int]):
    rng = np.random.default_rng(GEOMETRY_SEED)
    planes = {}
    for l, (point, normal) in zip((1, 2), (LEFT, BELOW)):
        for m in range(counts[l - 1]):
            planes[(l, m)] = _plane_cam_to_base(R, t, *_jittered(rng, point, normal, 0.02, 9.0))
    return planes


def _handheld(seed, pixel_sigma, alone2: list[int], pairs: list[tuple[int, int]]):
    camera, (R, t), fiducials = _side_mirror_scene()
    planes = _handheld_planes(R, t, (4, 3))
    views = [(f"m1_{m}", "camera", [[1, m]], True) for m in range(4)]
    views += [(f"m2_{k}", "camera", [[2, k]], True) for k in alone2]
    for m, k in pairs:
        views += [(f"m1_{m}_m2_{k}", "camera", [[1, m], [2, k]], True),
                  (f"m2_{k}_m1_{m}", "camera", [[2, k], [1, m]], True)]
    return build({"camera": camera}, {"camera": (R, t)}, fiducials, {}, planes, views, pixel_sigma, seed, 2,
                 single_camera=True, min_points=12)


def mixed_two_handheld(seed: int | None = 0, pixel_sigma: float = 0.5) -> tuple[dict, Truth]:
    """(b) Two hand-held mirrors: mirror 1 in 4 placements and mirror 2 in 3, each seen alone, and
    double views in both orders; no direct view."""
    return _handheld(seed, pixel_sigma, [0, 1, 2], [(0, 0), (1, 1), (2, 2), (3, 0)])


def mixed_one_mirror_gives_pose(seed: int | None = 0, pixel_sigma: float = 0.5) -> tuple[dict, Truth]:
    """(c) As (b) but mirror 2 is seen alone in one placement only: only mirror 1's four placements give
    the pose; mirror 2's placements 1 and 2 appear in double views only."""
    return _handheld(seed, pixel_sigma, [0], [(0, 1), (1, 2), (2, 0), (3, 1), (0, 2)])


def kaleidoscope_three_mirrors_one_point(seed: int | None = 0, pixel_sigma: float = 0.3,
                                         scale_by_points: bool = False) -> tuple[dict, Truth]:
    """(d) No known target (``fiducials: {}``): one point P0 inside a tapered three-mirror kaleidoscope
    around the optical axis; the direct view and every plausible view of order 1, 2 and 3. The base
    frame is the camera's; ``scale`` is placement (1, 0)'s distance, or with ``scale_by_points`` a
    second point P1 is added and the scale is the distance P0-P1."""
    camera = camera_dict(1280, 960, 1000.0, 1000.0, 640.0, 480.0)
    rng = np.random.default_rng(GEOMETRY_SEED)
    planes = {}
    for l, phi in zip((1, 2, 3), np.radians([90.0, 215.0, 330.0]) + rng.uniform(-0.1, 0.1, 3)):
        e = np.array([np.cos(phi), np.sin(phi), 0.0])
        planes[(l, 0)] = plane_through(0.045 * e, -e + [0, 0, 0.04 + 0.04 * rng.uniform()])
    points = {"P0": np.array([0.01, -0.008, 0.9])}
    levels = [[[]]]
    for _ in range(3):  # orders 1, 2, 3; two consecutive reflections never in the same mirror
        levels.append([o + [p] for o in levels[-1] for p in planes if not o or o[-1] != p])
    orders = [o for level in levels for o in level]
    views = [("k" + "".join(str(p[0]) for p in o) if o else "direct", "camera", [list(p) for p in o], len(o) <= 1)
             for o in orders]
    scale = {"mirror": 1, "config": 0, "distance": float(abs(planes[(1, 0)][1]))}
    if scale_by_points:
        points["P1"] = np.array([-0.012, 0.006, 0.93])
        scale = {"points": ["P0", "P1"], "distance": float(np.linalg.norm(points["P1"] - points["P0"]))}
    return build({"camera": camera}, {"camera": (np.eye(3), np.zeros(3))}, {}, points, planes, views, pixel_sigma,
                 seed, 3, single_camera=True, min_points=1, scale=scale)


def _rig(seed, pixel_sigma, with_top: bool):
    cameras = {"left": camera_dict(1280, 960, 1000.0, 1001.0, 645.0, 476.0),
               "right": camera_dict(1024, 768, 810.0, 806.0, 515.0, 380.0)}
    poses = {"left": (rotation([0.2, 1, 0], 4.0), np.array([0.06, 0.0, 0.0])),
             "right": (rotation([0.1, -1, 0.2], 6.0), np.array([-0.07, 0.005, 0.01]))}
    if with_top:
        cameras["top"] = camera_dict(800, 600, 650.0, 652.0, 402.0, 297.0)
        poses["top"] = (rotation([1, 0, 0.1], -7.0), np.array([0.0, 0.08, -0.01]))
    # base = robot body; the board below the cameras, facing the mirror ahead (+z)
    fiducials = grid(6, 5, 0.05, rotation([1, 0, 0], 12.0), np.array([0.0, 0.16, -0.04]))
    # each placement reflects the board's centre into the camera(s) that see it through a spot ahead
    board = np.mean(list(fiducials.values()), axis=0)
    spots = [(0.0, 0.0), (0.2, -0.15), (-0.3, 0.1), (-0.15, -0.3), (-0.1, 0.3),
             (0.3, 0.05), (0.1, -0.3), (0.25, 0.28)]
    seen = {"left": [0, 1, 2, 3, 4], "right": [0, 1, 5, 6, 7], "top": [0, 1]}
    planes = {}
    for m, (a, b) in enumerate(spots):
        centre = np.mean([-R.T @ t for c, (R, t) in poses.items() if m in seen[c]], axis=0)
        Q = centre + 0.45 * unit(np.array([a, b, 1.0]))
        planes[(1, m)] = plane_through(Q, unit(centre - Q) + unit(board - Q))
    views = [(f"{cam}_{m}", cam, [[1, m]], True) for cam in cameras for m in seen[cam]]
    return build(cameras, poses, fiducials, {}, planes, views, pixel_sigma, seed, 1, single_camera=False,
                 min_points=12)


def rig_two_cameras(seed: int | None = 0, pixel_sigma: float = 0.5) -> tuple[dict, Truth]:
    """(e) Cameras "left" (1280x960) and "right" (1024x768) on one body, a board, one hand-held mirror
    in 8 placements: 0 and 1 seen by both cameras (one plane each), 2-4 by left only, 5-7 by right only."""
    return _rig(seed, pixel_sigma, with_top=False)


def rig_three_cameras(seed: int | None = 0, pixel_sigma: float = 0.5) -> tuple[dict, Truth]:
    """(f) As (e) plus camera "top" (800x600) that sees only placements 0 and 1, both shared."""
    return _rig(seed, pixel_sigma, with_top=True)


CASES = {f.__name__: f for f in (kaleidoscope_two_mirrors, mixed_two_handheld, mixed_one_mirror_gives_pose,
                                 kaleidoscope_three_mirrors_one_point, rig_two_cameras, rig_three_cameras)}
