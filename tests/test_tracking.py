"""KLT tracking (mirror_fg.vision.tracking) and video captures through detect_capture."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mirror_fg.io.capture import load_capture
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.vision.detectors import FOUND
from mirror_fg.vision.detect import detect_capture
from mirror_fg.vision.tracking import KLTParams, PointTracker, track_klt

from test_detect import board_image  # tests/ is on sys.path under pytest's default (prepend) import mode


def texture(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, size=(h // 4, w // 4)).astype(np.float32)
    return cv2.resize(cv2.GaussianBlur(noise, (0, 0), 1.0), (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


def moved(img: np.ndarray, A: np.ndarray, border: int | None = None) -> np.ndarray:
    """``img`` under the 2x3 affine map A (pixel-centre convention); outside: reflected, or ``border``."""
    if border is None:
        return cv2.warpAffine(img, A, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return cv2.warpAffine(img, A, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=border)


def motion(k: int, centre=(160.0, 120.0)) -> np.ndarray:
    """Frame k's affine map from frame 0: a turn of 0.15 deg and a shift of (1.3, -0.7) px per frame.

    (Translational KLT drifts under image rotation: ~0.026 px per frame at 0.4 deg per frame.)
    """
    return cv2.getRotationMatrix2D(centre, 0.15 * k, 1.0) + np.array([[0, 0, 1.3 * k], [0, 0, -0.7 * k]])


def apply(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ A[:, :2].T + A[:, 2]


def test_track_klt_subpixel_shift_and_forward_backward_rejection():
    base = texture()
    pts = np.array([[100.0, 80.0], [200.5, 150.25], [60.0, 190.0]])
    A = np.array([[1.0, 0.0, 2.37], [0.0, 1.0, -1.61]])
    new, ok = track_klt(base, moved(base, A), pts)
    assert ok.all()
    assert np.max(np.linalg.norm(new - apply(A, pts), axis=1)) < 0.05
    _, ok = track_klt(base, texture(seed=1), pts)  # an unrelated frame: the tracks do not come back
    assert not ok.any()
    _, ok = track_klt(base, base, np.array([[-5.0, 10.0]]))
    assert not ok.any()


@pytest.mark.parametrize("kind, bound", [("klt", 0.5), ("template", 0.2)])
def test_point_tracker_over_30_frames_stays_within_half_a_pixel(kind: str, bound: float):
    """Points on plain texture (no corner): plain KLT, and the first-frame template that removes its drift."""
    base = texture()
    start = np.array([[90.0, 70.0], [230.0, 160.0], [150.0, 120.0], [260.0, 60.0]])
    tracker = PointTracker(KLTParams(), default_kind=kind, image_gamma="linear")
    worst = 0.0
    for k in range(30):
        frame = moved(base, motion(k))
        tracker.step(frame)
        if k == 0:
            for i, p in enumerate(start):
                tracker.set(f"P{i}", p)
        truth = apply(motion(k), start)
        assert set(tracker.points) == {f"P{i}" for i in range(4)}, k
        worst = max(worst, max(np.linalg.norm(tracker.points[f"P{i}"] - truth[i]) for i in range(4)))
    assert worst < bound, worst


def test_video_capture_tracks_where_detection_fails(tmp_path: Path):
    """A mirrored chessboard video: the board slides partly out of view and back. While it is cut
    the detector fails and KLT carries the corners still in view; then re-detection takes over."""
    board, corners = board_image(6, 5)
    w, h = 320, 240
    canvas = np.full((h, w), 128, np.uint8)
    y0, x0 = 40, 16
    canvas[y0 : y0 + board.shape[0], x0 : x0 + board.shape[1]] = board
    cv2.circle(canvas, (250, 200), 6, 255, -1)  # an unknown point to track, not on the board
    cv2.circle(canvas, (250, 200), 2, 0, -1)
    corners = corners + [x0, y0]
    point = np.array([250.0, 200.0])
    frames = 17

    def slide(k: int) -> np.ndarray:
        shift = -9.0 * min(k, frames - 1 - k)  # out to the left and back
        return cv2.getRotationMatrix2D((w / 2, h / 2), 0.15 * k, 1.0) + np.array([[0, 0, shift], [0, 0, 0.5 * k]])

    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 10, (w, h), isColor=False)
    truths = []
    for k in range(frames):
        A = slide(k)
        writer.write(cv2.flip(moved(canvas, A, border=128), 1))  # seen through one mirror
        c, p = apply(A, corners), apply(A, point[None])[0]
        truths.append((np.stack([w - 1 - c[:, 0], c[:, 1]], 1), np.array([w - 1 - p[0], p[1]])))
    writer.release()
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": w, "height": h, "fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0},
        "target": {"kind": "chessboard", "cols": 6, "rows": 5, "square": 0.02},
        "video": {"file": "run.avi", "segments": [{"frames": [0, frames - 1], "mirror_configs": ["each"]}]},
        "track": {"P0": {"frame": 0, "pixel": [float(w - 1 - point[0]), float(point[1])]}},
    }
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(capture))
    dataset, reports = detect_capture(load_capture(tmp_path / "capture.yaml"), progress=False)
    d = dataset_to_dict(dataset)
    assert [r.id for r in reports] == [f"run:{k}" for k in range(frames)]
    assert all(r.status == FOUND for r in reports), [r.line() for r in reports]
    tracked = [k for k, r in enumerate(reports) if "tracked by KLT" in r.reason]
    assert len(tracked) >= 3 and tracked[0] > 0 and tracked[-1] < frames - 1, [r.line() for r in reports]
    assert reports[0].reason == "" and reports[-1].reason == ""  # detected at both ends
    assert [im["mirror_configs"] for im in d["images"]] == [[k] for k in range(frames)]
    worst_corner = worst_point = 0.0
    for k, (im, (truth, truth_point)) in enumerate(zip(d["images"], truths)):
        names = sorted(n for n in im["observations"] if n.startswith("C"))
        assert len(names) == 30 or k in tracked, k
        assert len(names) >= 12, (k, len(names))
        found = np.array([im["observations"][n] for n in names])
        worst_corner = max(worst_corner, float(np.max(np.linalg.norm(found - truth[[int(n[1:]) for n in names]], axis=1))))
        worst_point = max(worst_point, float(np.linalg.norm(np.array(im["observations"]["P0"]) - truth_point)))
    assert worst_corner < 0.5 and worst_point < 0.5, (worst_corner, worst_point)
    ds = dataset_from_dict(d)
    assert ds.reconstruction_point_names == ["P0"]
