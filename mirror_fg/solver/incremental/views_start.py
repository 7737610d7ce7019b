"""Which waiting images of the general view model can join the incremental graph, and the values of the
unknowns they bring (``views.py``; the rules of ``propagation.py``).

The propagation's known state is seeded from the current estimate (camera poses, base-frame planes of
the placements, ``propagation.plane_from_camera``, points; fiducials), then run over the waiting images
only: every unknown of an image already in the graph has a value, so only the waiting ones can start
something new. Without a known target, the first camera's views (in the graph and waiting) seed what
the estimate lacks with Takahashi et al.'s linear start (rule 5) as ``propagate`` does: its base frame is
the first camera's, its scale the ``scale`` the estimate also meets.

An image joins when the propagation knows its camera's pose, the pose of each of its placements' owner
cameras, every placement's plane and every point it sees; a new point must further be seen by two
joining images (two measurements do not fix a point's three coordinates), else the images that see it
wait. Last, the joining images' factors must determine their new unknowns given the graph's (full column
rank of their Jacobian in the new unknowns, the scale prior counted at the first update): when the graph
determines its unknowns and the new factors determine the new ones, the whole system is determined.

The new unknowns' values are then moved to their optimum under the joining factors with the graph's
unknowns held (:func:`refined_new`); the first update's start meets the scale exactly
(:func:`scaled_start`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from mirror_fg.data import Dataset, Image, Scale
from mirror_fg.solver.model.lm import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.start.propagation import ViewObs, _Propagator, mirror_vector_in, plane_from_camera, takahashi_start
from mirror_fg.solver.model.views import ViewEstimate, tangent_dimension
from mirror_fg.solver.batch.views_solve import tree_start_for

__all__ = ["Joining", "joining_views", "determines_new_unknowns", "lm_settings", "refined_new", "scaled_start"]

#: Levenberg-Marquardt iterations that move an update's new unknowns to their optimum before iSAM2.
REFINE_ITERATIONS = 100
#: Levenberg-Marquardt's largest damping, times ``lm.cost_scale`` (:func:`lm_settings`).
LAMBDA_UPPER_BOUND = GENERAL_LAMBDA_UPPER_BOUND
#: Smallest singular value, relative to the largest, of the new unknowns' whitened Jacobian columns.
MIN_RELATIVE_SINGULAR_VALUE = 1e-9


@dataclass
class Joining:
    """Waiting images that can join (indices into the waiting list) and the values of their new
    unknowns: poses ``{camera: (R, t)}``, mirror vectors (owner frames), points (base frame)."""

    indices: list[int]
    poses: dict[str, tuple[np.ndarray, np.ndarray]]
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]


def joining_views(dataset: Dataset, waiting: list[tuple[Image, ViewObs]], estimate: ViewEstimate,
                  owners: dict[tuple[int, int], str], cameras: list[str],
                  fixed: dict[str, tuple[np.ndarray, np.ndarray]], graph_views: list[ViewObs],
                  options: SolveOptions) -> Joining:
    """The waiting images whose every unknown the propagation can start (module docstring);
    ``graph_views``: the views of the images in the graph (rule 5 solves them with the waiting ones);
    ``options``: the calibrator's (they reach rule 2's solves)."""
    views = [view for _, view in waiting]
    tree_start = tree_start_for(replace(dataset, images=[image for image, _ in waiting]), options)
    propagator = _Propagator(views, dataset.fiducials, cameras, fixed, tree_start)
    known = propagator.known
    known.poses.update(estimate.poses)
    reflected = {p for view in views for p in view.reflections}  # the propagation runs over the waiting views alone
    for p, v in estimate.mirror_vectors.items():
        if p in reflected:  # (every placement so far: a cost that grew with the images in the graph)
            known.planes[p] = plane_from_camera(v, estimate.poses[owners[p]])
    known.points.update(estimate.points)
    lacking = any(p not in estimate.mirror_vectors for view in views for p in view.reflections) or any(
        name not in estimate.points for view in views for name in view.names)
    if not dataset.fiducials and dataset.scale is not None and lacking:  # rule 5, as propagate() does
        seeded = takahashi_start(graph_views + views, cameras[0], dataset.scale)
        if seeded is not None:  # where the estimate has no value yet
            for p, plane in seeded.planes.items():
                known.planes.setdefault(p, plane)
            for name, x in seeded.points.items():
                known.points.setdefault(name, x)
    propagator.run()

    def startable(view: ViewObs) -> bool:
        return (view.camera in known.poses and all(p in known.planes and owners[p] in known.poses
                                                   for p in view.reflections)
                and all(name in known.points for name in view.names))

    indices = [k for k, view in enumerate(views) if startable(view)]
    while True:  # a new point needs two joining images
        seen: dict[str, int] = {}
        for k in indices:
            for name in set(views[k].names):
                if name not in estimate.points and name not in dataset.fiducials:
                    seen[name] = seen.get(name, 0) + 1
        lonely = {name for name, count in seen.items() if count < 2}
        kept = [k for k in indices if not lonely.intersection(views[k].names)]
        if kept == indices:
            break
        indices = kept
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    mirrors: dict[tuple[int, int], np.ndarray] = {}
    points: dict[str, np.ndarray] = {}
    for k in indices:
        view = views[k]
        for camera in [view.camera, *(owners[p] for p in view.reflections)]:
            if camera not in estimate.poses and camera not in fixed:
                poses[camera] = known.poses[camera]
        for p in view.reflections:
            if p not in estimate.mirror_vectors:
                mirrors[p] = mirror_vector_in(known.planes[p], known.poses[owners[p]])
        for name in view.names:
            if name not in estimate.points and name not in dataset.fiducials:
                points[name] = np.asarray(known.points[name], float)
    return Joining(indices, poses, mirrors, points)


def determines_new_unknowns(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, new_keys: list[int]) -> bool:
    """Whether ``factors``' whitened Jacobian at ``values`` has full column rank in ``new_keys``."""
    if not new_keys:
        return True
    columns: dict[int, int] = {}
    width = 0
    for key in new_keys:
        columns[key] = width
        width += tangent_dimension(key)
    blocks = []
    for i in range(factors.size()):
        linear = factors.at(i).linearize(values)
        A, _ = linear.jacobian()
        row = np.zeros((A.shape[0], width))
        offset = 0
        for key in linear.keys():
            dim = tangent_dimension(key)
            if key in columns:
                row[:, columns[key]:columns[key] + dim] = A[:, offset:offset + dim]
            offset += dim
        blocks.append(row)
    J = np.vstack(blocks)
    if J.shape[0] < J.shape[1]:
        return False
    s = np.linalg.svd(J, compute_uv=False)
    return bool(s[-1] > MIN_RELATIVE_SINGULAR_VALUE * s[0])


def lm_settings(max_iterations: int, dataset: Dataset) -> gtsam.LevenbergMarquardtParams:
    """The batch's Levenberg-Marquardt settings (``lm.lm_params``) with room for the damping to grow to
    :data:`LAMBDA_UPPER_BOUND` (times ``lm.cost_scale``): from a start far off (a gross measurement among
    the first images) the batch's bound, 1e5, stops it before its first step."""
    return lm_params(max_iterations, cost_scale(dataset), LAMBDA_UPPER_BOUND)


def refined_new(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, everything: gtsam.Values,
                dataset: Dataset) -> gtsam.Values:
    """The new unknowns moved to their optimum under the joining images' factors, the graph's unknowns
    held at the estimate (Levenberg-Marquardt, eq. 23; at the first update this is the start's LM
    refinement): iSAM2's undamped Gauss-Newton steps then start near the minimum."""
    graph = gtsam.NonlinearFactorGraph(factors)
    start = gtsam.Values()
    for key in sorted(set(factors.keyVector())):
        if tangent_dimension(key) == 6:
            pose = everything.atPose3(key)
            start.insert(key, pose)
            if not values.exists(key):
                graph.add(gtsam.NonlinearEqualityPose3(key, pose))
        elif _is_plane(key):
            plane = everything.atOrientedPlane3(key)
            start.insert(key, plane)
            if not values.exists(key):
                graph.add(_held_plane(key, plane))
        else:
            x = everything.atPoint3(key)
            start.insert(key, x)
            if not values.exists(key):
                graph.add(gtsam.NonlinearEqualityPoint3(key, x))
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, start, lm_settings(REFINE_ITERATIONS, dataset)).optimize()
    except RuntimeError:  # let iSAM2 try from the propagation's values
        return values
    refined = gtsam.Values()
    for key in values.keys():
        if tangent_dimension(key) == 6:
            refined.insert(key, result.atPose3(key))
        elif _is_plane(key):
            refined.insert(key, result.atOrientedPlane3(key))
        else:
            refined.insert(key, result.atPoint3(key))
    return refined



def scaled_start(new: ViewEstimate, scale: Scale | None) -> ViewEstimate | None:
    """The start with the scale constraint met exactly (no known target), as ``ViewProblem`` does; None
    where the scale's placement or points are not among its unknowns."""
    if scale is None:
        return new
    if scale.placement is not None:
        if scale.placement not in new.mirror_vectors:
            return None
        length = float(np.linalg.norm(new.mirror_vectors[scale.placement]))
    else:
        a, b = scale.points  # type: ignore[misc]
        if a not in new.points or b not in new.points:
            return None
        length = float(np.linalg.norm(new.points[a] - new.points[b]))
    f = scale.distance / length
    return ViewEstimate({n: (R, t * f) for n, (R, t) in new.poses.items()},
                        {p: v * f for p, v in new.mirror_vectors.items()},
                        {n: x * f for n, x in new.points.items()})


def _is_plane(key: int) -> bool:
    """Whether a key is a placement's plane ``V(i)`` (``OrientedPlane3``, solver/model/views.py)."""
    return gtsam.Symbol(key).chr() == ord("v")


def _held_plane(key: int, plane: gtsam.OrientedPlane3) -> gtsam.CustomFactor:
    """A plane held where it is (GTSAM has no NonlinearEquality for OrientedPlane3): its local
    coordinates from ``plane``, with a sigma far below any measurement's effect."""
    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        if jacobians is not None:
            jacobians[0] = np.eye(3)
        return np.asarray(plane.localCoordinates(values.atOrientedPlane3(key)), dtype=float)
    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(3, 1e-9), [key], error)


