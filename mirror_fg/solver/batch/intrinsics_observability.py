"""Whether the photographs determine the estimated intrinsics (``intrinsics.py`` estimates them).

Observability criterion (Fisher information). ``F = J^T J`` of the whitened pixel factors at the start
values; the intrinsics' marginal information is its Schur complement ``S`` with every other unknown
(pose, mirrors, points) eliminated; ``C = S^-1`` is the Cramér-Rao bound of the intrinsics. Each
intrinsic is measured by what it does to the image: ``sigma_corner_i = sqrt(C_ii) * s_i`` with ``s_i``
the displacement (pixels) at the farthest image corner per unit of it (``fx``: ``x_c``; ``cx``: 1;
``k1``: ``f x_c r_c^2`` ...; see :func:`corner_sensitivity`).

* **unobservable** (refused, :class:`SolveError`): ``S`` not positive definite (smallest eigenvalue of
  the scaled ``S`` below ``UNOBSERVABLE_RCOND`` times its largest), or ``3 sigma_corner`` of an intrinsic
  above ``UNOBSERVABLE_FRACTION`` of the image diagonal: such an "estimate" is no calibration (measured:
  nine simulated photographs of a 10-point board estimating all nine intrinsics, k2 and k3 at 300-400 px
  for a 1280 px diagonal, refused; the five real photographs of shared/data/takahashi2012 with six
  intrinsics reach at most 65 px (cx) for a 2000 px diagonal, accepted with a warning);
* **weak** (:class:`WeakIntrinsicsWarning`, the result is returned): ``3 sigma_corner`` of an intrinsic at
  the final estimate above ``WEAK_CORNER_PX`` pixels.
"""
from __future__ import annotations

import logging
import warnings

import gtsam
import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.factors.intrinsics import intrinsics_key
from mirror_fg.factors.views import vector_of_plane
from mirror_fg.solver.model.views import ViewProblem, tangent_dimension

__all__ = ["WeakIntrinsicsWarning", "IntrinsicsObservability", "intrinsics_observability", "corner_sensitivity",
           "unobservable_refusal", "warn_weak", "ADVICE", "WEAK_CORNER_PX", "UNOBSERVABLE_RCOND", "UNOBSERVABLE_FRACTION"]

logger = logging.getLogger("mirror_fg")

#: An intrinsic whose 3-sigma moves the farthest image corner by more than this (pixels) is weak.
WEAK_CORNER_PX = 5.0
#: An intrinsic whose 3-sigma moves the farthest image corner by more than this fraction of the image
#: diagonal is unobservable (refused).
UNOBSERVABLE_FRACTION = 0.1
#: The scaled marginal information of the intrinsics is singular below this ratio of its eigenvalues.
UNOBSERVABLE_RCOND = 1e-10
#: What a user can add when intrinsics are weak or unobservable.
ADVICE = ("add more points per image (a larger grid of fiducials), more tilt of the target in the "
          "mirrors, or more mirror placements")


class WeakIntrinsicsWarning(UserWarning):
    """The data constrain an estimated intrinsic only weakly (module docstring: the criterion)."""


def corner_sensitivity(camera: Camera, names: tuple[str, ...]) -> np.ndarray:
    """Pixels the farthest image corner moves per unit of each intrinsic of ``names`` (undistorted
    normalized corner ``(x_c, y_c)``, ``r_c^2 = x_c^2 + y_c^2``, ``f = max(fx, fy)``)."""
    xc = max(camera.cx, camera.width - 1 - camera.cx) / camera.fx
    yc = max(camera.cy, camera.height - 1 - camera.cy) / camera.fy
    r2 = xc * xc + yc * yc
    f = max(camera.fx, camera.fy)
    r = np.sqrt(r2)
    per_unit = {"fx": xc, "fy": yc, "cx": 1.0, "cy": 1.0, "k1": f * r * r2, "k2": f * r * r2**2,
                "k3": f * r * r2**3, "p1": 3.0 * f * r2, "p2": 3.0 * f * r2}
    return np.array([per_unit[n] for n in names])


class IntrinsicsObservability:
    """The intrinsics' Cramér-Rao bound from the Fisher information (module docstring)."""

    def __init__(self, names: tuple[str, ...], covariance: np.ndarray | None, sigma3_corner_px: np.ndarray,
                 singular: bool, diagonal_px: float) -> None:
        self.names = names
        self.covariance = covariance  # (k, k), None when singular
        self.sigma3_corner_px = sigma3_corner_px  # (k,), inf when singular
        self.singular = singular
        self.diagonal_px = diagonal_px

    @property
    def unobservable(self) -> list[str]:
        """Names whose 3-sigma corner displacement exceeds UNOBSERVABLE_FRACTION of the image diagonal
        (all when singular)."""
        if self.singular:
            return list(self.names)
        limit = UNOBSERVABLE_FRACTION * self.diagonal_px
        return [n for n, s in zip(self.names, self.sigma3_corner_px) if not s <= limit]

    @property
    def weak(self) -> list[str]:
        """Names whose 3-sigma corner displacement exceeds WEAK_CORNER_PX."""
        return [n for n, s in zip(self.names, self.sigma3_corner_px) if not s <= WEAK_CORNER_PX]

    def describe(self, names: list[str]) -> str:
        """``fx (3-sigma 12.3 px at the corner), ...``."""
        by_name = dict(zip(self.names, self.sigma3_corner_px))
        return ", ".join(f"{n} (3-sigma {by_name[n]:.3g} px at the image corner)" for n in names)


def intrinsics_observability(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: ViewProblem,
                             camera: Camera, names: tuple[str, ...]) -> IntrinsicsObservability:
    """Fisher information of ``graph`` at ``values``, the intrinsics' Schur complement and their bound."""
    key = intrinsics_key()
    others = [k for k in layout.keys if k != key]  # the pose, the placements' planes, the points
    ordering = gtsam.Ordering()
    for k in [key, *others]:
        ordering.push_back(k)
    information, _ = graph.linearize(values).hessian(ordering)
    k = len(names)
    information = _in_mirror_vectors(information, [key, *others], values, set(layout.mirror_keys.values()))
    scale = corner_sensitivity(camera, names)
    diagonal = float(np.hypot(camera.width, camera.height))
    A, B, D = information[:k, :k], information[:k, k:], information[k:, k:]
    # Jacobi-scale the rest so that its conditioning does not depend on units (metres, radians).
    d = np.sqrt(np.maximum(np.diag(D), np.finfo(float).tiny))
    D_scaled = D / np.outer(d, d)
    try:
        rest_eig = np.linalg.eigvalsh(D_scaled)
        if rest_eig[0] <= UNOBSERVABLE_RCOND * rest_eig[-1]:
            raise np.linalg.LinAlgError
        schur = A - (B / d) @ np.linalg.solve(D_scaled, (B / d).T)
    except np.linalg.LinAlgError:
        return IntrinsicsObservability(names, None, np.full(k, np.inf), True, diagonal)
    scaled = schur / np.outer(scale, scale)  # information in "pixels at the corner"
    eig = np.linalg.eigvalsh(scaled)
    if not eig[0] > UNOBSERVABLE_RCOND * max(eig[-1], np.finfo(float).tiny):
        return IntrinsicsObservability(names, None, np.full(k, np.inf), True, diagonal)
    covariance = np.linalg.inv(schur)
    return IntrinsicsObservability(names, covariance, 3.0 * np.sqrt(np.diag(covariance)) * scale, False, diagonal)


def _in_mirror_vectors(information: np.ndarray, keys: list[int], values: gtsam.Values, planes: set[int]) -> np.ndarray:
    """``information`` (in ``keys``' order and GTSAM's local coordinates) with each placement's columns in its
    mirror vector ``v = d n`` instead of its plane's coordinates (``views.vector_of_plane``: ``dv = J dxi``,
    so ``H_v = J^-T H J^-1``): the intrinsics' Schur complement does not depend on it, but the check of the
    rest's conditioning does, and it is stated for the mirror vectors (where one nears the camera centre,
    the rest is singular)."""
    T = np.eye(len(information))
    at = 0
    for key in keys:
        dim = tangent_dimension(key, values)
        if key in planes:
            J = vector_of_plane(values.atOrientedPlane3(key))[1]
            T[at:at + 3, at:at + 3] = np.linalg.pinv(J)
        at += dim
    return T.T @ information @ T


def unobservable_refusal(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: ViewProblem,
                  camera: Camera, names: tuple[str, ...], source: str) -> str | None:
    """The one-line refusal when the Fisher information at ``values`` leaves an intrinsic unobservable."""
    observability = intrinsics_observability(graph, values, layout, camera, names)
    unobservable = observability.unobservable
    if not unobservable:
        return None
    what = (", ".join(unobservable) + " (their Fisher information is singular)"
            if observability.singular else observability.describe(unobservable))
    return f"{source}: camera.estimate: the photographs do not determine {what}; {ADVICE}, or estimate fewer intrinsics"


def warn_weak(covariance: np.ndarray, camera: Camera, names: tuple[str, ...], source: str) -> None:
    """WeakIntrinsicsWarning (and a logged warning) naming the weakly determined intrinsics."""
    final = IntrinsicsObservability(names, covariance,
                                    3.0 * np.sqrt(np.diag(covariance)) * corner_sensitivity(camera, names), False,
                                    float(np.hypot(camera.width, camera.height)))
    weak = final.weak
    if weak:
        message = f"{source}: camera.estimate: weakly determined intrinsics: {final.describe(weak)}; {ADVICE}"
        logger.warning(message)
        warnings.warn(message, WeakIntrinsicsWarning, stacklevel=3)
