"""PnP per image (Hesch et al., Sect. 4.1, eqs. 10-12): candidate composite transforms ``(A_Nv, b_Nv)``.

Base-frame fiducials (metres) and their normalized image coordinates; for an odd number of mirrors the
image is mirror-imaged, so PnP runs on the y-flipped image and the flip is put back (eqs. 11-12).
"""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from itertools import combinations, islice
from typing import TypeVar

import cv2
import numpy as np

from mirror_fg.core.geometry import FLIP_Y, so3_exp_many

__all__ = ["pnp_candidates", "pnp_candidates_many", "pnp_minima", "pnp_starts", "first_of_each", "first_of_each_grouped", "is_planar",
           "lowest_reprojection", "reprojection_rms_many", "solved_in_threads", "PNP_CRITERIA", "PNP_THREADS"]

#: Two refined poses are the same minimum when their rotations (entries) and translations (relative)
#: differ by less than this (LM stops up to ~1e-4 apart in a shallow twin's valley); a planar target's twin
#: differs by about its viewing angle's change (>= 1e-2).
SAME_MINIMUM = 1e-3
#: Two solvers' starts this close (same measure) lie in one basin: only the better one is refined.
SAME_BASIN = 1e-3
#: OpenCV LM's stop (iterations, error change) for every refinement of the search.
PNP_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)


#: Threads that run the PnP of many images side by side: OpenCV releases Python's lock inside each solver,
#: so two images' solvers run at once on two cores (the Python around them still takes turns).
PNP_THREADS = max(1, min(4, os.cpu_count() or 1))
#: Fewer problems than this are solved in the calling thread (a pool costs more than it gains).
THREADED_FROM = 64

_Item = TypeVar("_Item")
_Answer = TypeVar("_Answer")


def solved_in_threads(solve: Callable[[_Item], _Answer], problems: Sequence[_Item]) -> list[_Answer]:
    """``[solve(p) for p in problems]``, in order, the problems in :data:`PNP_THREADS` contiguous runs solved
    side by side (each answer depends on its problem alone: the same answers as one at a time)."""
    if PNP_THREADS < 2 or len(problems) < THREADED_FROM:
        return [solve(p) for p in problems]
    bounds = np.linspace(0, len(problems), PNP_THREADS + 1).round().astype(int).tolist()
    with ThreadPoolExecutor(PNP_THREADS) as pool:
        runs = pool.map(lambda a_b: [solve(p) for p in problems[a_b[0]:a_b[1]]], zip(bounds[:-1], bounds[1:]))
        return [answer for run in runs for answer in run]


def reprojection_rms_many(R: np.ndarray, t: np.ndarray, base_points: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """RMS reprojection error (normalized coordinates) of base points (N, 3) under each pose ``(R[k], t[k])``
    (eqs. 2, 9); inf where a point is behind the camera."""
    camera_points = np.asarray(base_points, dtype=float) @ np.transpose(R, (0, 2, 1)) + t[:, None, :]
    depth = camera_points[..., 2]
    behind = np.any(depth <= 0, axis=1)
    projected = camera_points[..., :2] / camera_points[..., 2:3]
    rms = np.sqrt(np.mean(np.sum((projected - normalized) ** 2, axis=2), axis=1))
    return np.where(behind, np.inf, rms)


def _pnp_rotation_candidates(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """All admissible rigid poses (R, t) explaining normalized observations of base points (eq. 10)."""
    if len(base_points) == 3:  # up to four P3P solutions (Fischler & Bolles); every admissible one
        return _p3p_candidates_many([(base_points, normalized)])[0]
    minima = _pnp_minima(base_points, normalized)
    return minima[:1]


def _pnp_minima(base_points: np.ndarray, normalized: np.ndarray, collinear_p3p: bool = True,
                planar: bool | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The distinct local minima (R, t) of the reprojection error of >= 4 points (eq. 10), lowest first:
    the starts of several solvers, each refined by LM (SQPnP alone can be wrong, STYLE.md). The rotations
    of all starts, and of all refined poses, are formed at once (``so3_exp_many``), and which start lies
    in which basin is decided from one table of distances (:func:`_near_table`). ``collinear_p3p``
    False: no P3P start from three points on one line (:func:`pnp_minima`). ``planar``: whether the points
    lie on one plane, when the caller knows (else judged here)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    K = _IDENTITY
    rvecs_all, tvecs_all, _ = pnp_starts(base_points, normalized, collinear_p3p, planar)
    if not rvecs_all:
        return []
    R_starts = so3_exp_many(np.array([np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs_all]))
    t_starts = np.array([np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs_all])
    # Starts of one basin (the solvers agree on a clear view) are refined once, from the first of them.
    chosen = first_of_each(R_starts, t_starts, SAME_BASIN)
    refined_r, refined_t = [], []
    for k in chosen:
        rvec = cv2.Rodrigues(R_starts[k])[0]
        tvec = t_starts[k].reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, criteria=PNP_CRITERIA)
        except cv2.error:
            pass
        refined_r.append(np.asarray(rvec, dtype=np.float64).reshape(3))
        refined_t.append(np.asarray(tvec, dtype=np.float64).reshape(3))
    R_ref = so3_exp_many(np.array(refined_r))
    t_ref = np.array(refined_t)
    errors = reprojection_rms_many(R_ref, t_ref, base_points, normalized).tolist()
    finite = [k for k in range(len(chosen)) if np.isfinite(errors[k])]
    order = sorted(finite, key=lambda k: errors[k])  # stable: as the list of (error, R, t) sorted by error
    if not order:
        return []
    R_sorted, t_sorted = R_ref[order], t_ref[order]
    # the same minimum reached from several starts once
    return [(R_sorted[k], t_sorted[k]) for k in first_of_each(R_sorted, t_sorted, SAME_MINIMUM)]


def pnp_starts(base_points: np.ndarray, normalized: np.ndarray, collinear_p3p: bool = True, planar: bool | None = None,
               spread: np.ndarray | None = None) -> tuple[list[np.ndarray], list[np.ndarray], list[tuple[int, ...] | None]]:
    """The starts of :func:`_pnp_minima`'s search, in its order: each solver's poses ``(rvec, tvec)`` (OpenCV's
    SQPnP, EPnP, ITERATIVE, a planar target's IPPE), then P3P's of the first four triples of fiducials, with
    the triple each P3P pose solves (None for the others). ``spread``: the fiducials' centred singular values
    (descending), when the caller has them (ITERATIVE is not asked where OpenCV refuses it: fewer than six
    fiducials off a plane)."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    rvecs_all: list[np.ndarray] = []
    tvecs_all: list[np.ndarray] = []
    triples: list[tuple[int, ...] | None] = []
    if spread is None:
        spread = np.linalg.svd(base_points - base_points.mean(axis=0), compute_uv=False)
    flags = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP]
    # OpenCV's ITERATIVE takes the fiducials as planar where its scatter's eigenvalues fall below 1e-3 of the
    # next (a homography), else it needs six (DLT): ten times clear of that, it would refuse
    if len(base_points) >= 6 or spread[2] ** 2 < 1e-2 * spread[1] ** 2:
        flags.append(cv2.SOLVEPNP_ITERATIVE)
    if planar if planar is not None else bool(spread[2] < 1e-9 * max(1.0, np.abs(base_points - base_points.mean(axis=0)).max())):
        flags.append(cv2.SOLVEPNP_IPPE)  # both of a planar target's poses (its twin)
    for flag in flags:
        try:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, _IDENTITY, None, flags=flag)
        except cv2.error:
            continue
        if ok:
            rvecs_all.extend(rvecs)
            tvecs_all.extend(tvecs)
            triples.extend([None] * len(rvecs))
    for triple, index in _first_triples(len(base_points)):
        if not collinear_p3p and _collinear(base_points[index]):
            continue
        try:
            count, rvecs, tvecs = cv2.solveP3P(obj[index], img[index], _IDENTITY, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        rvecs_all.extend(rvecs[:count])
        tvecs_all.extend(tvecs[:count])
        triples.extend([triple] * count)
    return rvecs_all, tvecs_all, triples


@lru_cache(maxsize=64)
def _first_triples(count: int) -> tuple[tuple[tuple[int, ...], np.ndarray], ...]:
    """The search's triples of ``count`` fiducials (the first four), each with its index array."""
    # not list(combinations(...)): C(70, 3) tuples cost 3 ms
    return tuple((triple, np.array(triple)) for triple in islice(combinations(range(count), 3), 4))


def _planar_minima(base_points: np.ndarray, normalized: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """A planar target's minima: IPPE's two poses, each refined by LM, lowest first."""
    obj = np.ascontiguousarray(base_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(normalized, dtype=np.float64).reshape(-1, 1, 2)
    try:
        ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, _IDENTITY, None, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        ok = False
    if not ok or not len(rvecs):
        return _pnp_minima(base_points, normalized, False, True)
    refined_r, refined_t = [], []
    for rvec, tvec in zip(rvecs, tvecs):
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, _IDENTITY, None, rvec.copy(), tvec.copy(), criteria=PNP_CRITERIA)
        except cv2.error:
            pass
        refined_r.append(np.asarray(rvec, dtype=np.float64).reshape(3))
        refined_t.append(np.asarray(tvec, dtype=np.float64).reshape(3))
    R_ref, t_ref = so3_exp_many(np.array(refined_r)), np.array(refined_t)
    errors = reprojection_rms_many(R_ref, t_ref, base_points, normalized).tolist()
    order = sorted((k for k in range(len(errors)) if np.isfinite(errors[k])), key=lambda k: errors[k])
    if not order:
        return _pnp_minima(base_points, normalized, False, True)
    R_sorted, t_sorted = R_ref[order], t_ref[order]
    return [(R_sorted[k], t_sorted[k]) for k in first_of_each(R_sorted, t_sorted, SAME_MINIMUM)]


def is_planar(base_points: np.ndarray) -> bool:
    """Whether fiducials (N, 3) lie on one plane, relative to their spread (IPPE then gives both of the
    target's poses)."""
    centered = base_points - base_points.mean(axis=0)
    return bool(np.linalg.svd(centered, compute_uv=False)[2] < 1e-9 * max(1.0, np.abs(centered).max()))


def _collinear(points: np.ndarray) -> bool:
    """Whether three points (3, 3) lie on one line (relative to their spread): P3P's pose is then
    undetermined by a turn about it."""
    (ax, ay, az), (bx, by, bz), (cx, cy, cz) = np.asarray(points, dtype=float).tolist()
    ux, uy, uz, wx, wy, wz = bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az  # (numpy's cross costs 50 us)
    cross = (uy * wz - uz * wy) ** 2 + (uz * wx - ux * wz) ** 2 + (ux * wy - uy * wx) ** 2
    return cross <= 1e-18 * (ux * ux + uy * uy + uz * uz) * (wx * wx + wy * wy + wz * wz)  # |u x w| <= 1e-9 |u| |w|


def first_of_each(R: np.ndarray, t: np.ndarray, tolerance: float) -> list[int]:
    """Indices of the poses ``(R[k], t[k])`` kept when each is kept unless it is near one kept before it
    (rotations within ``tolerance`` entry-wise, translations within ``tolerance`` relative to its own)."""
    table = _near_table(R, t, tolerance)
    if np.count_nonzero(table) == len(table) and table.diagonal().all():  # each near itself alone: all kept
        return list(range(len(table)))
    kept: list[int] = []
    for k, near in enumerate(table.tolist()):
        if not any(near[j] for j in kept):
            kept.append(k)
    return kept


def first_of_each_grouped(R: np.ndarray, t: np.ndarray, owner: np.ndarray, tolerance: float) -> np.ndarray:
    """:func:`first_of_each` of every group of poses at once: ``owner`` (S,) the group of each pose
    ``(R[k], t[k])``, a group's poses contiguous; the indices (into all S poses, ascending) kept, each pose
    compared with the poses before it in its own group (``_near_table``'s test), those ``d`` back for one
    ``d`` at a time."""
    count = len(owner)
    if not count:
        return np.zeros(0, dtype=int)
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    sizes = np.diff(np.r_[starts, count])
    slot = np.arange(count) - np.repeat(starts, sizes)  # each pose's place in its group
    entries = R.reshape(count, 9)
    scale = np.maximum(np.sqrt(np.einsum("ij,ij->i", t, t)), 1e-12)
    width = int(sizes.max())
    near_back = np.zeros((count, width), dtype=bool)  # [k, d]: pose k is near pose k - d of its group
    for d in range(1, width):
        later = slot[d:] >= d  # pose k - d is in k's group
        rotation = np.abs(entries[d:] - entries[:-d]).max(axis=1)
        difference = t[d:] - t[:-d]
        translation = np.sqrt(np.einsum("ij,ij->i", difference, difference))
        near_back[d:, d] = later & (rotation <= tolerance) & (translation <= tolerance * scale[d:])
    kept = np.zeros(count, dtype=bool)
    for k in range(width):  # as first_of_each: kept unless near one kept before it in its group
        at = np.flatnonzero(slot == k)
        back = at[:, None] - np.arange(width)[None, :]
        earlier_kept = kept[np.maximum(back, 0)] & (np.arange(width)[None, :] >= 1) & (back >= 0)
        kept[at] = ~np.any(near_back[at] & earlier_kept, axis=1)
    return np.flatnonzero(kept)


def _near_table(R: np.ndarray, t: np.ndarray, tolerance: float) -> np.ndarray:
    """``near[k][j]``: pose k is within ``tolerance`` of pose j (rotation entries; translation relative to
    pose k's) -- all pairs at once."""
    entries = R.reshape(len(R), 9)
    rotation = np.abs(entries[:, None, :] - entries[None, :, :]).max(axis=2)
    scale = np.maximum(np.sqrt(np.einsum("ij,ij->i", t, t)), 1e-12)
    difference = t[:, None] - t[None, :]
    translation = np.sqrt(np.einsum("ijk,ijk->ij", difference, difference))
    return (rotation <= tolerance) & (translation <= tolerance * scale[:, None])


def pnp_minima(base_points: np.ndarray, normalized: np.ndarray, num_mirrors: int, collinear_p3p: bool = True,
               planar: bool | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every distinct local minimum ``(A_Nv, b_Nv)`` of the reprojection error of one image's >= 4
    fiducials (eqs. 5, 10-12), lowest first; the first is :func:`pnp_candidates`'. A small planar target
    far away has two minima that fit about equally (IPPE's twin poses): the caller tells them apart.

    ``collinear_p3p`` False: none of the P3P starts from three points on one line (a chessboard's first
    row, in a dataset's order: P3P leaves the turn about the line free, so these starts are arbitrary
    poses): about half the cost on a board, and the same lowest minimum on every board measured
    (``tests/test_pnp_collinear.py``); the search then misses some of the further, shallow minima of a far,
    noisy board that those arbitrary starts fall into. For a caller that needs the lowest minimum only."""
    if planar and not collinear_p3p:
        return _with_parity(_planar_minima, base_points, normalized, num_mirrors)
    return _with_parity(lambda points, observed: _pnp_minima(points, observed, collinear_p3p, planar), base_points,
                        normalized, num_mirrors)


def pnp_candidates(base_points: np.ndarray, normalized: np.ndarray, num_mirrors: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate composite transforms ``(A_Nv, b_Nv)`` of one image (eqs. 5, 10-12).

    base_points: (N, 3) fiducials, base frame, metres; normalized: (N, 2) their normalized image
    coordinates. For odd Nv the image is flipped in y so PnP sees a rotation (eq. 11), then
    ``A = F R``, ``b = F t`` (eq. 12). Three points give up to four candidates, four or more give one.
    """
    return _with_parity(_pnp_rotation_candidates, base_points, normalized, num_mirrors)


def _with_parity(solver, base_points: np.ndarray, normalized: np.ndarray, num_mirrors: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``solver``'s rigid poses of the (for odd Nv y-flipped, eq. 11) image as ``(A_Nv, b_Nv)`` (eq. 12)."""
    flip = num_mirrors % 2 == 1
    observed = np.array(normalized, dtype=float)
    if flip:
        observed[:, 1] *= -1.0  # eq. (11)
    candidates = solver(np.asarray(base_points, dtype=float), observed)
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


def _p3p_candidates_many(problems: list[tuple[np.ndarray, np.ndarray]]) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Every admissible pose ``(R, t)`` (each fiducial in front, reprojected to < 1e-3) of OpenCV's P3P and
    AP3P for each three-point problem ``(base_points, normalized)``, the same pose from both solvers once;
    all problems checked together."""
    results: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in problems]
    poses, owner = [], []
    for j, found in enumerate(solved_in_threads(lambda problem: _p3p_poses(*problem), problems)):
        poses.extend(found)
        owner.extend([j] * len(found))
    if not poses:
        return results
    owner_index = np.array(owner)
    R = so3_exp_many(np.array([rvec for rvec, _ in poses]))  # as cv2.Rodrigues, all at once
    t = np.array([tvec for _, tvec in poses], dtype=float).reshape(-1, 3)
    points = np.array([np.asarray(base, dtype=float) for base, _ in problems])[owner_index]
    observed = np.array([np.asarray(obs, dtype=float) for _, obs in problems])[owner_index]
    camera_points = np.einsum("kab,knb->kna", R, points) + t[:, None, :]
    depth = camera_points[..., 2]
    behind = np.any(depth <= 0, axis=1)
    projected = camera_points[..., :2] / np.where(depth > 0, depth, 1.0)[..., None]
    rms = np.where(behind, np.inf, np.sqrt(np.mean(np.sum((projected - observed) ** 2, axis=2), axis=1)))
    admissible = np.flatnonzero(rms < 1e-3)
    # the same pose from both solvers once: distances to the problem's previous poses (at most 7 back:
    # P3P and AP3P give up to four each), one offset at a time
    R_ok, t_ok, owner_ok = R[admissible], t[admissible], owner_index[admissible]
    back = np.full((len(admissible), 8), np.inf)
    for d in range(1, min(8, len(admissible))):
        same_problem = owner_ok[d:] == owner_ok[:-d]
        distance = (np.sqrt(np.sum((R_ok[d:] - R_ok[:-d]) ** 2, axis=(1, 2)))
                    + np.sqrt(np.sum((t_ok[d:] - t_ok[:-d]) ** 2, axis=1)))
        back[d:, d] = np.where(same_problem, distance, np.inf)
    back_rows = back.tolist()
    unique: dict[int, list[int]] = {}
    for row, k in enumerate(admissible.tolist()):
        kept = unique.setdefault(owner[k], [])
        if all(back_rows[row][row - j] > 1e-6 for j in kept):
            kept.append(row)
    for j in range(len(problems)):
        results[j] = [(R_ok[row], t_ok[row]) for row in unique.get(j, [])]
    return results


def pnp_candidates_many(
    problems: list[tuple[np.ndarray, np.ndarray]], num_mirrors: int
) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """:func:`pnp_candidates` of many images: ``(base_points, normalized)`` each, candidates each.

    Images with three fiducials are solved and checked together (:func:`_p3p_candidates_many`); the
    others go one by one through :func:`pnp_candidates`.
    """
    flip = num_mirrors % 2 == 1
    results: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in problems]
    three: list[int] = []
    three_problems: list[tuple[np.ndarray, np.ndarray]] = []
    for i, (base_points, normalized) in enumerate(problems):
        if len(base_points) != 3:
            results[i] = pnp_candidates(base_points, normalized, num_mirrors)
            continue
        observed = np.array(normalized, dtype=float)
        if flip:
            observed[:, 1] *= -1.0  # eq. (11)
        three.append(i)
        three_problems.append((np.asarray(base_points, dtype=float), observed))
    for i, candidates in zip(three, _p3p_candidates_many(three_problems)):
        if flip:
            candidates = [(FLIP_Y @ R_k, FLIP_Y @ t_k) for R_k, t_k in candidates]  # eq. (12)
        results[i] = candidates
    return results


def lowest_reprojection(candidates, points: np.ndarray, normalized: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The candidate map ``(A, b)`` (eq. 5) that puts ``points`` in front of the camera and reprojects them
    closest to ``normalized`` (squared error, eq. 10), or None where none is in front."""
    best, best_error = None, np.inf
    for A, b in candidates:
        x = points @ A.T + b
        if np.any(x[:, 2] <= 0):
            continue
        error = float(np.sum((x[:, :2] / x[:, 2:3] - normalized) ** 2))
        if error < best_error:
            best, best_error = (A, b), error
    return best
