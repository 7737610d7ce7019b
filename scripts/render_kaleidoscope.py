#!/usr/bin/env python
"""Render one kaleidoscope photograph: a printed board seen directly and through two fixed mirrors.

The board (a ChArUco board, or a chessboard with ``--target chessboard``) faces the camera; mirror 1
stands to its right and mirror 2 below it, both turned towards the camera, so one photograph holds the
direct view (``reflections: []``), the two single reflections (``[[1, 0]]``, ``[[2, 0]]``) and the two
double ones (``[[1, 0], [2, 0]]``: the light meets mirror 1, then mirror 2; and ``[[2, 0], [1, 0]]``),
each virtual board in its own region of the image. Base frame = board frame.

Each view is the board's printed face mapped into the image by the exact planar homography of its
virtual view (eqs. 5-9: ``A, b`` of :func:`mirror_fg.core.geometry.nested_transform` over the view's
mirrors in the order the light meets them; a board point ``(x, y, 0)`` images at ``K (x a1 + y a2 + b)``),
so a view through one mirror is mirror-imaged as in a real mirror and a view through two is not.
Rendered as tests/test_charuco.py does: 4 x 4 supersamples warped in linear reflectance and box-averaged,
a slight blur (optics), sRGB encoding and sensor noise. Simplification: the mirrors are planes without
edges (their frames are not drawn) and each view is composited into its own region of interest (the
regions are checked not to overlap), i.e. the photograph a kaleidoscope gives once the user has cut
it into views.

``python scripts/render_kaleidoscope.py OUT_DIR [--target charuco|chessboard]`` writes
``kaleidoscope.png``, ``capture.yaml`` (capture@1 with ``views`` and their rois) and ``truth.json``
(camera, ``T_cam_base``, mirror vectors, per view its reflections, roi and every corner's true pixel).
Used by tests/test_capture_views.py.
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from render_scene import srgb_encode  # noqa: E402

from mirror_fg.core.geometry import nested_transform, so3_exp  # noqa: E402
from mirror_fg.io.target import CharucoTarget, ChessboardTarget, target_from_dict  # noqa: E402

SIZE = (1600, 1200)
CAMERA = {"model": "pinhole", "width": SIZE[0], "height": SIZE[1], "fx": 1250.0, "fy": 1250.0,
          "cx": (SIZE[0] - 1) / 2, "cy": (SIZE[1] - 1) / 2, "dist": [0.0] * 5}
TARGETS = {
    "charuco": {"kind": "charuco", "cols": 5, "rows": 4, "square": 0.04, "marker": 0.03, "dictionary": "DICT_4X4_50"},
    "chessboard": {"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.035},  # cols + rows odd: no symmetry
}
#: The views of the photograph: placements in the order the light meets them (one fixed placement each).
VIEWS = ([], [[1, 0]], [[2, 0]], [[1, 0], [2, 0]], [[2, 0], [1, 0]])
TEXELS_PER_SQUARE = 100
QUIET_SQUARES = 0.6  # white margin around the printed board, in squares
SUPERSAMPLE = 4
BLUR_PX = 0.6
NOISE_GREY = 0.5
BLACK, WHITE, BACKGROUND = 0.04, 0.85, 0.3  # linear reflectances
ROI_MARGIN_PX = 12  # the roi around a view: its printed sheet's bounding box grown by this


@dataclass
class Kaleidoscope:
    camera: dict
    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[int, np.ndarray]  # mirror l's one (fixed) placement, camera frame
    target: CharucoTarget | ChessboardTarget
    target_dict: dict


def _mirror_vector(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The mirror vector (eq. 3) of the plane through ``point`` with ``normal``: ``(n . p) n``."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    return float(n @ point) * n


def scene(target: str = "charuco") -> Kaleidoscope:
    """The board 0.64 m ahead, up and left of the optical axis, facing the camera (slightly turned);
    mirror 1 a plane to its right, mirror 2 one below it (about 75 degrees between their normals), both
    turned towards the camera: the five views land in five separate regions (found by a random search
    over such layouts for the largest smallest view)."""
    spec = TARGETS[target]
    board = target_from_dict(spec, "render_kaleidoscope")
    extent = _sheet(board)
    centre = np.array([(extent[0] + extent[1]) / 2, (extent[2] + extent[3]) / 2, 0.0])
    # Board x right, y down on the printed face, z into it (away from the camera): R ~ identity.
    R = so3_exp(np.radians([5.4, 4.6, 2.7]))
    t = np.array([-0.203, -0.181, 0.637]) - R @ centre
    vectors = {1: _mirror_vector(np.array([0.062, 0.0, 0.70]), [-1.0, 0.088, -0.26]),
               2: _mirror_vector(np.array([0.0, 0.074, 0.575]), [0.278, -1.0, -0.262])}
    return Kaleidoscope(dict(CAMERA), R, t, vectors, board, spec)


def moved_camera(k: Kaleidoscope, R_rel: np.ndarray, t_rel: np.ndarray) -> Kaleidoscope:
    """The same board and mirrors seen by a second camera with ``x_2 = R_rel x_1 + t_rel``: its
    ``T_cam_base`` and its mirror vectors (eq. 3: the plane ``n . x = d`` has normal ``R_rel n`` and
    distance ``d + (R_rel n) . t_rel`` in the second camera's frame)."""
    vectors = {}
    for l, v in k.mirror_vectors.items():
        d = float(np.linalg.norm(v))
        n = R_rel @ (v / d)
        vectors[l] = (d + float(n @ t_rel)) * n
    return Kaleidoscope(dict(k.camera), R_rel @ k.R_cam_base, R_rel @ k.t_cam_base + t_rel, vectors, k.target,
                        k.target_dict)


#: The rig's second camera (``--rig``): 4 cm to the first one's left and turned 2 degrees about y,
#: ``x_right = R x_left + t``.
RIG_R, RIG_T = so3_exp(np.radians([0.0, 2.0, 0.0])), np.array([0.04, 0.0, 0.0])


def _sheet(board) -> tuple[float, float, float, float]:
    """The printed sheet (board and white margin) in the board frame: x0, x1, y0, y1 (metres)."""
    s, q = board.square, QUIET_SQUARES * board.square
    if isinstance(board, CharucoTarget):
        return -q, board.cols * s + q, -q, board.rows * s + q
    return -s - q, board.cols * s + q, -s - q, board.rows * s + q  # chessboard: C00 at (0, 0)


def texture(board) -> tuple[np.ndarray, np.ndarray]:
    """Linear reflectance of the printed sheet, and the affine map (3 x 3) from board metres to texels
    (texel centres at integers)."""
    x0, x1, y0, y1 = _sheet(board)
    texel = board.square / TEXELS_PER_SQUARE
    w, h = int(round((x1 - x0) / texel)), int(round((y1 - y0) / texel))
    board_to_texel = np.array([[1 / texel, 0, -x0 / texel - 0.5], [0, 1 / texel, -y0 / texel - 0.5], [0, 0, 1]])
    if isinstance(board, CharucoTarget):
        margin = int(round(QUIET_SQUARES * TEXELS_PER_SQUARE))
        img = board.board().generateImage((w, h), marginSize=margin, borderBits=1)
        return np.where(img > 127, WHITE, BLACK).astype(np.float32), board_to_texel
    tex = np.full((h, w), WHITE, np.float32)
    for i in range(-1, board.cols):  # square (i, j) spans [i, i + 1] x [j, j + 1] squares; (-1, -1) is black
        for j in range(-1, board.rows):
            if (i + j) % 2 == 0:
                u0, v0 = (board_to_texel @ [i * board.square, j * board.square, 1])[:2] + 0.5
                tex[int(round(v0)):int(round(v0)) + TEXELS_PER_SQUARE, int(round(u0)):int(round(u0)) + TEXELS_PER_SQUARE] = BLACK
    return tex, board_to_texel


def view_transform(k: Kaleidoscope, reflections) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` of a view: the camera sees board point ``p`` at ``A p + b`` (eqs. 5-8)."""
    return nested_transform(k.R_cam_base, k.t_cam_base, [k.mirror_vectors[l] for l, _ in reflections])


def homography(k: Kaleidoscope, reflections) -> np.ndarray:
    """Board (x, y, 1) metres -> pixel (eq. 9 with the intrinsics)."""
    A, b = view_transform(k, reflections)
    K = np.array([[k.camera["fx"], 0, k.camera["cx"]], [0, k.camera["fy"], k.camera["cy"]], [0, 0, 1.0]])
    return K @ np.column_stack([A[:, 0], A[:, 1], b])


def _faces_camera(k: Kaleidoscope, reflections) -> bool:
    """The printed face (normal -z of the board) of the virtual board is turned towards the camera,
    every point is in front of it, and each mirror is met on its reflecting side."""
    A, b = view_transform(k, reflections)
    x0, x1, y0, y1 = _sheet(k.target)
    sheet = np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)])
    points = sheet @ A.T + b
    return bool(np.all(points[:, 2] > 0.1) and np.all(points @ (A @ [0, 0, -1.0]) < 0))


def roi_of(k: Kaleidoscope, reflections) -> tuple[int, int, int, int]:
    """The view's region: the bounding box of its printed sheet, grown by ROI_MARGIN_PX, in the image."""
    x0, x1, y0, y1 = _sheet(k.target)
    uvw = (homography(k, reflections) @ np.array([[x, y, 1.0] for x in (x0, x1) for y in (y0, y1)]).T).T
    uv = uvw[:, :2] / uvw[:, 2:]
    lo = np.floor(uv.min(axis=0)).astype(int) - ROI_MARGIN_PX
    hi = np.ceil(uv.max(axis=0)).astype(int) + ROI_MARGIN_PX
    if np.any(lo < 0) or hi[0] >= SIZE[0] or hi[1] >= SIZE[1]:
        raise ValueError(f"view {reflections}: the board leaves the image ({lo}, {hi})")
    return int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])


def _overlap(a, b) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def render(k: Kaleidoscope, seed: int = 0) -> tuple[np.ndarray, list[dict]]:
    """The photograph (8-bit grey) and per view ``{reflections, roi, pixels: {name: [u, v]}}`` (truth)."""
    tex, board_to_texel = texture(k.target)
    s = SUPERSAMPLE
    linear = np.full((SIZE[1], SIZE[0]), BACKGROUND, np.float32)
    views, rois = [], []
    corners = k.target.target_points()
    for reflections in VIEWS:
        if not _faces_camera(k, reflections):
            raise ValueError(f"view {reflections}: the printed face is not seen")
        roi = roi_of(k, reflections)
        for other in rois:
            if _overlap(roi, other):
                raise ValueError(f"view {reflections}: its region {roi} overlaps {other}")
        rois.append(roi)
        x, y, w, h = roi
        H = homography(k, reflections)
        # fine pixel (i, j) of the roi -> image pixel ((i + 0.5) / s - 0.5 + x, ...) -> board -> texel
        fine_to_pixel = np.array([[1 / s, 0, 0.5 / s - 0.5 + x], [0, 1 / s, 0.5 / s - 0.5 + y], [0, 0, 1]])
        M = board_to_texel @ np.linalg.inv(H) @ fine_to_pixel
        fine = cv2.warpPerspective(tex, M, (w * s, h * s), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)
        linear[y:y + h, x:x + w] = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
        uvw = (H @ np.array([[p[0], p[1], 1.0] for p in corners.values()]).T).T
        pixels = {n: (q[:2] / q[2]).tolist() for n, q in zip(corners, uvw)}
        views.append({"reflections": [list(p) for p in reflections], "roi": list(roi), "pixels": pixels})
    linear = cv2.GaussianBlur(linear, (0, 0), BLUR_PX)
    rng = np.random.default_rng(seed)
    encoded = srgb_encode(linear) + rng.normal(0.0, NOISE_GREY, linear.shape)
    return np.clip(np.round(encoded), 0, 255).astype(np.uint8), views


def _image(file: str, views: list[dict], camera: str | None = None) -> dict:
    return {"file": file, **({"camera": camera} if camera else {}),
            "views": [{"roi": v["roi"], "reflections": v["reflections"]} for v in views]}


#: The capture's pixel_sigma per target kind.
PIXEL_SIGMA = {"chessboard": 0.1, "charuco": 0.5}


def capture_dict(k: Kaleidoscope, views: list[dict], image_file: str = "kaleidoscope.png",
                 pixel_sigma: float = 0.1) -> dict:
    """The capture@1 of the photograph: one image with its ``views`` (roi and reflections each)."""
    return {"format": "mirror-fg/capture@1", "num_mirrors": 2, "camera": k.camera, "pixel_sigma": pixel_sigma,
            "target": k.target_dict, "images": [_image(image_file, views)]}


def truth_dict(k: Kaleidoscope, views: list[dict]) -> dict:
    return {"camera": k.camera, "R_cam_base": k.R_cam_base.tolist(), "t_cam_base": k.t_cam_base.tolist(),
            "mirror_vectors": {str(l): v.tolist() for l, v in k.mirror_vectors.items()}, "views": views}


def write(out: Path, target: str = "charuco", seed: int = 0, rig: bool = False) -> tuple[Path, dict]:
    """Render into ``out``: the photograph, ``capture.yaml`` and ``truth.json``; the capture's path and the
    truth. ``rig``: two cameras (``left``, ``right``: :data:`RIG_R`, :data:`RIG_T`) photograph the same
    kaleidoscope at once (``kaleidoscope_left.png``, ``kaleidoscope_right.png``; their views share the two
    fixed placements); the truth is then ``{"left": ..., "right": ...}``."""
    import yaml

    out.mkdir(parents=True, exist_ok=True)
    k = scene(target)
    if not rig:
        image, views = render(k, seed)
        cv2.imwrite(str(out / "kaleidoscope.png"), image)
        # ChArUco corners interpolated on small, foreshortened views are worse than a chessboard's
        # (measured: medians 0.03-0.15 px, the worst 2.8 px): their sigma says so.
        capture, truth = capture_dict(k, views, pixel_sigma=PIXEL_SIGMA[target]), truth_dict(k, views)
    else:
        cameras, images, truth = {}, [], {}
        for index, (name, kc) in enumerate((("left", k), ("right", moved_camera(k, RIG_R, RIG_T)))):
            image, views = render(kc, seed + index)
            cv2.imwrite(str(out / f"kaleidoscope_{name}.png"), image)
            cameras[name] = kc.camera
            images.append(_image(f"kaleidoscope_{name}.png", views, name))
            truth[name] = truth_dict(kc, views)
        single = capture_dict(k, [])
        capture = {"format": single["format"], "num_mirrors": 2, "cameras": cameras,
                   **{key: single[key] for key in ("pixel_sigma", "target")}, "images": images}
    path = out / "capture.yaml"
    path.write_text(yaml.safe_dump(capture, sort_keys=False))
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return path, truth


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--target", choices=sorted(TARGETS), default="charuco")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rig", action="store_true", help="two cameras photograph the kaleidoscope at once")
    args = parser.parse_args(argv)
    path, _ = write(args.out, args.target, args.seed, args.rig)
    print(f"wrote {args.out}: photograph{'s' if args.rig else ''}, {path.name}, truth.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
