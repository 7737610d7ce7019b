"""Custom GTSAM factor for one multi-reflection measurement (Hesch et al., eqs. 5, 9, 23).

Shape follows GTSAM's ``CustomFactorExample.py``: a plain ``error(measurement, this, values, jacobians)``
function bound with ``functools.partial``, returning the *unwhitened* error ``h(x) - z`` and filling
``jacobians[i]`` only when asked.

Keys, in order: the ``Pose3`` node of ``T_cam_base`` (camera <- base), one ``Point3`` mirror-vector node
per mirror (mirror 1 first; metres, camera frame), and, for a reconstruction point, its ``Point3`` landmark
node (base frame, metres). A fiducial's base-frame position is a constant of the factor.
"""
from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from mirror_fg.core.geometry import measurement_jacobians
from mirror_fg.factors.robust import ROBUST_K, robust_noise_model

__all__ = ["reflection_error", "ReflectionFactor", "noise_model"]


def reflection_error(
    measurement: np.ndarray,
    fiducial: np.ndarray | None,
    num_mirrors: int,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    jacobians: list[np.ndarray] | None,
) -> np.ndarray:
    """Error ``h(T_cam_base, v_1..v_Nv, Bp) - z`` in normalized image coordinates (eq. 9).

    measurement: observed normalized coordinates (2,). fiducial: known base-frame point (3,), metres,
    or ``None`` when the last key is a landmark. num_mirrors: Nv, the number of mirror keys.
    """
    keys = this.keys()
    pose = values.atPose3(keys[0])
    mirror_vectors = [values.atPoint3(keys[1 + k]) for k in range(num_mirrors)]
    base_point = fiducial if fiducial is not None else values.atPoint3(keys[1 + num_mirrors])
    z, H_pose, H_mirrors, H_point = measurement_jacobians(
        pose.rotation().matrix(), pose.translation(), mirror_vectors, base_point
    )
    if jacobians is not None:
        jacobians[0] = H_pose
        for k in range(num_mirrors):
            jacobians[1 + k] = H_mirrors[k]
        if fiducial is None:
            jacobians[1 + num_mirrors] = H_point
    return z - measurement


def noise_model(
    sigma_normalized: np.ndarray, robust: str | None = None, robust_k: float = ROBUST_K
) -> gtsam.noiseModel.Base:
    """Diagonal measurement noise (2,) in normalized coordinates, optionally wrapped in a robust kernel.

    robust: ``None``, ``"huber"`` or ``"cauchy"``; ``robust_k`` is the kernel's threshold in sigmas.
    """
    return robust_noise_model(gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_normalized, dtype=float)), robust, robust_k)


def ReflectionFactor(
    noise: gtsam.noiseModel.Base,
    pose_key: int,
    mirror_keys: list[int],
    measurement: np.ndarray,
    fiducial: np.ndarray | None = None,
    landmark_key: int | None = None,
) -> gtsam.CustomFactor:
    """One multi-reflection projection factor: a fiducial (constant) or a landmark node, never both."""
    if (fiducial is None) == (landmark_key is None):
        raise ValueError("give exactly one of fiducial and landmark_key")
    keys = [pose_key, *mirror_keys] + ([landmark_key] if landmark_key is not None else [])
    fiducial_array = None if fiducial is None else np.asarray(fiducial, dtype=float)
    error = partial(reflection_error, np.asarray(measurement, dtype=float), fiducial_array, len(mirror_keys))
    return gtsam.CustomFactor(noise, keys, error)
