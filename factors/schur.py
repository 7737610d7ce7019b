"""Small dense linear algebra of the eliminated factors (``view_eliminated.py``, ``view_points_eliminated.py``): segment sums, the per-measurement
products of their 2-row blocks, closed-form inverses of 3x3 normal matrices (the placements' ``D``), the
Gauss-Newton steps of the placements, and the compression of a factor's normal equations to ``d + 1``
rows (Hesch et al., eq. 23 linearised), each run with one BLAS thread (:func:`one_blas_thread`).
"""
from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import numpy as np

__all__ = ["segment_sums", "row_products", "compressed_normal", "gauss_newton_steps", "inverses", "CHOLESKY_SHIFT",
           "one_blas_thread"]

_controller = None
_limited = threading.local()  # how deep this thread is inside one_blas_thread blocks


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS/LAPACK limited to one thread inside the block (threadpoolctl). The factors' matrices are a
    few hundred wide at most: a second BLAS thread gains nothing there, and on a loaded machine its
    spinning workers took the cores from the solve (benchmark.py's points case: 8.5 s instead of 1.4 s
    at load average 4 on 2 cores). A block inside another only counts (the limit costs ~0.1 ms: an
    incremental update's factors each enter one)."""
    global _controller
    depth = getattr(_limited, "depth", 0)
    if depth:
        _limited.depth = depth + 1
        try:
            yield
        finally:
            _limited.depth = depth
        return
    if _controller is None:
        from threadpoolctl import ThreadpoolController

        _controller = ThreadpoolController()
    with _controller.limit(limits=1, user_api="blas"):
        _limited.depth = 1
        try:
            yield
        finally:
            _limited.depth = 0


def segment_sums(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sums of ``values`` over contiguous segments beginning at ``starts`` (first axis)."""
    return np.add.reduceat(values, starts, axis=0)


#: The factor's information is positive semidefinite (alone it rarely fixes every unknown: a gauge),
#: so :func:`compressed_normal` factors ``J^T J + delta I`` with ``delta`` this fraction of its largest
#: diagonal entry: ~1e3 times the rounding of ``J^T J`` itself, a damping far below any of LM's. The
#: gradient and the cost are kept exactly (the optimum does not move); ``information`` and the
#: covariances use ``J^T J`` itself.
CHOLESKY_SHIFT = 1e-12


def row_products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a_m^T b_m`` (n, p, q) of the 2-row blocks ``a`` (n, 2, p) and ``b`` (n, 2, q): two broadcast
    products (numpy's einsum and batched matmul are several times slower on blocks this small)."""
    out = a[:, 0, :, None] * b[:, 0, None, :]
    out += a[:, 1, :, None] * b[:, 1, None, :]
    return out


def compressed_normal(information: np.ndarray, gradient: np.ndarray, cost: float) -> np.ndarray:
    """``[R | r; 0 | rho]`` ((d+1) x (d+1)) with ``R^T R = J^T J``, ``R^T r = J^T e`` and
    ``|r|^2 + rho^2 = |e|^2``, from those three: a system of d + 1 rows with the same normal equations
    and cost as ``(J, e)``. ``R`` is the Cholesky factor of ``J^T J`` shifted by :data:`CHOLESKY_SHIFT`
    (one LAPACK call on the augmented matrix, ~10x cheaper than an eigendecomposition); where that
    fails, ``R = sqrt(L) V^T`` from ``J^T J = V L V^T``, which holds where ``J`` is rank-deficient."""
    d = len(gradient)
    shift = CHOLESKY_SHIFT * max(float(np.max(np.diag(information), initial=0.0)), 1e-300)
    augmented = np.empty((d + 1, d + 1))
    augmented[:d, :d] = information
    augmented[np.arange(d), np.arange(d)] += shift
    augmented[:d, d] = augmented[d, :d] = gradient
    # any corner above g^T (J^T J + shift)^-1 g keeps the augmented matrix positive definite; rho from the cost
    augmented[d, d] = 1.0 + float(gradient @ gradient) / shift
    try:
        lower = np.linalg.cholesky(augmented)
    except np.linalg.LinAlgError:
        lower = None
    if lower is not None and np.all(np.isfinite(lower)):
        out = lower.T  # Fortran-ordered: its column blocks go to GTSAM without a copy
        r = out[:d, d]
        out[d, d] = np.sqrt(max(cost - float(r @ r), 0.0))
        return out
    eigenvalues, V = np.linalg.eigh(information)
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    root = np.sqrt(eigenvalues)
    projected = V.T @ gradient
    r = np.divide(projected, root, out=np.zeros(d), where=root > 1e-12 * max(root.max(initial=0.0), 1e-300))
    out = np.zeros((d + 1, d + 1))
    out[:d, :d] = root[:, None] * V.T
    out[:d, d] = r
    out[d, d] = np.sqrt(max(cost - float(r @ r), 0.0))
    return out


def gauss_newton_steps(moments: np.ndarray) -> np.ndarray:
    """Gauss-Newton steps ``-D^-1 g`` (3, S) from the moments of ``model.last_mirror_moments`` (rows 0-5
    the symmetric ``D``, 6-8 ``g``), with ``D^-1`` of :func:`inverses`."""
    return -np.einsum("sij,js->is", inverses(moments[:6]), moments[6:9])


def inverses(d: np.ndarray) -> np.ndarray:
    """Inverses (S, 3, 3) of the symmetric 3x3 matrices stored as rows (00, 01, 02, 11, 12, 22) of ``d``
    (6, S), by their adjugates; those singular or not positive by ``np.linalg.inv`` (``pinv`` when that
    fails), alone (a wrong start's degenerate placement must not send every other through LAPACK)."""
    cofactors = np.take(d, _COFACTOR_A, axis=0)
    cofactors *= np.take(d, _COFACTOR_B, axis=0)
    cofactors -= np.take(d, _COFACTOR_C, axis=0) * np.take(d, _COFACTOR_D, axis=0)
    det = np.einsum("is,is->s", d[:3], cofactors[:3])
    good = (det > 0.0) & np.isfinite(det)
    if good.all():
        cofactors /= det
        return np.ascontiguousarray(np.take(cofactors, _SYMMETRIC, axis=0).T).reshape(-1, 3, 3)
    with np.errstate(all="ignore"):
        cofactors /= det
    out = np.ascontiguousarray(np.take(cofactors, _SYMMETRIC, axis=0).T).reshape(-1, 3, 3)
    D = np.ascontiguousarray(np.take(d[:, ~good], _SYMMETRIC, axis=0).T).reshape(-1, 3, 3)
    try:
        out[~good] = np.linalg.inv(D)
    except np.linalg.LinAlgError:  # a placement its measurements do not constrain (degenerate values)
        out[~good] = np.linalg.pinv(D)
    return out


#: Cofactors of a symmetric 3x3 stored as (00, 01, 02, 11, 12, 22): ``C_k = d[A] d[B] - d[C] d[D]``,
#: in the same order; ``_SYMMETRIC`` spreads the 6 back to the 9 entries (row-major).
_COFACTOR_A = np.array([3, 2, 1, 0, 1, 0], dtype=np.intp)
_COFACTOR_B = np.array([5, 4, 4, 5, 2, 3], dtype=np.intp)
_COFACTOR_C = np.array([4, 1, 2, 2, 0, 1], dtype=np.intp)
_COFACTOR_D = np.array([4, 5, 3, 2, 4, 1], dtype=np.intp)
_SYMMETRIC = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5], dtype=np.intp)
