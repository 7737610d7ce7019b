"""The per-image PnP minima (``solver/start/pnp.py``) are those of the one-start-at-a-time search they replace:
the same poses, in the same order, on random problems of 4-8 points, planar and not, with noise."""
from __future__ import annotations

from itertools import combinations, islice

import cv2
import numpy as np
import pytest

from mirror_fg.core.geometry import apply_transform, project, so3_exp_many
from mirror_fg.solver.start.pnp import SAME_BASIN, SAME_MINIMUM, _pnp_minima

_PNP_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)


# The search one start at a time, as solver/start/pnp.py had it: the reference.
def _reprojection_rms(R, t, base_points, normalized):
    camera_points = apply_transform(R, t, base_points)
    if np.any(camera_points[:, 2] <= 0):
        return np.inf
    return float(np.sqrt(np.mean(np.sum((project(camera_points) - normalized) ** 2, axis=1))))


def _pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of OpenCV's ``(rvec, tvec)`` (``so3_exp_many``: the rotations of many poses at once
    are the same numbers as one's)."""
    return so3_exp_many(rvec)[0], np.asarray(tvec, dtype=np.float64).reshape(3)


def _reference_minima(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The distinct local minima (R, t) of the reprojection error of >= 4 points (eq. 10), lowest first:
    the starts of several solvers, each refined by LM (SQPnP alone can be wrong, STYLE.md)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    K = np.eye(3)
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    flags = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE]
    centered = base_points - base_points.mean(axis=0)
    if np.linalg.svd(centered, compute_uv=False)[2] < 1e-9 * max(1.0, np.abs(centered).max()):
        flags.append(cv2.SOLVEPNP_IPPE)  # both of a planar target's poses (its twin)
    for flag in flags:
        try:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=flag)
        except cv2.error:
            continue
        if ok:
            poses.extend(_pose_from_rvec(r, t) for r, t in zip(rvecs, tvecs))
    for triple in islice(combinations(range(len(base_points)), 3), 4):  # not list(): C(70, 3) tuples cost 3 ms
        try:
            count, rvecs, tvecs = cv2.solveP3P(obj[list(triple)], img[list(triple)], K, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        poses.extend(_pose_from_rvec(rvecs[i], tvecs[i]) for i in range(count))
    # Starts of one basin (the solvers agree on a clear view) are refined once, from the first of them.
    refined: list[tuple[float, np.ndarray, np.ndarray]] = []
    chosen = _Poses()
    for R, t in poses:
        if chosen.near(R, t, SAME_BASIN):
            continue
        chosen.add(R, t)
        rvec = cv2.Rodrigues(R)[0]
        tvec = t.reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, criteria=_PNP_CRITERIA)
        except cv2.error:
            pass
        R_ref, t_ref = _pose_from_rvec(rvec, tvec)
        error = _reprojection_rms(R_ref, t_ref, base_points, normalized)
        if np.isfinite(error):
            refined.append((error, R_ref, t_ref))
    refined.sort(key=lambda entry: entry[0])
    minima = _Poses()
    for _, R, t in refined:  # the same minimum reached from several starts once
        if not minima.near(R, t, SAME_MINIMUM):
            minima.add(R, t)
    return minima.poses


class _Poses:
    """Poses kept so far, and whether a pose is near one of them: rotations (entries) and translations
    (relative) both within a tolerance."""

    def __init__(self) -> None:
        self.poses: list[tuple[np.ndarray, np.ndarray]] = []
        self._R = np.zeros((0, 3, 3))
        self._t = np.zeros((0, 3))

    def add(self, R: np.ndarray, t: np.ndarray) -> None:
        self.poses.append((R, t))
        self._R = np.concatenate([self._R, R[None]])
        self._t = np.concatenate([self._t, t[None]])

    def near(self, R: np.ndarray, t: np.ndarray, tolerance: float) -> bool:
        if not self.poses:
            return False
        scale = max(float(np.linalg.norm(t)), 1e-12)
        close = (np.abs(self._R - R).max(axis=(1, 2)) <= tolerance) & (
            np.linalg.norm(self._t - t, axis=1) <= tolerance * scale)
        return bool(close.any())




def _problem(rng: np.random.Generator, count: int, planar: bool, noise: float):
    """Base points (N, 3) of a target in front of a camera and their noisy normalized coordinates."""
    points = rng.uniform(-0.15, 0.15, (count, 3))
    if planar:
        points[:, 2] = 0.0
    R = so3_exp_many(rng.normal(size=3) * rng.uniform(0.0, 1.2))[0]
    t = np.array([*rng.uniform(-0.2, 0.2, 2), rng.uniform(0.4, 3.0)])
    camera = points @ R.T + t
    normalized = camera[:, :2] / camera[:, 2:3] + rng.normal(scale=noise, size=(count, 2))
    return points, normalized


def _same(problems):
    for points, normalized in problems:
        new, old = _pnp_minima(points, normalized), _reference_minima(points, normalized)
        assert len(new) == len(old)
        for (R_new, t_new), (R_old, t_old) in zip(new, old):
            assert np.array_equal(R_new, R_old) and np.array_equal(t_new, t_old)


@pytest.mark.parametrize("planar", [False, True])
def test_minima_as_one_start_at_a_time(planar):
    rng = np.random.default_rng(1 if planar else 2)
    _same(_problem(rng, int(rng.integers(4, 9)), planar, float(rng.choice([0.0, 1e-3, 1e-2])))
          for _ in range(150))


@pytest.mark.slow
def test_minima_as_one_start_at_a_time_thousands():
    rng = np.random.default_rng(3)
    _same(_problem(rng, int(rng.integers(4, 9)), bool(rng.integers(2)), float(rng.choice([0.0, 1e-4, 1e-3, 1e-2, 3e-2])))
          for _ in range(4000))
