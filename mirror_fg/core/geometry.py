"""Geometry kernel of multi-mirror imaging (Hesch et al., ECCV 2010, eqs. 3-9). numpy only.

Frames: {B} base, {C} camera (OpenCV: x right, y down, z forward). ``T_cam_base = (R, t)`` maps base
points into the camera, ``Cp = R @ Bp + t`` (eq. 2). A mirror vector ``v`` (metres, camera frame) is the
shortest vector from the camera centre to the mirror plane; mirror 1 is the first the light meets,
mirror Nv the one the camera looks into.

Pose perturbations follow GTSAM's ``Pose3`` retraction, ``R <- R Exp(w)``, ``t <- t + R nu``, tangent
``[w, nu]``, so the Jacobians below plug straight into custom factors.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "skew",
    "householder",
    "reflect",
    "nested_transform",
    "apply_transform",
    "project",
    "project_jacobian",
    "so3_exp",
    "so3_exp_many",
    "project_to_orthogonal",
    "measurement",
    "measurement_jacobians",
    "householders",
    "reflect_transforms",
    "nested_transforms",
    "predict_camera_points",
    "FLIP_Y",
]

#: Reflection across the camera's xz-plane, ``I - 2 e2 e2^T`` (eq. 11).
FLIP_Y = np.diag([1.0, -1.0, 1.0])


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[w]x`` with ``[w]x @ u == np.cross(w, u)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``Exp(w)`` of an axis-angle vector ``w`` (radians), Rodrigues' formula."""
    w = np.asarray(w, dtype=float)
    angle = float(np.linalg.norm(w))
    K = skew(w)
    if angle < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(angle) / angle * K + (1.0 - np.cos(angle)) / angle**2 * (K @ K)


def so3_exp_many(w: np.ndarray) -> np.ndarray:
    """:func:`so3_exp` of each row of ``w`` (n, 3) at once: rotation matrices (n, 3, 3)."""
    w = np.asarray(w, dtype=float).reshape(-1, 3)
    angle = np.linalg.norm(w, axis=1)
    small = angle < 1e-12
    safe = np.where(small, 1.0, angle)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    first = np.where(small, 1.0, np.sin(angle) / safe)
    second = np.where(small, 0.0, (1.0 - np.cos(angle)) / safe**2)
    return np.eye(3) + first[:, None, None] * K + second[:, None, None] * (K @ K)


def householder(mirror_vector: np.ndarray) -> np.ndarray:
    """Householder matrix ``M = I - 2 v v^T / (v^T v)`` of a mirror vector (eq. 3)."""
    v = np.asarray(mirror_vector, dtype=float)
    return np.eye(3) - 2.0 * np.outer(v, v) / float(v @ v)


def reflect(points: np.ndarray, mirror_vector: np.ndarray) -> np.ndarray:
    """Reflect camera-frame points (..., 3) in the mirror plane of ``mirror_vector``: ``M x + 2 v`` (eq. 3)."""
    v = np.asarray(mirror_vector, dtype=float)
    return points @ householder(v).T + 2.0 * v


def nested_transform(
    R_cam_base: np.ndarray, t_cam_base: np.ndarray, mirror_vectors: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Composite ``(A_Nv, b_Nv)`` of the camera-to-base transform and Nv reflections (eqs. 5-8).

    ``A_0 = R, b_0 = t``; ``A_k = M_k A_{k-1}``, ``b_k = M_k b_{k-1} + 2 v_k``. ``mirror_vectors[0]``
    is mirror 1. The camera sees base point ``Bp`` at ``A_Nv @ Bp + b_Nv``; ``det A_Nv = (-1)^Nv``.
    """
    A = np.array(R_cam_base, dtype=float)  # eq. (8)
    b = np.array(t_cam_base, dtype=float)
    for v in mirror_vectors:
        M = householder(v)
        A = M @ A  # eq. (6)
        b = M @ b + 2.0 * np.asarray(v, dtype=float)  # eq. (7)
    return A, b


# --------------------------------------------------------------------------------------------------
# Batched: many images (mirror placements) at once. The one way to predict every measurement.
# --------------------------------------------------------------------------------------------------


def householders(mirror_vectors: np.ndarray, unit: bool = False) -> np.ndarray:
    """Householder matrices (K, 3, 3) of mirror vectors (K, 3): ``I - 2 v v^T / (v^T v)`` (eq. 3).

    ``unit``: the vectors are unit normals already; use them as they are (renormalising changes their
    last bits, which the mirror peeling's alternation amplifies to ~5e-11 in the covariances).
    """
    v = np.asarray(mirror_vectors, dtype=float).reshape(-1, 3)
    n = v if unit else v / np.linalg.norm(v, axis=1, keepdims=True)
    return np.eye(3) - 2.0 * np.einsum("ka,kb->kab", n, n)


def reflect_transforms(A: np.ndarray, b: np.ndarray, mirror_vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One more mirror on K composite transforms: ``A <- M A``, ``b <- M b + 2 v`` (eqs. 6-7).

    ``A`` (K, 3, 3), ``b`` (K, 3) (or one transform, broadcast), ``mirror_vectors`` (K, 3).
    """
    v = np.asarray(mirror_vectors, dtype=float).reshape(-1, 3)
    M = householders(v)
    return M @ A, np.einsum("kab,kb->ka", M, np.broadcast_to(b, v.shape)) + 2.0 * v


def nested_transforms(
    R_cam_base: np.ndarray, t_cam_base: np.ndarray, mirror_vectors: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Composite ``(A_Nv, b_Nv)`` of K mirror placements at once (eqs. 5-8, batched).

    ``mirror_vectors[l]`` (K, 3): the vector of mirror l+1 in each of the K placements. Returns ``A``
    (K, 3, 3) and ``b`` (K, 3); row k equals ``nested_transform(R, t, [v[k] for v in mirror_vectors])``.
    """
    count = len(mirror_vectors[0]) if len(mirror_vectors) else 1
    A = np.broadcast_to(np.asarray(R_cam_base, dtype=float), (count, 3, 3)).copy()  # eq. (8)
    b = np.broadcast_to(np.asarray(t_cam_base, dtype=float), (count, 3)).copy()
    for vectors in mirror_vectors:
        A, b = reflect_transforms(A, b, vectors)
    return A, b


def predict_camera_points(A: np.ndarray, b: np.ndarray, transform_index: np.ndarray, base_points: np.ndarray) -> np.ndarray:
    """Camera-frame positions (N, 3) of N measured base points (eq. 5), point i seen through
    transform ``transform_index[i]`` of ``A`` (K, 3, 3), ``b`` (K, 3). Project them with :func:`project`."""
    index = np.asarray(transform_index, dtype=int)
    return np.einsum("iab,ib->ia", A[index], np.asarray(base_points, dtype=float)) + b[index]


def apply_transform(A: np.ndarray, b: np.ndarray, base_points: np.ndarray) -> np.ndarray:
    """Camera-frame positions ``A @ Bp + b`` of base points (N, 3) (eq. 5)."""
    return np.asarray(base_points, dtype=float) @ np.asarray(A).T + np.asarray(b)


def project(camera_points: np.ndarray) -> np.ndarray:
    """Normalized image coordinates ``(p1/p3, p2/p3)`` of camera-frame points (..., 3) (eq. 9)."""
    p = np.asarray(camera_points, dtype=float)
    return p[..., :2] / p[..., 2:3]


def project_jacobian(camera_point: np.ndarray) -> np.ndarray:
    """2x3 Jacobian of eq. (9) at one camera-frame point."""
    p1, p2, p3 = camera_point
    inv = 1.0 / p3
    return np.array([[inv, 0.0, -p1 * inv * inv], [0.0, inv, -p2 * inv * inv]])


def project_to_orthogonal(matrix: np.ndarray, determinant: float | None = None) -> np.ndarray:
    """Nearest orthogonal matrix (Frobenius norm) to ``matrix`` (3, 3) or a stack (..., 3, 3), optionally
    with a fixed determinant sign."""
    U, _, Vt = np.linalg.svd(matrix)
    Q = U @ Vt
    if determinant is not None:
        wrong = np.sign(np.linalg.det(Q)) != np.sign(determinant)
        if np.any(wrong):
            U = U.copy()
            U[..., :, -1] *= np.where(wrong, -1.0, 1.0)[..., None]
            Q = U @ Vt
    return Q


def measurement(
    R_cam_base: np.ndarray,
    t_cam_base: np.ndarray,
    mirror_vectors: Sequence[np.ndarray],
    base_point: np.ndarray,
) -> np.ndarray:
    """Predicted normalized measurement ``h`` of one base point through the mirrors (eqs. 5, 9)."""
    A, b = nested_transform(R_cam_base, t_cam_base, mirror_vectors)
    return project(A @ np.asarray(base_point, dtype=float) + b)


def _reflection_jacobian_wrt_mirror(point: np.ndarray, v: np.ndarray) -> np.ndarray:
    """3x3 Jacobian of ``x - 2 v (v.x)/(v.v) + 2 v`` with respect to ``v`` (derivative of eq. 3)."""
    vv = float(v @ v)
    vx = float(v @ point)
    return 2.0 * np.eye(3) - 2.0 * (
        (vx / vv) * np.eye(3) + np.outer(v, point) / vv - 2.0 * vx * np.outer(v, v) / vv**2
    )


def measurement_jacobians(
    R_cam_base: np.ndarray,
    t_cam_base: np.ndarray,
    mirror_vectors: Sequence[np.ndarray],
    base_point: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Predicted measurement and its Jacobians (eqs. 3-9).

    Returns ``(z, H_pose, H_mirrors, H_point)``: ``z`` (2,), ``H_pose`` (2, 6) in GTSAM's Pose3 tangent
    ``[w, nu]`` of ``T_cam_base`` (``R Exp(w)``, ``t + R nu``), one (2, 3) block per mirror vector, and
    ``H_point`` (2, 3) with respect to the base-frame point.
    """
    R = np.asarray(R_cam_base, dtype=float)
    Bp = np.asarray(base_point, dtype=float)
    Cp = R @ Bp + np.asarray(t_cam_base, dtype=float)  # eq. (2)
    # Forward pass: the point before each mirror, and each Householder matrix.
    points_before = []
    householders = []
    x = Cp
    for v in mirror_vectors:
        v = np.asarray(v, dtype=float)
        M = householder(v)
        points_before.append(x)
        householders.append(M)
        x = M @ x + 2.0 * v  # eq. (3)
    J_proj = project_jacobian(x)  # eq. (9)
    # Backward pass: d(final point)/d(point after mirror k) = M_Nv ... M_{k+1}.
    downstream = np.eye(3)
    H_mirrors: list[np.ndarray] = [np.empty((2, 3))] * len(householders)
    for k in range(len(householders) - 1, -1, -1):
        v = np.asarray(mirror_vectors[k], dtype=float)
        H_mirrors[k] = J_proj @ downstream @ _reflection_jacobian_wrt_mirror(points_before[k], v)
        downstream = downstream @ householders[k]
    J_cam = J_proj @ downstream  # d z / d Cp; downstream = M_Nv ... M_1
    H_pose = np.hstack([J_cam @ (-R @ skew(Bp)), J_cam @ R])
    H_point = J_cam @ R
    return project(x), H_pose, H_mirrors, H_point
