"""Synthetic datasets of the general view model (docs/formats.md, "Views of any reflection order, and
several cameras"), measured through ``factors/views.py``'s model with Gaussian pixel noise: the
kaleidoscope, the two-camera rig and the no-target scene of the integrator's smoke runs, and a mixed
single/double scene of two hand-held mirrors."""
from __future__ import annotations

import gtsam
import numpy as np

from mirror_fg.factors.views import view_model

CAMERA = {"model": "pinhole", "width": 1280, "height": 960, "fx": 1000.0, "fy": 1000.0, "cx": 640.0, "cy": 480.0,
          "dist": [0, 0, 0, 0, 0]}


def rot(w) -> np.ndarray:
    return gtsam.Rot3.Expmap(np.asarray(w, float)).matrix()


def board(nx: int = 5, ny: int = 4, pitch: float = 0.04) -> dict[str, list[float]]:
    return {f"F{i}_{j}": [i * pitch, j * pitch, 0.0] for i in range(nx) for j in range(ny)}


def images_of(views, poses, mirrors, owners, fiducials, points, cameras, sigma=0.5, seed=0, named=False) -> list[dict]:
    """dataset@1 images of ``views`` ``[(camera, reflections, names)]``; ``named``: give each its camera."""
    rng = np.random.default_rng(seed)
    images = []
    for k, (c, reflections, names) in enumerate(views):
        B = np.array([fiducials[n] if n in fiducials else points[n] for n in names], float).T
        z = view_model(c, reflections, poses, mirrors, owners, B)[0].T
        K = cameras[c]
        px = np.column_stack([K["fx"] * z[:, 0] + K["cx"], K["fy"] * z[:, 1] + K["cy"]])
        assert np.all((px > 0) & (px < [K["width"], K["height"]])), f"view {k} leaves the image"
        px = px + rng.normal(scale=sigma, size=px.shape)
        image = {"id": f"v{k}", "reflections": [list(p) for p in reflections],
                 "observations": {n: [float(u), float(v)] for n, (u, v) in zip(names, px)}}
        if named:
            image["camera"] = c
        images.append(image)
    return images


def kaleidoscope() -> dict:
    """One camera, two fixed mirrors: a direct view, each mirror alone, both in either order."""
    fid = board()
    poses = {"camera": (rot([0.1, -0.05, 0.02]), np.array([-0.08, -0.06, 0.8]))}
    mirrors = {(1, 0): np.array([0.15, 0.0, 0.02]), (2, 0): np.array([0.0, 0.12, 0.01])}
    owners = {p: "camera" for p in mirrors}
    views = [("camera", s, list(fid)) for s in [(), ((1, 0),), ((2, 0),), ((1, 0), (2, 0)), ((2, 0), (1, 0))]]
    return {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "camera": CAMERA, "pixel_sigma": 0.5, "fiducials": fid,
            "images": images_of(views, poses, mirrors, owners, fid, {}, {"camera": CAMERA})}


def rig() -> dict:
    """Two cameras; the right one sees the target only through the mirrors."""
    fid = board()
    RL, tL = rot([0.1, -0.05, 0.02]), np.array([-0.08, -0.06, 0.8])
    Rrl, trl = rot([0.0, -0.08, 0.0]), np.array([-0.1, 0.0, 0.0])
    poses = {"left": (RL, tL), "right": (Rrl @ RL, Rrl @ tL + trl)}
    mirrors = {(1, 0): np.array([0.15, 0.0, 0.02]), (2, 0): np.array([0.0, 0.12, 0.01])}
    owners = {p: "left" for p in mirrors}
    right = dict(CAMERA, fx=900.0, fy=905.0, cx=650.0, cy=470.0)
    views = [(c, s, list(fid)) for c in ("left", "right")
             for s in [(), ((1, 0),), ((2, 0),), ((1, 0), (2, 0)), ((2, 0), (1, 0))] if c == "left" or s]
    cameras = {"left": CAMERA, "right": right}
    return {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "cameras": cameras, "pixel_sigma": 0.5,
            "fiducials": fid, "images": images_of(views, poses, mirrors, owners, fid, {}, cameras, named=True)}


def no_target() -> dict:
    """No known target: two points seen directly and through three fixed mirrors (alone and in pairs);
    the scale is the length of mirror 1's vector."""
    I = (np.eye(3), np.zeros(3))
    mirrors = {(1, 0): np.array([0.12, 0, 0.01]), (2, 0): np.array([0, 0.1, 0.02]),
               (3, 0): np.array([-0.07, -0.07, 0.01])}
    owners = {p: "camera" for p in mirrors}
    points = {"P0": np.array([0.01, 0.02, 0.6]), "P1": np.array([-0.02, 0.0, 0.55])}
    sequences = [()] + [((l, 0),) for l in (1, 2, 3)] + [((a, 0), (b, 0)) for a in (1, 2, 3) for b in (1, 2, 3)
                                                          if a != b]
    views = [("camera", s, list(points)) for s in sequences]
    return {"format": "mirror-fg/dataset@1", "num_mirrors": 3, "camera": CAMERA, "pixel_sigma": 0.3, "fiducials": {},
            "scale": {"mirror": 1, "config": 0, "distance": float(np.linalg.norm(mirrors[(1, 0)]))},
            "images": images_of(views, {"camera": I}, mirrors, owners, {}, points, {"camera": CAMERA}, sigma=0.3)}


def mixed() -> dict:
    """Two hand-held mirrors: four placements of mirror 1 seen alone, two of mirror 2, and double views
    in both orders; two reconstruction points seen in every view besides the target."""
    fid = board()
    points = {"P0": [0.06, 0.05, 0.05], "P1": [0.1, 0.08, -0.03]}
    poses = {"camera": (rot([0.1, -0.05, 0.02]), np.array([-0.08, -0.06, 0.8]))}
    mirrors = {(1, 0): np.array([0.15, 0.0, 0.02]), (1, 1): np.array([0.14, 0.02, 0.03]),
               (1, 2): np.array([0.16, -0.02, 0.0]), (1, 3): np.array([0.13, -0.03, 0.02]),
               (2, 0): np.array([0.0, 0.12, 0.01]), (2, 1): np.array([0.01, 0.13, 0.03])}
    owners = {p: "camera" for p in mirrors}
    names = [*fid, *points]
    singles = [((1, m),) for m in range(4)]
    doubles = [((1, 0), (2, 0)), ((2, 0), (1, 1)), ((1, 2), (2, 1)), ((2, 1), (1, 3)), ((2, 0), (1, 0))]
    views = [("camera", s, names) for s in singles + doubles]
    return {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "camera": CAMERA, "pixel_sigma": 0.5, "fiducials": fid,
            "images": images_of(views, poses, mirrors, owners, fid, points, {"camera": CAMERA}, seed=3)}


SCENES = {"kaleidoscope": kaleidoscope, "rig": rig, "no_target": no_target, "mixed": mixed}
