"""Image-level dispersion: do the images agree with each other as closely as their noise model says?

docs/formats.md, "Has it moved? `mirror-fg verify`". Each image's measurements determine its virtual
camera (the camera seen through its mirrors: a 6-dof rigid, or with one mirror improper, transform of
the target; Sect. 3 of the paper). A per-image systematic error (a corner detector's bias, distortion the
model lacks) moves that virtual camera without showing in the image's own residuals: its mirror
placement absorbs it, the residuals look right, the pose is biased. What shows it is how far each image
would go on its own: with the image's camera pose and mirror placements free for it alone, its cost falls
by ``c_i = |P_i r_i|^2`` (whitened rows ``r_i`` at the solution, ``P_i`` the projection onto the column
space of its Jacobian on the camera pose and its mirror placements, rank 6 where the image determines its
virtual camera). Under the noise model (linearised) ``B = sum_i c_i`` has expectation
``nu = sum_i rank_i - sum_i tr(Sigma G_i)`` (``G_i = (U_i^T J_i)^T (U_i^T J_i)``, ``U_i`` an orthonormal
basis of that column space, ``J_i`` the image's whole Jacobian, ``Sigma`` the solution's covariance):
``r = (I - H) e`` so ``E[B] = tr(P (I - H))``. For one camera and one mirror, ``nu = 3 n - 6`` (each
image adds 6 conditions, its placement takes 3, the pose 6).

``factor = B / nu`` is the variance factor of the images' virtual cameras: about 1 where the noise model
holds (``nu factor ~ chi2_nu``), larger where the images disagree beyond it. ``mirror-fg verify`` divides
its statistic by it (an F-test: the noise level estimated from the image-level redundancy, the standard
remedy when sigma is not known). ``nu = 0`` (every image needed to determine the solution): no estimate.
Whitened units (each row by its measurement sigma); measurements the solve left out are not counted.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.io.dataset import Dataset
from mirror_fg.solver.validation import _problem, estimate_of_calibration
from mirror_fg.solver.views import ViewEstimate, tangent_dimension

__all__ = ["Dispersion", "image_dispersion", "dispersion_of_calibration"]


@dataclass(frozen=True)
class Dispersion:
    """``cost``: ``B`` (chi^2 units); ``dof``: ``nu``, its expectation under the noise model; ``images``: how
    many images counted."""

    cost: float
    dof: float
    images: int

    @property
    def factor(self) -> float:
        """``B / nu`` (1 where the noise model holds); NaN where ``nu`` is not positive."""
        return self.cost / self.dof if self.dof > 0.5 else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """result@1's ``dispersion`` (docs/formats.md)."""
        return {"factor": self.factor if self.dof > 0.5 else None, "dof": self.dof, "cost": self.cost,
                "images": self.images}


def dispersion_of_calibration(dataset: Dataset, calibration: Any) -> Dispersion:
    """:func:`image_dispersion` of a calibration of ``dataset`` (stored in its result by ``calibrate``)."""
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded]
    return image_dispersion(dataset, estimate, excluded, estimated)


def image_dispersion(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
                     estimated_cameras: Mapping[str, Any] | None = None) -> Dispersion:
    """``B`` and ``nu`` (module docstring) of ``dataset``'s images at ``estimate``; arguments as
    :func:`~mirror_fg.solver.validation.validate`."""
    used, problem, values, masks = _problem(dataset, estimate, excluded, estimated_cameras)
    graph = problem.graph()
    offset: dict[int, int] = {}
    size = 0
    for key in problem.keys:
        offset[key] = size
        size += tangent_dimension(key, values)
    own_keys = set(problem.pose_keys.values()) | set(problem.mirror_keys.values())
    information = np.zeros((size, size))
    parts = []  # per image: its global columns, U_i^T J_i
    cost = 0.0
    rank_sum = 0
    for factor, mask in zip(problem.factors, masks):
        gaussian = factor.factor().linearize(values)
        A, b = gaussian.jacobian()
        A, r = A[mask], -b[mask]
        columns, own, at = [], [], 0
        for key in gaussian.keys():
            dim = tangent_dimension(key, values)
            columns += list(range(offset[key], offset[key] + dim))
            if key in own_keys:
                own += list(range(at, at + dim))
            at += dim
        information[np.ix_(columns, columns)] += A.T @ A
        if not own or not len(r):
            continue
        U = _range(A[:, own])
        rank_sum += U.shape[1]
        cost += float(np.sum((U.T @ r) ** 2))
        parts.append((np.array(columns, dtype=int), U.T @ A))
    for k in range(len(problem.factors), graph.size()):  # priors (intrinsics, scale): in Sigma only
        gaussian = graph.at(k).linearize(values)
        A, _ = gaussian.jacobian()
        columns = [i for key in gaussian.keys() for i in range(offset[key], offset[key] + tangent_dimension(key, values))]
        information[np.ix_(columns, columns)] += A.T @ A
    covariance = np.linalg.pinv(information, hermitian=True)
    explained = sum(float(np.sum((UJ @ covariance[np.ix_(c, c)]) * UJ)) for c, UJ in parts)
    return Dispersion(cost, max(rank_sum - explained, 0.0), len(parts))


def _range(J: np.ndarray) -> np.ndarray:
    """An orthonormal basis of ``J``'s column space."""
    U, s, _ = np.linalg.svd(J, full_matrices=False)
    rank = int(np.sum(s > max(s[0], 1e-300) * 1e-10)) if len(s) else 0  # as validation's complement
    return U[:, :rank]
