"""KLT point tracking through video frames (cv2.calcOpticalFlowPyrLK) with forward-backward checks.

Pixels follow OpenCV's convention (the centre of the top-left pixel is (0, 0)). Frames are 8-bit
grayscale arrays of one size. A track is dropped when the pyramidal Lucas-Kanade step fails in either
direction, when tracking the new position back into the previous frame lands more than
``fb_threshold_px`` from where it started (Kalal et al.'s forward-backward error), or when the point
leaves the image.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["KLTParams", "track_klt", "PointTracker"]


@dataclass(frozen=True)
class KLTParams:
    """Settings of :func:`track_klt`.

    ``win_size``: side of the search window (pixels, odd); ``max_level``: pyramid levels above the
    image; ``fb_threshold_px``: largest forward-backward error kept (pixels); ``iterations``/``epsilon``:
    Lucas-Kanade stopping criteria (pixels); ``min_eig``: smallest normalized minimum eigenvalue of the
    window's gradient matrix (textureless windows fail).
    """

    win_size: int = 21
    max_level: int = 3
    fb_threshold_px: float = 0.5
    iterations: int = 50
    epsilon: float = 1e-3
    min_eig: float = 1e-4


def track_klt(
    prev: np.ndarray, nxt: np.ndarray, points: np.ndarray, params: KLTParams = KLTParams()
) -> tuple[np.ndarray, np.ndarray]:
    """Follow ``points`` (N, 2) from frame ``prev`` into frame ``nxt``.

    Returns the new positions (N, 2) (pixels; meaningful only where kept) and a boolean mask (N,) of the
    tracks that passed the forward-backward check and stayed inside ``nxt``.
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 1, 2)
    n = pts.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    kwargs = dict(
        winSize=(params.win_size, params.win_size),
        maxLevel=params.max_level,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon),
        minEigThreshold=params.min_eig,
    )
    fwd, st_f, _ = cv2.calcOpticalFlowPyrLK(prev, nxt, pts, None, **kwargs)
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(nxt, prev, fwd, None, **kwargs)
    fwd = fwd.reshape(n, 2).astype(np.float64)
    fb_error = np.linalg.norm(back.reshape(n, 2) - pts.reshape(n, 2), axis=1)
    h, w = nxt.shape[:2]
    inside = (fwd[:, 0] >= 0) & (fwd[:, 1] >= 0) & (fwd[:, 0] <= w - 1) & (fwd[:, 1] <= h - 1)
    ok = (st_f.ravel() == 1) & (st_b.ravel() == 1) & (fb_error <= params.fb_threshold_px) & inside
    return fwd, ok


@dataclass
class PointTracker:
    """Named points followed frame to frame.

    ``points`` maps a name to its pixel in the last frame given to :meth:`step`. :meth:`set` places or
    re-places a point (a fresh detection), :meth:`step` moves every point into the next frame and
    forgets those whose track failed, :meth:`reset` forgets all (a gap in the frames).
    """

    params: KLTParams = field(default_factory=KLTParams)
    points: dict[str, np.ndarray] = field(default_factory=dict)
    _prev: np.ndarray | None = field(default=None, repr=False)

    def reset(self) -> None:
        self.points.clear()
        self._prev = None

    def set(self, name: str, pixel: np.ndarray) -> None:
        self.points[name] = np.asarray(pixel, dtype=np.float64).copy()

    def step(self, frame: np.ndarray) -> list[str]:
        """Track every point into ``frame`` (grayscale); return the names dropped."""
        dropped: list[str] = []
        if self._prev is not None and self.points:
            names = list(self.points)
            new, ok = track_klt(self._prev, frame, np.array([self.points[n] for n in names]), self.params)
            for name, p, good in zip(names, new, ok):
                if good:
                    self.points[name] = p
                else:
                    del self.points[name]
                    dropped.append(name)
        self._prev = frame
        return dropped
