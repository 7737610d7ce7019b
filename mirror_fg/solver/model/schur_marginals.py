"""Marginal covariances of the general view model by the Schur complement over the unknowns that one factor
alone sees, read like ``gtsam.Marginals`` (``marginalCovariance``, ``jointMarginalCovariance``).

Why: the stacked factors (``factors/view_stack.py``, ``factors/view_points.py``) see each placement of a
photograph in one factor only, while the camera poses, the fixed mirrors and the reconstruction points are
shared. ``gtsam.Marginals`` answers each key's query from the Bayes tree, whose cliques over the shared
unknowns are dense: with reconstruction points every placement's query took milliseconds (2.3 s for 200
images and 60 points). Here the information ``J^T J`` of the linearised graph (eq. 23) is split as the
tree's marginals split it (``marginals.marginal_covariances``): per factor its own unknowns ``p``
(information ``D``, coupling ``B`` to the shared ones), the shared ones ``s`` summed with each factor's
``D`` eliminated (``H_ss - B^T D^-1 B``) and inverted once (dense: they are few), then each factor's
``Sigma_pp = D^-1 + D^-1 B Sigma_ss B^T D^-1``: every marginal exactly. Where the shared unknowns are
many (more than :data:`MAX_SHARED`) or a block is not positive definite (an unknown the data leave
free), :func:`marginals_of` gives ``gtsam.Marginals`` itself, which names the unconstrained unknown.
"""
from __future__ import annotations

import gtsam
import numpy as np

from mirror_fg.factors.schur import one_blas_thread

__all__ = ["SchurMarginals", "marginals_of", "MAX_SHARED"]

#: The shared unknowns' dimension above which ``gtsam.Marginals`` is used (a dense inverse of this size).
MAX_SHARED = 1500


class NotSchur(ValueError):
    """The graph is not one this split serves (too many shared unknowns, a block not positive definite)."""


def marginals_of(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
    """:class:`SchurMarginals` of ``graph`` at ``values``, else ``gtsam.Marginals`` (module docstring)."""
    try:
        with one_blas_thread():  # small dense blocks (factors/schur.py: a second BLAS thread gains nothing)
            return SchurMarginals(graph, values)
    except NotSchur:
        return gtsam.Marginals(graph, values)


class SchurMarginals:
    """Covariances of every unknown of ``graph`` at ``values`` (module docstring)."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        linear = graph.linearize(values)
        zero = values.zeroVectors()
        factors = []
        touches: dict[int, int] = {}
        for f in range(linear.size()):
            factor = linear.at(f)
            if factor is None:
                continue
            keys = list(factor.keys())
            factors.append((keys, factor.jacobian()[0]))
            for key in keys:
                touches[key] = touches.get(key, 0) + 1
        dims = {key: int(zero.at(key).shape[0]) for key in touches}
        shared = [key for key in touches if touches[key] > 1]
        self._shared: dict[int, slice] = {}
        size = 0
        for key in shared:
            self._shared[key] = slice(size, size + dims[key])
            size += dims[key]
        if size > MAX_SHARED:
            raise NotSchur(f"{size} shared unknowns")
        information = np.zeros((size, size))
        blocks = []  # per factor with own unknowns: its own keys' columns, D^-1, B (own x shared rows), shared rows
        for keys, J in factors:
            columns: dict[int, np.ndarray] = {}
            at = 0
            for key in keys:
                columns[key] = np.arange(at, at + dims[key])
                at += dims[key]
            own_keys = [key for key in keys if touches[key] == 1]
            own = np.concatenate([columns[k] for k in own_keys]) if own_keys else np.zeros(0, dtype=int)
            mine = [key for key in keys if touches[key] > 1]
            cols = np.concatenate([columns[k] for k in mine]) if mine else np.zeros(0, dtype=int)
            rows = np.concatenate([np.arange(self._shared[k].start, self._shared[k].stop) for k in mine]) if mine \
                else np.zeros(0, dtype=int)
            H = J.T @ J
            H_ss = H[np.ix_(cols, cols)]
            if len(own):
                D_inv = _inverse(H[np.ix_(own, own)])
                B = H[np.ix_(own, cols)]
                H_ss = H_ss - B.T @ D_inv @ B
                blocks.append((own_keys, [dims[k] for k in own_keys], D_inv, B, rows))
            information[np.ix_(rows, rows)] += H_ss
        self.covariance = _inverse(information) if size else np.zeros((0, 0))
        self._own: dict[int, tuple[int, int]] = {}  # key -> (block, first column in the block)
        self._blocks = []
        self._D_inv: list[np.ndarray] = []
        for b, (own_keys, own_dims, D_inv, B, rows) in enumerate(blocks):
            K = D_inv @ B  # D^-1 B
            self._blocks.append((D_inv + K @ self.covariance[np.ix_(rows, rows)] @ K.T, K, rows))
            self._D_inv.append(D_inv)
            at = 0
            for key, dim in zip(own_keys, own_dims):
                self._own[key] = (b, at)
                at += dim
        self._dims = dims

    def marginalCovariance(self, key: int) -> np.ndarray:
        if key in self._shared:
            c = self._shared[key]
            return self.covariance[c, c].copy()
        b, at = self._own[key]
        dim = self._dims[key]
        return self._blocks[b][0][at:at + dim, at:at + dim].copy()

    def jointMarginalCovariance(self, keys) -> "_Block":
        """The joint covariance of ``keys``, all at once: each key's unknowns as a map of the shared ones
        (a shared key picks its columns, an own key ``p = -K s`` plus its block's ``D^-1`` part, module
        docstring), ``M Sigma_ss M^T`` plus ``D^-1`` between the own keys of one block."""
        keys = list(keys)
        dims = [self._dims[k] for k in keys]
        starts = np.concatenate([[0], np.cumsum(dims)]).astype(int)
        M = np.zeros((int(starts[-1]), len(self.covariance)))
        own: dict[int, list[tuple[int, int]]] = {}  # block -> (output row, column in the block) of its own keys' unknowns
        for key, first, dim in zip(keys, starts[:-1].tolist(), dims):
            if key in self._shared:
                c = self._shared[key]
                M[first + np.arange(dim), np.arange(c.start, c.stop)] = 1.0
                continue
            block, at = self._own[key]
            _, K, rows = self._blocks[block]
            M[first:first + dim, rows] = -K[at:at + dim]
            own.setdefault(block, []).extend((first + d, at + d) for d in range(dim))
        out = M @ self.covariance @ M.T
        for block, pairs in own.items():
            where, local = np.array(pairs).T
            out[np.ix_(where, where)] += self._D_inv[block][np.ix_(local, local)]
        return _Block(out)

    def _pair(self, a: int, b: int) -> np.ndarray:
        """The covariance block of unknowns ``a`` and ``b``."""
        if a in self._shared and b in self._shared:
            return self.covariance[self._shared[a], self._shared[b]]
        if a in self._shared:
            return self._pair(b, a).T
        block, at = self._own[a]
        sigma, K, rows = self._blocks[block]
        own = slice(at, at + self._dims[a])
        if b in self._shared:  # cov(p, s) = -D^-1 B Sigma_ss
            return -K[own] @ self.covariance[rows, self._shared[b]]
        other, at_b = self._own[b]
        if other == block:
            return sigma[own, at_b:at_b + self._dims[b]]
        _, K_b, rows_b = self._blocks[other]  # cov(p_a, p_b) = K_a Sigma_ss K_b^T across factors
        return K[own] @ self.covariance[np.ix_(rows, rows_b)] @ K_b[at_b:at_b + self._dims[b]].T


class _Block:
    def __init__(self, matrix: np.ndarray):
        self.matrix = matrix

    def fullMatrix(self) -> np.ndarray:
        return self.matrix


def _inverse(H: np.ndarray) -> np.ndarray:
    """The inverse of a symmetric positive definite ``H`` by Cholesky; :class:`NotSchur` where it is not."""
    try:
        lower = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        raise NotSchur("not positive definite") from None
    inverse_lower = np.linalg.solve(lower, np.eye(len(H)))  # L^-1
    return inverse_lower.T @ inverse_lower
