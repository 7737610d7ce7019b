"""Each mirror placement's covariance jointly with the camera pose (docs/formats.md, "Has it moved?"): what
``mirror-fg verify`` needs to hold a mirror that still stands at its stored plane, so that one placement
determines the camera (the plane no longer absorbs a rotation about a line in it).

Frames and units: ``v`` the placement's mirror vector in the camera frame (metres, eq. 3's ``v = d n``),
the pose ``[dtheta (rad), dt (m)]`` of ``covariance_cam_base`` (the uncertainty convention). From the
solution's Gauss-Newton information over every unknown (the view model, ``solver/model/views.py``, at the
calibration's estimate; the rows the solve left out dropped): the pose's six columns of its inverse (a
sparse LU), per placement ``(3 x 6)`` of ``v`` with the pose, beside the solver's own ``(3 x 3)`` of ``v``
(``Calibration.mirror_covariances``; a robust solve's marginals carry its weights, the cross-covariance
is the Gaussian model's). Single-camera results only; none where the unknowns have
more than :data:`MAX_COLUMNS` columns (the information is built dense: thousands of hand-held
placements, where no mirror stands still anyway).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from mirror_fg.data import Dataset
from mirror_fg.factors.schur import one_blas_thread
from mirror_fg.factors.views import vector_of_plane
from mirror_fg.solver.fit.validation import _problem, estimate_of_calibration
from mirror_fg.solver.model.views import SINGLE_CAMERA, tangent_dimension

__all__ = ["placement_covariances", "MAX_COLUMNS"]

#: Above this many unknown columns no joint covariance is stored.
MAX_COLUMNS = 1500
#: Up to this many columns the pose's columns of ``H^-1`` come from a dense Cholesky factor, above from a
#: sparse LU (scipy).
DENSE_COLUMNS = 1000


def placement_covariances(dataset: Dataset, calibration: Any) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] | None:
    """``{placement: (covariance of v (3, 3), cross-covariance of v with the pose (3, 6))}`` of a single
    camera's calibration (module docstring), or None (several cameras, an arm, no covariance, too large)."""
    if calibration.cameras or calibration.covariance is None or getattr(calibration, "robot", None):
        return None
    if 6 + 3 * (len(calibration.mirror_vectors) + len(calibration.points)) > MAX_COLUMNS:  # before building anything
        return None
    with one_blas_thread():  # small matrices, many of them: a second BLAS thread only spins (same results)
        return _placement_covariances(dataset, calibration)


def _placement_covariances(dataset: Dataset, calibration: Any) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] | None:
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded]
    _, problem, values, masks = _problem(dataset, estimate, excluded, estimated)
    if SINGLE_CAMERA not in problem.pose_keys:
        return None
    columns, size = {}, 0
    for key in problem.keys:
        dim = tangent_dimension(key, values)
        columns[key] = np.arange(size, size + dim)
        size += dim
    if size > MAX_COLUMNS:
        return None
    H = np.zeros((size, size))
    graph = problem.graph(stacked=False)  # the views' factors first (one per image), then the priors
    for k in range(graph.size()):
        gaussian = graph.at(k).linearize(values)
        A, _ = gaussian.jacobian()
        if k < len(masks):
            A = A[masks[k]]
        index = np.concatenate([columns[key] for key in gaussian.keys()])
        H[np.ix_(index, index)] += A.T @ A
    pose = problem.pose_keys[SINGLE_CAMERA]
    unit = np.zeros((size, 6))
    unit[columns[pose], np.arange(6)] = 1.0
    if size <= DENSE_COLUMNS:  # small: a dense Cholesky (and no scipy to import: a few photographs' start-up)
        try:
            factor = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:  # not positive definite: a direction no image determines
            return None
        pose_columns = np.linalg.solve(factor.T, np.linalg.solve(factor, unit))
    else:
        from scipy.sparse import csc_matrix  # here: `calibrate`'s import loads no scipy (start-up time)
        from scipy.sparse.linalg import splu

        try:  # sparse (each plane meets the pose and the planes seen with it): the pose's columns of H^-1 alone
            pose_columns = splu(csc_matrix(H)).solve(unit)
        except RuntimeError:  # singular: a direction no image determines
            return None
    R = values.atPose3(pose).rotation().matrix()
    to_convention = np.kron(np.eye(2), R)  # [dtheta, dt] = blkdiag(R, R) [w, nu] (GTSAM's right perturbation)
    out = {}
    for placement, key in problem.mirror_keys.items():
        cov_v = calibration.mirror_covariances.get(placement)
        if cov_v is None:
            continue
        J = vector_of_plane(values.atOrientedPlane3(key))[1]  # dv / d(plane tangent)
        cross = J @ pose_columns[columns[key]] @ to_convention.T
        out[placement] = (np.asarray(cov_v, float), cross)
    return out
