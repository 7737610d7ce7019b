"""A synthetic multi-camera ``Calibration`` for the output tests (no solver): three cameras with random
poses, a random SPD joint covariance with cross terms, one camera estimating intrinsics, one fisheye."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mirror_fg.core.camera import Camera
from mirror_fg.solver.result.calibration import Calibration, CameraPose, EstimatedCamera
from mirror_fg.solver.model.rig import rig_transforms

NAMES = ("left", "right", "wrist")


def random_spd(rng: np.random.Generator, n: int, rotation_sd: float = 2e-3, position_sd: float = 1.5e-3) -> np.ndarray:
    """An (n, n) SPD covariance (n a multiple of 6) with strong cross terms, pose-like scales per block."""
    scale = np.tile(np.r_[[rotation_sd] * 3, [position_sd] * 3], n // 6)
    A = rng.normal(size=(n, n))
    C = A @ A.T / n + 0.05 * np.eye(n)
    d = np.sqrt(np.diag(C))
    return (C / np.outer(d, d)) * np.outer(scale, scale)


def random_poses(rng: np.random.Generator, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.6, 0.6, size=3)) for _ in range(count)]


def rig_calibration(seed: int = 0, names: tuple[str, ...] = NAMES, covariance: bool = True) -> Calibration:
    """A Calibration with ``cameras`` (``names``), ``camera_pose_covariance``, ``rig`` and ``mirror_frames``."""
    rng = np.random.default_rng(seed)
    poses = random_poses(rng, len(names))
    P = random_spd(rng, 6 * len(names)) if covariance else None
    intrinsics = [
        Camera(1600, 1200, 1510.0, 1505.5, 801.25, 598.75, (-0.11, 0.08, 1e-4, -2e-4, 0.0)),
        Camera(1280, 1024, 1210.0, 1211.0, 640.5, 512.5, (0.01, -0.02, 0.0, 0.0, 0.0)),
        Camera(1920, 1080, 700.0, 700.5, 960.0, 540.0, (0.02, -0.01, 0.003, -0.001), model="fisheye"),
    ]
    estimated_cov = np.diag([4.0, 4.0, 1.0, 1.0]) if covariance else None
    estimated = EstimatedCamera(intrinsics[0], ("fx", "fy", "cx", "cy"), estimated_cov,
                                None if not covariance else 1e-4 * rng.normal(size=(4, 6)))
    cameras = {}
    for k, name in enumerate(names):
        R, t = poses[k]
        block = None if P is None else P[6 * k: 6 * k + 6, 6 * k: 6 * k + 6]
        cameras[name] = CameraPose(name, R, t, block, camera=intrinsics[k % 3], estimated=estimated if k == 0 else None)
    configs = [(1, 0), (1, 1), (1, 2), (2, 0)]
    mirror_vectors = {c: rng.uniform(-0.5, 0.5, size=3) + np.array([0.0, 0.0, 1.0]) for c in configs}
    frames = {c: names[i % len(names)] for i, c in enumerate(configs)}
    first = cameras[names[0]]
    return Calibration(
        R_cam_base=first.R_cam_base, t_cam_base=first.t_cam_base, covariance=first.covariance,
        mirror_vectors=mirror_vectors, mirror_covariances={c: 1e-6 * np.eye(3) for c in configs},
        points={}, point_covariances={}, analytic=None, iterations=5, initial_error=100.0, final_error=40.0,
        converged=True, residuals=0.3 * rng.normal(size=(80, 2)), residual_labels=[("i", "p")] * 80,
        residual_units="px", expected_final_error=38.0, camera=estimated,
        cameras=cameras, camera_pose_covariance=P,
        rig=rig_transforms(list(names), poses, P), mirror_frames=frames,
    )
