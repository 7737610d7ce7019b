"""``verify --update``'s estimate (docs/formats.md, "Has it moved?"): the stored transforms, as priors with
their stored covariance (jointly with the intrinsics or a standing mirror's plane, where ``verify`` holds
them), combined with the new data. Frames and units as ``analysis/verify.py``: ``[dtheta (rad), dt (m)]``
in the uncertainty convention outside, GTSAM's Pose3 tangent inside.
"""
from __future__ import annotations

from typing import Any

import gtsam
import numpy as np

from mirror_fg.core.transform import covariance_from_pose3, covariance_to_pose3

__all__ = ["fused_estimate"]


def fused_estimate(fits: Any, held: gtsam.Values, tested: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The stored transforms (priors, their stored covariance) combined with the new data: the fit with
    every camera held, and each camera's marginal of ``H_data + blockdiag(S^-1)`` (in the convention
    at the fused estimate), never wider than ``S``."""
    H, columns = fits.information(held)
    out = {}
    rotations = {}
    for name in tested:
        estimate = held.atPose3(fits.problem.pose_keys[name])
        R = estimate.rotation().matrix()
        rotations[name] = R
        c = columns[fits.problem.pose_keys[name]]
        if name in fits.intrinsics:  # the pose given the intrinsics (their marginal is in the data graph)
            k = columns[fits.problem.intrinsics_keys[name]]
            B, conditional = fits.intrinsics[name].conditional(covariance_to_pose3(R, fits.stored[name][2]), R)
            E = np.zeros((6, H.shape[0]))
            E[:, c] = np.eye(6)
            E[:, k] = -B
            H += E.T @ np.linalg.inv(conditional) @ E
        elif fits.plane is not None:  # the pose given the held plane (whose marginal is in the data graph)
            gaussian = fits.prior(name).linearize(held)
            A, _ = gaussian.jacobian()
            index = np.concatenate([np.arange(columns[k].start, columns[k].stop) for k in gaussian.keys()])
            H[np.ix_(index, index)] += A.T @ A
        else:
            H[c, c] += np.linalg.inv(covariance_to_pose3(R, fits.stored[name][2]))
    covariance = np.linalg.pinv(H, rcond=1e-14, hermitian=True)
    for name in tested:
        estimate = held.atPose3(fits.problem.pose_keys[name])
        c = columns[fits.problem.pose_keys[name]]
        C = covariance_from_pose3(rotations[name], covariance[c, c])
        out[name] = (rotations[name], np.asarray(estimate.translation(), float), 0.5 * (C + C.T))
    return out
