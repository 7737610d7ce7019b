"""The stored intrinsics as priors of ``verify`` (``analysis/verify.py``): where a result estimated a camera's
intrinsics, its pose covariance includes their uncertainty and the two errors are correlated (result@1's
``camera.covariance`` and ``camera.cross_covariance_cam_base``, docs/formats.md). Holding the intrinsics
at their estimate would charge their error to the pose; instead they are unknowns under their stored
marginal in every fit, and the held pose's prior is the pose *given* the intrinsics:

    xi = Local(T_stored, X) (GTSAM's Pose3 tangent [w, nu]),  kappa = K - K_stored,
    xi | kappa ~ N(B kappa, A - B C B^T),  B = Sigma_xi,kappa C^-1

(``A`` the pose's stored covariance, ``C`` the intrinsics', ``Sigma_xi,kappa`` their cross-covariance, all
in the tangent), which with the marginal prior on ``kappa`` is the stored joint prior exactly.
The convention's ``[dtheta, dt] = blkdiag(R, R) [w, nu]`` (docs/formats.md, "Uncertainty convention").
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import gtsam
import numpy as np

from mirror_fg.factors.intrinsics import IntrinsicsModel
from mirror_fg.solver.batch.intrinsics import camera_intrinsics

__all__ = ["StoredIntrinsics", "stored_intrinsics", "joint_prior"]


@dataclass(frozen=True)
class StoredIntrinsics:
    """One camera's estimated intrinsics as a result stored them, in the ``K`` vector's order
    (``model.estimated``): ``values`` (k,), ``covariance`` (k, k), ``cross`` (k, 6) with the pose's
    ``[dtheta, dt]``."""

    model: IntrinsicsModel
    values: np.ndarray
    covariance: np.ndarray
    cross: np.ndarray

    def marginal_prior(self, key: int) -> gtsam.PriorFactorVector:
        """The intrinsics at their stored values with their stored covariance."""
        return gtsam.PriorFactorVector(key, self.values, gtsam.noiseModel.Gaussian.Covariance(self.covariance))

    def conditional(self, pose_tangent: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(B, covariance)`` of the pose's tangent given the intrinsics (module docstring); ``pose_tangent``
        the pose's stored covariance in the tangent at rotation ``R``."""
        J = np.kron(np.eye(2), R)
        cross_tangent = (self.cross @ J).T  # (6, k): cov(xi, kappa), xi = J^T [dtheta, dt]
        B = cross_tangent @ np.linalg.inv(self.covariance)
        covariance = pose_tangent - B @ cross_tangent.T
        return B, 0.5 * (covariance + covariance.T)


def stored_intrinsics(result: Mapping[str, Any], name: str, camera, source: str) -> StoredIntrinsics | None:
    """Camera ``name``'s estimated intrinsics with their covariances in a validated result (``camera`` the
    camera at the stored values), or None where it estimated none or stored no covariance."""
    block = (result["cameras"][name].get("camera") if result.get("cameras") else result.get("camera")) or {}
    names = list(block.get("estimated") or [])
    if not names or block.get("covariance") is None or block.get("cross_covariance_cam_base") is None:
        return None
    model = IntrinsicsModel(camera_intrinsics(camera), names)
    order = [names.index(n) for n in model.estimated]
    covariance = np.array(block["covariance"], dtype=float)[np.ix_(order, order)]
    cross = np.array(block["cross_covariance_cam_base"], dtype=float)[order]
    return StoredIntrinsics(model, model.fixed[model.index].copy(), covariance, cross)


def joint_prior(pose_key: int, intrinsics_key: int, stored_pose: gtsam.Pose3, stored: StoredIntrinsics,
                pose_tangent: np.ndarray) -> gtsam.CustomFactor:
    """The held pose's prior given the intrinsics (module docstring): error ``xi - B kappa``."""
    B, covariance = stored.conditional(pose_tangent, stored_pose.rotation().matrix())
    return gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Covariance(covariance), [pose_key, intrinsics_key],
                              partial(_conditional_error, stored_pose, stored.values, B))


def _conditional_error(stored_pose: gtsam.Pose3, values0: np.ndarray, B: np.ndarray, this: gtsam.CustomFactor,
                       values: gtsam.Values, jacobians) -> np.ndarray:
    """``Local(T_stored, X) - B (K - K_stored)`` and its Jacobians (GTSAM's CustomFactor shape)."""
    pose_key, intrinsics_key = this.keys()
    H_stored = np.zeros((6, 6), order="F")
    H_pose = np.zeros((6, 6), order="F")
    xi = stored_pose.localCoordinates(values.atPose3(pose_key), H_stored, H_pose)
    kappa = np.asarray(values.atVector(intrinsics_key), float) - values0
    if jacobians is not None:
        jacobians[0] = np.array(H_pose)
        jacobians[1] = -B
    return np.asarray(xi, float) - B @ kappa
