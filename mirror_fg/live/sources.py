"""Frame sources of a live session (``mirror-fg live --source``): a camera, a video file, a folder.

Each source yields ``(index, gray)`` pairs in order and counts what it had to drop:

- a **camera index** (OpenCV ``VideoCapture``): a reader thread keeps only the newest frame, so a slow
  consumer never queues frames without bound; frames overwritten before they were taken are
  ``dropped`` (and counted in the indices, which stay those of the camera's frames);
- a **video file**: every frame once, in order, as fast as the consumer takes them (not paced at the
  file's frame rate, so the throughput can be measured); a frame the decoder cannot read is skipped
  and counted in ``unreadable``;
- a **folder** another program fills: image files (``.png .jpg .jpeg .bmp .tif .tiff``) in name order,
  each once, read when their size has stopped changing; the source ends after ``idle_s`` seconds
  without a new file.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.fileio import native_stderr

__all__ = ["FrameSource", "VideoFileSource", "CameraSource", "FolderSource", "open_source", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: A folder is polled this often (seconds).
POLL_S = 0.1


def _gray(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


class FrameSource:
    """Base: ``frames()`` yields ``(index, gray)``; ``dropped`` / ``unreadable`` count the rest."""

    description = "source"

    def __init__(self) -> None:
        self.dropped = 0
        self.unreadable = 0
        self.stopped = threading.Event()

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        raise NotImplementedError

    def stop(self) -> None:
        """Ask the source to end (e.g. from a signal handler or another thread)."""
        self.stopped.set()

    def close(self) -> None:
        self.stop()


class VideoFileSource(FrameSource):
    def __init__(self, path: str):
        super().__init__()
        self.path = path
        self.description = f"video {path}"
        with native_stderr():
            self.capture = cv2.VideoCapture(path)
        if not self.capture.isOpened():
            raise DatasetError(f"--source {path}: cannot open the video (not a video file OpenCV reads, or damaged)")
        self.frame_count = int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        index = 0
        failures = 0
        while not self.stopped.is_set():
            with native_stderr():
                ok, image = self.capture.read()
            if not ok or image is None:
                # A damaged frame in the middle: skip it; the end of the file: stop.
                if self.frame_count and index < self.frame_count - 1 and failures < 50:
                    failures += 1
                    self.unreadable += 1
                    index += 1
                    continue
                break
            failures = 0
            yield index, _gray(image)
            index += 1

    def close(self) -> None:
        super().close()
        self.capture.release()


class CameraSource(FrameSource):
    """The newest frame of a camera, read by a thread; older untaken frames are dropped and counted."""

    def __init__(self, capture: Any, description: str):
        """``capture``: an opened ``cv2.VideoCapture`` (or anything with ``read()`` and ``release()``)."""
        super().__init__()
        self.description = description
        self.capture = capture
        self._slot: tuple[int, np.ndarray] | None = None
        self._ready = threading.Condition()
        self._count = 0
        self._ended = False
        self._slot_time = 0.0
        #: Wall-clock time (seconds since the epoch) the frame last yielded was read at (joint states by time).
        self.frame_time = 0.0
        self._thread = threading.Thread(target=self._read, name="mirror-fg camera", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self.stopped.is_set():
            with native_stderr():
                ok, image = self.capture.read()
            with self._ready:
                if not ok or image is None:
                    self._ended = True
                    self._ready.notify_all()
                    return
                if self._slot is not None:
                    self.dropped += 1  # the consumer did not take the previous frame in time
                self._slot, self._slot_time = (self._count, _gray(image)), time.time()
                self._count += 1
                self._ready.notify_all()

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        while not self.stopped.is_set():
            with self._ready:
                while self._slot is None and not self._ended and not self.stopped.is_set():
                    self._ready.wait(0.2)
                if self._slot is None:
                    return
                item, self._slot, self.frame_time = self._slot, None, self._slot_time
            yield item

    def close(self) -> None:
        super().close()
        self._thread.join(timeout=2.0)
        self.capture.release()


class FolderSource(FrameSource):
    def __init__(self, folder: str, idle_s: float):
        super().__init__()
        self.folder = folder
        self.idle_s = idle_s
        self.description = f"folder {folder}"
        #: The file name of the frame last yielded (joint states by image name).
        self.frame_name = ""

    def frames(self) -> Iterator[tuple[int, np.ndarray]]:
        seen: set[str] = set()
        sizes: dict[str, int] = {}
        index = 0
        last_new = time.monotonic()
        while not self.stopped.is_set():
            fresh = []
            for entry in sorted(os.scandir(self.folder), key=lambda e: e.name):
                if entry.name in seen or not entry.is_file() or not entry.name.lower().endswith(IMAGE_SUFFIXES):
                    continue
                if entry.name.startswith("."):
                    continue  # a file still being written under a temporary name
                size = entry.stat().st_size
                if sizes.get(entry.name) == size and size > 0:
                    fresh.append(entry.path)
                sizes[entry.name] = size
            for path in fresh:
                seen.add(os.path.basename(path))
                with native_stderr():
                    image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
                last_new = time.monotonic()
                if image is None:
                    self.unreadable += 1
                    index += 1
                    continue
                self.frame_name = os.path.basename(path)
                yield index, image
                index += 1
            if not fresh:
                if time.monotonic() - last_new > self.idle_s:
                    return
                self.stopped.wait(POLL_S)


def open_source(text: str, idle_s: float = 30.0) -> FrameSource:
    """``--source``: a camera index (digits), a folder, or a video file."""
    if text.isdigit():
        with native_stderr():
            camera = cv2.VideoCapture(int(text))
        if not camera.isOpened():
            raise DatasetError(f"--source {text}: no camera with that index can be opened")
        return CameraSource(camera, f"camera {text}")
    path = Path(text)
    if path.is_dir():
        return FolderSource(text, idle_s)
    if not path.exists():
        raise DatasetError(f"--source {text}: no such file, folder or camera index")
    return VideoFileSource(text)
