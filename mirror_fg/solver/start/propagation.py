"""The analytical start of the general view model, by propagation over what is known (docs/formats.md,
"Views of any reflection order"): camera poses, mirror planes and points are found one at a time, each
from what is already known, until everything is or nothing more can be.

Planes are held in the base frame while propagating (``n . y = d``, ``n`` unit; a reflection there is
``y -> y - 2 (n . y - d) n``, eq. 3 in the base frame), because a reflection commutes with the camera's
rigid map: a view ``(c, p_1..p_k)`` sees ``T_c(Refl_k(... Refl_1(Bp)))``. The rules:

1. known planes of a whole view and >= 4 known points: PnP on the virtual points ``Refl(Bp)`` gives the
   camera's pose (a direct view, k = 0, is the simplest case);
2. >= 3 placements of one mirror seen alone by a camera, or the paper's tree (``mirror_configs``), give
   its pose and those planes (Sects. 4-5, ``initial.initial_estimate``);
3. a known pose and a view with one unknown placement: PnP with the view's parity gives the composite
   map ``G = T_c Refl_k ... Refl_1``; peeling the known ones off both ends leaves that plane;
4. a point seen in two or more views with known poses and planes is triangulated (the rays carried back
   through the reflections, eq. 20 generalised);
5. without a known target (the first camera's frame is the base), Takahashi et al. (CVPR 2017): a point
   seen in a view and in the same view followed by placement p lies, with the camera centre, in a plane
   that contains p's normal, so the normal is the null vector of those planes' normals; then every
   depth and every mirror distance solve one homogeneous linear system, its scale fixed by ``scale``.

What stays unknown is named with the view that would solve it (:class:`Unsolvable`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.solver.start.pnp import lowest_reprojection, pnp_candidates

__all__ = ["ViewObs", "Propagation", "KnownPnP", "Unsolvable", "propagate", "mirror_vector_in", "plane_from_camera"]

Placement = tuple[int, int]
#: Points PnP needs for one unique pose (three give up to four).
MIN_PNP_POINTS = 4
#: Rays closer than this (radians) to parallel do not triangulate a point.
MIN_RAY_ANGLE = np.radians(0.2)


class Unsolvable(SolveError):
    """The data leave an unknown without an analytical start (exit 3)."""


@dataclass
class ViewObs:
    """One image as the propagation sees it: camera, placements, point names, normalized (N, 2)."""

    image_id: str
    camera: str
    reflections: tuple[Placement, ...]
    names: list[str]
    normalized: np.ndarray


@dataclass
class Propagation:
    """What is known: poses ``{camera: (R_cam_base, t_cam_base)}``, base-frame planes ``{placement:
    (n, d)}`` and base-frame points (fiducials included)."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    planes: dict[Placement, tuple[np.ndarray, float]] = field(default_factory=dict)
    points: dict[str, np.ndarray] = field(default_factory=dict)


def _reflect(points: np.ndarray, plane: tuple[np.ndarray, float]) -> np.ndarray:
    """Points (N, 3) reflected in a base-frame plane (eq. 3)."""
    n, d = plane
    return points - 2.0 * np.outer(points @ n - d, n)


def _reflection_matrix(plane: tuple[np.ndarray, float]) -> np.ndarray:
    """The 4x4 homogeneous map of the reflection in ``plane``."""
    n, d = plane
    H = np.eye(4)
    H[:3, :3] -= 2.0 * np.outer(n, n)
    H[:3, 3] = 2.0 * d * n
    return H


def _affine(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 homogeneous matrix of ``x -> R x + t`` (``R`` a rotation, or a composite with reflections)."""
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = R, t
    return H


def plane_from_camera(v: np.ndarray, pose: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float]:
    """The base-frame plane of mirror vector ``v`` (camera frame) of a camera at ``pose`` (T_cam_base)."""
    R, t = pose
    d_c = float(np.linalg.norm(v))
    n_c = v / d_c
    return R.T @ n_c, d_c - float(n_c @ t)


def mirror_vector_in(plane: tuple[np.ndarray, float], pose: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The mirror vector (camera frame) of a base-frame plane seen by a camera at ``pose``."""
    n, d = plane
    R, t = pose
    n_c = R @ n
    return (d + float(n_c @ t)) * n_c


#: PnP candidates ``(A, b)`` already found for an image (``consensus.screen``'s), with the point names
#: they were found from, in order: ``{image_id: (names, candidates)}``.
KnownPnP = dict[str, tuple[tuple[str, ...], list[tuple[np.ndarray, np.ndarray]]]]


def _best_pnp(points: np.ndarray, normalized: np.ndarray, parity: int,
              candidates: list[tuple[np.ndarray, np.ndarray]] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The PnP composite map (A, b) of lowest reprojection error, or None. ``candidates``: the PnP of
    these very points and observations, found before (then not solved again)."""
    if candidates is None:
        try:
            candidates = pnp_candidates(points, normalized, parity)
        except Exception:  # degenerate geometry: OpenCV refuses it
            return None
    return lowest_reprojection(candidates, points, normalized)


class _Propagator:
    def __init__(self, views: list[ViewObs], fiducials: dict[str, np.ndarray], cameras: list[str],
                 fixed: dict[str, tuple[np.ndarray, np.ndarray]], tree_start, known_pnp: KnownPnP | None = None):
        self.views, self.cameras, self.tree_start = views, cameras, tree_start
        self.known_pnp = known_pnp or {}
        self.known = Propagation(poses=dict(fixed), points={n: np.asarray(p, float) for n, p in fiducials.items()})
        self.tried_tree: set[str] = set()

    def _known_points(self, view: ViewObs) -> tuple[np.ndarray, np.ndarray]:
        rows = [k for k, n in enumerate(view.names) if n in self.known.points]
        points = np.array([self.known.points[view.names[k]] for k in rows]).reshape(-1, 3)
        return points, view.normalized[rows]

    def _found_pnp(self, view: ViewObs) -> list[tuple[np.ndarray, np.ndarray]] | None:
        """The view's PnP candidates found before, where they are of the same points (its known ones, in
        order; rules 1 and 3 on the view's own points), else None."""
        found = self.known_pnp.get(view.image_id)
        if found is None:
            return None
        names, candidates = found
        known = tuple(n for n in view.names if n in self.known.points)
        return candidates if known == names else None

    def pose_from_view(self, view: ViewObs) -> bool:  # rule 1
        if view.camera in self.known.poses or any(p not in self.known.planes for p in view.reflections):
            return False
        points, z = self._known_points(view)
        if len(points) < MIN_PNP_POINTS:
            return False
        virtual = points
        for p in view.reflections:
            virtual = _reflect(virtual, self.known.planes[p])
        found = _best_pnp(virtual, z, 0, None if view.reflections else self._found_pnp(view))
        if found is None:
            return False
        self.known.poses[view.camera] = found
        return True

    def plane_from_view(self, view: ViewObs) -> bool:  # rule 3
        if view.camera not in self.known.poses:
            return False
        unknown = [p for p in view.reflections if p not in self.known.planes]
        if len(set(unknown)) != 1 or len(unknown) != 1:
            return False
        points, z = self._known_points(view)
        if len(points) < MIN_PNP_POINTS:
            return False
        found = _best_pnp(points, z, len(view.reflections), self._found_pnp(view))
        if found is None:
            return False
        j = view.reflections.index(unknown[0])
        G = _affine(*found)
        before, after = np.eye(4), np.eye(4)
        for p in view.reflections[:j]:
            before = _reflection_matrix(self.known.planes[p]) @ before
        for p in view.reflections[j + 1:]:
            after = _reflection_matrix(self.known.planes[p]) @ after
        H = np.linalg.inv(after) @ np.linalg.inv(_affine(*self.known.poses[view.camera])) @ G @ np.linalg.inv(before)
        outer = 0.5 * (np.eye(3) - 0.5 * (H[:3, :3] + H[:3, :3].T))  # = n n^T for a reflection
        eigenvalues, eigenvectors = np.linalg.eigh(outer)
        n = eigenvectors[:, -1]
        if eigenvalues[-1] < 0.5:  # not a reflection: the view disagrees with what is known
            return False
        self.known.planes[unknown[0]] = (n, 0.5 * float(n @ H[:3, 3]))
        return True

    def tree_for_camera(self, camera: str) -> bool:  # rule 2
        """Rule 2 for ``camera``: its pose where unknown, and the planes of its own placements. A camera
        whose pose another rule found (rule 1 through shared placements) still needs it where its views
        hold two or more unknown placements each (its own mirror's placements under the tree): rule 3
        takes one at a time. Mirror vectors are camera-frame, so those planes are placed with the known
        pose and the tree's own pose is not used."""
        if camera in self.tried_tree or self.tree_start is None:
            return False
        if camera in self.known.poses and not any(
                view.camera == camera and any(p not in self.known.planes for p in view.reflections)
                for view in self.views):
            return False
        self.tried_tree.add(camera)
        found = self.tree_start(camera)
        if found is None:
            return False
        tree_pose, mirror_vectors = found
        added = camera not in self.known.poses
        pose = self.known.poses.setdefault(camera, tree_pose)
        for p, v in mirror_vectors.items():
            if p not in self.known.planes:
                self.known.planes[p] = plane_from_camera(v, pose)
                added = True
        return added

    def _ray_in_base(self, view: ViewObs, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ray of observation k carried back to the real point's side of every mirror (base frame)."""
        R, t = self.known.poses[view.camera]
        origin = -R.T @ t
        direction = R.T @ np.array([*view.normalized[k], 1.0])
        for p in reversed(view.reflections):
            n, d = self.known.planes[p]
            origin = origin - 2.0 * (origin @ n - d) * n
            direction = direction - 2.0 * (direction @ n) * n
        return origin, direction / np.linalg.norm(direction)

    def triangulate_points(self) -> bool:  # rule 4
        rays: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        for view in self.views:
            if view.camera not in self.known.poses or any(p not in self.known.planes for p in view.reflections):
                continue
            for k, name in enumerate(view.names):
                if name not in self.known.points:
                    rays.setdefault(name, []).append(self._ray_in_base(view, k))
        changed = False
        for name, lines in rays.items():
            directions = np.array([d for _, d in lines])
            if len(lines) < 2 or np.linalg.svd(directions, compute_uv=False)[1] < np.sin(MIN_RAY_ANGLE):
                continue
            A, b = np.zeros((3, 3)), np.zeros(3)
            for o, d in lines:
                P = np.eye(3) - np.outer(d, d)
                A += P
                b += P @ o
            self.known.points[name] = np.linalg.solve(A, b)
            changed = True
        return changed

    def run(self, tree_first: bool = False) -> Propagation:
        if tree_first:  # rule 2 for every camera before any one view's PnP (another start)
            for camera in self.cameras:
                self.tree_for_camera(camera)
        changed = True
        # a view whose camera is posed gives rule 1 nothing more, one whose planes are all known rule 3
        # nothing more (poses and planes are only ever added): each pass takes the others, in order
        posing, placing = list(self.views), list(self.views)
        while changed:
            changed = False
            for view in posing:
                changed |= self.pose_from_view(view)
            posing = [view for view in posing if view.camera not in self.known.poses]
            for view in placing:
                changed |= self.plane_from_view(view)
            placing = [view for view in placing if any(p not in self.known.planes for p in view.reflections)]
            changed |= self.triangulate_points()
            if not changed:
                for camera in self.cameras:
                    if self.tree_for_camera(camera):
                        changed = True
                        break
        return self.known


def takahashi_start(views: list[ViewObs], camera: str, scale) -> Propagation | None:
    """Rule 5 (module docstring): planes and points in ``camera``'s frame (the base frame) from views of
    unknown points only, scaled by ``scale`` (:class:`~mirror_fg.io.dataset.Scale`); None where no
    placement's normal is constrained twice."""
    own = [v for v in views if v.camera == camera]
    rays: dict[tuple[str, tuple[Placement, ...]], np.ndarray] = {}
    for view in own:
        for k, name in enumerate(view.names):
            r = np.array([*view.normalized[k], 1.0])
            rays[(name, view.reflections)] = r / np.linalg.norm(r)
    pairs = [(name, seq, seq + (p,)) for (name, seq) in rays for (other, longer) in rays
             if other == name and len(longer) == len(seq) + 1 and longer[:-1] == seq for p in [longer[-1]]]
    constraints: dict[Placement, list[np.ndarray]] = {}
    for name, a, b in pairs:
        c = np.cross(rays[(name, a)], rays[(name, b)])
        if np.linalg.norm(c) > 1e-9:
            constraints.setdefault(b[-1], []).append(c / np.linalg.norm(c))
    normals = {}
    for p, rows in constraints.items():
        if len(rows) >= 2:
            _, s, Vt = np.linalg.svd(np.array(rows))
            if s[1] > 1e-6:
                normals[p] = Vt[-1]
    usable = [(name, a, b) for name, a, b in pairs if b[-1] in normals]
    if not usable:
        return None
    # unknowns: one depth per (point, view) of a usable pair, one distance per placement
    depth_index: dict[tuple[str, tuple], int] = {}
    for name, a, b in usable:
        for seq in (a, b):
            depth_index.setdefault((name, seq), len(depth_index))
    placements = sorted(normals)
    column = {p: len(depth_index) + k for k, p in enumerate(placements)}
    rows = []
    for name, a, b in usable:
        n = normals[b[-1]]
        ra, rb = rays[(name, a)], rays[(name, b)]
        block = np.zeros((3, len(depth_index) + len(placements)))
        block[:, depth_index[(name, a)]] = ra - 2.0 * (n @ ra) * n  # lambda_a (r_a - 2 (n.r_a) n)
        block[:, column[b[-1]]] = 2.0 * n  # + 2 d_p n
        block[:, depth_index[(name, b)]] = -rb  # - lambda_b r_b = 0
        rows.append(block)
    x = np.linalg.svd(np.vstack(rows))[2][-1]
    depths = x[:len(depth_index)]
    if np.sum(depths > 0) < np.sum(depths < 0):
        x = -x
    distances = {p: float(x[column[p]]) for p in placements}
    points = {}
    for (name, seq), k in depth_index.items():
        if not seq:
            points[name] = x[k] * rays[(name, seq)]
    factor = None
    if scale.placement is not None and scale.placement in distances:
        factor = scale.distance / abs(distances[scale.placement])
    elif scale.points is not None and all(n in points for n in scale.points):
        factor = scale.distance / float(np.linalg.norm(points[scale.points[0]] - points[scale.points[1]]))
    if factor is None or not np.isfinite(factor):
        return None
    known = Propagation()
    known.planes = {p: (normals[p], distances[p] * factor) for p in placements}
    known.points = {name: p * factor for name, p in points.items()}
    return known


def propagate(views: list[ViewObs], fiducials: dict[str, np.ndarray], cameras: list[str],
              fixed: dict[str, tuple[np.ndarray, np.ndarray]], tree_start=None, scale=None,
              tree_first: bool = False, known_pnp: KnownPnP | None = None) -> Propagation:
    """Every pose, plane and point found by the rules of the module docstring; raises
    :class:`Unsolvable` naming the first camera, placement or point left unknown and what would solve it.

    ``fixed``: poses known beforehand (the first camera without a known target). ``tree_start(camera)``:
    rule 2 for one camera, ``((R, t), {placement: v})`` or None. ``tree_first``: rule 2 for every camera
    before the others (by default rule 2 only where the others are stuck: a direct view's PnP is the
    better start where there is one), the second start ``calibrate`` tries when the first ends implausibly.
    ``known_pnp``: images' PnP candidates already found (``consensus.screen``'s), used by rules 1 and 3
    where a view's known points are the ones they were found from."""
    propagator = _Propagator(views, fiducials, cameras, fixed, tree_start, known_pnp)
    if not fiducials:
        first = cameras[0]
        seeded = takahashi_start(views, first, scale)
        if seeded is not None:
            propagator.known.planes.update(seeded.planes)
            propagator.known.points.update(seeded.points)
    known = propagator.run(tree_first)
    _name_unknown(views, known, cameras)
    return known


def _name_unknown(views: list[ViewObs], known: Propagation, cameras: list[str]) -> None:
    for camera in cameras:
        if camera not in known.poses and any(v.camera == camera for v in views):
            who = "the camera" if len(cameras) == 1 else f"camera {camera!r}"
            raise Unsolvable(f"{who}: its pose cannot be started from these images: give it a direct view "
                             "of 4 or more fiducials, 3 or more placements of one mirror seen alone, or views through "
                             "placements that a solved camera also sees")
    placements = sorted({p for v in views for p in v.reflections})
    for p in placements:
        if p not in known.planes:
            raise Unsolvable(f"mirror {p[0]} placement {p[1]}: its plane cannot be started: add a view of 4 or more "
                             "fiducials through it alone (or through it and placements already solved)")
    for v in views:
        for name in v.names:
            if name not in known.points:
                raise Unsolvable(f"point {name!r}: seen in fewer than two views whose rays it could be found from "
                                 "(add an image that sees it through another placement)")
