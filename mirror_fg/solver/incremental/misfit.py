"""An image's misfit with the estimate so far, judged with that estimate's uncertainty.

The incremental screen (``tree.py``) refuses an image whose fiducials, seen through the estimate's
``T_cam_base`` and parent placements (eqs. 5-8) and the best last mirror (eq. 3, fitted to it alone), reproject
more than ``CONSENSUS_MIN_SIGMAS`` from where they were seen (RMS, whitened). Judged at the estimate's value
alone, an image that constrains the direction the images so far leave loose misfits by tens of sigma while it
agrees with the truth: on a 60-image stream (1 px, 3 fiducials, Huber) thirteen such images in a row were
refused, each the more informative. So the misfit is the Mahalanobis size of the whitened residual ``e``
(2N) under its predicted covariance: ``d^2 = e^T [Q (I + J Sigma J^T) Q]^+ e``, with ``J`` its Jacobian in
the pose (GTSAM's Pose3 tangent) and the parent placements' mirror vectors, ``Sigma`` their joint marginal
from iSAM2, and ``Q`` the projection that takes out the last mirror's three directions (fitted to the
image). With ``Sigma = 0`` it is ``e^T e``, so ``sqrt(d^2 / N)`` is the plain RMS misfit, never larger.
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mirror_fg.core.geometry import nested_transform
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.screen.placement_consensus import fiducial_names, mirror_fit, reflected_errors

__all__ = ["misfit_sigmas_with_uncertainty"]

#: Central differences of the residuals in the pose and the parents' vectors (radians, metres).
_STEP = 1e-6


def misfit_sigmas_with_uncertainty(dataset: Dataset, image: Image, poses: list[tuple[np.ndarray, np.ndarray]],
                                   T_cam_base: gtsam.Pose3, parents: Sequence[np.ndarray],
                                   last: np.ndarray | None, covariance: np.ndarray) -> float:
    """RMS-equivalent misfit ``sqrt(d^2 / N)`` (module docstring) of ``image``'s fiducials at the estimate
    ``T_cam_base`` and ``parents`` (mirror vectors, camera frame, metres, mirror 1 first), its last mirror
    ``last`` where known (else fitted from its PnP ``poses``, as ``consensus.misfit_sigmas``);
    ``covariance``: the joint marginal of the pose (6, GTSAM's tangent) and the parents (3 each)."""
    names = fiducial_names(dataset, image)
    points = np.array([dataset.fiducials[n] for n in names])
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])
    sigma = dataset.normalized_sigma
    R, t = T_cam_base.rotation().matrix(), np.asarray(T_cam_base.translation(), float)
    A_parent, b_parent = nested_transform(R, t, list(parents))  # eqs. (6)-(8)
    _, vector = mirror_fit(dataset, image, poses, A_parent, b_parent, last)
    if not np.all(np.isfinite(vector)):
        return float("inf")
    rows = np.repeat(vector.reshape(1, 3), len(points), axis=0)

    def residuals(pose: gtsam.Pose3, mirrors: Sequence[np.ndarray]) -> np.ndarray:
        A, b = nested_transform(pose.rotation().matrix(), np.asarray(pose.translation(), float), list(mirrors))
        return reflected_errors(points @ A.T + b, rows, observed, sigma, False)[0].ravel()  # eqs. (5), (3), (9)

    e = residuals(T_cam_base, parents)
    _, jacobian_v = reflected_errors(points @ A_parent.T + b_parent, rows, observed, sigma, True)
    assert jacobian_v is not None
    J_v = np.swapaxes(jacobian_v, 0, 1).reshape(-1, 3)  # rows as ``e``: x, y of each fiducial in turn
    columns = []
    for k in range(6):
        step = np.zeros(6)
        step[k] = _STEP
        columns.append((residuals(T_cam_base.retract(step), parents) - residuals(T_cam_base.retract(-step), parents))
                       / (2 * _STEP))
    for level in range(len(parents)):
        for k in range(3):
            plus = [np.array(v, float) for v in parents]
            minus = [np.array(v, float) for v in parents]
            plus[level][k] += _STEP
            minus[level][k] -= _STEP
            columns.append((residuals(T_cam_base, plus) - residuals(T_cam_base, minus)) / (2 * _STEP))
    J = np.array(columns).T  # (2N, 6 + 3 (Nv - 1))
    Q = np.eye(len(e)) - J_v @ np.linalg.pinv(J_v)
    predicted = Q @ (np.eye(len(e)) + J @ covariance @ J.T) @ Q
    d2 = float(e @ np.linalg.pinv(0.5 * (predicted + predicted.T), rcond=1e-10, hermitian=True) @ e)  # rank 2N - 3
    return float(np.sqrt(max(d2, 0.0) / len(points)))
