"""What an :class:`~mirror_fg.solver.incremental.graph.IncrementalGraph` holds: its state
(:class:`GraphState`, what a failed start-up rolls back), its blocks of eliminated placements
(:class:`PlacementBlock`) and iSAM2's relinearisation thresholds. Frames, keys and units as
``calibrator.py``.
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from mirror_fg.core.errors import SolveError
from mirror_fg.data import Image
from mirror_fg.factors.view_eliminated import EliminatedViewStack
from mirror_fg.factors.view_points_eliminated import EliminatedViewPointStack
from mirror_fg.solver.model.graph import GraphLayout, Measurement

__all__ = ["GraphState", "PlacementBlock", "RelinearizeThresholds"]


@dataclass(frozen=True)
class RelinearizeThresholds:
    """iSAM2 relinearisation thresholds per kind of unknown (absolute tangent components).

    A variable is relinearised (each of its factors re-evaluated in Python: the expensive part) when a
    component of its iSAM2 delta exceeds the threshold. ``pose``: ``[w (rad) x3, nu (m) x3]``, GTSAM's
    Pose3 tangent of ``T_cam_base``; ``mirror``: a plane's local coordinates (``OrientedPlane3``: two
    angles in radians and the distance in metres); ``point``: metres. Every factor touches the pose, so
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


def new_isam2(thresholds: RelinearizeThresholds | None = None) -> gtsam.ISAM2:
    """The one iSAM2 configuration of both incremental calibrators: relinearisation by ``thresholds``
    (default :class:`RelinearizeThresholds`), checked on every update; full back-substitution on every
    update (wildfire 0: cheap next to the Python factors, and the estimate never lags the linear solution)."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold((thresholds or RelinearizeThresholds()).threshold_map())
    params.relinearizeSkip = 1
    params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
    return gtsam.ISAM2(params)


@dataclass
class PlacementBlock:
    """Last-mirror placements eliminated inside the factors of their views (``view_factors.eliminated_block``:
    one stack, one factor of fiducials or a few with reconstruction points), all under ``parent`` (the
    placements of mirrors 1..Nv-1). ``indices``: the factors' indices in iSAM2 (``None`` until an update
    gave them); ``level``: merges so far in the sense of ``MERGE_FANOUT``."""

    parent: tuple[int, ...]
    level: int
    measurements: list[Measurement]
    placements: list[tuple[int, int]]
    evaluator: EliminatedViewStack | EliminatedViewPointStack
    factors: list[gtsam.CustomFactor]
    indices: list[int] | None = None


@dataclass
class GraphState:
    """What a failed start-up rolls back: the graph, the estimate, and the images in and waiting for it.

    ``R``, ``t``: ``T_cam_base`` (metres); ``mirrors`` (camera frame; in iSAM2 a kept one is the plane
    ``OrientedPlane3`` of its vector, ``views.plane_of``) and ``points`` (base frame), metres;
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
    pending: list[tuple[PlacementBlock, list[int]]] = field(default_factory=list)  # new blocks, positions in the update

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
