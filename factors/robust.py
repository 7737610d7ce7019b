"""Robust kernels, in one place: their names, the default threshold, the one check of a kernel name, the
weight and loss of GTSAM's mEstimators, the per-measurement row scales of a stacked factor, and GTSAM's
robust noise model.

No numpy or GTSAM at module level: the command line shows :data:`KERNELS` and :data:`ROBUST_K` in its help
without loading either (to keep the start-up fast); the functions import them when called.

Kernels (``e`` a measurement's whitened residual norm, ``k`` the threshold in sigmas), as GTSAM's
``noiseModel.mEstimator``:

* Huber: ``w = min(1, k/e)``, ``rho = e^2/2`` (e <= k) else ``k e - k^2/2``;
* Cauchy: ``w = k^2/(k^2+e^2)``, ``rho = k^2/2 log(1 + e^2/k^2)``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import gtsam
    import numpy as np

__all__ = [
    "KERNELS", "ROBUST_K", "check_kernel", "robust_weight_and_loss", "robust_row_scales", "robust_noise_model",
]

#: Names of the robust kernels (``robust=`` of the solvers, ``--robust`` of the command line).
KERNELS = ("huber", "cauchy")
#: Default robust threshold in sigmas (GTSAM's and the literature's 95 % efficiency for Huber).
ROBUST_K = 1.345


def check_kernel(name: str | None) -> None:
    """Raise ValueError unless ``name`` is ``None`` (no kernel) or one of :data:`KERNELS`."""
    if name is not None and name not in KERNELS:
        raise ValueError(f"unknown robust kernel {name!r}: use {' or '.join(repr(k) for k in KERNELS)}")


def robust_weight_and_loss(kind: str | None, residual: np.ndarray, k: float = ROBUST_K) -> tuple[np.ndarray, np.ndarray]:
    """Weight ``w(e)`` and loss ``rho(e)`` of GTSAM's mEstimators at whitened residual norms ``e`` (module
    docstring). ``kind=None``: ``w = 1``, ``rho = e^2/2``."""
    import numpy as np

    check_kernel(kind)
    e = np.abs(np.asarray(residual, dtype=float))
    if kind is None:
        return np.ones_like(e), 0.5 * e * e
    if kind == "huber":
        inside = e <= k
        weight = np.where(inside, 1.0, k / np.where(inside, 1.0, e))
        return weight, np.where(inside, 0.5 * e * e, k * e - 0.5 * k * k)
    k2 = k * k  # cauchy
    return k2 / (k2 + e * e), 0.5 * k2 * np.log1p(e * e / k2)


def robust_row_scales(kind: str, residual: np.ndarray, k: float = ROBUST_K) -> tuple[np.ndarray, np.ndarray]:
    """How a stacked factor scales each measurement's rows to act as one robust factor per measurement.

    ``residual``: whitened residual norms ``r_i`` (n,). Returns ``(sqrt_w, loss_scale)``: when linearising,
    error and Jacobian rows times ``sqrt(w(r_i))`` (GTSAM's ``Robust::WhitenSystem``); for ``error()``,
    rows times ``sqrt(2 rho(r_i)) / r_i`` (1 where ``r_i = 0``) so that ``0.5 ||e_i||^2 = rho(r_i)``.
    """
    import numpy as np

    r = np.asarray(residual, dtype=float)
    weight, loss = robust_weight_and_loss(kind, r, k)
    positive = r > 0.0
    loss_scale = np.ones_like(r)
    loss_scale[positive] = np.sqrt(2.0 * loss[positive]) / r[positive]
    return np.sqrt(weight), loss_scale


def robust_noise_model(base: gtsam.noiseModel.Base, kind: str | None, k: float = ROBUST_K) -> gtsam.noiseModel.Base:
    """``base`` wrapped in GTSAM's robust kernel ``kind`` with threshold ``k`` sigmas; ``base`` itself for None."""
    check_kernel(kind)
    if kind is None:
        return base
    import gtsam

    estimator = gtsam.noiseModel.mEstimator
    create = estimator.Huber.Create if kind == "huber" else estimator.Cauchy.Create
    return gtsam.noiseModel.Robust.Create(create(k), base)
