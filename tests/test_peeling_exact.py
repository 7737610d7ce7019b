"""One node of the paper's peeling (solver/start/peeling.py, eqs. 13-17) on noise-free children: the parent's
``(A, b)`` and every child's mirror vector come out exact, however many children and observations.

The children are made here from eq. (3) alone: ``A_l = M_m A_{l-1}``, ``b_l = M_m b_{l-1} + 2 v_m``
with ``M_m = I - 2 n_m n_m^T`` and ``v_m = d_m n_m``."""
import numpy as np
import pytest

from mirror_fg.solver.start.peeling import solve_children

TOLERANCE = 1e-9


def rotation(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def facing_normals(rng, count: int, spread_deg: float) -> np.ndarray:
    """Unit normals within ``spread_deg`` of the optical axis, pointing back at the camera (-z)."""
    tilt = np.radians(rng.uniform(5.0, spread_deg, count))
    azimuth = rng.uniform(0.0, 2 * np.pi, count)
    return -np.c_[np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]


@pytest.mark.parametrize("children,repeats,parent_det,seed", [
    (3, 1, 1.0, 0), (5, 2, -1.0, 1), (8, 1, 1.0, 2), (20, 2, -1.0, 3), (40, 1, 1.0, 4)])
def test_a_node_of_noise_free_children_is_exact(children, repeats, parent_det, seed):
    rng = np.random.default_rng(seed)
    A_parent = rotation(rng) * (1.0 if parent_det > 0 else -1.0)  # det(-R) = -1: a parent behind an odd count
    b_parent = np.array([0.05, -0.1, 0.6]) + rng.normal(0.0, 0.05, 3)
    normals = facing_normals(rng, children, 35.0)
    distances = rng.uniform(0.3, 0.7, children)
    observations = []
    for _ in range(repeats):
        for k, (n, d) in enumerate(zip(normals, distances)):
            M = np.eye(3) - 2.0 * np.outer(n, n)  # eq. (3)
            observations.append((k, M @ A_parent, M @ b_parent + 2.0 * d * n))
    solution = solve_children(observations, children, parent_det)
    assert np.abs(solution.A_parent - A_parent).max() < TOLERANCE
    assert np.linalg.norm(solution.b_parent - b_parent) < TOLERANCE
    for k, v in enumerate(solution.mirror_vectors):
        assert np.linalg.norm(v - distances[k] * normals[k]) < TOLERANCE, k
    assert solution.residual < 1e-12
