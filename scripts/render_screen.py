#!/usr/bin/env python
"""Render a monitor showing a ``mirror-fg pattern`` PNG, seen by the webcam above it in a hand-held mirror.

The screen is an emitter: pixel (i, j) of the PNG covers [i, i + 1) x [j, j + 1) of the pixel-edge
coordinates, at ``(e_u * width_mm / width_px, e_v * height_mm / height_px, 0) / 1000`` metres in the
screen frame (origin top-left of the active area, x right, y down, z into the screen); its value v
shows as the linear luminance ``BLACK + (WHITE - BLACK) * (v / 255) ** DISPLAY_GAMMA`` (display gamma).
The webcam (pinhole, OpenCV axes) sits above the top edge, looking out of the screen, tilted down.
Each photograph is taken through a flat rectangular mirror (:class:`Mirror`): the camera sees the
screen as the *reflected* camera would (the virtual camera ``x -> M x + 2 v``, Householder ``M = I -
2 n n^T``, ``v = d n`` the mirror vector in the camera frame), so the screen plane maps to the image by
the homography ``K [a1 a2 b]`` of ``p_cam' = M (R s + t) + 2 v``. Pixels whose ray misses the mirror
see the room. Each pixel is the box average of 4 x 4 supersamples in linear intensity, blurred by the
optics, sRGB-encoded like a webcam's PNG and given sensor noise; the image is mirror-imaged, as a
photograph through one mirror is. Written independently of mirror_fg's geometry (tests compare with it).

``python scripts/render_screen.py --out DIR`` writes a pattern for a 24-inch 1920 x 1080 monitor, six
photographs, ``capture.yaml`` and ``truth.json`` (the true ``T_cam_screen`` and mirror vectors).
``--screens 2``: two such monitors side by side (:func:`two_screens`), six photographs of each (mirror
placements 0-5 aimed at the left one, 6-11 at the right one: :func:`side_placements`), a capture with ``screens: {left, right}``
and each image's ``screen``, and ``truth.json`` with ``screens: {name: T_cam_screen}``.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_scene import srgb_encode  # noqa: E402 - the webcam's encoding, as the other renderers'

WEBCAM = {"model": "pinhole", "width": 640, "height": 480, "fx": 520.0, "fy": 520.0, "cx": 319.5, "cy": 239.5,
          "dist": [0.0, 0.0, 0.0, 0.0, 0.0]}
DISPLAY_GAMMA = 2.2
BLACK, WHITE = 0.03, 0.85  # the panel's black and white, linear (of the camera's full scale)
BEZEL, ROOM = 0.02, 0.25  # linear: the frame around the active area; what the mirror does not show
SUPERSAMPLE = 4
BLUR_PX = 0.7  # optics, Gaussian sigma in pixels
NOISE_GREY = 1.0  # sensor noise, grey levels (of 255)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def webcam_above(width_m: float, gap_m: float = 0.012, tilt_deg: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of ``T_cam_screen`` (``p_cam = R s + t``) for a webcam centred ``gap_m`` above the top edge,
    8 mm in front of the screen, looking out of it and tilted ``tilt_deg`` down."""
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    z_c = np.array([0.0, s, -c])  # the optical axis, in the screen frame: out of the screen, a little down
    y_c = np.array([0.0, c, s])
    x_c = np.cross(y_c, z_c)  # (-1, 0, 0): the webcam's right is the screen's left
    R_screen_cam = np.column_stack([x_c, y_c, z_c])
    centre = np.array([width_m / 2, -gap_m, -0.008])
    R = R_screen_cam.T
    return R, -R @ centre


def two_screens(width_m: float, gap_m: float = 0.02, turn_deg: float = 35.0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{"left": (R, t), "right": (R, t)}`` of ``T_cam_screen``: the webcam's monitor (:func:`webcam_above`)
    and a second one of the same size ``gap_m`` right of it (as the viewer sees them), turned ``turn_deg``
    about its left edge towards the viewer (its x axis leaves the first screen's plane towards the viewer)."""
    R, t = webcam_above(width_m)
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    R_left_right = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # x -> (c, 0, -s): towards -z, the viewer
    t_left_right = np.array([width_m + gap_m, 0.0, 0.0])
    return {"left": (R, t), "right": (R @ R_left_right, R @ t_left_right + t)}


@dataclass(frozen=True)
class Mirror:
    """A rectangular mirror ``size_m`` (w, h) centred at ``centre`` (camera frame) with unit normal ``normal``
    pointing away from the camera; ``v`` is its mirror vector (camera frame, metres)."""

    centre: np.ndarray
    normal: np.ndarray
    size_m: tuple[float, float] = (0.25, 0.18)

    @property
    def v(self) -> np.ndarray:
        return float(self.normal @ self.centre) * self.normal


def aim_mirror(distance_m: float, towards_px: tuple[float, float], screen_point_cam: np.ndarray,
               camera: dict = WEBCAM, size_m: tuple[float, float] = (0.25, 0.18)) -> Mirror:
    """A mirror ``distance_m`` along the ray of image point ``towards_px`` that sends that ray to
    ``screen_point_cam``: its normal bisects the ray in and the ray out."""
    ray = unit([(towards_px[0] - camera["cx"]) / camera["fx"], (towards_px[1] - camera["cy"]) / camera["fy"], 1.0])
    centre = distance_m * ray
    out = unit(screen_point_cam - centre)
    return Mirror(centre, unit(ray - out), size_m)


def screen_homography(R: np.ndarray, t: np.ndarray, mirror: Mirror, camera: dict = WEBCAM) -> np.ndarray:
    """3 x 3: screen metres (x, y, 1) -> pixel of the photograph through ``mirror``."""
    n = mirror.normal
    M = np.eye(3) - 2.0 * np.outer(n, n)
    A, b = M @ R, M @ t + 2.0 * mirror.v
    K = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
    return K @ np.column_stack([A[:, 0], A[:, 1], b])


def project(H: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    uvw = np.c_[points_xy, np.ones(len(points_xy))] @ H.T
    return uvw[:, :2] / uvw[:, 2:]


def render(pattern_png: np.ndarray, mm: tuple[float, float], R: np.ndarray, t: np.ndarray, mirror: Mirror,
           rng: np.random.Generator, camera: dict = WEBCAM) -> np.ndarray:
    """8-bit photograph of the screen showing ``pattern_png`` (width_mm, height_mm ``mm``) through ``mirror``."""
    height_px, width_px = pattern_png.shape
    w, h, s = camera["width"], camera["height"], SUPERSAMPLE
    metres_per_px = np.array(mm) / 1000.0 / np.array([width_px, height_px])
    luminance = (BLACK + (WHITE - BLACK) * (pattern_png.astype(np.float32) / 255.0) ** DISPLAY_GAMMA).astype(np.float32)
    H = screen_homography(R, t, mirror, camera)
    fine_to_pixel = np.array([[1 / s, 0, 0.5 / s - 0.5], [0, 1 / s, 0.5 / s - 0.5], [0, 0, 1]])
    metres_to_texel = np.array([[1 / metres_per_px[0], 0, -0.5], [0, 1 / metres_per_px[1], -0.5], [0, 0, 1]])
    to_texel = metres_to_texel @ np.linalg.inv(H) @ fine_to_pixel
    fine = cv2.warpPerspective(luminance, to_texel, (w * s, h * s), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=BEZEL)
    # rays that miss the mirror see the room: the mirror's outline is the image of its four corners
    e1 = unit(np.cross([0.0, 1.0, 0.0], mirror.normal))
    e2 = np.cross(mirror.normal, e1)
    half_w, half_h = mirror.size_m[0] / 2, mirror.size_m[1] / 2
    corners = np.array([mirror.centre + a * half_w * e1 + b * half_h * e2 for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    uv = np.c_[camera["fx"] * corners[:, 0] / corners[:, 2] + camera["cx"],
               camera["fy"] * corners[:, 1] / corners[:, 2] + camera["cy"]]
    shift = 8  # sub-pixel polygon vertices
    fine_uv = np.round(((uv + 0.5) * s - 0.5) * (1 << shift)).astype(np.int32)
    on_mirror = np.zeros((h * s, w * s), np.uint8)
    cv2.fillConvexPoly(on_mirror, fine_uv, 1, lineType=cv2.LINE_8, shift=shift)
    fine = np.where(on_mirror > 0, fine, np.float32(ROOM)).astype(np.float32)
    linear = cv2.GaussianBlur(cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA), (0, 0), BLUR_PX)
    encoded = srgb_encode(linear) + rng.normal(0.0, NOISE_GREY, linear.shape)
    return np.clip(np.round(encoded), 0, 255).astype(np.uint8)


def placements(R: np.ndarray, t: np.ndarray, width_m: float, height_m: float) -> list[Mirror]:
    """Six hand-held mirror placements 0.25-0.45 m in front of the webcam, each aimed at a part of the screen."""
    def on_screen(fx: float, fy: float) -> np.ndarray:
        return R @ np.array([fx * width_m, fy * height_m, 0.0]) + t

    return [
        aim_mirror(0.30, (320, 250), on_screen(0.50, 0.50)),
        aim_mirror(0.35, (250, 230), on_screen(0.40, 0.45)),
        aim_mirror(0.40, (390, 260), on_screen(0.62, 0.55)),
        aim_mirror(0.27, (300, 300), on_screen(0.55, 0.40)),
        aim_mirror(0.45, (350, 200), on_screen(0.45, 0.60)),
        aim_mirror(0.33, (280, 270), on_screen(0.35, 0.55)),
    ]


def side_placements(R: np.ndarray, t: np.ndarray, width_m: float, height_m: float) -> list[Mirror]:
    """Six placements 0.22-0.33 m in front of the webcam, on the left of its image (towards a second monitor
    right of the first, as the viewer sees them), each aimed at a part of that monitor ``(R, t)``: a mirror
    straight ahead shows it too far and too oblique for its markers to decode."""
    def on_screen(fx: float, fy: float) -> np.ndarray:
        return R @ np.array([fx * width_m, fy * height_m, 0.0]) + t

    return [
        aim_mirror(0.22, (130, 250), on_screen(0.50, 0.50)),
        aim_mirror(0.26, (100, 200), on_screen(0.45, 0.55)),
        aim_mirror(0.30, (160, 280), on_screen(0.55, 0.45)),
        aim_mirror(0.24, (180, 220), on_screen(0.40, 0.50)),
        aim_mirror(0.28, (120, 300), on_screen(0.60, 0.60)),
        aim_mirror(0.33, (140, 190), on_screen(0.50, 0.40)),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--screens", type=int, choices=[1, 2], default=1, help="one monitor, or two side by side")
    args = parser.parse_args()
    import yaml

    from mirror_fg.vision.pattern import design_pattern, draw_pattern, screen_mm_from_diagonal

    width_mm, height_mm = screen_mm_from_diagonal(1920, 1080, 24.0)
    screen = design_pattern(1920, 1080, width_mm, height_mm)
    png = draw_pattern(screen)
    R, t = webcam_above(width_mm / 1000)
    rng = np.random.default_rng(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.screens == 2:
        write_two_screens(args.out, screen, png, (width_mm, height_mm), rng)
        return
    images = []
    mirrors = placements(R, t, width_mm / 1000, height_mm / 1000)
    for k, mirror in enumerate(mirrors):
        cv2.imwrite(str(args.out / f"mirror{k}.png"), render(png, (width_mm, height_mm), R, t, mirror, rng))
        images.append({"file": f"mirror{k}.png", "mirror_configs": [k]})
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": WEBCAM, "pixel_sigma": 0.3,
               "target": screen.to_dict(), "images": images}
    (args.out / "capture.yaml").write_text(yaml.safe_dump(capture, default_flow_style=None, sort_keys=False))
    truth = {"T_cam_screen": {"R": R.tolist(), "t": t.tolist()}, "mirrors": [m.v.tolist() for m in mirrors]}
    (args.out / "truth.json").write_text(json.dumps(truth, indent=2))
    print(f"wrote {len(images)} photographs, capture.yaml and truth.json to {args.out}")


def write_two_screens(out: Path, screen, png: np.ndarray, mm: tuple[float, float], rng: np.random.Generator) -> None:
    """Two monitors showing the same pattern (:func:`two_screens`), six photographs of each, the capture
    with ``screens`` and the truth (module docstring)."""
    import yaml

    poses = two_screens(mm[0] / 1000)
    images, truth_mirrors, label = [], [], 0
    for name, (R, t) in poses.items():
        for mirror in (placements if name == "left" else side_placements)(R, t, mm[0] / 1000, mm[1] / 1000):
            cv2.imwrite(str(out / f"{name}{label}.png"), render(png, mm, R, t, mirror, rng))
            images.append({"file": f"{name}{label}.png", "mirror_configs": [label], "screen": name})
            truth_mirrors.append(mirror.v.tolist())
            label += 1
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": WEBCAM, "pixel_sigma": 0.3,
               "screens": {name: screen.to_dict() for name in poses}, "images": images}
    (out / "capture.yaml").write_text(yaml.safe_dump(capture, default_flow_style=None, sort_keys=False))
    truth = {"screens": {name: {"R": R.tolist(), "t": t.tolist()} for name, (R, t) in poses.items()},
             "mirrors": truth_mirrors}
    (out / "truth.json").write_text(json.dumps(truth, indent=2))
    print(f"wrote {len(images)} photographs of two screens, capture.yaml and truth.json to {out}")


if __name__ == "__main__":
    main()
