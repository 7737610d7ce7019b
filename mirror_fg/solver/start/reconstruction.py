"""Reconstruction points (Hesch et al., Sect. 5, eqs. 19-20): each unknown point triangulated from the
images that see it, once the pose and mirror vectors are known."""
from __future__ import annotations

from collections import defaultdict
from typing import TYPE_CHECKING

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.geometry import nested_transform
from mirror_fg.data import Dataset, Image

if TYPE_CHECKING:
    from mirror_fg.solver.start.analytic_solution import AnalyticSolution

__all__ = ["triangulate_point", "image_transform", "reconstruct_points"]


def triangulate_point(transforms: list[tuple[np.ndarray, np.ndarray]], normalized: list[np.ndarray]) -> np.ndarray:
    """Base-frame point from >= 2 images: ``s_j u_j = A_j Bp + b_j`` solved in least squares (eq. 20).

    The depths ``s_j`` are eliminated exactly: for a unit ray ``u_j`` the least-squares residual of
    image j is ``(I - u_j u_j^T)(A_j Bp + b_j)``, so eq. (20) reduces to a 3x3 normal equation.
    """
    A = np.array([A for A, _ in transforms])
    b = np.array([b for _, b in transforms])
    rays = np.column_stack([np.asarray(normalized, dtype=float).reshape(-1, 2), np.ones(len(transforms))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)  # eq. (19)
    projectors = np.eye(3) - np.einsum("ia,ib->iab", rays, rays)
    weighted = np.swapaxes(A, 1, 2) @ projectors  # A_j^T (I - u_j u_j^T)
    normal_matrix = np.sum(weighted @ A, axis=0)
    rhs = -np.einsum("iab,ib->a", weighted, b)
    return np.linalg.solve(normal_matrix, rhs)


def image_transform(solution: AnalyticSolution, image: Image) -> tuple[np.ndarray, np.ndarray]:
    """``(A_Nv, b_Nv)`` of an image from the solved pose and mirror vectors (eqs. 6-7)."""
    vectors = [solution.mirror_vectors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)]
    return nested_transform(solution.R_cam_base, solution.t_cam_base, vectors)


def reconstruct_points(
    dataset: Dataset, solution: AnalyticSolution, normalized: dict[str, dict[str, np.ndarray]] | None = None
) -> dict[str, np.ndarray]:
    """Every reconstruction point by eq. (20) from all images that see it.

    ``normalized``: each image's normalized observations (``Dataset.normalized``) when already at hand.
    """
    seen: dict[str, list[Image]] = defaultdict(list)
    for image in dataset.images:
        for name in image.observations:
            if name not in dataset.fiducials:
                seen[name].append(image)
    if not seen:
        return {}
    if normalized is None:
        normalized = {}
    transforms: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    points = {}
    for name in sorted(seen):
        images = seen[name]
        if len(images) < 2:
            raise DatasetError(
                f"{dataset.source}: point '{name}' is seen only in image '{images[0].id}'; "
                "a reconstruction point needs >= 2 images"
            )
        for im in images:
            if im.id not in transforms:
                transforms[im.id] = image_transform(solution, im)
            if im.id not in normalized:
                normalized[im.id] = dataset.normalized(im)
        rays = [normalized[im.id][name] for im in images]
        points[name] = triangulate_point([transforms[im.id] for im in images], rays)
    return points
