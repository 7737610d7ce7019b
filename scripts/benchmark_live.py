"""Live-session throughput: does ``mirror-fg live`` keep up with the camera?

Renders a hand-held AprilTag session (scripts/render_live.py: each placement held ``--hold`` frames,
``--move`` frames of motion-blurred sweep between them) at 800 x 600 and 1280 x 720, then:

- **video file** (each frame once, as fast as it is processed): frames per second of the whole
  session loop (detection, the judgement of each frame, iSAM2 and the suggestion on added frames, the
  page's picture when ``--serve`` would draw it). Goals: >= 30 frames/s at 800 x 600, >= 15 at 1280 x 720.
- **camera** (the same frames delivered at 30 frames/s by a reader thread, as ``--source 0`` reads a
  camera): frames taken and dropped (a slow step drops frames, it never queues them).

    python scripts/benchmark_live.py [--placements 10] [--hold 30] [--move 15]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import render_live  # noqa: E402
from mirror_fg.io.capture import capture_from_dict  # noqa: E402
from mirror_fg.live.session import LiveSession, run  # noqa: E402
from mirror_fg.live.sources import CameraSource, VideoFileSource  # noqa: E402

GOALS = {(800, 600): 30.0, (1280, 720): 15.0}


class PacedVideo:
    """A video file read at ``fps`` frames per second: what a camera delivers."""

    def __init__(self, path: str, fps: float):
        self.capture = cv2.VideoCapture(path)
        self.period = 1.0 / fps
        self.next = time.perf_counter()

    def read(self):
        delay = self.next - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        self.next = max(self.next + self.period, time.perf_counter() - self.period)
        return self.capture.read()

    def release(self) -> None:
        self.capture.release()


def session_files(folder: str, width: int, height: int, args) -> tuple[str, dict]:
    s = render_live.session(width, height, args.placements, hold=args.hold, move=args.move)
    path = os.path.join(folder, f"session_{width}x{height}.avi")
    render_live.write_video(s, Path(path))
    return path, render_live.capture_dict(s.camera)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--placements", type=int, default=10)
    parser.add_argument("--hold", type=int, default=30)
    parser.add_argument("--move", type=int, default=15)
    args = parser.parse_args(argv)
    ok = True
    print(f"load {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as folder:
        for (width, height), goal in GOALS.items():
            path, capture_data = session_files(folder, width, height, args)
            capture = capture_from_dict(yaml.safe_load(yaml.safe_dump(capture_data)), "bench", folder, media=False)
            session = LiveSession(capture, picture=True)
            figures = run(session, VideoFileSource(path))
            met = figures["fps"] >= goal
            ok &= met
            print(f"{width}x{height} video file: {figures['frames']} frames in {figures['seconds']:.2f} s = "
                  f"{figures['fps']:.1f} frames/s (goal >= {goal:g}: {'met' if met else 'NOT met'}); "
                  f"{len(session.added)} placements added; {session.summary()}")
            session = LiveSession(capture, picture=True)
            figures = run(session, CameraSource(PacedVideo(path, 30.0), "paced video"))
            print(f"{width}x{height} camera at 30 frames/s: {figures['frames']} taken, {figures['dropped']} dropped "
                  f"in {figures['seconds']:.2f} s; {len(session.added)} placements added")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
