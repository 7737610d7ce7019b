"""The paper's tree in its own factors, the reference the one measurement model is checked against: the
graph of a dataset with one factor per measurement (``reflection.py``), stacked (``batched.py``) or with
the last mirror's placements eliminated (``eliminated.py``) (eq. 23). Unknowns (eq. 21): one ``Pose3``
node ``X(0)`` for ``T_cam_base``, one ``Point3`` node ``V(i)`` per mirror configuration (mirror vector,
camera frame, metres) and one ``Point3`` node ``L(j)`` per reconstruction point (base frame, metres).
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.data import Dataset
from mirror_fg.solver.model.graph import GraphLayout, InitialEstimate, Measurement, measurement_sigmas, measurements_of
from reference.batched import batched_factors
from reference.eliminated import EliminatedEvaluator, NotEliminable, eliminated_evaluator
from reference.reflection import ReflectionFactor, noise_model

__all__ = ["measurement_factor", "build_graph", "extract_values", "initial_values", "EliminatedGraph",
           "build_eliminated_graph"]


def measurement_factor(
    dataset: Dataset, layout: GraphLayout, meas: Measurement, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """The reflection factor of one measurement (fiducial constant, or landmark node)."""
    mirror_keys = [layout.mirror_keys[(l + 1, m)] for l, m in enumerate(meas.mirror_configs)]
    if meas.point in dataset.fiducials:
        return ReflectionFactor(noise, layout.pose_key, mirror_keys, meas.normalized, fiducial=dataset.fiducials[meas.point])
    return ReflectionFactor(noise, layout.pose_key, mirror_keys, meas.normalized, landmark_key=layout.point_keys[meas.point])


def build_graph(
    dataset: Dataset, initial: InitialEstimate, robust: str | None = None, fast: bool = True
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, GraphLayout, list[Measurement]]:
    """Factor graph of every measurement and the initial values of every unknown.

    fast: stacked, vectorised factors (``factors/batched.py``, same model and Jacobians, per-measurement
    robust weights); otherwise one reference ``ReflectionFactor`` per measurement. Each measurement is
    whitened with its own sigma (:func:`measurement_sigmas`).
    """
    layout = GraphLayout.for_dataset(dataset)
    graph = gtsam.NonlinearFactorGraph()
    measurements = measurements_of(dataset)
    sigmas = measurement_sigmas(dataset, measurements)
    if fast:
        for factor in batched_factors(dataset, layout, measurements, sigmas, robust):
            graph.add(factor)
    else:
        noises: dict[bytes, gtsam.noiseModel.Base] = {}
        for meas, sigma in zip(measurements, sigmas):
            noise = noises.get(sigma.tobytes())
            if noise is None:
                noise = noises[sigma.tobytes()] = noise_model(sigma, robust)
            graph.add(measurement_factor(dataset, layout, meas, noise))
    return graph, initial_values(layout, initial), layout, measurements


def initial_values(layout: GraphLayout, initial: InitialEstimate, without: frozenset = frozenset()) -> gtsam.Values:
    """GTSAM values of every unknown of ``layout`` (but the mirror configurations in ``without``)."""
    values = gtsam.Values()
    values.insert(layout.pose_key, gtsam.Pose3(gtsam.Rot3(initial.R_cam_base), np.asarray(initial.t_cam_base, dtype=float)))
    for config, key in layout.mirror_keys.items():
        if config not in without:
            values.insert(key, np.asarray(initial.mirror_vectors[config], dtype=float))
    for name, key in layout.point_keys.items():
        values.insert(key, np.asarray(initial.points[name], dtype=float))
    return values


def extract_values(
    values: gtsam.Values, layout: GraphLayout, evaluator: EliminatedEvaluator | None = None
) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """``(R_cam_base, t_cam_base, mirror_vectors, points)`` read from GTSAM values (and the placements an
    ``evaluator`` eliminated, at those values)."""
    pose = values.atPose3(layout.pose_key)
    eliminated = evaluator.mirror_vectors(values) if evaluator is not None else {}
    mirror_vectors = {
        config: eliminated[config] if config in eliminated else np.array(values.atPoint3(key))
        for config, key in layout.mirror_keys.items()
    }
    points = {name: np.array(values.atPoint3(key)) for name, key in layout.point_keys.items()}
    return pose.rotation().matrix(), np.array(pose.translation()), mirror_vectors, points


@dataclass
class EliminatedGraph:
    """The graph of ``factors/eliminated.py``: the last mirror's placements solved inside the factors.

    ``values`` holds ``T_cam_base``, the placements of mirrors 1..Nv-1 and the points only;
    ``evaluator`` gives the eliminated placements and every covariance at a solution of ``graph``.
    """

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    layout: GraphLayout
    measurements: list[Measurement]
    evaluator: EliminatedEvaluator


def build_eliminated_graph(
    dataset: Dataset, initial: InitialEstimate, measurements: list[Measurement] | None = None,
    sigmas: np.ndarray | None = None,
) -> EliminatedGraph | None:
    """The eliminated graph (``factors/eliminated.py``) and initial values, or None where the schedule
    does not allow it (a last-mirror placement under two parent placements: use :func:`build_graph`).
    ``measurements`` / ``sigmas``: the dataset's (``measurements_of``, ``measurement_sigmas``) where the
    caller already has them (e.g. one subtree solved from several hypotheses)."""
    layout = GraphLayout.for_dataset(dataset)
    if measurements is None:
        measurements = measurements_of(dataset)
    if sigmas is None:
        sigmas = measurement_sigmas(dataset, measurements)
    try:
        evaluator = eliminated_evaluator(dataset, layout, measurements, sigmas, initial.mirror_vectors)
    except NotEliminable:
        return None
    graph = gtsam.NonlinearFactorGraph()
    for factor in evaluator.factors:
        graph.add(factor)
    evaluator.factors = []  # the factors hold the evaluator: no cycle through C++
    values = initial_values(layout, initial, frozenset(evaluator.eliminated))
    return EliminatedGraph(graph, values, layout, measurements, evaluator)
