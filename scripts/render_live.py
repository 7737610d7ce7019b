"""A hand-held mirror session rendered as a video: an AprilTag board on the body seen through one mirror.

Each frame is the board's printed face mapped into the image by the homography of its virtual view
(the reflection of eq. 3 applied to ``T_cam_base``: ``A = M R``, ``b = M t + 2 v``; a board point
``(x, y, 0)`` images at ``K (x a1 + y a2 + b)``), so the picture is mirror-imaged as in a real mirror.
Linear-light blending, then the sRGB curve, a slight blur and 1-2 grey levels of noise. The mirror is
held still for ``hold`` frames at each placement and swept to the next one over ``move`` frames (those
frames are motion-blurred), as a person at the bench would do it.

Used by tests/test_live.py and scripts/benchmark_live.py; ``python scripts/render_live.py OUT_DIR``
writes ``session.avi`` (MJPG), ``capture.yaml`` and ``truth.json`` for trying ``mirror-fg live``.
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mirror_fg.core.geometry import householder, so3_exp  # noqa: E402

TAG_SIZE = 0.08  # metres, black square's edge
TAG_SPACING = 0.11  # metres between tag centres
TAG_IDS = (0, 1, 2, 3)
#: Texture resolution: pixels per metre of the printed board.
TEXTURE_PX_PER_M = 4000
BOARD_HALF = 0.125  # metres: the printed board spans [-0.1, 0.1]^2 in its frame


@dataclass
class Session:
    """A rendered session: camera, board pose, mirror placements and the frames' placement indices."""

    camera: dict
    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: list[np.ndarray]
    frame_placements: list[int | None]  # placement index of each frame, None while moving


def tag_layout() -> dict[int, np.ndarray]:
    """Tag centres in the board (base) frame: a 2 x 2 grid, x right, y up on the printed face."""
    h = TAG_SPACING / 2
    return {0: np.array([-h, h, 0.0]), 1: np.array([h, h, 0.0]), 2: np.array([-h, -h, 0.0]), 3: np.array([h, -h, 0.0])}


def board_texture() -> np.ndarray:
    """The printed board (float linear light, 1 = white), ``TEXTURE_PX_PER_M`` pixels per metre."""
    size = int(round(2 * BOARD_HALF * TEXTURE_PX_PER_M))
    texture = np.ones((size, size), dtype=np.float32)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    side = int(round(TAG_SIZE * TEXTURE_PX_PER_M))
    for tag_id, centre in tag_layout().items():
        marker = cv2.aruco.generateImageMarker(dictionary, tag_id, side)  # the black square, border included
        u0 = int(round((centre[0] + BOARD_HALF) * TEXTURE_PX_PER_M)) - marker.shape[1] // 2
        v0 = int(round((BOARD_HALF - centre[1]) * TEXTURE_PX_PER_M)) - marker.shape[0] // 2
        texture[v0:v0 + marker.shape[0], u0:u0 + marker.shape[1]] = marker.astype(np.float32) / 255.0
    return texture


def capture_dict(camera: dict, pixel_sigma: float = 0.5) -> dict:
    """The capture@1 of a session (images/video not needed by ``mirror-fg live``)."""
    tags = {i: {"R": np.eye(3).tolist(), "t": c.tolist()} for i, c in tag_layout().items()}
    return {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": camera, "pixel_sigma": pixel_sigma,
            "target": {"kind": "apriltag", "dictionary": "tag36h11", "tag_size": TAG_SIZE, "tags": tags}}


def session(width: int = 800, height: int = 600, placements: int = 8, hold: int = 4, move: int = 2,
            seed: int = 0, tilt_deg: float = 22.0, same_tilt: bool = False, from_behind: bool = False) -> Session:
    """Camera (f = 1.05 width), board pose (facing the mirror, 12 cm below the camera) and placements
    (distance 0.45-0.6 m, normals within ``tilt_deg`` of the optical axis; ``same_tilt``: all about one
    axis, a degenerate session)."""
    rng = np.random.default_rng(seed)
    f = 1.05 * width
    camera = {"model": "pinhole", "width": width, "height": height, "fx": f, "fy": f,
              "cx": (width - 1) / 2, "cy": (height - 1) / 2, "dist": [0.0] * 5}
    # Board face towards +z of the camera (the mirror): x_base = -x_cam, y_base = -y_cam, slightly turned.
    R = np.diag([-1.0, -1.0, 1.0]) @ so3_exp(np.deg2rad(8.0) * np.array([0.6, -0.3, 0.74]))
    t = np.array([0.01, 0.12, -0.02])
    if from_behind:  # the printed face turned away from the mirror (half a turn about the board's y axis)
        R = R @ np.diag([-1.0, 1.0, -1.0])
    vectors: list[np.ndarray] = []
    tries = 0
    while len(vectors) < placements:
        tries += 1
        if tries > 10000:
            raise RuntimeError("render_live: no mirror placement keeps the board in view; lower tilt_deg")
        if same_tilt:
            angle = np.deg2rad(tilt_deg) * (-0.35 + 0.7 * len(vectors) / max(placements - 1, 1)) + rng.uniform(-0.01, 0.01)
            axis = np.array([0.0, 1.0, 0.0])
        else:
            angle = np.deg2rad(tilt_deg) * np.sqrt(rng.uniform(0.3, 1.0))
            turn = len(vectors) + tries // 20  # golden-angle turns; the next turn where one stays out of view
            phi = turn * np.pi * (3.0 - np.sqrt(5.0)) + rng.uniform(-0.3, 0.3)
            axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        normal = so3_exp(angle * axis) @ np.array([0.0, 0.0, 1.0])
        v = rng.uniform(0.45, 0.6) * normal
        if _corners_in_view(camera, R, t, v):
            vectors.append(v)
    frames: list[int | None] = []
    for k in range(placements):
        frames += [None] * (move if k else 0) + [k] * hold
    return Session(camera, R, t, vectors, frames)


def _virtual(R: np.ndarray, t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    M = householder(v)
    return M @ R, M @ t + 2.0 * v  # eqs. (5)-(8), one mirror


def _corners_in_view(camera: dict, R: np.ndarray, t: np.ndarray, v: np.ndarray, margin: float = 40.0) -> bool:
    A, b = _virtual(R, t, v)
    corners = np.array([[x, y, 0.0] for x in (-BOARD_HALF, BOARD_HALF) for y in (-BOARD_HALF, BOARD_HALF)])
    p = corners @ A.T + b
    if np.any(p[:, 2] <= 0.05) or np.any((corners @ R.T + t) @ v >= v @ v):
        return False
    u = camera["fx"] * p[:, 0] / p[:, 2] + camera["cx"]
    w = camera["fy"] * p[:, 1] / p[:, 2] + camera["cy"]
    return bool(np.all((u > margin) & (u < camera["width"] - margin) & (w > margin) & (w < camera["height"] - margin)))


def render(camera: dict, R: np.ndarray, t: np.ndarray, v: np.ndarray, texture: np.ndarray, rng: np.random.Generator,
           blur_px: float = 0.6, noise: float = 1.5) -> np.ndarray:
    """One 8-bit grey frame of the board seen through the mirror ``v``."""
    A, b = _virtual(R, t, v)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
    # Texture pixel (u, v) -> board metres (x, y): x = u / s - half, y = half - v / s (pixel centres).
    s = TEXTURE_PX_PER_M
    texture_to_board = np.array([[1 / s, 0, 0.5 / s - BOARD_HALF], [0, -1 / s, BOARD_HALF - 0.5 / s], [0, 0, 1.0]])
    H = K @ np.column_stack([A[:, 0], A[:, 1], b]) @ texture_to_board
    size = (int(camera["width"]), int(camera["height"]))
    linear = cv2.warpPerspective(texture, H, size, flags=cv2.INTER_AREA, borderMode=cv2.BORDER_CONSTANT, borderValue=0.35)
    if blur_px > 0:
        linear = cv2.GaussianBlur(linear, (0, 0), blur_px)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(np.clip(linear, 0, 1), 1 / 2.4) - 0.055)
    return np.clip(255 * srgb + rng.normal(scale=noise, size=srgb.shape), 0, 255).astype(np.uint8)


def frames(s: Session, seed: int = 1):
    """Every frame of the session in order (the moving frames swept and motion-blurred)."""
    texture = board_texture()
    rng = np.random.default_rng(seed)
    previous = s.mirror_vectors[0]
    for index, placement in enumerate(s.frame_placements):
        if placement is not None:
            previous = s.mirror_vectors[placement]
            yield render(s.camera, s.R_cam_base, s.t_cam_base, previous, texture, rng)
        else:
            after = next(p for p in s.frame_placements[index:] if p is not None)
            v = 0.5 * (previous + s.mirror_vectors[after])
            yield render(s.camera, s.R_cam_base, s.t_cam_base, v, texture, rng, blur_px=4.0)


def write_video(s: Session, path: Path, seed: int = 1) -> Path:
    """The session as an MJPG AVI (high quality), grey frames stored as BGR."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0,
                             (int(s.camera["width"]), int(s.camera["height"])))
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 98)
    for frame in frames(s, seed):
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def truth_dict(s: Session) -> dict:
    return {"R_cam_base": s.R_cam_base.tolist(), "t_cam_base": s.t_cam_base.tolist(),
            "mirror_vectors": [v.tolist() for v in s.mirror_vectors]}


def main(argv: list[str] | None = None) -> int:
    import argparse

    import yaml

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", default="800x600")
    parser.add_argument("--placements", type=int, default=8)
    args = parser.parse_args(argv)
    width, height = (int(x) for x in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    s = session(width, height, args.placements)
    write_video(s, args.out / "session.avi")
    (args.out / "capture.yaml").write_text(yaml.safe_dump(capture_dict(s.camera), sort_keys=False))
    (args.out / "truth.json").write_text(json.dumps(truth_dict(s), indent=1))
    print(f"wrote {args.out}/session.avi ({len(s.frame_placements)} frames), capture.yaml, truth.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
