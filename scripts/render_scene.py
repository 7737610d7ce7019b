#!/usr/bin/env python
"""Render the two-mirror test scene with Mitsuba 3 and write the images, a capture file and the truth.

A "robot" (a body box with a head box on top, AprilTags 36h11 on their front faces) stands beside and
behind a camera that sees it only through two planar mirrors: mirror 2 in front of the camera (the
one the camera looks into) and mirror 1 to its left, which faces the robot. Mirror 1 takes three
placements; under each, mirror 2 takes three placements of its own (a 3 x 3 tree, the paper's
schedule), so 9 images of 800 x 600 pixels. The tags are emitters with the tag pattern as
radiance, so the images carry no lighting noise; mirrors are perfect conductors (true reflections,
path tracing). Images are 8-bit grayscale PNGs, sRGB-encoded like a camera's.

Writes into ``--out`` (default ``tests/data/capture/rendered``):
- ``img_M_N.png``: mirror 1 in placement M, mirror 2 in its N-th placement under it;
- ``capture.yaml``: the mirror-fg/capture@1 file for them (mirror 2 configs ``each``);
- ``truth.json``: camera, ``T_cam_base``, every mirror vector (dataset config numbering), the tag
  poses and, per image, the true pixel of every tag corner that the two-mirror path really shows.

Conventions pinned by :func:`check_camera_convention` (run first, a direct-view render): a Mitsuba
``perspective`` sensor at the origin with ``look_at(target=+z, up=-y)`` is OpenCV's camera
(x right, y down, z forward); Mitsuba's pixel centres are at half-integers, so OpenCV's principal point
is ``(W/2 - 0.5, H/2 - 0.5)`` and ``fx = (W/2) / tan(fov_x/2)``; a ``bitmap`` texture's first row lands
at the rectangle's local -y, so textures are written upside down to put the tag's top at local +y.

Needs ``pip install mitsuba`` (scalar_rgb variant, CPU). Takes about a minute.

``--sequence SEED`` instead writes a video-like sequence without Mitsuba: one mirror moving
along a smooth loop, a new placement every frame, a textured plane with a corner-like and a blob-like
unknown point and four dark squares (fiducials), rendered exactly through the plane's homography with
sRGB gamma and 4 x 4 supersampling (:func:`render_sequence`); ``frame_KKK.png`` and ``truth.json``.

Over 500 lines: one standalone script (tests load it by path) whose two renderers share its scene helpers.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mirror_fg.core.geometry import nested_transform, reflect  # noqa: E402

DICTIONARY = cv2.aruco.DICT_APRILTAG_36h11
TAG_SIZE = 0.12  # metres, edge of the black square
MARGIN_CELLS = 1  # white quiet zone around the black square, in tag cells (36h11: 8 cells across)
TAG_CELLS = 8


# --------------------------------------------------------------------------------------------------
# Small geometry helpers (camera frame = Mitsuba world frame)
# --------------------------------------------------------------------------------------------------


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def plane_frame(normal: np.ndarray, up_hint=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Right-handed 3x3 [u, w, n] with n the plane normal, w as close to ``up_hint`` as possible."""
    n = unit(normal)
    u = unit(np.cross(up_hint, n))
    w = np.cross(n, u)
    return np.column_stack([u, w, n])


class Mirror:
    """A rectangular mirror: centre, unit normal (towards the side it reflects), half sizes (metres)."""

    def __init__(self, centre, normal, half_u: float, half_w: float):
        self.centre = np.asarray(centre, dtype=float)
        self.normal = unit(normal)
        self.half = (half_u, half_w)
        self.frame = plane_frame(self.normal)

    @property
    def v(self) -> np.ndarray:
        """Mirror vector: shortest vector from the camera centre (origin) to the plane."""
        return float(self.normal @ self.centre) * self.normal

    def hit(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
        """Where the ray hits the mirror's front face inside its rectangle, else None."""
        denom = float(self.normal @ direction)
        if denom >= 0:  # parallel, or arriving at the back
            return None
        s = float(self.normal @ (self.centre - origin)) / denom
        if s <= 1e-9:
            return None
        p = origin + s * direction
        local = self.frame.T @ (p - self.centre)
        if abs(local[0]) > self.half[0] or abs(local[1]) > self.half[1]:
            return None
        return p

    def to_world(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.frame @ np.diag([self.half[0], self.half[1], 1.0])
        m[:3, 3] = self.centre
        return m


# --------------------------------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------------------------------


def camera_model(width: int, height: int, fov_x_deg: float) -> dict:
    fx = (width / 2) / np.tan(np.deg2rad(fov_x_deg) / 2)
    return {"model": "pinhole", "width": width, "height": height, "fx": float(fx), "fy": float(fx),
            "cx": width / 2 - 0.5, "cy": height / 2 - 0.5, "dist": [0.0, 0.0, 0.0, 0.0, 0.0]}


def robot() -> tuple[list[dict], dict[int, tuple[np.ndarray, np.ndarray]], list[int]]:
    """Boxes (base frame: x right, y up, z out of the front face) and tags ``id -> (R, t)`` in base.

    Returns (boxes, tags, listed ids): tag 7 is on the robot but not listed in the capture.
    """
    boxes = [
        {"centre": [0.0, 0.0, -0.15], "half": [0.22, 0.17, 0.15]},  # body, front face z = 0
        {"centre": [0.0, 0.27, -0.07], "half": [0.10, 0.10, 0.15]},  # head on top, front face z = 0.08
    ]
    eye = np.eye(3)
    tags = {
        0: (eye, np.array([-0.10, 0.07, 0.0005])),
        1: (eye, np.array([0.10, 0.07, 0.0005])),
        2: (eye, np.array([0.0, 0.27, 0.0805])),
        7: (eye, np.array([0.0, -0.09, 0.0005])),
    }
    return boxes, tags, [0, 1, 2]


TAG_CENTRE_BASE = np.array([0.0, 0.14, 0.0])
#: Distances along the nominal line of sight (metres): camera to mirror 2, mirror 2 to mirror 1,
#: mirror 1 to the robot's tags.
D_CAM_M2, D_M2_M1, D_M1_ROBOT = 0.6, 0.6, 0.75
#: Placements are given by where the robot's tag centre appears: offsets (metres; x right, y down, z
#: depth) from its nominal virtual position on the optical axis. Each mirror is then the
#: perpendicular bisector of the object it reflects and that image (a turn of a mirror sweeps the
#: view by twice the angle, so this keeps the robot in view while the normals spread).
M1_OFFSETS = [(0.45, 0.0, 0.0), (-0.30, 0.30, 0.15), (-0.30, -0.30, -0.15)]
M2_OFFSETS = [(0.30, -0.10, 0.10), (-0.30, 0.22, 0.0), (-0.15, -0.28, -0.12)]
M1_HALF, M2_HALF = (0.38, 0.30), (0.20, 0.16)  # half sizes (metres): the reflections used, and a margin


def bisector_mirror(obj: np.ndarray, image: np.ndarray, viewer: np.ndarray, half) -> Mirror:
    """The mirror that reflects point ``obj`` to ``image``, facing ``obj``'s side, centred where the
    line of sight from ``viewer`` to ``image`` crosses it."""
    n = unit(obj - image)
    mid = (obj + image) / 2
    direction = unit(image - viewer)
    centre = viewer + (n @ (mid - viewer)) / (n @ direction) * direction
    return Mirror(centre, n, *half)


def scene_truth() -> tuple[np.ndarray, np.ndarray, list[Mirror], list[list[Mirror]]]:
    """``R_cam_base``, ``t_cam_base``, mirror 1 placements, mirror 2 placements under each."""
    # Nominal layout (camera frame): mirror 2 in front of the camera sends the view to the left (-x);
    # mirror 1 there sends it back past the camera to the robot.
    c2 = np.array([0.0, 0.0, D_CAM_M2])
    n2 = unit([-1.0, 0.0, -1.0])
    d1 = np.array([-1.0, 0.0, 0.0])  # view direction after mirror 2
    c1 = c2 + D_M2_M1 * d1
    d_robot = unit([0.25, 0.0, -1.0])  # view direction after mirror 1
    # Robot: its tags' centre D_M1_ROBOT from mirror 1 along d_robot, front face turned to mirror 1,
    # then yawed and pitched a little so that the rotation is generic.
    z_b = -d_robot
    y_b = unit(np.array([0.0, -1.0, 0.0]) - (np.array([0.0, -1.0, 0.0]) @ z_b) * z_b)
    x_b = np.cross(y_b, z_b)
    R = np.column_stack([x_b, y_b, z_b]) @ rot("y", 12.0) @ rot("x", -6.0)
    X = c1 + D_M1_ROBOT * d_robot  # the tags' centre, camera frame
    t = X - R @ TAG_CENTRE_BASE
    nominal2 = Mirror(c2, n2, *M2_HALF)
    V0 = np.array([0.0, 0.0, D_CAM_M2 + D_M2_M1 + D_M1_ROBOT])  # nominal final image of X

    mirror1, mirror2 = [], []
    for i, off1 in enumerate(M1_OFFSETS):
        W = reflect(V0 + np.asarray(off1), nominal2.v)  # where mirror 1 must put X
        m1 = bisector_mirror(X, W, c2, M1_HALF)
        mirror1.append(m1)
        row = []
        for j, off2 in enumerate(M2_OFFSETS):
            jitter = 0.04 * np.array([i - 1, (i * 7 + j) % 3 - 1, 0.0])  # a different set under each
            row.append(bisector_mirror(W, V0 + np.asarray(off2) + jitter, np.zeros(3), M2_HALF))
        mirror2.append(row)
    return R, t, mirror1, mirror2


def tag_corners_base(tags: dict[int, tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    h = TAG_SIZE / 2
    local = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    return {f"T{i}_{k}": tags[i][0] @ local[k] + tags[i][1] for i in sorted(tags) for k in range(4)}


def project_two_mirror(
    K: np.ndarray, R: np.ndarray, t: np.ndarray, m1: Mirror, m2: Mirror, points: dict[str, np.ndarray], size
) -> dict[str, list[float]]:
    """True pixels of base points seen via mirror 1 then mirror 2, only where both rectangles are hit."""
    A, b = nested_transform(R, t, [m1.v, m2.v])
    A1, b1 = nested_transform(R, t, [m1.v])
    out = {}
    for name, p in points.items():
        virtual = A @ p + b
        if virtual[2] <= 0:
            continue
        hit2 = m2.hit(np.zeros(3), unit(virtual))
        if hit2 is None:
            continue
        towards = unit((A1 @ p + b1) - hit2)  # after mirror 2 (backwards along the light) to mirror 1's image
        hit1 = m1.hit(hit2, towards)
        if hit1 is None:
            continue
        uvw = K @ virtual
        u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
        if 0 <= u <= size[0] - 1 and 0 <= v <= size[1] - 1:
            out[name] = [float(u), float(v)]
    return out


# --------------------------------------------------------------------------------------------------
# Mitsuba
# --------------------------------------------------------------------------------------------------


def _mi():
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    return mi


def tag_texture(tag_id: int, folder: str, cell_px: int = 16) -> tuple[str, float]:
    """Write tag ``tag_id`` with its white margin, upside down (see module doc); return (file, side metres)."""
    d = cv2.aruco.getPredefinedDictionary(DICTIONARY)
    black = cv2.aruco.generateImageMarker(d, tag_id, TAG_CELLS * cell_px, borderBits=1)
    m = MARGIN_CELLS * cell_px
    tex = np.full((black.shape[0] + 2 * m,) * 2, 255, np.uint8)
    tex[m:-m, m:-m] = black
    path = os.path.join(folder, f"tag{tag_id}.png")
    cv2.imwrite(path, np.ascontiguousarray(np.flipud(tex)))
    return path, TAG_SIZE * (TAG_CELLS + 2 * MARGIN_CELLS) / TAG_CELLS


def _tag_shape(mi, texture: str, side: float, R: np.ndarray, t: np.ndarray) -> dict:
    m = np.eye(4)
    m[:3, :3] = R * (side / 2)
    m[:3, 3] = t
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        "emitter": {"type": "area", "radiance": {"type": "bitmap", "filename": texture, "filter_type": "nearest"}},
    }


def _sensor(mi, camera: dict, spp: int, fov_x_deg: float) -> dict:
    return {
        "type": "perspective",
        "fov": fov_x_deg,
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f.look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        "film": {"type": "hdrfilm", "width": camera["width"], "height": camera["height"], "rfilter": {"type": "gaussian"}},
        "sampler": {"type": "multijitter", "sample_count": spp, "seed": 1},
    }


def render_gray(mi, scene_dict: dict) -> np.ndarray:
    """Render and return an 8-bit sRGB-encoded grayscale image."""
    image = mi.render(mi.load_dict(scene_dict))
    bmp = mi.Bitmap(image).convert(mi.Bitmap.PixelFormat.Y, mi.Struct.Type.UInt8, srgb_gamma=True)
    return np.ascontiguousarray(np.array(bmp).reshape(scene_dict["sensor"]["film"]["height"], -1))


def check_camera_convention(folder: str) -> float:
    """Direct-view render of one tag at a known pose: the detected corners must be the projected ones.

    Returns the largest corner error (pixels); raises RuntimeError if the conventions are off.
    """
    mi = _mi()
    fov = 50.0
    camera = camera_model(320, 240, fov)
    texture, side = tag_texture(5, folder)
    R = rot("y", 25.0) @ np.diag([1.0, -1.0, -1.0])  # tag facing the camera, turned 25 degrees
    t = np.array([0.08, 0.04, 0.9])
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": _sensor(mi, camera, 36, fov),
        "tag": _tag_shape(mi, texture, side, R, t),
        "background": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
    }
    gray = render_gray(mi, scene)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
    truth = tag_corners_base({5: (R, t)})
    proj = np.array([(K @ p)[:2] / p[2] for p in truth.values()])
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(DICTIONARY), params).detectMarkers(gray)
    if ids is None or ids.ravel().tolist() != [5]:
        raise RuntimeError(f"direct view: expected tag 5 unmirrored, detected {ids}")
    err = float(np.max(np.linalg.norm(corners[0].reshape(4, 2) - proj, axis=1)))
    if err > 1.0:  # sRGB edges pull OpenCV's corners ~0.5 px inwards; an axis error is tens of pixels
        raise RuntimeError(f"direct view: detected corners {err:.2f} px from the projection; conventions are off")
    return err


def build_scene(mi, camera: dict, spp: int, fov: float, R: np.ndarray, t: np.ndarray,
                m1: Mirror, m2: Mirror, textures: dict[int, tuple[str, float]]) -> dict:
    boxes, tags, _ = robot()
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 5},
        "sensor": _sensor(mi, camera, spp, fov),
        "background": {"type": "constant", "radiance": {"type": "rgb", "value": 0.35}},
    }
    for k, box in enumerate(boxes):
        m = np.eye(4)
        m[:3, :3] = R @ np.diag(box["half"])
        m[:3, 3] = R @ np.asarray(box["centre"]) + t
        scene[f"box{k}"] = {"type": "cube", "to_world": mi.ScalarTransform4f(m.tolist()),
                            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.25}}}
    for tag_id, (Rt, tt) in tags.items():
        texture, side = textures[tag_id]
        scene[f"tag{tag_id}"] = _tag_shape(mi, texture, side, R @ Rt, R @ tt + t)
    for name, mirror in (("mirror1", m1), ("mirror2", m2)):
        scene[name] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(mirror.to_world().tolist()),
                       "bsdf": {"type": "conductor", "material": "none"}}
    return scene


def pose_dict(R: np.ndarray, t: np.ndarray) -> dict:
    return {"R": [[float(x) for x in row] for row in R], "t": [float(x) for x in t]}


def write_capture(path: Path, camera: dict, images: list[dict], listed: list[int]) -> None:
    _, tags, _ = robot()
    lines = [
        "# Rendered by scripts/render_scene.py (Mitsuba 3): two mirrors, 3 placements of mirror 1, 3 of",
        "# mirror 2 under each. Base frame: the robot's (x right, y up, z out of its front face).",
        "format: mirror-fg/capture@1",
        "num_mirrors: 2",
        "camera: " + json.dumps(camera),
        "pixel_sigma: 0.5",
        "target:",
        "  kind: apriltag",
        "  dictionary: tag36h11",
        f"  tag_size: {TAG_SIZE}",
        "  tags:",
    ]
    for tag_id in listed:
        lines.append(f"    {tag_id}: " + json.dumps(pose_dict(*tags[tag_id])))
    lines.append("images:")
    for im in images:
        lines.append(f"  - {{file: {im['file']}, mirror_configs: [{im['mirror_configs'][0]}, each]}}")
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------------------
# Video-like sequence: one mirror moving along a smooth loop (planar-homography renderer, no Mitsuba)
# --------------------------------------------------------------------------------------------------
# The target is a textured plane (the robot's front face, base z = 0; x right, y up). Through one
# mirror the camera sees it as a pinhole "virtual camera" would: base point (x, y, 0) lands at pixel
# K (A [x, y, 0] + b) with (A, b) of eqs. (5)-(8), i.e. the plane's homography H = K [a1 a2 b]. Each
# output pixel is the box average of SEQ_SUPERSAMPLE^2 samples of the texture in *linear* intensity,
# then sRGB-encoded to 8 bits like a camera (plus a little sensor noise). The mirror covers the view.

SEQ_SIZE = (800, 600)
SEQ_FOV_DEG = 50.0
SEQ_SUPERSAMPLE = 4
SEQ_TEXEL_M = 0.0002  # texture resolution (metres per texel): ~ 1/7 of a supersample at 1.2 m
SEQ_EXTENT_M = (0.24, 0.18)  # the plane's textured half sizes (metres, x and y)
#: Unknown points on the plane (base frame, metres) and their feature kind: the top-left corner of a
#: dark box on a light mat, and the centre of a dark disc of radius SEQ_DOT_RADIUS_M.
SEQ_POINTS = {"P0": ((-0.03, 0.04, 0.0), "corner"), "P1": ((0.09, -0.06, 0.0), "blob")}
SEQ_BOX_M = (0.07, 0.05)  # P0's box: width (+x from the corner) and height (-y)
SEQ_DOT_RADIUS_M = 0.006
#: Fiducials: the corners of four dark squares (SEQ_SQUARE_M side) near the plane's corners.
SEQ_SQUARE_M = 0.05
SEQ_SQUARE_CENTRES = [(-0.17, 0.12), (0.17, 0.12), (0.17, -0.12), (-0.17, -0.12)]


def sequence_fiducials() -> dict[str, np.ndarray]:
    """``F{i}_{k}``: corner k (tag order: top-left, top-right, bottom-right, bottom-left) of square i."""
    h = SEQ_SQUARE_M / 2
    local = [(-h, h), (h, h), (h, -h), (-h, -h)]
    return {f"F{i}_{k}": np.array([cx + dx, cy + dy, 0.0])
            for i, (cx, cy) in enumerate(SEQ_SQUARE_CENTRES) for k, (dx, dy) in enumerate(local)}


def plane_texture(seed: int = 0) -> np.ndarray:
    """The plane's linear-intensity texture (float32, 0..1); texel (i, j) is centred at
    ``x = -EXTENT_x + (i + 0.5) * TEXEL``, ``y = EXTENT_y - (j + 0.5) * TEXEL``."""
    ex, ey = SEQ_EXTENT_M
    w, h = int(round(2 * ex / SEQ_TEXEL_M)), int(round(2 * ey / SEQ_TEXEL_M))
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0.15, 0.7, size=(int(2 * ey / 0.006), int(2 * ex / 0.006))).astype(np.float32)
    tex = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC).clip(0.05, 0.9)  # ~6 mm blotches
    xs = -ex + (np.arange(w) + 0.5) * SEQ_TEXEL_M
    ys = ey - (np.arange(h) + 0.5) * SEQ_TEXEL_M
    X, Y = np.meshgrid(xs, ys)

    def rect(x0, x1, y0, y1, value):
        tex[(X >= x0) & (X < x1) & (Y >= y0) & (Y < y1)] = value

    for cx, cy in SEQ_SQUARE_CENTRES:  # fiducial squares on white margins
        rect(cx - SEQ_SQUARE_M, cx + SEQ_SQUARE_M, cy - SEQ_SQUARE_M, cy + SEQ_SQUARE_M, 0.8)
        rect(cx - SEQ_SQUARE_M / 2, cx + SEQ_SQUARE_M / 2, cy - SEQ_SQUARE_M / 2, cy + SEQ_SQUARE_M / 2, 0.03)
    (px, py, _), _ = SEQ_POINTS["P0"]
    m = 0.012  # light mat around the box's corner
    rect(px - m, px + SEQ_BOX_M[0] + m, py - SEQ_BOX_M[1] - m, py + m, 0.8)
    rect(px, px + SEQ_BOX_M[0], py - SEQ_BOX_M[1], py, 0.04)
    (qx, qy, _), _ = SEQ_POINTS["P1"]
    rect(qx - 0.014, qx + 0.035, qy - 0.014, qy + 0.03, 0.8)  # off-centre: KLT's window sees its edges
    tex[(X - qx) ** 2 + (Y - qy) ** 2 < SEQ_DOT_RADIUS_M**2] = 0.04
    return tex


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear 0..1 -> sRGB-encoded float 0..255."""
    x = np.clip(linear, 0.0, 1.0)
    return 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def render_plane_view(texture: np.ndarray, H: np.ndarray, size=SEQ_SIZE, noise: float = 0.5,
                      rng: np.random.Generator | None = None) -> np.ndarray:
    """8-bit sRGB grayscale image of the plane whose homography (base (x, y, 1) -> pixel) is ``H``.

    Exact pinhole geometry through the mirror; anti-aliased by box-averaging SEQ_SUPERSAMPLE^2
    bilinear texture samples per pixel in linear intensity; ``noise``: Gaussian sensor noise (grey
    levels) added before rounding.
    """
    s = SEQ_SUPERSAMPLE
    ex, ey = SEQ_EXTENT_M
    # supersample pixel (us, vs) -> image pixel ((us + 0.5)/s - 0.5, ...) -> plane -> texel
    sub = np.array([[1 / s, 0, 0.5 / s - 0.5], [0, 1 / s, 0.5 / s - 0.5], [0, 0, 1]])
    texel = np.array([[1 / SEQ_TEXEL_M, 0, ex / SEQ_TEXEL_M - 0.5], [0, -1 / SEQ_TEXEL_M, ey / SEQ_TEXEL_M - 0.5], [0, 0, 1]])
    M = texel @ np.linalg.inv(H) @ sub
    fine = cv2.warpPerspective(texture, M, (size[0] * s, size[1] * s), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.3)
    linear = cv2.resize(fine, size, interpolation=cv2.INTER_AREA)  # exact box average (integer factor)
    encoded = srgb_encode(linear)
    if noise > 0:
        encoded = encoded + (rng or np.random.default_rng(0)).normal(0.0, noise, encoded.shape)
    return np.clip(np.round(encoded), 0, 255).astype(np.uint8)


def sequence_geometry(seed: int = 0, frames: int = 54) -> tuple[dict, np.ndarray, np.ndarray, list[np.ndarray]]:
    """Camera, ``R_cam_base``, ``t_cam_base`` and one mirror vector per frame.

    The camera looks at a mirror 0.6 m ahead whose normal is turned ~20 deg about y (scene-dependent),
    so it sees the plane 0.6 m beyond, beside and behind the camera. Over the sequence the mirror's
    normal runs once around a cone (tilt ``beta`` deg) while its distance breathes by +-4 cm: a smooth
    closed loop, a new placement in every frame.
    """
    rng = np.random.default_rng(1000 + seed)
    camera = camera_model(SEQ_SIZE[0], SEQ_SIZE[1], SEQ_FOV_DEG)
    alpha = np.deg2rad(rng.uniform(32.0, 38.0))
    n0 = rot("x", rng.uniform(-5.0, 5.0)) @ np.array([-np.sin(alpha), 0.0, -np.cos(alpha)])
    c0 = np.array([0.0, 0.0, 0.6])
    d_out = unit(np.array([0.0, 0.0, 1.0]) - 2 * (n0 @ [0.0, 0.0, 1.0]) * n0)  # view direction after the mirror
    X = c0 + rng.uniform(0.4, 0.5) * d_out  # the plane's origin, camera frame
    z_b = -d_out
    y_b = unit(np.array([0.0, -1.0, 0.0]) - (np.array([0.0, -1.0, 0.0]) @ z_b) * z_b)
    R = np.column_stack([np.cross(y_b, z_b), y_b, z_b]) @ rot("y", rng.uniform(-20, 20)) @ rot("x", rng.uniform(-15, 15)) @ rot("z", rng.uniform(-30, 30))
    t = X
    u_axis, w_axis = plane_frame(n0)[:, 0], plane_frame(n0)[:, 1]
    beta = np.deg2rad(rng.uniform(6.0, 8.0))
    phase = rng.uniform(0, 2 * np.pi)
    vs = []
    for k in range(frames):
        phi = 2 * np.pi * k / frames
        n = unit(n0 + np.tan(beta) * (np.cos(phi) * u_axis + 0.7 * np.sin(phi) * w_axis))
        c = c0 + np.array([0.0, 0.0, 0.06 * np.sin(phi + phase)])
        vs.append(float(n @ c) * n)
    return camera, R, t, vs


def plane_homography(K: np.ndarray, R: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Base-plane (x, y, 1) -> pixel through one mirror (eqs. 5-9)."""
    A, b = nested_transform(R, t, [v])
    return K @ np.column_stack([A[:, 0], A[:, 1], b])


def render_sequence(seed: int = 0, frames: int = 54, noise: float = 0.5) -> tuple[list[np.ndarray], dict]:
    """The frames (8-bit grayscale) and the truth: camera, ``T_cam_base``, mirror vectors, base points
    (unknown points with their kinds, fiducials) and every point's true pixel in every frame."""
    camera, R, t, vs = sequence_geometry(seed, frames)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
    texture = plane_texture(seed)
    rng = np.random.default_rng(seed)
    points = {name: np.array(p) for name, (p, _) in SEQ_POINTS.items()}
    points.update(sequence_fiducials())
    images, pixels = [], []
    for v in vs:
        H = plane_homography(K, R, t, v)
        images.append(render_plane_view(texture, H, noise=noise, rng=rng))
        uvw = (H @ np.array([[p[0], p[1], 1.0] for p in points.values()]).T).T
        pixels.append({n: [float(q[0] / q[2]), float(q[1] / q[2])] for n, q in zip(points, uvw)})
    truth = {
        "note": "Ground truth of scripts/render_scene.py --sequence (planar homography renderer). Pixels: OpenCV convention.",
        "seed": seed,
        "camera": camera,
        "T_cam_base": pose_dict(R, t),
        "mirror_vectors": [[float(x) for x in v] for v in vs],
        "points": {n: {"xyz": [float(x) for x in p], "kind": kind} for n, (p, kind) in SEQ_POINTS.items()},
        "fiducials": {n: [float(x) for x in p] for n, p in sequence_fiducials().items()},
        "pixels": pixels,
    }
    return images, truth



def write_sequence(out: Path, seed: int, frames: int) -> int:
    """``frame_KKK.png`` and ``truth.json`` (every point's true pixel per frame) of the loop into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    images, truth = render_sequence(seed, frames)
    truth["frames"] = []
    for k, image in enumerate(images):
        name = f"frame_{k:03d}.png"
        cv2.imwrite(str(out / name), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        truth["frames"].append(name)
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    print(f"wrote {len(images)} frames and truth.json to {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(REPO / "tests" / "data" / "capture" / "rendered"))
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--height", type=int, default=600)
    parser.add_argument("--fov", type=float, default=50.0, help="horizontal field of view, degrees")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (a square number)")
    parser.add_argument("--sequence", type=int, metavar="SEED", default=None,
                        help="instead: the one-mirror loop of scene SEED (homography renderer, no Mitsuba)")
    parser.add_argument("--frames", type=int, default=54, help="frames of --sequence")
    args = parser.parse_args(argv)
    if args.sequence is not None:
        return write_sequence(Path(args.out), args.sequence, args.frames)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mi = _mi()
    with tempfile.TemporaryDirectory() as tmp:
        err = check_camera_convention(tmp)
        print(f"camera convention: direct-view tag corners within {err:.2f} px of the projection")
        camera = camera_model(args.width, args.height, args.fov)
        K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
        R, t, mirror1, mirror2 = scene_truth()
        _, tags, listed = robot()
        textures = {tag_id: tag_texture(tag_id, tmp) for tag_id in tags}
        corners = tag_corners_base(tags)
        listed_corners = {n: p for n, p in corners.items() if int(n[1:].split("_")[0]) in listed}
        images, mirrors = [], []
        for i, m1 in enumerate(mirror1):
            mirrors.append({"mirror": 1, "config": i, "v": [float(x) for x in m1.v]})
            for j, m2 in enumerate(mirror2[i]):
                config2 = len(images)  # 'each' numbering: fresh integers in image order
                mirrors.append({"mirror": 2, "config": config2, "v": [float(x) for x in m2.v]})
                name = f"img_{i}_{j}.png"
                gray = render_gray(mi, build_scene(mi, camera, args.spp, args.fov, R, t, m1, m2, textures))
                cv2.imwrite(str(out / name), gray, [cv2.IMWRITE_PNG_COMPRESSION, 9])
                truth = project_two_mirror(K, R, t, m1, m2, listed_corners, (args.width, args.height))
                images.append({"file": name, "id": Path(name).stem, "mirror_configs": [i, config2], "corners": truth})
                print(f"{name}: {len(truth)} of {len(listed_corners)} listed tag corners in view", flush=True)
    truth_doc = {
        "note": "Ground truth of the rendered scene (scripts/render_scene.py). Pixels: OpenCV convention.",
        "camera": camera,
        "T_cam_base": pose_dict(R, t),
        "tags_in_base": {str(k): pose_dict(*v) for k, v in tags.items()},
        "tag_size": TAG_SIZE,
        "listed_tags": listed,
        "mirrors": mirrors,
        "images": images,
    }
    (out / "truth.json").write_text(json.dumps(truth_doc, indent=1) + "\n")
    write_capture(out / "capture.yaml", camera, images, listed)
    total = sum(f.stat().st_size for f in out.iterdir())
    print(f"wrote {len(images)} images, capture.yaml and truth.json to {out} ({total / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
