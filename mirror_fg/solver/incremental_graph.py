"""The iSAM2 side of :class:`~mirror_fg.solver.incremental.IncrementalCalibrator`: its graph state, and
how waiting images join the graph (values of new placements and points, their factors, one update).

Frames, keys and units as ``incremental.py``. :class:`GraphState` is everything a failed start-up rolls
back; :class:`GraphGrowth` is the part of the calibrator that grows that graph (a mixin: it works on
the calibrator's ``_g`` state, ``_ds`` images dataset, ``_robust`` kernel, ``_thresholds``, ``_pnp``
cache and ``timings``).

Eliminated placements (issue 14; without a robust kernel). The last mirror moves in (nearly) every image,
so one ``Point3`` per placement in iSAM2 makes each update cost O(images): every Python factor call gets
a copy of iSAM2's whole ``Values``, and reading the estimate back touches every unknown. Instead each
last-mirror placement is eliminated inside its factor (``factors/eliminated.py``: a Schur complement, as
GTSAM's ``SmartProjectionFactor`` eliminates its landmark; the factor's cost is the minimum over the
placement, eq. 23, and its linearisation has the same normal equations as the placement's measurements
with the placement eliminated first). iSAM2 then holds only ``T_cam_base``, the placements of mirrors
1..Nv-1 and the points. The placements are grouped in :class:`PlacementBlock` s, one factor each, all
under one parent placement: a new image's placement starts a block of its own, and ``MERGE_FANOUT``
blocks of one level are merged into one (the old factors removed from iSAM2 in the same update): O(log n)
factors for n images, so neither the root clique's re-elimination nor a relinearisation of the pose
grows with the number of Python factors. A merged factor, linearised at iSAM2's linearisation point,
is the sum of the factors it replaces: the same linear system. The placements' values come from their
block (at the estimate when it was made, and for every placement in ``calibration(full=True)``); a
placement seen under two parents (or with a robust kernel, every placement) stays a ``Point3`` in iSAM2
with the batch's stacked factors (``factors/batched.py``).
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from mirror_fg.core.geometry import householder, nested_transform
from mirror_fg.core.errors import SolveError
from mirror_fg.factors.batched import batched_factors
from mirror_fg.factors.eliminated import EliminatedEvaluator, collapsed, eliminated_evaluator
from mirror_fg.io.dataset import Dataset, Image
from mirror_fg.solver.pnp import pnp_candidates
from mirror_fg.solver.analytic import triangulate_point
from mirror_fg.solver.graph import GraphLayout, Measurement, measurement_sigmas
from mirror_fg.solver.marginals import unconstrained_message
from mirror_fg.solver.peeling import MIN_NORMAL_SPREAD, reflection_fit, solve_node
from mirror_fg.solver.timing import timed

__all__ = [
    "GraphState", "GraphGrowth", "RelinearizeThresholds", "PlacementBlock", "MIN_PNP_FIDUCIALS", "REFINE_ITERATIONS",
    "POLISH_UPDATES", "POLISH_SIGMAS", "MERGE_FANOUT",
]

#: Minimum number of fiducials in an image for its own PnP (eq. 10; 3 gives up to four candidates).
MIN_PNP_FIDUCIALS = 3
#: Gauss-Newton iterations on a new unknown alone before it goes to iSAM2.
REFINE_ITERATIONS = 3
#: ``calibration(full=True)`` relinearises every factor at most this many times ...
POLISH_UPDATES = 5
#: ... until a relinearisation moves the pose by less than this (Mahalanobis).
POLISH_SIGMAS = 1e-3
#: Blocks of eliminated placements under one parent are merged this many at a time (a block of level k
#: holds >= MERGE_FANOUT**k placements): at most ``MERGE_FANOUT - 1`` blocks per level and parent, so
#: O(log n) factors in iSAM2 for n images, and each placement is re-blocked O(log n) times in all.
MERGE_FANOUT = 8


@dataclass(frozen=True)
class RelinearizeThresholds:
    """iSAM2 relinearisation thresholds per kind of unknown (absolute tangent components).

    A variable is relinearised (each of its factors re-evaluated in Python: the expensive part) when a
    component of its iSAM2 delta exceeds the threshold. ``pose``: ``[w (rad) x3, nu (m) x3]``, GTSAM's
    Pose3 tangent of ``T_cam_base``; ``mirror`` and ``point``: metres. Every factor touches the pose, so
    its threshold sets how often an update costs a pass over the whole graph; what a linearisation
    point that far from the estimate costs in accuracy is second order (one Gauss-Newton step).

    Measured on a 10,000-image stream (``scripts/benchmark_incremental.py --latency``): the pose is not
    relinearised at all in the last 1,200 images, and the last per-image estimate is 0.03 of a standard
    deviation from the fully relinearised one (``calibration(full=True)``). A threshold tied to the pose's
    shrinking standard deviation would add a pass over every image every ~n/4 images for no gain there.
    """

    pose: tuple[float, float, float, float, float, float] = (0.005, 0.005, 0.005, 0.01, 0.01, 0.01)
    mirror: float = 0.003
    point: float = 0.003

    def threshold_map(self) -> gtsam.ISAM2ThresholdMap:
        thresholds = gtsam.ISAM2ThresholdMap()
        thresholds.insert(("x", np.asarray(self.pose, dtype=float)))
        thresholds.insert(("v", np.full(3, float(self.mirror))))
        thresholds.insert(("l", np.full(3, float(self.point))))
        return thresholds


@dataclass
class PlacementBlock:
    """Last-mirror placements eliminated inside one factor (``factors/eliminated.py``), all under ``parent``
    (the placements of mirrors 1..Nv-1). ``index``: the factor's index in iSAM2 (``None`` until an update
    gave it one); ``level``: merges so far in the sense of ``MERGE_FANOUT``."""

    parent: tuple[int, ...]
    level: int
    measurements: list[Measurement]
    placements: list[tuple[int, int]]
    evaluator: EliminatedEvaluator
    factor: gtsam.CustomFactor
    index: int | None = None


@dataclass
class GraphState:
    """What a failed start-up rolls back: the graph, the estimate, and the images in and waiting for it.

    ``R``, ``t``: ``T_cam_base`` (metres); ``mirrors`` (camera frame) and ``points`` (base frame), metres;
    ``pose_cov``: 6x6 in GTSAM's Pose3 tangent ``[w, nu]``; ``step_sigmas``: Mahalanobis size of the
    last pose step; ``initial_error``: the latest start-up graph's cost at its analytical solution.
    ``factors`` holds the stacked factors of the placements iSAM2 has as unknowns; ``blocks`` the factors
    with eliminated placements (``block_of`` finds a placement's); ``kept``: the mirror placements that
    are iSAM2 unknowns (every placement of ``layout`` that is not eliminated).
    """

    isam: gtsam.ISAM2 | None
    factors: gtsam.NonlinearFactorGraph  # the stacked factors (iSAM2 holds them too)
    layout: GraphLayout
    images: list[Image]  # in the graph, in the order added (the calibrator's dataset holds this list)
    waiting: list[Image]  # accepted, not in the graph
    measurements: list[Measurement]  # in the graph, in the order added
    point_waiting: dict[str, list[Measurement]]  # measurements of points without a value
    rng: np.random.Generator
    R: np.ndarray
    t: np.ndarray
    mirrors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]
    pose_cov: np.ndarray
    initial_error: float
    step_sigmas: float
    kept: dict[tuple[int, int], int] = field(default_factory=dict)
    blocks: list[PlacementBlock] = field(default_factory=list)
    block_of: dict[tuple[int, int], PlacementBlock] = field(default_factory=dict)
    removals: list[int] = field(default_factory=list)  # iSAM2 factors the next update removes
    pending: list[tuple[PlacementBlock, int]] = field(default_factory=list)  # new blocks, position in the update

    @classmethod
    def empty(cls, waiting: Iterable[Image], seed: int) -> GraphState:
        """No graph and no estimate yet (before a start-up); ``waiting``: the images accepted so far."""
        return cls(
            isam=None,
            factors=gtsam.NonlinearFactorGraph(),
            layout=GraphLayout(pose_key=X(0), mirror_keys={}, point_keys={}),
            images=[],
            waiting=list(waiting),
            measurements=[],
            point_waiting=defaultdict(list),
            rng=np.random.default_rng(seed),
            R=np.eye(3),
            t=np.zeros(3),
            mirrors={},
            points={},
            pose_cov=np.full((6, 6), np.nan),
            initial_error=math.nan,
            step_sigmas=math.inf,
        )

    def require_isam(self) -> gtsam.ISAM2:
        """The iSAM2 instance; only a started graph has one (``SolveError`` before start-up)."""
        if self.isam is None:
            raise SolveError("no iSAM2 yet: the calibrator has not started")
        return self.isam


@dataclass
class _Candidate:
    """One hypothesis for a node's ``(A_k, b_k)`` and the new mirror vectors it implies below it."""

    A: np.ndarray
    b: np.ndarray
    mirrors: dict[tuple[int, int], list[np.ndarray]] = field(default_factory=dict)


class GraphGrowth:
    """Mixin of :class:`~mirror_fg.solver.incremental.IncrementalCalibrator`: waiting images into the graph."""

    _g: GraphState
    _ds: Dataset
    _robust: str | None
    _thresholds: RelinearizeThresholds
    _pnp: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    timings: dict[str, float]
    _updates: int  # iSAM2 updates so far

    # --- adding images ------------------------------------------------------------------------------

    def _collect(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Move every waiting image that can be added into the graph: new values and factors."""
        ready: list[Measurement] = []
        progress = True
        while progress:
            progress = False
            still_waiting = []
            for image in self._g.waiting:
                if all((l + 1, m) in self._g.layout.mirror_keys for l, m in enumerate(image.mirror_configs)):
                    self._add_to_graph(image, ready)
                    progress = True
                else:
                    still_waiting.append(image)
            self._g.waiting = still_waiting
            if self._g.waiting:
                with timed(self.timings, "initialise"):
                    found = self._initialise_placements()
                for config in sorted(found):
                    self._new_mirror(config, found[config], values)
                    progress = True
        ready.extend(self._initialise_points(values))
        self._add_factors(ready, factors, values)

    def _add_to_graph(self, image: Image, ready: list[Measurement]) -> None:
        """Put an image in the graph: its measurements go to ``ready``, or wait for their point's value."""
        self._ds.images.append(image)
        normalized = self._ds.normalized(image)
        for name in image.observations:
            meas = Measurement(image.id, name, normalized[name], image.mirror_configs)
            if name in self._ds.fiducials or name in self._g.layout.point_keys:
                ready.append(meas)
            else:
                self._g.point_waiting[name].append(meas)

    def _add_factors(
        self, measurements: list[Measurement], factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> None:
        """The factors of ``measurements`` into ``factors`` (the next update's), and into the graph state.

        Without a robust kernel, measurements whose last placement is eliminated go to placement blocks
        (module docstring, :meth:`_place_in_blocks`); the others get the batch pipeline's stacked factors
        (``factors.batched``: one vectorised factor per image or group of images instead of one Python
        factor per measurement; the layout handed over holds only the keys these measurements use).
        """
        if not measurements:
            return
        self._g.measurements.extend(measurements)
        if self._robust is None:
            measurements = self._place_in_blocks(measurements, factors, values)
            if not measurements:
                return
        configs = {(l + 1, m) for meas in measurements for l, m in enumerate(meas.mirror_configs)}
        names = {meas.point for meas in measurements if meas.point not in self._ds.fiducials}
        layout = GraphLayout(
            pose_key=self._g.layout.pose_key,
            mirror_keys={config: self._g.layout.mirror_keys[config] for config in configs},
            point_keys={name: self._g.layout.point_keys[name] for name in names},
        )
        sigmas = measurement_sigmas(self._ds, measurements)  # point_sigma where given
        for factor in batched_factors(self._ds, layout, measurements, sigmas, self._robust):
            factors.add(factor)
            self._g.factors.add(factor)

    def _place_in_blocks(
        self, measurements: list[Measurement], factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> list[Measurement]:
        """Put measurements whose last placement is eliminated into placement blocks; return the others.

        A block holding a placement that gets new measurements (a point's value came, the placement is
        seen again) is dissolved and re-made with them. A placement seen under a second parent becomes an
        iSAM2 unknown (inserted into ``values``; its measurements are returned). Then ``MERGE_FANOUT``
        blocks of one level and parent are merged, until none are. Removed blocks' iSAM2 indices go to
        ``removals``, new blocks' factors into ``factors`` (``pending`` until the update numbers them).
        """
        g = self._g
        Nv = self._ds.num_mirrors
        explicit = [m for m in measurements if (Nv, m.mirror_configs[-1]) in g.kept]
        pool = [m for m in measurements if (Nv, m.mirror_configs[-1]) not in g.kept]
        parents: dict[tuple[int, int], set[tuple[int, ...]]] = defaultdict(set)
        for meas in pool:
            parents[(Nv, meas.mirror_configs[-1])].add(tuple(meas.mirror_configs[:-1]))
        dissolved: dict[int, PlacementBlock] = {}
        for config, seen in parents.items():
            block = g.block_of.get(config)
            if block is not None:
                seen.add(block.parent)
                dissolved[id(block)] = block
        for block in dissolved.values():
            self._drop_block(block)
            pool.extend(block.measurements)
        for config, seen in parents.items():
            if len(seen) > 1:  # one placement under two parents: an iSAM2 unknown of its own
                g.kept[config] = g.layout.mirror_keys[config]
                values.insert(g.layout.mirror_keys[config], g.mirrors[config])
        explicit += [m for m in pool if (Nv, m.mirror_configs[-1]) in g.kept]
        pool = [m for m in pool if (Nv, m.mirror_configs[-1]) not in g.kept]
        by_parent: dict[tuple[int, ...], list[Measurement]] = defaultdict(list)
        for meas in pool:
            by_parent[tuple(meas.mirror_configs[:-1])].append(meas)
        for parent, block_measurements in by_parent.items():
            placements = list(dict.fromkeys((Nv, m.mirror_configs[-1]) for m in block_measurements))
            level = 0
            while MERGE_FANOUT ** (level + 1) <= len(placements):
                level += 1
            while True:  # merge MERGE_FANOUT blocks of the new one's level into it, as long as there are
                same = [b for b in g.blocks if b.parent == parent and b.level == level]
                if len(same) + 1 < MERGE_FANOUT:
                    break
                for block in same:
                    self._drop_block(block)
                    block_measurements = block.measurements + block_measurements
                    placements = block.placements + placements
                level += 1
            self._make_block(parent, level, block_measurements, placements, factors)
        return explicit

    def _make_block(
        self, parent: tuple[int, ...], level: int, measurements: list[Measurement], placements: list[tuple[int, int]],
        factors: gtsam.NonlinearFactorGraph,
    ) -> None:
        """One factor with ``placements`` (all under ``parent``) eliminated, into the state and ``factors``."""
        g = self._g
        configs = {(l + 1, m) for meas in measurements for l, m in enumerate(meas.mirror_configs)}
        names = {meas.point for meas in measurements if meas.point not in self._ds.fiducials}
        layout = GraphLayout(
            pose_key=g.layout.pose_key,
            mirror_keys={config: g.layout.mirror_keys[config] for config in configs},
            point_keys={name: g.layout.point_keys[name] for name in names},
        )
        sigmas = measurement_sigmas(self._ds, measurements)
        evaluator = eliminated_evaluator(self._ds, layout, measurements, sigmas, {c: g.mirrors[c] for c in placements})
        (factor,) = evaluator.factors  # one parent: one factor
        evaluator.factors = []  # the block holds the factor, the factor the evaluator: no cycle
        block = PlacementBlock(parent, level, measurements, placements, evaluator, factor)
        g.blocks.append(block)
        for config in placements:
            g.block_of[config] = block
        g.pending.append((block, factors.size()))
        factors.add(factor)

    def _drop_block(self, block: PlacementBlock) -> None:
        """Take a block out of the state; its factor leaves iSAM2 with the next update."""
        g = self._g
        g.blocks.remove(block)
        for config in block.placements:
            if g.block_of.get(config) is block:
                del g.block_of[config]
        if block.index is not None:
            g.removals.append(block.index)
        else:  # made earlier in this same update: not in iSAM2 yet
            g.pending = [(b, position) for b, position in g.pending if b is not block]

    def _new_mirror(self, config: tuple[int, int], v: np.ndarray, values: gtsam.Values) -> None:
        """A key and a value for a new placement; into ``values`` (iSAM2's) unless it is eliminated."""
        key = V(len(self._g.layout.mirror_keys))
        self._g.layout.mirror_keys[config] = key
        self._g.mirrors[config] = np.asarray(v, dtype=float)
        if self._robust is not None or config[0] < self._ds.num_mirrors:
            self._g.kept[config] = key
            values.insert(key, self._g.mirrors[config])

    def _initialise_points(self, values: gtsam.Values) -> list[Measurement]:
        """Eq. (20) for every point seen in two images of the graph, from the current estimate.

        Returns the measurements that now have every value they need.
        """
        ready: list[Measurement] = []
        transforms: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}  # per image placements
        for name in sorted(self._g.point_waiting):
            waiting = self._g.point_waiting[name]
            if len({m.image_id for m in waiting}) < 2:
                continue
            for m in waiting:
                if m.mirror_configs not in transforms:
                    transforms[m.mirror_configs] = self._transform(m.mirror_configs)
            point = triangulate_point([transforms[m.mirror_configs] for m in waiting], [m.normalized for m in waiting])
            key = L(len(self._g.layout.point_keys))
            self._g.layout.point_keys[name] = key
            self._g.points[name] = point
            values.insert(key, point)
            ready.extend(waiting)
            del self._g.point_waiting[name]
        return ready

    def _refine_new(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Gauss-Newton on each new unknown alone, every other unknown held at its estimate.

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
        current = self._values(involved - new_keys)
        current.insert(values)
        for key, key_factors in touching.items():
            for _ in range(REFINE_ITERATIONS):
                normal, rhs = np.zeros((3, 3)), np.zeros(3)
                for factor in key_factors:
                    linear = factor.linearize(current)
                    keys = list(linear.keys())
                    column = sum(6 if k == self._g.layout.pose_key else 3 for k in keys[: keys.index(key)])
                    A, b = linear.jacobian()  # whitened, A delta = b = -error
                    A_key = A[:, column : column + 3]
                    normal += A_key.T @ A_key
                    rhs += A_key.T @ b
                step = np.linalg.lstsq(normal, rhs, rcond=None)[0]
                current.update(key, current.atPoint3(key) + step)
                if np.max(np.abs(step)) < 1e-9:
                    break
            values.update(key, current.atPoint3(key))

    def _transform(self, mirror_configs: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """``(A_Nv, b_Nv)`` of an image from the current estimate (eqs. 6-7)."""
        return nested_transform(self._g.R, self._g.t, [self._g.mirrors[(l + 1, m)] for l, m in enumerate(mirror_configs)])

    # --- values of new placements (eqs. 6-7, 13-18) -------------------------------------------------

    def _initialise_placements(self) -> dict[tuple[int, int], np.ndarray]:
        """Mirror vectors of the new placements the waiting images determine, from the current estimate.

        Each waiting image is grouped under its lowest placement without a value, ``(j, c)`` (the mirrors
        before it have values). The subtree below ``(j, c)`` gives candidates for ``(A_j, b_j)``; the
        known ``(A_{j-1}, b_{j-1})`` picks the most consistent one and leaves one reflection.
        """
        groups: dict[tuple[int, int], dict[tuple[int, ...], list[Image]]] = defaultdict(lambda: defaultdict(list))
        for image in self._g.waiting:
            configs = image.mirror_configs
            j = next(l + 1 for l, m in enumerate(configs) if (l + 1, m) not in self._g.layout.mirror_keys)
            groups[(j, configs[j - 1])][configs[:j]].append(image)
        estimates: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        for (j, c), by_prefix in groups.items():
            for prefix, images in by_prefix.items():
                A_parent, b_parent = nested_transform(
                    self._g.R, self._g.t, [self._g.mirrors[(l + 1, m)] for l, m in enumerate(prefix[:-1])]
                )
                for candidates in self._node_entries(j, prefix, images):
                    misfits, vectors = reflection_fit(
                        np.array([cand.A for cand in candidates]), np.array([cand.b for cand in candidates]),
                        A_parent, b_parent,
                    )
                    best = int(np.argmin(misfits))
                    estimates[(j, c)].append(vectors[best])
                    for config, vs in candidates[best].mirrors.items():
                        estimates[config].extend(vs)
        return {config: np.mean(vs, axis=0) for config, vs in estimates.items()}

    def _node_entries(self, level: int, prefix: tuple[int, ...], images: list[Image]) -> list[list[_Candidate]]:
        """Independent measurements of node ``prefix``'s ``(A_level, b_level)``, each a candidate list.

        Leaves (level Nv): each image's PnP candidates. Inner nodes: a child whose placement has a value
        is peeled off (eqs. 6-7); >= 3 children without values are solved as a node of the analytical
        solution (eqs. 13-18), which also gives their mirror vectors.
        """
        if level == self._ds.num_mirrors:
            return [[_Candidate(A, b) for A, b in self._pnp_of(im)] for im in images if self._pnp_of(im)]
        by_child: dict[int, list[Image]] = defaultdict(list)
        for image in images:
            by_child[image.mirror_configs[level]].append(image)
        entries: list[list[_Candidate]] = []
        unknown: dict[int, list[list[_Candidate]]] = {}
        for c, child_images in by_child.items():
            child_entries = self._node_entries(level + 1, prefix + (c,), child_images)
            if not child_entries:
                continue
            v = self._g.mirrors.get((level + 1, c))
            if v is None:
                unknown[c] = child_entries
                continue
            M = householder(v)
            for candidates in child_entries:  # A_{l-1} = M_l A_l, b_{l-1} = M_l (b_l - 2 v_l)
                entries.append([_Candidate(M @ cand.A, M @ (cand.b - 2.0 * v), cand.mirrors) for cand in candidates])
        if len(unknown) >= 3:
            node = self._solve_children(level, unknown)
            if node is not None:
                entries.append([node])
        return entries

    def _solve_children(self, level: int, unknown: dict[int, list[list[_Candidate]]]) -> _Candidate | None:
        """Node ``(A_level, b_level)`` and its children's mirror vectors from >= 3 new children (eqs. 13-18)."""
        child_ids = sorted(unknown)
        flat = [(k, candidates) for k, c in enumerate(child_ids) for candidates in unknown[c]]
        parent_det = (-1.0) ** level
        picks, node = solve_node(
            [k for k, _ in flat], [[(cand.A, cand.b) for cand in cands] for _, cands in flat],
            len(child_ids), parent_det, self._g.rng,
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

    def _pnp_of(self, image: Image) -> list[tuple[np.ndarray, np.ndarray]]:
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

    # --- iSAM2 ----------------------------------------------------------------------------------------

    def _update(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """One ``ISAM2.update`` with only the new factors and values (and the removal of the blocks merged
        or re-made); refresh the estimate."""
        g = self._g
        isam = g.require_isam()
        with timed(self.timings, "isam2"):
            pending, g.pending, removals, g.removals = g.pending, [], g.removals, []
            try:
                result = isam.update(factors, values, removals)
                pose_cov = isam.marginalCovariance(g.layout.pose_key)
            except RuntimeError as error:  # IndeterminantLinearSystemException
                raise SolveError(f"{self._ds.source}: {unconstrained_message(error, g.layout)}") from None
            indices = result.getNewFactorsIndices()
            for block, position in pending:
                block.index = int(indices[position])
            self._updates += 1
        with timed(self.timings, "estimate"):
            before = (g.R, g.t, g.pose_cov)
            estimate = isam.calculateEstimate()
            self._set_estimate(estimate, [block for block, _ in pending])
            g.pose_cov = pose_cov
            g.step_sigmas = self._pose_step_sigmas(*before)

    def _pose_step_sigmas(self, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> float:
        """Mahalanobis size of the pose step from ``(R, t)`` to the estimate, against ``covariance``
        (GTSAM's tangent; the current covariance when it is undefined, as at a start-up)."""
        step = gtsam.Pose3(gtsam.Rot3(R), t).localCoordinates(gtsam.Pose3(gtsam.Rot3(self._g.R), self._g.t))
        reference = covariance if np.all(np.isfinite(covariance)) else self._g.pose_cov
        quadratic = float(step @ np.linalg.solve(reference, step))
        return float(np.sqrt(max(quadratic, 0.0)))

    def _new_isam2(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self._thresholds.threshold_map())
        params.relinearizeSkip = 1
        # Full back-substitution on every update (wildfire 0): cheap next to the Python factors, and
        # the estimate never lags the linear solution.
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
        return gtsam.ISAM2(params)

    def _all_factors(self) -> gtsam.NonlinearFactorGraph:
        """Every factor of the graph (stacked ones, then the blocks'); the blocks pending as new."""
        g = self._g
        factors = gtsam.NonlinearFactorGraph()
        factors.push_back(g.factors)
        g.pending = []
        for block in g.blocks:
            g.pending.append((block, factors.size()))
            factors.add(block.factor)
        return factors

    def _polish(self) -> None:
        """Relinearise every factor at the current estimate until the pose stops moving.

        The thresholds leave variables linearised up to a threshold away from the estimate (second-order
        error); a fresh iSAM2 holding the same factors, linearised at the current estimate, is a full
        Gauss-Newton step (one pass over every factor, like one batch iteration).
        """
        for _ in range(POLISH_UPDATES):
            values = self._values()
            self._g.isam = self._new_isam2()
            self._g.removals = []  # a fresh iSAM2 holds nothing to remove
            self._update(self._all_factors(), values)
            if self._g.step_sigmas < POLISH_SIGMAS:
                break

    def _set_estimate(self, values: gtsam.Values, blocks: Iterable[PlacementBlock] = ()) -> None:
        """Read the estimate of iSAM2's unknowns from ``values``, and the placements of ``blocks`` at it
        (every other eliminated placement keeps the value its block last gave)."""
        g = self._g
        pose = values.atPose3(g.layout.pose_key)
        g.R, g.t = pose.rotation().matrix(), np.array(pose.translation())
        for config, key in g.kept.items():
            g.mirrors[config] = np.array(values.atPoint3(key))
        for name, key in g.layout.point_keys.items():
            g.points[name] = np.array(values.atPoint3(key))
        for block in blocks:
            g.mirrors.update(block.evaluator.mirror_vectors(values))

    def _values(self, keys: Iterable[int] | None = None) -> gtsam.Values:
        """The current estimate of iSAM2's unknowns (not the eliminated placements) as GTSAM values: every
        one, or those of ``keys``."""
        g = self._g
        values = gtsam.Values()
        wanted = None if keys is None else set(keys)
        if wanted is None or g.layout.pose_key in wanted:
            values.insert(g.layout.pose_key, gtsam.Pose3(gtsam.Rot3(g.R), g.t))
        for config, key in g.kept.items():
            if wanted is None or key in wanted:
                values.insert(key, g.mirrors[config])
        for name, key in g.layout.point_keys.items():
            if wanted is None or key in wanted:
                values.insert(key, g.points[name])
        return values

    def _explicit_graph(self, refresh: bool = True) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The graph with every placement an unknown (the batch's stacked factors) and its values at the
        estimate, every eliminated placement at its optimum there (``refresh``; else at the value it has):
        what ``calibration(full=True)`` takes covariances and residuals of (O(images), once)."""
        g = self._g
        values = self._values()
        for block in g.blocks if refresh else []:
            g.mirrors.update(block.evaluator.mirror_vectors(values))
        if not g.blocks:
            return g.factors, values
        for config, key in g.layout.mirror_keys.items():
            if config not in g.kept:
                values.insert(key, g.mirrors[config])
        factors = gtsam.NonlinearFactorGraph()
        sigmas = measurement_sigmas(self._ds, g.measurements)
        for factor in batched_factors(self._ds, g.layout, g.measurements, sigmas, self._robust):
            factors.add(factor)
        return factors, values

    def _collapsed(self, values: gtsam.Values) -> bool:
        """Whether an eliminated placement at ``values`` has run into the camera centre
        (``factors.eliminated.collapsed``)."""
        return collapsed([v for block in self._g.blocks for v in block.evaluator.mirror_vectors(values).values()])

    def _solve_with_every_placement(
        self, params: gtsam.LevenbergMarquardtParams
    ) -> tuple[gtsam.LevenbergMarquardtOptimizer, gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Levenberg-Marquardt on the graph with every placement an unknown, from the current values (a
        start-up's, before its solve), as the batch does without elimination; then the blocks made anew
        from its solution. Returns the optimizer, every factor (for a fresh iSAM2) and iSAM2's values."""
        g = self._g
        factors, values = self._explicit_graph(refresh=False)
        optimizer = gtsam.LevenbergMarquardtOptimizer(factors, values, params)
        try:
            optimized = optimizer.optimize()
        except RuntimeError as error:  # IndeterminantLinearSystemException
            raise SolveError(f"{self._ds.source}: {unconstrained_message(error, g.layout)}") from None
        self._set_estimate(optimized)
        for config, key in g.layout.mirror_keys.items():
            g.mirrors[config] = np.array(optimized.atPoint3(key))
        old, g.blocks, g.block_of, g.pending = g.blocks, [], {}, []
        factors = gtsam.NonlinearFactorGraph()
        factors.push_back(g.factors)
        for block in old:  # their placements start from the solution
            self._make_block(block.parent, block.level, block.measurements, block.placements, factors)
        return optimizer, factors, self._values()
