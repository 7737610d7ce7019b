"""A video with a damaged middle: every frame OpenCV can still decode is used, in its place,
and FFmpeg's own complaints never reach stderr."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from mirror_fg.cli import main
from mirror_fg.io.capture import load_capture
from mirror_fg.vision.detectors import FOUND
from mirror_fg.vision.detect import detect_capture

from test_detect import board_image

FRAMES = 16
KEYFRAME = 12  # OpenCV's MPEG-4 writer starts a group of pictures every 12 frames


def _damaged_video(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    """An mp4 (MPEG-4 part 2) of a chessboard sliding 5 px per frame, 20 % of its middle bytes garbled;
    each frame's true corners. (With the noise strip most of a frame's
    bytes are its own, so the damage loses whole frames instead of blurring every later one.)"""
    board, corners = board_image(6, 5)
    w, h = 320, 240
    path = tmp_path / "run.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (w, h), isColor=False)
    truths = []
    rng = np.random.default_rng(0)
    for k in range(FRAMES):
        canvas = np.full((h, w), 128, np.uint8)
        canvas[-20:] = rng.integers(0, 256, (20, w))  # noise: every frame carries many bytes
        y0, x0 = 30, 10 + 5 * k
        canvas[y0 : y0 + board.shape[0], x0 : x0 + board.shape[1]] = board
        writer.write(cv2.flip(canvas, 1))  # seen through one mirror
        c = corners + [x0, y0]
        truths.append(np.stack([w - 1 - c[:, 0], c[:, 1]], 1))
    writer.release()
    data = bytearray(path.read_bytes())
    a, b = int(0.3 * len(data)), int(0.5 * len(data))
    data[a:b] = np.random.default_rng(3).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": w, "height": h, "fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0},
        "target": {"kind": "chessboard", "cols": 6, "rows": 5, "square": 0.02},
        "video": {"file": "run.mp4", "segments": [{"frames": [0, FRAMES - 1], "mirror_configs": ["each"]}]},
    }
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(capture))
    return tmp_path / "capture.yaml", truths


def _decodable_frames(path: Path) -> list[int]:
    """Reference: the frames a plain sequential cv2 read returns (read k returns frame k)."""
    vc = cv2.VideoCapture(str(path))
    ok_frames = [k for k in range(FRAMES) if vc.read()[0]]
    vc.release()
    return ok_frames


def test_frames_after_a_damaged_stretch_are_used_in_their_place(tmp_path):
    capture_path, truths = _damaged_video(tmp_path)
    readable = _decodable_frames(tmp_path / "run.mp4")
    assert 0 < len(readable) < FRAMES and readable[-1] == FRAMES - 1  # the damage is in the middle
    dataset, reports = detect_capture(load_capture(capture_path), progress=False)
    unreadable = {r.id for r in reports if "could not be read" in r.reason}
    assert unreadable == {f"run:{k}" for k in range(FRAMES) if k not in readable}
    # Frames between the damage and the next key frame decode from a damaged reference (the decoder's
    # concealment): what they show is the codec's business. From the key frame on each frame is exact:
    # the frame at its index has that frame's corners.
    late = [k for k in readable if k >= KEYFRAME]
    assert late == list(range(KEYFRAME, FRAMES)) and min(set(range(FRAMES)) - set(readable)) < KEYFRAME
    by_id = {image.id: image for image in dataset.images}
    found = {r.id for r in reports if r.status == FOUND}
    for k in [0, *late]:
        assert f"run:{k}" in found, [r.line() for r in reports]
        image = by_id[f"run:{k}"]
        names = sorted(n for n in image.observations if n.startswith("C"))
        got = np.array([image.observations[n] for n in names])
        assert np.max(np.linalg.norm(got - truths[k][[int(n[1:]) for n in names]], axis=1)) < 1.0, k


def test_ffmpeg_messages_do_not_reach_stderr(tmp_path, capfd):
    capture_path, _ = _damaged_video(tmp_path)
    main(["detect", str(capture_path), "-o", str(tmp_path / "d.json")])
    err = capfd.readouterr().err
    assert "@ 0x" not in err and "damaged" not in err, err
