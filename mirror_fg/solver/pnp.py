"""PnP per image (Hesch et al., Sect. 4.1, eqs. 10-12): candidate composite transforms ``(A_Nv, b_Nv)``.

Base-frame fiducials (metres) and their normalized image coordinates; for an odd number of mirrors the
image is mirror-imaged, so PnP runs on the y-flipped image and the flip is put back (eqs. 11-12).
"""
from __future__ import annotations

from itertools import combinations

import cv2
import numpy as np

from mirror_fg.core.geometry import FLIP_Y, apply_transform, project, so3_exp_many

__all__ = ["pnp_candidates", "pnp_candidates_many"]

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
    """``(R, t)`` of OpenCV's ``(rvec, tvec)`` (``so3_exp_many``: the rotations of many poses at once
    are the same numbers as one's)."""
    return so3_exp_many(rvec)[0], np.asarray(tvec, dtype=np.float64).reshape(3)


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
        if not admissible:
            return []
        # the same pose from both solvers once: Frobenius distances of every pair at once
        R_all = np.array([R for R, _ in admissible])
        t_all = np.array([t for _, t in admissible])
        distance = (np.sqrt(np.sum((R_all[:, None] - R_all[None]) ** 2, axis=(2, 3)))
                    + np.sqrt(np.sum((t_all[:, None] - t_all[None]) ** 2, axis=2)))
        unique: list[int] = []
        for i in range(len(admissible)):
            if all(distance[i, j] > 1e-6 for j in unique):
                unique.append(i)
        return [admissible[i] for i in unique]
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


def _p3p_poses(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every solution ``(rvec, tvec)`` of OpenCV's P3P and AP3P (Fischler & Bolles) for three points,
    unchecked (rotation vectors: :func:`so3_exp_many` turns many into matrices at once)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    for flag in (cv2.SOLVEPNP_P3P, cv2.SOLVEPNP_AP3P):
        try:
            count, rvecs, tvecs = cv2.solveP3P(obj, img, _IDENTITY, None, flags=flag)
        except cv2.error:
            continue
        poses.extend(zip(rvecs[:count], tvecs[:count]))
    return poses


_IDENTITY = np.eye(3)


def pnp_candidates_many(
    problems: list[tuple[np.ndarray, np.ndarray]], num_mirrors: int
) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """:func:`pnp_candidates` of many images: ``(base_points, normalized)`` each, candidates each.

    Images with three fiducials are checked together (every P3P pose's reprojection and the
    duplicates of the two solvers at once); the others go one by one through :func:`pnp_candidates`.
    """
    flip = num_mirrors % 2 == 1
    results: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in problems]
    three, poses, owner = [], [], []
    for i, (base_points, normalized) in enumerate(problems):
        if len(base_points) != 3:
            results[i] = pnp_candidates(base_points, normalized, num_mirrors)
            continue
        observed = np.array(normalized, dtype=float)
        if flip:
            observed[:, 1] *= -1.0  # eq. (11)
        three.append((i, np.asarray(base_points, dtype=float), observed))
        found = _p3p_poses(three[-1][1], observed)
        poses.extend(found)
        owner.extend([len(three) - 1] * len(found))
    if not poses:
        return results
    owner_index = np.array(owner)
    R = so3_exp_many(np.array([rvec for rvec, _ in poses]))  # as cv2.Rodrigues, all at once
    t = np.array([tvec for _, tvec in poses], dtype=float).reshape(-1, 3)
    points = np.array([base for _, base, _ in three])[owner_index]
    observed_all = np.array([obs for _, _, obs in three])[owner_index]
    camera_points = np.einsum("kab,knb->kna", R, points) + t[:, None, :]  # as _reprojection_rms_many
    depth = camera_points[..., 2]
    behind = np.any(depth <= 0, axis=1)
    projected = camera_points[..., :2] / np.where(depth > 0, depth, 1.0)[..., None]
    rms = np.where(behind, np.inf, np.sqrt(np.mean(np.sum((projected - observed_all) ** 2, axis=2), axis=1)))
    admissible = np.flatnonzero(rms < 1e-3)
    # the same pose from both solvers once: distances to the image's previous poses (at most 7 back:
    # P3P and AP3P give up to four each), one offset at a time
    R_ok, t_ok, owner_ok = R[admissible], t[admissible], owner_index[admissible]
    back = np.full((len(admissible), 8), np.inf)
    for d in range(1, min(8, len(admissible))):
        same_image = owner_ok[d:] == owner_ok[:-d]
        distance = (np.sqrt(np.sum((R_ok[d:] - R_ok[:-d]) ** 2, axis=(1, 2)))
                    + np.sqrt(np.sum((t_ok[d:] - t_ok[:-d]) ** 2, axis=1)))
        back[d:, d] = np.where(same_image, distance, np.inf)
    back_rows = back.tolist()
    unique: dict[int, list[int]] = {}
    for row, k in enumerate(admissible.tolist()):
        kept = unique.setdefault(owner[k], [])
        if all(back_rows[row][row - j] > 1e-6 for j in kept):
            kept.append(row)
    for j, (i, _, _) in enumerate(three):
        candidates = [(R_ok[row], t_ok[row]) for row in unique.get(j, [])]
        if flip:
            candidates = [(FLIP_Y @ R_k, FLIP_Y @ t_k) for R_k, t_k in candidates]  # eq. (12)
        results[i] = candidates
    return results
