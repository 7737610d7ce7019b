"""The incremental tree graph's factors on the one measurement model (``model/views.py``, Hesch et al.,
eqs. 2, 3, 9, 23): its measurements as views keyed as the graph is, stacked, or with the placements of
one block eliminated inside them.

Frames, keys and units as ``graph.py``: one camera (``views.SINGLE_CAMERA``) whose pose is the graph's
``T_cam_base`` key; every placement owned by that camera, its unknown an ``OrientedPlane3`` (the view
model's variable, ``factors/views.py``) where it is an iSAM2 unknown, its mirror vector ``v`` solved
inside the factors where it is eliminated (``factors/view_eliminated.py`` for views of fiducials only,
``factors/view_points_eliminated.py`` where some view sees reconstruction points); points in the base
frame, ``Point3`` keys. A measurement's view is its image restricted to the measurements handed over
(an image's fiducials and its points can join the graph at different updates: two views, whose costs add).
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mirror_fg.data import Dataset
from mirror_fg.factors.view_eliminated import EliminatedViewStack
from mirror_fg.factors.view_points_eliminated import EliminatedViewPointStack
from mirror_fg.factors.view_stack import stacked_view_factors
from mirror_fg.factors.views import ViewFactor, plane_of, vector_of_plane
from mirror_fg.solver.model.graph import GraphLayout, Measurement
from mirror_fg.solver.model.views import SINGLE_CAMERA, points_of

__all__ = ["view_factors_of", "stacked_factors", "eliminated_block", "plane_of", "vector_at", "vector_jacobian",
           "vector_covariance"]

Placement = tuple[int, int]

#: One block's views in one stack whatever its number of placements (``view_table.merged_sets``' limit).
ONE_STACK = 1 << 40


def view_factors_of(dataset: Dataset, layout: GraphLayout, measurements: Sequence[Measurement],
                    robust: str | None = None) -> list[ViewFactor]:
    """One ``ViewFactor`` per image of ``measurements`` (in order of first measurement; its points in the
    order given), keyed by ``layout`` (each view takes the keys of its own placements and points): the view
    of those measurements (module docstring)."""
    by_image: dict[str, list[Measurement]] = {}
    for meas in measurements:
        by_image.setdefault(meas.image_id, []).append(meas)
    pose_keys = {SINGLE_CAMERA: layout.pose_key}
    views = []
    for ms in by_image.values():
        sigmas, base, landmarks = points_of(dataset, dataset.camera, [m.point for m in ms], layout.point_keys)
        observed = np.array([m.normalized for m in ms], dtype=float).reshape(-1, 2).T
        reflections = tuple((l + 1, int(m)) for l, m in enumerate(ms[0].mirror_configs))
        views.append(ViewFactor(SINGLE_CAMERA, reflections, pose_keys, {}, layout.mirror_keys,
                                dict.fromkeys(reflections, SINGLE_CAMERA), base, landmarks, observed, sigmas, robust))
    return views


def stacked_factors(dataset: Dataset, layout: GraphLayout, measurements: Sequence[Measurement],
                    robust: str | None = None) -> list[gtsam.CustomFactor]:
    """The factors of ``measurements`` with every placement an unknown (``view_stack.stacked_view_factors``:
    fiducials stacked, views with points in compressed stacks)."""
    return stacked_view_factors(view_factors_of(dataset, layout, measurements, robust))


def eliminated_block(dataset: Dataset, layout: GraphLayout, measurements: Sequence[Measurement],
                     start: dict[Placement, np.ndarray]) -> EliminatedViewStack | EliminatedViewPointStack:
    """The factors of ``measurements`` with the placements of ``start`` (each seen by these measurements
    only, the last reflection of each view) eliminated inside them, started at ``start``'s vectors; every
    other placement stays a key. Its ``factors`` go to iSAM2; ``mirror_vectors(values)`` recovers the
    eliminated ones."""
    views = view_factors_of(dataset, layout, measurements)
    keep = {p for view in views for p in view.reflections if p not in start}
    if any(view.unique_landmarks for view in views):
        evaluator: EliminatedViewStack | EliminatedViewPointStack = EliminatedViewPointStack(views, start, keep, ONE_STACK)
    else:
        evaluator = EliminatedViewStack(views, start, keep, ONE_STACK)
    if set(evaluator.eliminated) != set(start):
        raise RuntimeError(f"a block's placements {sorted(set(start) - set(evaluator.eliminated))} were not eliminated")
    return evaluator


def vector_at(values: gtsam.Values, key: int) -> np.ndarray:
    """The mirror vector ``v = d n`` of the plane at ``key`` in ``values``."""
    return vector_of_plane(values.atOrientedPlane3(key))[0]


def vector_jacobian(v: np.ndarray) -> np.ndarray:
    """``dv/dxi`` (3x3) of the plane of mirror vector ``v``: the vector over the plane's local coordinates."""
    return vector_of_plane(plane_of(v))[1]


def vector_covariance(v: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """The covariance of the plane of mirror vector ``v`` in its local coordinates (iSAM2's, 3x3) as the
    vector's (m^2)."""
    J = vector_jacobian(v)
    return J @ covariance @ J.T
