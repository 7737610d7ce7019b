"""Initial values of the unknowns new images bring into an
:class:`~mirror_fg.solver.incremental.graph.IncrementalGraph`, from its current estimate. Frames, keys and
units as ``calibrator.py``.

A new placement gets its value from the image's PnP ``(A, b)`` (eqs. 10-12) and the current estimate:
the known mirrors after it are peeled off ``(A, b)`` and those before it applied to ``T_cam_base``, which
leaves one reflection (eqs. 6-7): its normal is the -1 eigenvector of ``A_l A_{l-1}^T``, its offset the
part of ``b_l - M_l b_{l-1}`` along it. Several new placements in one image (a new placement of mirror 1
with a new one of mirror 2) wait until their subtree can be solved like a node of the analytical
solution (eqs. 13-18) under the known parent. A reconstruction point gets its value by eq. (20) from the
current estimate once two images in the graph see it; until then its observations wait (once it has
one, the blocks of the images that saw it are re-made with them). Each new unknown is then moved to its
optimum with everything else held (a few Gauss-Newton steps on its own factors) so that iSAM2 does not
keep it linearised at a rough initial value; an eliminated placement is at its optimum in every
evaluation of its factor anyway.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L

from mirror_fg.core.geometry import householder, nested_transform
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic import triangulate_point
from mirror_fg.solver.model.graph import Measurement
from mirror_fg.solver.incremental.state import GraphState
from mirror_fg.solver.start.peeling import MIN_NORMAL_SPREAD, reflection_fit, solve_node
from mirror_fg.solver.start.pnp import pnp_candidates

__all__ = ["MIN_PNP_FIDUCIALS", "REFINE_ITERATIONS", "PlacementInitialiser", "initialise_points", "refine_alone"]

#: Minimum number of fiducials in an image for its own PnP (eq. 10; 3 gives up to four candidates).
MIN_PNP_FIDUCIALS = 3
#: Gauss-Newton iterations on a new unknown alone before it goes to iSAM2.
REFINE_ITERATIONS = 3


@dataclass
class _Candidate:
    """One hypothesis for a node's ``(A_k, b_k)`` and the new mirror vectors it implies below it."""

    A: np.ndarray
    b: np.ndarray
    mirrors: dict[tuple[int, int], list[np.ndarray]] = field(default_factory=dict)


class PlacementInitialiser:
    """Initial mirror vectors of new placements for the images of ``dataset`` (camera frame, metres);
    each image's PnP candidates are computed once and cached (a start-up's new graph state reuses them)."""

    def __init__(self, dataset: Dataset) -> None:
        self._ds = dataset
        self._pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}

    def placements(self, state: GraphState) -> dict[tuple[int, int], np.ndarray]:
        """Mirror vectors of the new placements the waiting images determine, from the current estimate.

        Each waiting image is grouped under its lowest placement without a value, ``(j, c)`` (the mirrors
        before it have values). The subtree below ``(j, c)`` gives candidates for ``(A_j, b_j)``; the
        known ``(A_{j-1}, b_{j-1})`` picks the most consistent one and leaves one reflection.
        """
        groups: dict[tuple[int, int], dict[tuple[int, ...], list[Image]]] = defaultdict(lambda: defaultdict(list))
        for image in state.waiting:
            configs = image.mirror_configs
            j = next(l + 1 for l, m in enumerate(configs) if (l + 1, m) not in state.layout.mirror_keys)
            groups[(j, configs[j - 1])][configs[:j]].append(image)
        estimates: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        for (j, c), by_prefix in groups.items():
            for prefix, images in by_prefix.items():
                A_parent, b_parent = nested_transform(
                    state.R, state.t, [state.mirrors[(l + 1, m)] for l, m in enumerate(prefix[:-1])]
                )
                for candidates in self._node_entries(state, j, prefix, images):
                    misfits, vectors = reflection_fit(
                        np.array([cand.A for cand in candidates]), np.array([cand.b for cand in candidates]),
                        A_parent, b_parent,
                    )
                    best = int(np.argmin(misfits))
                    estimates[(j, c)].append(vectors[best])
                    for config, vs in candidates[best].mirrors.items():
                        estimates[config].extend(vs)
        return {config: np.mean(vs, axis=0) for config, vs in estimates.items()}

    def _node_entries(self, state: GraphState, level: int, prefix: tuple[int, ...], images: list[Image]) -> list[list[_Candidate]]:
        """Independent measurements of node ``prefix``'s ``(A_level, b_level)``, each a candidate list.

        Leaves (level Nv): each image's PnP candidates. Inner nodes: a child whose placement has a value
        is peeled off (eqs. 6-7); >= 3 children without values are solved as a node of the analytical
        solution (eqs. 13-18), which also gives their mirror vectors.
        """
        if level == self._ds.num_mirrors:
            return [[_Candidate(A, b) for A, b in self.pnp_of(im)] for im in images if self.pnp_of(im)]
        by_child: dict[int, list[Image]] = defaultdict(list)
        for image in images:
            by_child[image.mirror_configs[level]].append(image)
        entries: list[list[_Candidate]] = []
        unknown: dict[int, list[list[_Candidate]]] = {}
        for c, child_images in by_child.items():
            child_entries = self._node_entries(state, level + 1, prefix + (c,), child_images)
            if not child_entries:
                continue
            v = state.mirrors.get((level + 1, c))
            if v is None:
                unknown[c] = child_entries
                continue
            M = householder(v)
            for candidates in child_entries:  # A_{l-1} = M_l A_l, b_{l-1} = M_l (b_l - 2 v_l)
                entries.append([_Candidate(M @ cand.A, M @ (cand.b - 2.0 * v), cand.mirrors) for cand in candidates])
        if len(unknown) >= 3:
            node = self._solve_children(state, level, unknown)
            if node is not None:
                entries.append([node])
        return entries

    def _solve_children(self, state: GraphState, level: int, unknown: dict[int, list[list[_Candidate]]]) -> _Candidate | None:
        """Node ``(A_level, b_level)`` and its children's mirror vectors from >= 3 new children (eqs. 13-18)."""
        child_ids = sorted(unknown)
        flat = [(k, candidates) for k, c in enumerate(child_ids) for candidates in unknown[c]]
        parent_det = (-1.0) ** level
        picks, node = solve_node(
            [k for k, _ in flat], [[(cand.A, cand.b) for cand in cands] for _, cands in flat],
            len(child_ids), parent_det, state.rng,
        )
        chosen = [cands[p] for (_, cands), p in zip(flat, picks)]
        normals = np.stack([v / np.linalg.norm(v) for v in node.mirror_vectors])
        if np.linalg.svd(normals, compute_uv=False)[2] < MIN_NORMAL_SPREAD:
            return None  # nearly coplanar normals (eqs. 14-15): wait for more placements
        mirrors: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        for cand in chosen:
            for config, vs in cand.mirrors.items():
                mirrors[config].extend(vs)
        for c, v in zip(child_ids, node.mirror_vectors):
            mirrors[(level + 1, c)].append(v)
        return _Candidate(node.A_parent, node.b_parent, dict(mirrors))

    def pnp_of(self, image: Image) -> list[tuple[np.ndarray, np.ndarray]]:
        """PnP candidates ``(A_Nv, b_Nv)`` of an image (eqs. 10-12), cached; ``[]`` without 3 fiducials."""
        if image.id not in self._pnp:
            names = [n for n in image.observations if n in self._ds.fiducials]
            if len(names) < MIN_PNP_FIDUCIALS:
                self._pnp[image.id] = []
            else:
                normalized = self._ds.normalized(image)
                self._pnp[image.id] = pnp_candidates(
                    np.array([self._ds.fiducials[n] for n in names]),
                    np.array([normalized[n] for n in names]),
                    self._ds.num_mirrors,
                )
        return self._pnp[image.id]


def initialise_points(state: GraphState, values: gtsam.Values) -> list[Measurement]:
    """Eq. (20) for every point seen in two images of ``state``'s graph, from its estimate: a key, a value
    (also into ``values``, iSAM2's new ones). Returns the measurements that now have every value they need.
    """
    ready: list[Measurement] = []
    transforms: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}  # per image placements
    for name in sorted(state.point_waiting):
        waiting = state.point_waiting[name]
        if len({m.image_id for m in waiting}) < 2:
            continue
        for m in waiting:
            if m.mirror_configs not in transforms:
                transforms[m.mirror_configs] = nested_transform(  # (A_Nv, b_Nv), eqs. (6)-(7)
                    state.R, state.t, [state.mirrors[(l + 1, c)] for l, c in enumerate(m.mirror_configs)])
        point = triangulate_point([transforms[m.mirror_configs] for m in waiting], [m.normalized for m in waiting])
        key = L(len(state.layout.point_keys))
        state.layout.point_keys[name] = key
        state.points[name] = point
        values.insert(key, point)
        ready.extend(waiting)
        del state.point_waiting[name]
    return ready


def refine_alone(
    factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, estimate: Callable[[set[int]], gtsam.Values],
    pose_key: int,
) -> None:
    """Gauss-Newton on each new unknown of ``values`` alone (``REFINE_ITERATIONS`` steps on ``factors``),
    every other unknown held at its estimate (``estimate(keys)``: their current values; ``pose_key``: the
    6-dof unknown).

    iSAM2 linearises a new unknown at its initial value and keeps it there until its delta exceeds
    the threshold; starting it at its conditional optimum instead keeps that lag out of the pose
    (measured on a 40-image one-mirror stream: the last estimate 0.25 sigma from the batch
    optimum with the peeled initial values, 0.02 sigma with this).
    """
    new_keys = set(values.keys())
    if not new_keys:
        return
    touching: dict[int, list] = defaultdict(list)
    involved: set[int] = set()
    for i in range(factors.size()):
        factor = factors.at(i)
        keys = factor.keys()
        for key in keys:
            if key in new_keys:
                touching[key].append(factor)
                involved.update(keys)
    current = estimate(involved - new_keys)
    current.insert(values)
    for key, key_factors in touching.items():
        plane = gtsam.Symbol(key).chr() == ord("v")  # a placement's plane (the graph's V keys), else a point
        for _ in range(REFINE_ITERATIONS):
            normal, rhs = np.zeros((3, 3)), np.zeros(3)
            for factor in key_factors:
                linear = factor.linearize(current)
                keys = list(linear.keys())
                column = sum(6 if k == pose_key else 3 for k in keys[: keys.index(key)])
                A, b = linear.jacobian()  # whitened, A delta = b = -error
                A_key = A[:, column : column + 3]
                normal += A_key.T @ A_key
                rhs += A_key.T @ b
            step = np.linalg.lstsq(normal, rhs, rcond=None)[0]
            if plane:  # a placement: its plane moved in its local coordinates
                current.update(key, current.atOrientedPlane3(key).retract(step))
            else:
                current.update(key, current.atPoint3(key) + step)
            if np.max(np.abs(step)) < 1e-9:
                break
        values.update(key, current.atOrientedPlane3(key) if plane else current.atPoint3(key))
