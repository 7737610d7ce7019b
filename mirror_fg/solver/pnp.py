"""PnP per image (Hesch et al., Sect. 4.1, eqs. 10-12): candidate composite transforms ``(A_Nv, b_Nv)``.

Base-frame fiducials (metres) and their normalized image coordinates; for an odd number of mirrors the
image is mirror-imaged, so PnP runs on the y-flipped image and the flip is put back (eqs. 11-12).
"""
from __future__ import annotations

from itertools import combinations

import cv2
import numpy as np

from mirror_fg.core.geometry import FLIP_Y, apply_transform, project

__all__ = ["pnp_candidates"]

_PNP_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def _reprojection_rms(R: np.ndarray, t: np.ndarray, base_points: np.ndarray, normalized: np.ndarray) -> float:
    camera_points = apply_transform(R, t, base_points)
    if np.any(camera_points[:, 2] <= 0):
        return np.inf
    return float(np.sqrt(np.mean(np.sum((project(camera_points) - normalized) ** 2, axis=1))))


def _reprojection_rms_many(
    poses: list[tuple[np.ndarray, np.ndarray]], base_points: np.ndarray, normalized: np.ndarray
) -> np.ndarray:
    """:func:`_reprojection_rms` of several poses at once (inf for a pose with a point behind the camera)."""
    if not poses:
        return np.zeros(0)
    R = np.array([R for R, _ in poses])
    t = np.array([t for _, t in poses])
    camera_points = np.einsum("kab,nb->kna", R, base_points) + t[:, None, :]
    depth = camera_points[..., 2]
    behind = np.any(depth <= 0, axis=1)
    projected = camera_points[..., :2] / np.where(depth > 0, depth, 1.0)[..., None]
    rms = np.sqrt(np.mean(np.sum((projected - normalized) ** 2, axis=2), axis=1))
    return np.where(behind, np.inf, rms)


def _pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0], np.asarray(tvec, dtype=np.float64).reshape(3)


def _pnp_rotation_candidates(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """All admissible rigid poses (R, t) explaining normalized observations of base points (eq. 10)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    K = np.eye(3)
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    if len(base_points) == 3:
        # Up to four P3P solutions (Fischler & Bolles); every admissible one is a candidate.
        for flag in (cv2.SOLVEPNP_P3P, cv2.SOLVEPNP_AP3P):
            try:
                count, rvecs, tvecs = cv2.solveP3P(obj, img, K, None, flags=flag)
            except cv2.error:
                continue
            for i in range(count):
                poses.append(_pose_from_rvec(rvecs[i], tvecs[i]))
        admissible = [pose for pose, rms in zip(poses, _reprojection_rms_many(poses, base_points, normalized)) if rms < 1e-3]
        unique: list[tuple[np.ndarray, np.ndarray]] = []
        for R, t in admissible:
            if all(np.linalg.norm(R - R2) + np.linalg.norm(t - t2) > 1e-6 for R2, t2 in unique):
                unique.append((R, t))
        return unique
    # >= 4 points: one pose. SQPnP alone can be wrong (STYLE.md), so refine the candidates of several
    # solvers with LM and keep the one with the lowest reprojection error.
    flags = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE]
    centered = base_points - base_points.mean(axis=0)
    if np.linalg.svd(centered, compute_uv=False)[2] < 1e-9 * max(1.0, np.abs(centered).max()):
        flags.append(cv2.SOLVEPNP_IPPE)
    for flag in flags:
        try:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=flag)
        except cv2.error:
            continue
        if ok:
            poses.extend(_pose_from_rvec(r, t) for r, t in zip(rvecs, tvecs))
    for triple in list(combinations(range(len(base_points)), 3))[:4]:
        try:
            count, rvecs, tvecs = cv2.solveP3P(obj[list(triple)], img[list(triple)], K, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        poses.extend(_pose_from_rvec(rvecs[i], tvecs[i]) for i in range(count))
    best, best_error = None, np.inf
    for R, t in poses:
        rvec = cv2.Rodrigues(R)[0]
        tvec = t.reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, criteria=_PNP_CRITERIA)
        except cv2.error:
            pass
        R_ref, t_ref = _pose_from_rvec(rvec, tvec)
        error = _reprojection_rms(R_ref, t_ref, base_points, normalized)
        if error < best_error:
            best, best_error = (R_ref, t_ref), error
    return [] if best is None or not np.isfinite(best_error) else [best]


def pnp_candidates(base_points: np.ndarray, normalized: np.ndarray, num_mirrors: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate composite transforms ``(A_Nv, b_Nv)`` of one image (eqs. 5, 10-12).

    base_points: (N, 3) fiducials, base frame, metres; normalized: (N, 2) their normalized image
    coordinates. For odd Nv the image is flipped in y so PnP sees a rotation (eq. 11), then
    ``A = F R``, ``b = F t`` (eq. 12). Three points give up to four candidates, four or more give one.
    """
    flip = num_mirrors % 2 == 1
    observed = np.array(normalized, dtype=float)
    if flip:
        observed[:, 1] *= -1.0  # eq. (11)
    candidates = _pnp_rotation_candidates(np.asarray(base_points, dtype=float), observed)
    if flip:
        candidates = [(FLIP_Y @ R, FLIP_Y @ t) for R, t in candidates]  # eq. (12)
    return candidates
