"""The analytical start of an arm's calibration through mirrors (docs/formats.md, "Robot arms"), no truth
needed: per image the PnP of the mirrored target, per placement OpenCV's robot-world hand-eye solver on
those virtual poses and the forward kinematics, then the paper's peeling across placements (eqs. 13-18).

Frames: {B} the base link. With the camera on the base link (eye-to-hand) an image's map from target to
camera is ``A_i = M_c^-1 H F_i M_t`` (``H`` the reflection in the placement's plane in {B}, improper,
eq. 3); with ``S = diag(1, 1, -1)`` the PnP of the points ``S p`` gives the proper ``A_i S = X F'_i Z``,
``X = M_c^-1 H S``, ``F'_i = S F_i S``, ``Z = S M_t S``: OpenCV's ``A = X B Z``. With the target on the
base link (eye-in-hand) ``A_i S = M_c^-1 F_i^-1 (H M_t S)``. Either way each placement gives the map
``Y^-1 H`` from {B} into the frame of the one on the base (``Y`` its pose in {B}): the paper's virtual
camera of one mirror, whose placements the peeling (``peeling.solve_children``) separates into ``Y`` and
the planes.
"""
from __future__ import annotations

from itertools import combinations

import cv2
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.geometry import project_to_orthogonal
from mirror_fg.factors.robot import inverse
from mirror_fg.solver.start.peeling import solve_children
from mirror_fg.solver.start.pnp import lowest_reprojection, pnp_candidates
from mirror_fg.solver.start.propagation import plane_from_camera

__all__ = ["arm_start", "camera_from_planes", "mean_pose", "triangulate", "MIN_POSES"]

#: Arm poses per placement that OpenCV's robot-world hand-eye solver needs (distinct rotations).
MIN_POSES = 3
#: Images per placement a start uses at most (evenly spread over the file's order): a start, refined by
#: LM over every image; the PnP of each image is most of its cost.
MAX_START_IMAGES = 12
S = np.diag([1.0, 1.0, -1.0])


def _best_map(points: np.ndarray, normalized: np.ndarray, minima=None):
    """The improper map ``(A, b)`` target -> camera through one mirror of lowest reprojection error
    (``minima``: ``pnp.pnp_minima`` of these very points and observations, when the screen found them:
    its first is ``pnp_candidates``')."""
    candidates = minima[:1] if minima is not None else pnp_candidates(points, normalized, 1)
    return lowest_reprojection(candidates, points, normalized)


def mean_pose(poses):
    """The chordal mean of poses ``(R, t)``: the rotation nearest their sum, the mean translation."""
    R = project_to_orthogonal(sum(p[0] for p in poses), 1.0)
    return R, np.mean([p[1] for p in poses], axis=0)


def _affine(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = pose
    return T


def camera_from_planes(images, target, planes: dict):
    """A camera's mount ``T_link_cam`` from known planes and the target's mount, or None where no image
    gives one. ``images`` as :func:`arm_start`'s, of this camera; ``target`` the target's mount ``(R, t)``;
    ``planes`` ``{placement: v_B}``. Each image's PnP map ``x_cam = A x_target + b`` (improper, one
    mirror) is ``C^-1 H D`` (eq. 3: ``H`` the reflection in the plane, ``D = F_t M_t``), so
    ``C = H D (A, b)^-1`` and the mount is ``F_c^-1 C``; the mean over the images."""
    mounts = []
    for placement, points, normalized, F_c, F_t, *minima in images:
        if len(points) < 4 or placement not in planes:
            continue
        found = _best_map(points, normalized, minima[0] if minima else None)
        if found is None:
            continue
        v = np.asarray(planes[placement], float)
        H = np.eye(4)
        H[:3, :3] -= 2.0 * np.outer(v, v) / (v @ v)  # eq. (3): x -> M x + 2 v
        H[:3, 3] = 2.0 * v
        C = H @ F_t @ _affine(target) @ np.linalg.inv(_affine(found))
        M = np.linalg.inv(F_c) @ C
        mounts.append((M[:3, :3], M[:3, 3]))
    return mean_pose(mounts) if mounts else None


def arm_start(images, eye_to_hand: bool, source: str, max_starts: int = 1) -> list:
    """Up to ``max_starts`` starts ``(M_c, M_t, {placement: v_B})`` from ``images``: ``(placement, target
    points (N, 3), normalized (N, 2), T_B_camlink (4x4), T_B_targetlink (4x4)[, PnP minima or None])`` of
    the images seen through one mirror (the minima: ``pnp.pnp_minima`` of those points, when known). The first peels every placement at once; the others (restarts) one triple of placements each,
    the rest's planes then from their own virtual maps."""
    groups: dict = {}
    by_placement: dict = {}
    for entry in images:
        by_placement.setdefault(entry[0], []).append(entry)
    chosen = []
    for group in by_placement.values():
        keep = np.unique(np.linspace(0, len(group) - 1, min(len(group), MAX_START_IMAGES)).round().astype(int))
        chosen += [group[k] for k in keep]
    for placement, points, normalized, F_c, F_t, *minima in chosen:
        if len(points) < 4:
            continue
        found = _best_map(points, normalized, minima[0] if minima else None)
        if found is None:
            continue
        A, b = found
        F = F_t if eye_to_hand else np.linalg.inv(F_c)
        groups.setdefault(placement, []).append(((A @ S, b), (F[:3, :3], F[:3, 3])))
    usable = {p: g for p, g in groups.items() if len(g) >= MIN_POSES}
    if len(usable) < 3:
        raise SolveError(f"{source}: the analytical start needs 3 mirror placements each seen from {MIN_POSES} or more "
                         f"arm poses with 4 or more known target points (found {len(usable)})")
    maps, moving = [], []
    placements = sorted(usable)
    for k, p in enumerate(placements):
        virtual, recorded = zip(*usable[p])
        arm = [(S @ R @ S, S @ t) for R, t in recorded] if eye_to_hand else list(recorded)  # S F S
        try:
            out = cv2.calibrateRobotWorldHandEye([R for R, _ in virtual], [t.reshape(3, 1) for _, t in virtual],
                                                 [R for R, _ in arm], [t.reshape(3, 1) for _, t in arm])
        except cv2.error as error:
            message = str(error).strip().splitlines()[-1] if str(error).strip() else "failed"
            raise SolveError(f"{source}: mirror {p[0]} placement {p[1]}: no hand-eye start from its {len(arm)} arm poses "
                             f"({message}): give arm poses with rotations about different axes") from None
        X = (out[2], out[3].ravel())
        Z = inverse((out[0], out[1].ravel()))  # OpenCV returns base2world = Z^-1
        if eye_to_hand:  # X = M_c^-1 H S: the map x_B -> M_c^-1 H x_B is (R_X S, t_X)
            maps.append((k, X[0] @ S, X[1]))
            moving.append((S @ Z[0] @ S, S @ Z[1]))  # M_t = S Z S
        else:  # Z = H M_t S: M_t^-1 H = S Z^-1
            Zi = inverse(Z)
            maps.append((k, S @ Zi[0], S @ Zi[1]))
            moving.append(inverse(X))  # M_c = X^-1
    triples = [None, *combinations(range(len(placements)), 3)] if len(placements) > 3 else [None]
    starts = []
    for subset in triples[:max_starts]:
        chosen_maps = maps if subset is None else [(i, maps[k][1], maps[k][2]) for i, k in enumerate(subset)]
        node = solve_children(chosen_maps, len(chosen_maps), 1.0)  # eqs. (13)-(18)
        Y_inv = (project_to_orthogonal(node.A_parent, 1.0), node.b_parent)  # {B} -> the fixed one's frame
        planes = {}
        for k, p in enumerate(placements):
            planes[p] = _plane_of_map(maps[k][1], maps[k][2], Y_inv)
        Y = inverse(Y_inv)
        mount = mean_pose(moving)
        starts.append((Y, mount, planes) if eye_to_hand else (mount, Y, planes))
    return starts


def _plane_of_map(A: np.ndarray, b: np.ndarray, Y_inv) -> np.ndarray:
    """The plane in {B} (its ``v = d n``) of a placement's virtual map ``x -> A x + b`` = ``Y^-1 H`` given
    ``Y^-1``: in Y's frame ``A = M R``, ``b = M t + 2 v`` (eqs. 3, 13), ``M``'s -1 eigenvector the normal."""
    R, t = Y_inv
    M = A @ R.T
    normal = np.linalg.eigh(0.5 * (M + M.T))[1][:, 0]  # eigenvalue -1
    v = 0.5 * (b - M @ t)
    v = float(normal @ v) * normal
    n, d = plane_from_camera(v, Y_inv)
    return d * n


def triangulate(maps, normalized) -> np.ndarray:
    """A target-frame point from its observations: each ``[u, v, 1] x (A p + b) = 0`` (``(A, b)`` the image's
    map from target to camera), least squares."""
    rows, rhs = [], []
    for (A, b), z in zip(maps, normalized):
        u, v = z
        for a_row, b_val in ((A[0] - u * A[2], b[0] - u * b[2]), (A[1] - v * A[2], b[1] - v * b[2])):
            rows.append(a_row)
            rhs.append(-b_val)
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]

