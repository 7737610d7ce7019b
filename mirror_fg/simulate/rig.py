"""Synthetic rigs: several cameras with different intrinsics on one body (docs/formats.md "Several cameras on one
body"), seen through the paper's tree of two mirrors (Sect. 7) or through two hand-held mirrors in mixed
reflection orders (:func:`mirror_fg.simulate.views.simulate_mixed`'s scene).

Photographs are either *shared* (every camera of the rig was triggered together: the same mirror
placements in an image of each camera) or a camera's *own* (no other camera sees their placements). The
rig: ``cam0`` is the simulator's default camera and pose; camera i sits RIG_BASELINE * i metres along
x (alternating sides) and 0.01 * i below, turned a few degrees, with its own resolution and focal length.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.geometry import apply_transform, so3_exp
from mirror_fg.simulate.tree import (
    _random_mirror_vector,
    _random_points,
    default_camera,
    default_fiducials,
    default_T_cam_base,
    normal_spread,
)
from mirror_fg.simulate.views import (
    MIN_FIDUCIALS_PER_VIEW,
    _add_noise,
    _dataset,
    _image,
    _kaleidoscope_walls,
    _owners,
    _scene_points,
    _scene_pose,
    kaleidoscope_fiducials,
    observe,
)
from mirror_fg.simulate.views_truth import ViewsTruth, plane_in_camera

__all__ = ["rig_cameras", "rig_poses", "simulate_rig_tree", "simulate_rig_mixed", "RIG_BASELINE"]

#: Spacing (metres) of the rig's cameras along x.
RIG_BASELINE = 0.06
_TRIES = 200  # draws of a mirror-1 placement (tree) or of a photograph's placements (mixed)
_LEAF_TRIES = 2000  # draws of mirror 2 for one photograph of the tree
_GROUP_TRIES = 50


def rig_cameras(num_cameras: int) -> dict[str, Camera]:
    """``cam0``..: the default camera first, then cameras of other resolutions and focal lengths."""
    if num_cameras < 2:
        raise ValueError(f"a rig has at least 2 cameras, got {num_cameras}")
    cameras = {"cam0": default_camera()}
    sizes = [(1280, 960, 1010.0), (800, 600, 610.0), (1024, 768, 860.0)]
    for i in range(1, num_cameras):
        width, height, focal = sizes[(i - 1) % len(sizes)]
        cameras[f"cam{i}"] = Camera(width=width, height=height, fx=focal, fy=focal * 1.002,
                                    cx=width / 2.0 + 3.0 * i, cy=height / 2.0 - 2.0 * i)
    return cameras


def rig_poses(names: Sequence[str], pose0: tuple[np.ndarray, np.ndarray], baseline: float = RIG_BASELINE
              ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """T_cam_base of every camera: the first has ``pose0``; camera i is at ``p_i`` in the first camera's
    frame, turned by ``R_i0``: ``x_i = R_i0 x_0 - R_i0 p_i``, so ``T_i = (R_i0 R_0, R_i0 (t_0 - p_i))``."""
    R0, t0 = pose0
    poses = {names[0]: (np.asarray(R0, dtype=float), np.asarray(t0, dtype=float))}
    for i, name in enumerate(names[1:], start=1):
        side = 1.0 if i % 2 else -1.0
        position = np.array([side * baseline * ((i + 1) // 2), 0.01 * i, 0.0])
        R_i0 = so3_exp(np.deg2rad([1.0 * i, side * 3.0, -0.5 * i]))
        poses[name] = (R_i0 @ R0, R_i0 @ (t0 - position))
    return poses


def _photographs(names: Sequence[str], own: Sequence[int], shared: int) -> list[tuple[str, tuple[str, ...]]]:
    """``(group, cameras)`` per photograph: ``shared`` seen by every camera, then each camera's own."""
    if len(own) != len(names):
        raise ValueError(f"own photographs: {len(own)} counts given for {len(names)} cameras")
    if shared < 0 or any(n < 0 for n in own):
        raise ValueError("the numbers of shared and own photographs must be >= 0")
    photos = [("shared", tuple(names))] * shared
    for name, count in zip(names, own):
        photos += [(name, (name,))] * int(count)
    return photos


def _check_solvable(names, alone: dict[str, bool], shared: int, needed_shared: int, lacks: str) -> None:
    """ValueError naming the first camera that is neither solvable alone nor tied to one that is."""
    anchored = any(alone.values())
    for name in names:
        if not alone[name] and not (anchored and shared >= needed_shared):
            raise ValueError(f"camera {name}: {lacks}, and {shared} shared photograph(s) with a camera that "
                             f"has them (needs >= {needed_shared})" if anchored else
                             f"camera {name}: no camera of the rig can be solved on its own ({lacks})")


# --------------------------------------------------------------------------------------------------
# The paper's tree, one per group of photographs


def simulate_rig_tree(num_cameras: int = 2, own: Sequence[int] | None = None, shared: int = 8,
                      placements: int = 3, num_mirrors: int = 2, num_fiducials: int = 3, num_points: int = 0,
                      pixel_sigma: float = 1.0, mirror_distance: float = 0.5, tilt_deg: float = 30.0,
                      seed: int = 0, min_normal_spread_deg: float = 2.0) -> tuple[dict, ViewsTruth]:
    """A rig of ``num_cameras`` seen through the paper's mirrors: (dataset@1 dict, truth).

    ``own[c]`` photographs (default 30 each) only camera c sees, ``shared`` photographs every camera
    sees (one image per camera, the same ``mirror_configs``). Each group (the shared photographs, each
    camera's own) has its own ``placements`` placements of mirror 1 (behind the camera; a two-mirror
    tree: its photographs split among them in turn) and mirror 2 moves in every photograph;
    ``num_mirrors=1``: one mirror, moving in every photograph. Every point must be seen in every image
    (reflective sides, positive depth, inside with 20 px). A camera must be solvable: its own tree (>= 3
    photographs under each mirror-1 placement, or >= 3 with one mirror) or the shared photographs (>= 2
    with 3 fiducials, else >= 1) with a camera that is (ValueError naming it otherwise).
    """
    names = list(rig_cameras(num_cameras))
    own = [30] * num_cameras if own is None else [int(n) for n in own]
    photos = _photographs(names, own, shared)
    if num_mirrors not in (1, 2):
        raise ValueError(f"a simulated rig sees one or two mirrors, got {num_mirrors}")
    if placements < 1:
        raise ValueError(f"placements of mirror 1 must be >= 1, got {placements}")
    if pixel_sigma < 0.0 or mirror_distance <= 0.0:
        raise ValueError("pixel_sigma must be >= 0 and mirror_distance > 0")
    tree = 3 * (placements if num_mirrors == 2 else 1)
    enough = (placements >= 3 or num_mirrors == 1)
    alone = {name: enough and (own[i] >= tree or shared >= tree) for i, name in enumerate(names)}
    _check_solvable(names, alone, shared, 2 if num_fiducials == 3 else 1,
                    f"fewer than {tree} photographs of its own, 3 under each of {placements} placements of mirror 1"
                    if num_mirrors == 2 else "fewer than 3 photographs of its own")
    rng = np.random.default_rng(seed)
    cameras = rig_cameras(num_cameras)
    poses = rig_poses(names, default_T_cam_base())
    fiducials = default_fiducials(num_fiducials)
    points = _random_points(rng, fiducials, num_points)
    base = np.array([*fiducials.values(), *points.values()])
    camera_points = {name: apply_transform(*poses[name], base) for name in names}  # eq. (2)
    # Mirror 1 is behind the camera, mirror 2 (the one it looks into) in front (simulate.py's scene).
    front, back = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    spread = np.sin(np.deg2rad(min_normal_spread_deg))

    def seen(photo_cameras, vectors_cam0) -> bool:
        for name in photo_cameras:
            path = [plane_in_camera(v, poses[names[0]], poses[name]) for v in vectors_cam0]
            if not observe(cameras[name], camera_points[name], path)[1].all():
                return False
        return True

    # Mirror-1 placements: each camera's own photographs have their own; the shared photographs are
    # taken while the first camera with a tree of its own holds its mirror 1 still (a mirror-1 placement
    # seen in one photograph only leaves its plane's rotation about the line it shares with mirror 2
    # unseen: two reflections are one rigid motion, eqs. 5-8).
    anchor = next((name for i, name in enumerate(names) if own[i] >= tree), "shared")
    groups: dict[str, list[list[int]]] = {}  # group -> [own photographs, shared photographs under them]
    for index, (group, _) in enumerate(photos):
        lists = groups.setdefault(anchor if group == "shared" else group, [[], []])
        lists[group == "shared" and anchor != "shared"].append(index)
    vectors: dict[tuple[int, int], np.ndarray] = {}  # cam0 frame while drawing
    configs: list[tuple[int, ...]] = [()] * len(photos)
    next_config = 0
    for group, (indices, extra) in groups.items():
        count = min(placements, len(indices)) if num_mirrors == 2 else 0
        for _ in range(_GROUP_TRIES):
            drawn: dict[tuple[int, int], np.ndarray] = {}
            for j in range(max(count, 1)):
                under = (indices[j::count] + extra[j::count]) if count else indices + extra
                for _ in range(_TRIES):
                    first = [_random_mirror_vector(rng, back, mirror_distance, tilt_deg)] if count else []
                    leaves = {}
                    for index in under:
                        for _ in range(_LEAF_TRIES):
                            v = _random_mirror_vector(rng, front, mirror_distance, tilt_deg)
                            if seen(photos[index][1], first + [v]):
                                leaves[index] = v
                                break
                        else:
                            break
                    if len(leaves) == len(under) and (len(under) < 3 or normal_spread(list(leaves.values())) >= spread):
                        break
                else:
                    raise RuntimeError("simulate: found no mirror placements that every camera of the rig sees")
                for index, v in leaves.items():
                    configs[index] = ((next_config + j,) if count else ()) + (index,)
                    drawn[(num_mirrors, index)] = v
                if count:
                    drawn[(1, next_config + j)] = first[0]
            if count < 3 or normal_spread([drawn[(1, next_config + j)] for j in range(count)]) >= spread:
                break
        vectors.update(drawn)
        next_config += count
    images = []
    for index, (group, photo_cameras) in enumerate(photos):
        path_keys = [(l + 1, m) for l, m in enumerate(configs[index])]
        for name in photo_cameras:
            path = [plane_in_camera(vectors[p], poses[names[0]], poses[name]) for p in path_keys]
            pixels, _ = observe(cameras[name], camera_points[name], path)
            images.append({"id": f"{name}_{index:04d}", "camera": name,
                           "mirror_configs": [int(m) for m in configs[index]],
                           "observations": {n: pixels[i] for i, n in enumerate([*fiducials, *points])}})
    _add_noise(images, pixel_sigma, rng)
    return _rig_result(num_mirrors, cameras, poses, pixel_sigma, fiducials, points, images, vectors)


def _rig_result(num_mirrors, cameras, poses, pixel_sigma, fiducials, points, images, vectors_cam0):
    """(dataset dict, truth) with every mirror vector moved to the frame of its first camera."""
    names = list(cameras)
    images.sort(key=lambda image: names.index(image["camera"]))  # grouped by camera, in rig order
    owners = _owners(images, names)
    truth = ViewsTruth(poses=poses, mirror_cameras=owners, points=points,
                       mirror_vectors={p: plane_in_camera(v, poses[names[0]], poses[owners[p]])
                                       for p, v in vectors_cam0.items()})
    return _dataset(num_mirrors, cameras, pixel_sigma, fiducials, images, None), truth


# --------------------------------------------------------------------------------------------------
# Two hand-held mirrors, views of orders 0-2


def simulate_rig_mixed(num_cameras: int = 2, own: Sequence[int] | None = None, shared: int = 2, direct: int = 0,
                       num_points: int = 0, pixel_sigma: float = 1.0, seed: int = 0, tilt_deg: float = 6.0,
                       min_normal_spread_deg: float = 2.0) -> tuple[dict, ViewsTruth]:
    """A rig of ``num_cameras`` and two hand-held mirrors: (dataset@1 dict, truth).

    Photograph i has its own placements ``(1, i)`` and ``(2, i)`` (a wedge around the target as in
    :func:`mirror_fg.simulate.views.simulate_mixed`); each camera seeing it gives the views
    ``[[1, i]]``, ``[[2, i]]``, ``[[1, i], [2, i]]``, ``[[2, i], [1, i]]`` (and ``[]`` in the first
    ``direct`` photographs), every one of them seen (traced). ``shared`` photographs are seen by every
    camera, ``own[c]`` (default 4 each) by camera c only. A camera with >= 3 photographs (3 placements of
    mirror 1 seen alone) or a direct view is solvable alone; the others need a shared photograph with one.
    """
    names = list(rig_cameras(num_cameras))
    own = [4] * num_cameras if own is None else [int(n) for n in own]
    photos = _photographs(names, own, shared)
    if direct < 0 or direct > len(photos):
        raise ValueError(f"direct views must be between 0 and the {len(photos)} photographs, got {direct}")
    if pixel_sigma < 0.0 or num_points < 0:
        raise ValueError("pixel_sigma and the number of points must be >= 0")
    direct_of = {name: sum(1 for i, (_, c) in enumerate(photos) if i < direct and name in c) for name in names}
    alone = {name: own[i] + shared >= 3 or direct_of[name] > 0 for i, name in enumerate(names)}
    _check_solvable(names, alone, shared, 1, "fewer than 3 photographs (placements of mirror 1 seen alone) and "
                    "no direct view")
    rng = np.random.default_rng(seed)
    cameras = rig_cameras(num_cameras)
    fiducials = kaleidoscope_fiducials()
    poses = rig_poses(names, _scene_pose(fiducials), baseline=0.5 * RIG_BASELINE)
    points = _scene_points(rng, fiducials, poses[names[0]], num_points)
    point_names = [*fiducials, *points]
    base = np.array([*fiducials.values(), *points.values()]).reshape(-1, 3)
    camera_points = {name: apply_transform(*poses[name], base) for name in names}  # eq. (2)
    spread = np.sin(np.deg2rad(min_normal_spread_deg))
    for _ in range(_GROUP_TRIES):
        vectors: dict[tuple[int, int], np.ndarray] = {}
        images: list[dict] = []
        for i, (_, photo_cameras) in enumerate(photos):
            for _ in range(_TRIES):
                walls = _kaleidoscope_walls(rng, 2, tilt_deg, 8.0, spread=0.15)
                photo_images = _photo(cameras, poses, names[0], camera_points, point_names, set(fiducials),
                                      i, photo_cameras, walls, i < direct)
                if photo_images is not None:
                    break
            else:
                raise RuntimeError("simulate: found no hand-held mirror placements that every camera sees")
            vectors[(1, i)], vectors[(2, i)] = walls
            images += photo_images
        per_camera = [[vectors[(1, i)] for i, (_, c) in enumerate(photos) if name in c] for name in names]
        if all(len(vs) < 3 or normal_spread(vs) >= spread for vs in per_camera):
            break
    _add_noise(images, pixel_sigma, rng)
    return _rig_result(2, cameras, poses, pixel_sigma, fiducials, points, images, vectors)


def _photo(cameras, poses, first, camera_points, point_names, fiducial_names, i, photo_cameras, walls,
           with_direct) -> list[dict] | None:
    """The images of photograph i in each of its cameras, or None when a view is not seen."""
    a, b = (1, i), (2, i)
    images = []
    for name in photo_cameras:
        local = {a: plane_in_camera(walls[0], poses[first], poses[name]),
                 b: plane_in_camera(walls[1], poses[first], poses[name])}
        direct: list[list[tuple[int, int]]] = [[]] if with_direct else []
        for view in direct + [[a], [b], [a, b], [b, a]]:
            tag = "".join(str(l) for l, _ in view) or "d"
            image = _image(cameras[name], f"{name}_{i:03d}_{tag}", view, camera_points[name], point_names,
                           fiducial_names, local, [a, b], MIN_FIDUCIALS_PER_VIEW)
            if image is None:
                return None
            images.append({"id": image["id"], "camera": name, **{k: image[k] for k in ("reflections", "observations")}})
    return images
