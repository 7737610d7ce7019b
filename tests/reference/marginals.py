"""Marginal covariances of the tree's own factor graphs (``graph.py``) at the MLE, the reference the one
model's covariances (``views.ViewProblem.covariances``) are checked against.

Pose covariance in docs/formats.md's convention ``[dtheta (rad), dt (m)]`` (converted from GTSAM's Pose3
tangent by :func:`~mirror_fg.core.transform.covariance_from_pose3`); mirror vectors (camera frame) and
points (base frame) 3x3 in m^2.
"""
from __future__ import annotations

from types import SimpleNamespace

import gtsam
import numpy as np

from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.data import Dataset
from mirror_fg.solver.model.graph import GraphLayout
from mirror_fg.solver.model.marginals import unconstrained_as_solve_error, unconstrained_message
from reference.eliminated import EliminatedEvaluator
from reference.graph import build_graph, extract_values

__all__ = ["marginal_covariances", "eliminated_covariances"]


def marginal_covariances(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: GraphLayout, source: str
) -> tuple[np.ndarray, dict, dict]:
    """Pose covariance (docs/formats.md convention), mirror and point covariances at ``values``.

    The information matrix ``J^T J`` of the linearised graph is split into the last mirror's
    placements, which never share a measurement (so their block is block-diagonal), and everything
    else; the Schur complement gives every marginal exactly, far faster than per-key
    ``gtsam.Marginals`` queries. Should a factor ever couple two of those placements, this falls back
    to ``gtsam.Marginals``.
    """
    last_mirror = max(l for l, _ in layout.mirror_keys) if layout.mirror_keys else 0
    diagonal_keys = [k for (l, _), k in layout.mirror_keys.items() if l == last_mirror]
    diagonal_index = {k: i for i, k in enumerate(diagonal_keys)}
    rest_keys = [layout.pose_key] + [k for (l, _), k in layout.mirror_keys.items() if l != last_mirror]
    rest_keys += list(layout.point_keys.values())
    rest_offset, size = {}, 0
    for key in rest_keys:
        rest_offset[key] = size
        size += 6 if key == layout.pose_key else 3
    A = np.zeros((size, size))  # rest-rest information
    B = np.zeros((len(diagonal_keys), size, 3))  # rest-placement information
    D = np.zeros((len(diagonal_keys), 3, 3))  # placement information (block-diagonal)
    linear = graph.linearize(values)
    for f in range(linear.size()):
        factor = linear.at(f)
        J = factor.jacobian()[0]  # whitened, columns in the factor's key order
        rest_columns: list[int] = []
        rest_index: list[int] = []
        diagonal_blocks: list[tuple[int, np.ndarray]] = []
        column = 0
        for key in factor.keys():
            width = 6 if key == layout.pose_key else 3
            if key in diagonal_index:
                diagonal_blocks.append((diagonal_index[key], J[:, column : column + width]))
            else:
                rest_columns.extend(range(column, column + width))
                rest_index.extend(range(rest_offset[key], rest_offset[key] + width))
            column += width
        J_rest = J[:, rest_columns]
        A[np.ix_(rest_index, rest_index)] += J_rest.T @ J_rest
        for n, (i, J_block) in enumerate(diagonal_blocks):
            B[i][rest_index] += J_rest.T @ J_block
            D[i] += J_block.T @ J_block
            for _, other in diagonal_blocks[n + 1 :]:
                if np.any(J_block.T @ other != 0.0):
                    return _marginals_from_gtsam(graph, values, layout, source)
    try:
        D_inv = np.linalg.inv(D)
        BD = B @ D_inv  # B_i D_i^-1, (n, size, 3)
        schur = A - BD.transpose(1, 0, 2).reshape(size, -1) @ B.transpose(1, 0, 2).reshape(size, -1).T
        rest_covariance = np.linalg.inv(schur)
    except np.linalg.LinAlgError:
        return _marginals_from_gtsam(graph, values, layout, source)
    if not np.all(np.isfinite(rest_covariance)) or np.min(np.linalg.eigvalsh(schur)) <= 1e-12 * np.max(np.diag(schur)):
        return _marginals_from_gtsam(graph, values, layout, source)
    DB = BD.transpose(0, 2, 1)  # D_i^-1 B_i^T (D symmetric)
    diagonal_covariances = D_inv + (DB @ rest_covariance) @ BD
    pose = values.atPose3(layout.pose_key)
    covariance = covariance_from_pose3(pose.rotation().matrix(), rest_covariance[:6, :6])

    def block(key: int) -> np.ndarray:
        if key in diagonal_index:
            return diagonal_covariances[diagonal_index[key]]
        o = rest_offset[key]
        return rest_covariance[o : o + 3, o : o + 3]

    mirrors = {config: block(key) for config, key in layout.mirror_keys.items()}
    points = {name: block(key) for name, key in layout.point_keys.items()}
    return covariance, mirrors, points


def eliminated_covariances(
    dataset: Dataset, evaluator: EliminatedEvaluator, values: gtsam.Values, layout: GraphLayout
) -> tuple[np.ndarray, dict, dict]:
    """The same marginals from the graph of ``factors/eliminated.py`` at its solution ``values``: the
    kept unknowns' information is the Schur complement its factors hold; the eliminated placements'
    covariances follow from it. Where that information is singular the full graph is built and
    :func:`marginal_covariances` names the unconstrained unknown."""
    found = evaluator.covariances(values)
    if found is None:
        R, t, mirror_vectors, points = extract_values(values, layout, evaluator)
        estimate = SimpleNamespace(R_cam_base=R, t_cam_base=t, mirror_vectors=mirror_vectors, points=points)
        graph, full_values, _, _ = build_graph(dataset, estimate)
        return marginal_covariances(graph, full_values, layout, dataset.source)
    kept, eliminated = found
    offsets = evaluator.kept_offsets()
    pose = values.atPose3(layout.pose_key)
    covariance = covariance_from_pose3(pose.rotation().matrix(), kept[:6, :6])

    def block(key: int) -> np.ndarray:
        o = offsets[key]
        return kept[o : o + 3, o : o + 3]

    mirrors = {config: eliminated[config] if config in eliminated else block(key) for config, key in layout.mirror_keys.items()}
    points = {name: block(key) for name, key in layout.point_keys.items()}
    return covariance, mirrors, points


def _marginals_from_gtsam(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: GraphLayout, source: str
) -> tuple[np.ndarray, dict, dict]:
    """The same marginals from ``gtsam.Marginals`` (also names unconstrained unknowns)."""
    with unconstrained_as_solve_error(source, lambda error: unconstrained_message(error, layout)):
        marginals = gtsam.Marginals(graph, values)
    pose = values.atPose3(layout.pose_key)
    covariance = covariance_from_pose3(pose.rotation().matrix(), marginals.marginalCovariance(layout.pose_key))
    mirrors = {config: marginals.marginalCovariance(key) for config, key in layout.mirror_keys.items()}
    points = {name: marginals.marginalCovariance(key) for name, key in layout.point_keys.items()}
    return covariance, mirrors, points
