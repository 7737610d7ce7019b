"""The camera intrinsics as one shared unknown of the pixel-predicting view factors (``views.py``).

The one measurement model predicts pixels through :class:`IntrinsicsModel` and :func:`pixel_jacobians` of
this module, and takes the prior :func:`intrinsics_prior_factor`. (The tree's own stacked pixel factors, the
reference the model is checked against, live with the tests: ``tests/reference/intrinsics_factors.py``.)

Where ``camera.estimate`` names intrinsics, a measurement is no longer undistorted once with fixed
intrinsics: the factor predicts the *pixel* (Hesch et al. eqs. 2, 3, 5-9 to the normalized point
``h = (x, y)``, then OpenCV's pinhole distortion applied forward and ``K``):

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2),   yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx xd + cx,   v = fy yd + cy

Unknowns (keys): the intrinsics as one ``Vector`` ``K(k)`` per camera holding the *estimated* names in
:data:`INTRINSIC_NAMES` order (the others are constants of the factors).
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import gtsam
import numpy as np

from mirror_fg.core.camera import INTRINSIC_NAMES  # the K(0) order; re-exported here

__all__ = [
    "INTRINSIC_NAMES", "intrinsics_key", "full_intrinsics", "distort_forward", "pixel_jacobians",
    "IntrinsicsModel", "intrinsics_prior_factor", "predict_pixels",
]


def intrinsics_key() -> int:
    """The GTSAM key of the intrinsics vector, ``K(0)``."""
    return gtsam.symbol_shorthand.K(0)


def full_intrinsics(fixed: np.ndarray, estimated_index: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """All nine intrinsics (INTRINSIC_NAMES order): ``fixed`` (9,) with the ``estimated`` values put
    at ``estimated_index``."""
    theta = np.array(fixed, dtype=float)
    theta[estimated_index] = estimated
    return theta


def distort_forward(theta: np.ndarray, normalized_T: np.ndarray) -> np.ndarray:
    """Pixels (2, M) of normalized points (2, M) through OpenCV's pinhole model (module docstring);
    ``theta`` the nine intrinsics in INTRINSIC_NAMES order."""
    return _project(theta, normalized_T, jacobians=False)[0]


def pixel_jacobians(theta: np.ndarray, normalized_T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(pixels (2, M), d pixel / d (x, y) (2, 2, M), d pixel / d theta (2, 9, M))``."""
    pixels, D, T = _project(theta, normalized_T, jacobians=True)
    assert D is not None and T is not None
    return pixels, D, T


def _project(theta: np.ndarray, h: np.ndarray, jacobians: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = (float(v) for v in theta)
    x, y = h[0], h[1]
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    r4 = r2 * r2
    radial = 1.0 + k1 * r2 + k2 * r4 + k3 * r4 * r2
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    pixels = np.stack([fx * xd + cx, fy * yd + cy])
    if not jacobians:
        return pixels, None, None
    dradial = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4  # d radial / d r2
    D = np.empty((2, 2, h.shape[1]))
    D[0, 0] = fx * (radial + 2.0 * xx * dradial + 2.0 * p1 * y + 6.0 * p2 * x)
    D[0, 1] = fx * (2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[1, 0] = fy * (2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[1, 1] = fy * (radial + 2.0 * yy * dradial + 6.0 * p1 * y + 2.0 * p2 * x)
    zero, one = np.zeros_like(x), np.ones_like(x)
    T = np.stack([
        np.stack([xd, zero, one, zero, fx * x * r2, fx * x * r4, fx * 2.0 * xy, fx * (r2 + 2.0 * xx), fx * x * r4 * r2]),
        np.stack([zero, yd, zero, one, fy * y * r2, fy * y * r4, fy * (r2 + 2.0 * yy), fy * 2.0 * xy, fy * y * r4 * r2]),
    ])  # (2, 9, M)
    return pixels, D, T


class IntrinsicsModel:
    """What every factor shares: the fixed intrinsics and which of them the ``K(0)`` vector holds."""

    def __init__(self, fixed: np.ndarray, estimated: Sequence[str]) -> None:
        unknown = [n for n in estimated if n not in INTRINSIC_NAMES]
        if unknown:
            raise ValueError(f"unknown intrinsics {unknown}: use {', '.join(INTRINSIC_NAMES)}")
        self.fixed = np.asarray(fixed, dtype=float).reshape(9)
        self.estimated = tuple(n for n in INTRINSIC_NAMES if n in estimated)
        self.index = np.array([INTRINSIC_NAMES.index(n) for n in self.estimated], dtype=np.intp)

    def theta(self, vector: np.ndarray) -> np.ndarray:
        """All nine intrinsics from the ``K(0)`` vector."""
        return full_intrinsics(self.fixed, self.index, vector)


def _prior_error(index: np.ndarray, given: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values,
                 jacobians: list[np.ndarray] | None) -> np.ndarray:
    """``K(0)[index] - given``: a Gaussian prior on some of the estimated intrinsics."""
    vector = values.atVector(this.keys()[0])
    if jacobians is not None:
        J = np.zeros((len(index), len(vector)))
        J[np.arange(len(index)), index] = 1.0
        jacobians[0] = J
    return vector[index] - given


def intrinsics_prior_factor(model: IntrinsicsModel, sigmas: dict[str, float],
                            key: int | None = None) -> gtsam.CustomFactor | None:
    """Prior factor on ``K(0)``: each estimated name in ``sigmas`` at its value in ``model.fixed`` (the
    given value) with that sigma (pixels or unitless). None when no estimated name has a sigma."""
    names = [n for n in model.estimated if n in sigmas]
    if not names:
        return None
    index = np.array([model.estimated.index(n) for n in names], dtype=np.intp)
    given = model.fixed[[INTRINSIC_NAMES.index(n) for n in names]]
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigmas[n] for n in names], dtype=float))
    return gtsam.CustomFactor(noise, [intrinsics_key() if key is None else key], partial(_prior_error, index, given))


def predict_pixels(theta: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of predicted normalized coordinates (N, 2) through the intrinsics ``theta`` (9,)."""
    return distort_forward(np.asarray(theta, dtype=float), np.asarray(normalized, dtype=float).reshape(-1, 2).T).T
