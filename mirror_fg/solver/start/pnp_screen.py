"""The screen's PnP minima of many images at once (Sect. 4.1, eq. 10): the minima the full search
(:func:`~mirror_fg.solver.start.pnp.pnp_minima`) would let the screen keep, from fewer refinements.

The full search refines each of its ~10 starts (:func:`~mirror_fg.solver.start.pnp.pnp_starts`) with
OpenCV's LM, a fixed cost of ~70 us a call; on a clear view all of them end at one minimum. Here the starts
of every image are formed and judged together (numpy, all images at once), each image's lowest-cost start
is refined, and every other start is refined too unless it is vouched for:

- a start in that minimum's basin: one Gauss-Newton step from it, with the minimum's Jacobian, lands within
  ``CONTRACTION`` of its distance from the minimum (both measured as whitened residual changes);
- a P3P start far from every pose the screen keeps: a pose the screen keeps (the lowest minimum or one
  ``relevant_cost`` above it, ``consensus.TWIN_COST_GAP``) puts each fiducial within
  ``b = sqrt(c0 + relevant_cost)`` sigma, so it nearly solves the start's three fiducials and lies near
  that P3P solution, where the other fiducials' errors are those of the pose give or take
  ``|J_O J_T^-1| b sqrt(3)`` (linearised: ``J_T`` the three fiducials' Jacobian, ``J_O`` the others');
  an other fiducial missing by more than ``b`` plus that (``MISS_MARGIN`` times) leaves no kept pose there.

The image's minima are then those of the refined starts, sorted and merged as the full search does (on a
clear view: the lowest alone, one LM call). Only where that minimum is well determined: its cost's
ellipsoid ``|J d|^2 <= c0 + relevant_cost`` reaches no further than ``ELLIPSOID_REACH`` and the steps from
twice its ends contract too; else (a far, small target's flat valley of twins), and for a planar target
(IPPE's twin), the full search as before, the same numbers.

``tests/test_pnp_screen.py`` compares with the full search on thousands of random and adversarial views
(far, noisy, nearly flat or on a line, a rig's target, boards): polished by an independent least squares,
the lowest minimum and the twins the screen keeps are the same; the full search's other "twins" there are
its LM's early stops, the lowest minimum again. Estimates of whole calibrations (rigs, kaleidoscopes,
mixed views, the examples) move by at most ~5e-11 relative: a different start of the same minimum.

Frames and units: base-frame fiducials (metres), normalized image coordinates, whitened by ``sigma``; the
search sees rigid poses ``(R, t)`` (an odd number of mirrors flips the image in y, eq. 11, and the pose
back, eq. 12).
"""
from __future__ import annotations

import cv2
import numpy as np

from mirror_fg.core.geometry import FLIP_Y, so3_exp_many
from mirror_fg.solver.start.pnp import (PNP_CRITERIA, SAME_BASIN, SAME_MINIMUM, first_of_each, first_of_each_grouped,
                                        pnp_minima, pnp_starts, reprojection_rms_many, solved_in_threads)

__all__ = ["screen_minima_many", "CONTRACTION", "MISS_MARGIN", "ELLIPSOID_REACH"]

#: A start is in the lowest minimum's basin when a Gauss-Newton step from it (the minimum's Jacobian) misses
#: the minimum by at most this fraction of its distance (whitened residual change, the Jacobian's range).
CONTRACTION = 0.5
#: A P3P start's other fiducial must miss by ``b`` plus this many times what the triple's error can move it.
MISS_MARGIN = 1.0
#: The lowest minimum's cost ellipsoid reaches at most this far (radians; translations relative to depth).
ELLIPSOID_REACH = 0.2

Pose = tuple[np.ndarray, np.ndarray]


def _whitened(R: np.ndarray, t: np.ndarray, points: np.ndarray, observed: np.ndarray, sigma: np.ndarray,
              with_jacobian: bool = True):
    """Whitened residuals (M, N, 2) of ``points`` (M, N, 3) under poses ``(R, t)`` ((M, 3, 3), (M, 3)) against
    ``observed`` (M, N, 2) (eqs. 2, 9), their Jacobians (M, N, 2, 6) in a left turn and a shift ``(w, v)``
    (``R <- exp(w) R``, ``t <- t + v``; None without ``with_jacobian``) and the depths (M, N)."""
    turned = np.einsum("mab,mnb->mna", R, points)
    camera = turned + t[:, None, :]
    depth = camera[..., 2]
    safe = np.where(depth > 0, depth, 1.0)
    projected = camera[..., :2] / safe[..., None]
    if not with_jacobian:
        return (projected - observed) / sigma, None, depth
    # row a of d(x/z, y/z)/dX: e_a - (x/z, y/z)_a e_z over z; times dX/dw = -[R p]x: (R p) x row, dX/dv = I
    rows = np.zeros(camera.shape[:2] + (2, 3))
    rows[..., 0, 0] = rows[..., 1, 1] = 1.0
    rows[..., :, 2] = -projected
    rows /= (safe[..., None, None] * sigma[:, None])
    jacobian = np.concatenate([np.cross(turned[..., None, :], rows), rows], axis=-1)
    return (projected - observed) / sigma, jacobian, depth


def _so3_log_many(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-angle vectors (M, 3) of rotations (M, 3, 3) by less than pi, and their angles (M,)."""
    angle = np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sine = np.sin(angle)
    scale = np.where(angle < 1e-8, 0.5, angle / (2.0 * np.where(sine > 1e-12, sine, 1.0)))
    return scale[:, None] * axis, angle


def _finite(*arrays: np.ndarray) -> np.ndarray:
    """Per leading index: every entry of every array finite."""
    ok = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        ok &= np.all(np.isfinite(a), axis=tuple(range(1, a.ndim)))
    return ok


def _vouched(points: np.ndarray, observed: np.ndarray, sigma: np.ndarray, relevant_cost: float,
             R0: np.ndarray, t0: np.ndarray, R_start: np.ndarray, t_start: np.ndarray, owner: np.ndarray,
             triples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For images (``points`` (M, N, 3), ``observed`` (M, N, 2)) with lowest-cost refined start ``(R0, t0)``
    and their other starts ``(R_start, t_start)`` of image ``owner`` (``triples`` (S, 3): a P3P start's three
    fiducials, -1 for the solvers'): whether each image's minimum is well determined (M,) and whether each
    start is vouched for (S,) (module docstring)."""
    count = len(points)
    residual, jacobian, depth = _whitened(R0, t0, points, observed, sigma)
    ok = np.all(depth > 0, axis=1) & _finite(residual, jacobian)
    residual, jacobian = np.where(ok[:, None, None], residual, 0.0), np.where(ok[:, None, None, None], jacobian, 1.0)
    cost = np.sum(residual**2, axis=(1, 2))
    reach = np.sqrt(cost + relevant_cost)  # b: the largest whitened error of one fiducial under a kept pose
    J = jacobian.reshape(count, -1, 6)
    _, singular, vt = np.linalg.svd(J, full_matrices=False)
    ok &= singular[:, -1] > 1e-12 * singular[:, 0]
    axes = reach[:, None, None] * vt / np.where(singular > 0, singular, 1.0)[:, :, None]  # the ellipsoid's semi-axes
    depth_scale = np.mean(depth, axis=1)
    ok &= (np.linalg.norm(axes[..., :3], axis=2).max(axis=1) <= ELLIPSOID_REACH)
    ok &= (np.linalg.norm(axes[..., 3:], axis=2).max(axis=1) <= ELLIPSOID_REACH * depth_scale)
    basis, _ = np.linalg.qr(J)  # the Jacobian's range

    def contracts(R: np.ndarray, t: np.ndarray, of: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whether a Gauss-Newton step from each pose ``(R, t)`` of image ``of``, with its minimum's Jacobian,
        lands within ``CONTRACTION`` of the way to the minimum; the poses' residuals and depths."""
        turn, angle = _so3_log_many(R @ np.transpose(R0[of], (0, 2, 1)))
        step = np.concatenate([turn, t - t0[of]], axis=1)
        s_residual, _, s_depth = _whitened(R, t, points[of], observed[of], sigma, with_jacobian=False)
        linear = np.einsum("sk,sjk->sj", step, J[of])
        change = (s_residual - residual[of]).reshape(len(of), -1)
        miss = np.einsum("sjk,sj->sk", basis[of], change - linear)  # in the range's basis: as long as in it
        ratio = np.linalg.norm(miss, axis=1) / np.linalg.norm(linear, axis=1)
        return ((angle <= 2.0) & np.all(s_depth > 0, axis=1) & _finite(s_residual) & (ratio <= CONTRACTION),
                s_residual, s_depth)

    # one minimum in the ellipsoid: the steps from its ends (twice as far) contract too
    ends = np.concatenate([axes, -axes], axis=1).reshape(-1, 6) * 2.0
    end_of = np.repeat(np.arange(count), 12)
    ok &= contracts(so3_exp_many(ends[:, :3]) @ R0[end_of], t0[end_of] + ends[:, 3:], end_of)[0].reshape(count, 12).all(axis=1)
    if not len(owner):
        return ok, np.zeros(0, dtype=bool)
    contracted, s_residual, s_depth = contracts(R_start, t_start, owner)
    # a P3P start far from every kept pose: an other fiducial misses by more than a kept pose's could
    judged = np.flatnonzero((triples[:, 0] >= 0) & ~contracted)
    far = np.zeros(len(owner), dtype=bool)
    if len(judged):
        far[judged] = _far(points, observed, sigma, reach, R_start[judged], t_start[judged], owner[judged],
                           triples[judged], s_residual[judged], s_depth[judged])
    return ok, contracted | far


def _far(points: np.ndarray, observed: np.ndarray, sigma: np.ndarray, reach: np.ndarray, R_start: np.ndarray,
         t_start: np.ndarray, owner: np.ndarray, triples: np.ndarray, s_residual: np.ndarray,
         s_depth: np.ndarray) -> np.ndarray:
    """Whether each P3P start (of its ``triples``' fiducials) is far from every pose the screen keeps: an other
    fiducial misses by more than ``reach`` plus ``MISS_MARGIN`` times what the triple's error can move it
    (module docstring; Frobenius norms, above the spectral ones: on the safe side)."""
    _, s_jacobian, _ = _whitened(R_start, t_start, points[owner], observed[owner], sigma)
    rows = np.arange(len(owner))[:, None]
    in_triple = np.zeros(s_depth.shape, dtype=bool)
    in_triple[rows, triples] = True
    clear = _finite(s_jacobian, s_residual) & np.all(s_depth[rows, triples] > 0, axis=1)
    J_T = np.where(clear[:, None, None], s_jacobian[rows, triples].reshape(-1, 6, 6), np.eye(6))
    J_O = np.where(clear[:, None, None], s_jacobian[~in_triple].reshape(len(owner), -1, 6), 0.0)
    J_inverse = np.linalg.inv(J_T)
    clear &= _finite(J_inverse)
    J_inverse = np.where(clear[:, None, None], J_inverse, 0.0)
    clear &= np.linalg.norm(J_T, axis=(1, 2)) * np.linalg.norm(J_inverse, axis=(1, 2)) < 1e9  # not singular
    moved = np.linalg.norm(J_O @ J_inverse, axis=(1, 2)) * reach[owner] * np.sqrt(3.0)
    others = np.linalg.norm(s_residual[~in_triple].reshape(len(owner), -1, 2), axis=2)
    behind = s_depth[~in_triple].reshape(len(owner), -1) <= 0
    return clear & np.any(behind | (others > (reach[owner] + MISS_MARGIN * moved)[:, None]), axis=1)


def screen_minima_many(problems: list[tuple[np.ndarray, np.ndarray]], parities: list[int], sigma: np.ndarray,
                       relevant_cost: float) -> list[list[Pose]]:
    """:func:`~mirror_fg.solver.start.pnp.pnp_minima` of many images (``(base_points, normalized)`` each, >= 4
    fiducials, with its number of mirrors ``parities``) for a screen that keeps the lowest minimum and those
    less than ``relevant_cost`` (whitened squared reprojection, ``sigma`` (2,) normalized) above it: the
    minima of the starts refined (module docstring: the lowest alone where every other start is vouched
    for), or the full search's."""
    sigma = np.asarray(sigma, dtype=float)
    results: list[list[Pose] | None] = [None] * len(problems)
    groups: dict[int, list[int]] = {}
    for i, (base_points, _) in enumerate(problems):
        groups.setdefault(len(base_points), []).append(i)
    for count, members in groups.items():
        points = np.array([np.asarray(problems[i][0], dtype=np.float64) for i in members])
        observed = np.array([np.asarray(problems[i][1], dtype=np.float64) for i in members])
        flips = np.array([parities[i] % 2 == 1 for i in members])
        observed[flips, :, 1] *= -1.0  # eq. (11)
        centred = points - points.mean(axis=1, keepdims=True)
        spreads = np.linalg.svd(centred, compute_uv=False)
        planar = spreads[:, 2] < 1e-9 * np.maximum(1.0, np.abs(centred).max(axis=(1, 2)))  # as pnp.is_planar
        owner: list[int] = []
        rvecs: list[np.ndarray] = []
        tvecs: list[np.ndarray] = []
        triples: list[tuple[int, ...]] = []
        judged: list[int] = []
        searched = [k for k in range(len(members)) if count >= 4 and not planar[k]]  # planar: its twin, the full search
        found = solved_in_threads(lambda k: pnp_starts(points[k], observed[k], True, False, spreads[k]), searched)
        for k, (r, t, of) in zip(searched, found):
            if not r:
                continue
            judged.append(k)
            owner.extend([k] * len(r))
            rvecs.extend(r)
            tvecs.extend(t)
            triples.extend(triple if triple is not None else (-1, -1, -1) for triple in of)
        if judged:
            _judge(members, points, observed, flips, judged, np.array(owner), rvecs, tvecs, np.array(triples),
                   sigma, relevant_cost, results)
    missing = [i for i, result in enumerate(results) if result is None]
    for i, minima in zip(missing, solved_in_threads(lambda i: pnp_minima(problems[i][0], problems[i][1], parities[i]),
                                                     missing)):
        results[i] = minima
    return results  # type: ignore[return-value]


def _judge(members: list[int], points: np.ndarray, observed: np.ndarray, flips: np.ndarray, judged: list[int],
           owner: np.ndarray, rvecs: list[np.ndarray], tvecs: list[np.ndarray], triples: np.ndarray,
           sigma: np.ndarray, relevant_cost: float, results: list[list[Pose] | None]) -> None:
    """The starts of the ``judged`` images of one fiducial count: refine each image's lowest-cost start, and
    those of its other starts that are not vouched for (:func:`_vouched`), where its minimum is well
    determined; the others are left to the full search (``results`` None)."""
    R_all = so3_exp_many(np.array(rvecs, dtype=np.float64).reshape(-1, 3))
    t_all = np.array(tvecs, dtype=np.float64).reshape(-1, 3)
    # the search's starts of one basin: the first (pnp._pnp_minima), every image's at once
    chosen_index = first_of_each_grouped(R_all, t_all, owner, SAME_BASIN)
    R_s, t_s, of = R_all[chosen_index], t_all[chosen_index], owner[chosen_index]
    residual, _, depth = _whitened(R_s, t_s, points[of], observed[of], sigma, with_jacobian=False)
    cost = np.where(np.all(depth > 0, axis=1) & _finite(residual), np.sum(residual**2, axis=(1, 2)), np.inf)
    lowest: dict[int, int] = {}
    for s, (k, c) in enumerate(zip(of.tolist(), cost.tolist())):
        if c < np.inf and (k not in lowest or c < cost[lowest[k]]):
            lowest[k] = s
    if not lowest:
        return
    images = np.array(sorted(lowest))
    refined = solved_in_threads(lambda k: _refined(points[k], observed[k], R_s[lowest[k]], t_s[lowest[k]]),
                                images.tolist())
    R0, t0 = so3_exp_many(np.array([r for r, _ in refined])), np.array([t for _, t in refined])
    position = {k: j for j, k in enumerate(images.tolist())}
    others = np.array([s for s in range(len(of)) if of[s] in position and s != lowest[of[s]]], dtype=int)
    other_owner = np.array([position[k] for k in of[others].tolist()], dtype=int)
    with np.errstate(all="ignore"):
        determined, vouched = _vouched(points[images], observed[images], sigma, relevant_cost, R0, t0, R_s[others],
                                       t_s[others], other_owner, triples[chosen_index][others])
    # the starts not vouched for are refined too (an image whose minimum is not well determined: the full
    # search, pnp.pnp_minima)
    unvouched: dict[int, list[int]] = {}
    for s, j in zip(others[~vouched].tolist(), other_owner[~vouched].tolist()):
        if determined[j]:
            unvouched.setdefault(j, []).append(s)
    for j, k in enumerate(images.tolist()):
        if not determined[j]:
            continue
        if j not in unvouched:
            minima = [(R0[j], t0[j])]
        else:
            minima = _minima(points[k], observed[k], R0[j], t0[j], R_s[unvouched[j]], t_s[unvouched[j]])
        results[members[k]] = [(FLIP_Y @ R, FLIP_Y @ t) for R, t in minima] if flips[k] else minima  # eq. (12)


def _refined(points: np.ndarray, observed: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's LM from the start ``(R, t)`` (as ``pnp._pnp_minima`` refines each start): ``(rvec, tvec)``."""
    rvec, tvec = cv2.Rodrigues(R)[0], t.reshape(3, 1).copy()
    try:
        rvec, tvec = cv2.solvePnPRefineLM(points.reshape(-1, 1, 3), observed.reshape(-1, 1, 2), np.eye(3), None,
                                          rvec, tvec, criteria=PNP_CRITERIA)
    except cv2.error:
        pass
    return np.asarray(rvec, dtype=np.float64).reshape(3), np.asarray(tvec, dtype=np.float64).reshape(3)


def _minima(points: np.ndarray, observed: np.ndarray, R0: np.ndarray, t0: np.ndarray, R_starts: np.ndarray,
            t_starts: np.ndarray) -> list[Pose]:
    """The distinct minima, lowest first, of the refined start ``(R0, t0)`` and the starts ``(R_starts,
    t_starts)`` refined by LM (as :func:`~mirror_fg.solver.start.pnp.pnp_minima` sorts and merges them)."""
    refined = [_refined(points, observed, R, t) for R, t in zip(R_starts, t_starts)]
    R_all = np.concatenate([R0[None], so3_exp_many(np.array([r for r, _ in refined]))])
    t_all = np.concatenate([t0[None], np.array([t for _, t in refined])])
    errors = reprojection_rms_many(R_all, t_all, points, observed).tolist()
    order = sorted((k for k in range(len(errors)) if np.isfinite(errors[k])), key=lambda k: errors[k])
    R_sorted, t_sorted = R_all[order], t_all[order]
    return [(R_sorted[k], t_sorted[k]) for k in first_of_each(R_sorted, t_sorted, SAME_MINIMUM)]
