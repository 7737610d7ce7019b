"""Views with reconstruction points whose own placements (the paper's last mirror: a photograph's own
placement) are eliminated inside the factors, as ``view_eliminated.py`` does for views of fiducials only
and the tree's factors for the last mirror (Hesch et al., eqs. 2, 3, 9, 23; the model of ``views.py``).

Why: with those placements as graph unknowns (``view_points.py``) GTSAM eliminates each of them from its
stack's rows at every linear solve, a dense update of the shared unknowns (pose, the placements several
stacks see, every point) per stack: 30-40 ms per damped solve of 200 images and 60 points against the
tree's 10 ms. Here they never enter the ``Values``:

* the placements to eliminate are ``view_eliminated.private_placements``'s (seen by one stack's views only,
  at most one per view, each the last reflection of its owner camera's views);
* at new values of the kept unknowns, each eliminated mirror vector ``v`` is first optimised on its own
  measurements (Gauss-Newton per placement, damped where a step raises its cost, warm-started; variable
  projection), so the factors' cost is ``min_v`` of eq. (23)'s: the same minimiser as the joint graph;
* linearised there, the stacks' normal equations are those of ``view_points.ViewPointStack`` with the
  eliminated placements' Jacobian in ``v`` itself; their rows ``[R_o | R_c]`` are kept and only the rest's
  Schur complement (``N_rest - R_c^T R_c``) reaches the graph, in the shared factors.

The placements and their covariances are recovered afterwards (:meth:`EliminatedViewPointStack.vectors_at`,
:meth:`EliminatedViewPointStack.covariances`: ``Sigma_v = D^-1 + D^-1 C Sigma_k C^T D^-1`` with
``D^-1 C = R_o^-1 R_c``). Intrinsics known, no robust kernel. Not thread-safe.
``tests/test_view_points_eliminated.py`` checks it against the per-view graph.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import gtsam
import numpy as np

import mirror_fg.factors.view_last_reflection as last
from mirror_fg.factors.view_eliminated import IDENTITY, private_placements, restart_collapsed, solve_placements
from mirror_fg.factors.view_points import PLACEMENTS_PER_FACTOR, ViewPointStack
from mirror_fg.factors.view_stack import _Group, read_poses_and_planes, stacks_by_placements
from mirror_fg.factors.views import ViewFactor

__all__ = ["EliminatedViewPointStack"]

Placement = tuple[int, int]


class EliminatedViewPointStack(ViewPointStack):
    """Views with reconstruction points (intrinsics known, no robust kernel) with their own placements
    eliminated (module docstring). ``start``: each placement's mirror vector to start from (owner frame,
    metres); ``keep``: placements that stay unknowns. ``eliminated``: the placements solved inside;
    ``factors``: the graph's factors (the kept unknowns only)."""

    _own_factors = False

    def __init__(self, view_factors: Sequence[ViewFactor], start: dict[Placement, np.ndarray],
                 keep: frozenset | set = frozenset(), placements_per_factor: int = PLACEMENTS_PER_FACTOR):
        if any(f.robust is not None or f.intrinsics is not None for f in view_factors):
            raise ValueError("eliminated placements need known intrinsics and no robust kernel")
        stacks = stacks_by_placements(view_factors, placements_per_factor)
        self.eliminated: list[Placement] = private_placements(view_factors, stacks, set(keep))
        index = {p: e for e, p in enumerate(self.eliminated)}
        every_key = {p: k for f in view_factors for p, k in f.mirror_keys.items()}
        self._eliminated_keys = {every_key[p]: p for p in self.eliminated}
        self._start = np.array([start[p] for p in self.eliminated], dtype=float).reshape(-1, 3)
        self._vectors = self._start.copy()
        super().__init__(view_factors, placements_per_factor)
        self.kept_mirror_keys = {p: k for p, k in self.mirror_keys.items() if p not in index}
        # each view with an eliminated placement, grouped by shape and that placement's local position
        group_of = {int(i): g for g, members in enumerate(self._members) for i in members}
        by_shape: dict[tuple[int, int], list[int]] = {}
        for i, f in enumerate(view_factors):
            order = list(f.mirror_keys)  # (in order of first reflection: the model's local placements)
            u = next((u for u, p in enumerate(order) if p in index), None)
            if u is not None:
                by_shape.setdefault((group_of[i], u), []).append(i)
        self._inner = []  # (group, local placement, each view's eliminated placement, point rows, seen, unique)
        row = {key: j for j, key in enumerate(self.point_keys)}
        for (_, u), members in by_shape.items():
            group = _Group([view_factors[i] for i in members])
            seen = group.landmarks >= 0
            rows = np.array([row[int(k)] for k in group.landmarks[seen]], dtype=np.intp)
            placement_of = np.array([index[list(view_factors[i].mirror_keys)[u]] for i in members], dtype=np.intp)
            self._inner.append((group, u, placement_of, rows, seen, len(np.unique(placement_of)) == len(placement_of)))
        # the closed form of the last reflection (view_last_reflection.py) where the group's eliminated
        # placement is its last reflection and no earlier one (private_placements: its own camera's)
        self._fast = [group.steps[-1][1] == u and [w for _, w in group.steps].count(u) == 1
                      for group, u, *_ in self._inner]
        self._soa = [(np.ascontiguousarray(group.observed.transpose(1, 2, 0)),
                      np.ascontiguousarray(group.sigmas.transpose(1, 2, 0))) for group, *_ in self._inner]
        self._solved_state: dict[int, bytes] | None = None
        self._own_rows_of: dict[int, np.ndarray] = {}

    def _is_own(self, key: int, seen: Counter) -> bool:
        return key in self._eliminated_keys

    # --- evaluation -------------------------------------------------------------------------------

    def _read(self, values: gtsam.Values) -> tuple[dict, dict, dict, dict[int, bytes]]:
        """The kept unknowns from ``values``, the eliminated placements at their current vectors (their
        variable ``v`` itself: identity Jacobians)."""
        poses, vectors, jacobians, state = read_poses_and_planes(values, self.fixed, self.pose_keys,
                                                                 self.kept_mirror_keys)
        points = np.array([values.atPoint3(k) for k in self.point_keys], dtype=float).reshape(-1, 3)
        solved = dict(state)
        for k, x in zip(self.point_keys, points):
            solved[k] = x.tobytes()
        if solved != self._solved_state:  # the placements are at their optimum for these values otherwise
            self._solve(poses, vectors, jacobians, points)
            self._solved_state = solved
        for p, v in zip(self.eliminated, self._vectors):
            vectors[p], jacobians[p] = v, IDENTITY
        return poses, vectors, jacobians, state

    def _bases(self, points: np.ndarray) -> list[np.ndarray]:
        """Each inner group's points (b, 3, N): the fiducials, the reconstruction points at ``points``."""
        out = []
        for group, _, _, rows, seen, _ in self._inner:
            base = group.base.transpose(0, 2, 1).copy()
            base[seen] = points[rows]
            out.append(base.transpose(0, 2, 1))
        return out

    def _prefixes(self, poses, vectors, jacobians, bases) -> list[np.ndarray | None]:
        """Each fast group's points before its last mirror (3, N, b): they depend on the kept unknowns."""
        return [np.ascontiguousarray(group.reflected(poses, vectors, jacobians, False, base, None, None,
                                                     group.steps[:-1])[0].transpose(1, 2, 0)) if fast else None
                for (group, *_), base, fast in zip(self._inner, bases, self._fast)]

    def _moments(self, poses, vectors, jacobians, bases, prefixes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``D = J_v^T J_v`` (E, 3, 3), ``J_v^T e`` (E, 3) and the cost (E,) of each eliminated placement's
        views at the current vectors, the rest held."""
        for p, v in zip(self.eliminated, self._vectors):
            vectors[p], jacobians[p] = v, IDENTITY
        E = len(self.eliminated)
        D, g, cost = np.zeros((E, 3, 3)), np.zeros((E, 3)), np.zeros(E)
        for (group, u, placement_of, _, _, unique), base, y, (observed, sigmas) in zip(
                self._inner, bases, prefixes, self._soa):
            if y is not None:
                D_views, g_views, cost_views = last.moments(y, self._vectors[placement_of], observed, sigmas)
            else:
                z, dz, _ = group.model(poses, vectors, jacobians, True, base, wrt=u)
                e = (z - group.observed) / group.sigmas  # (b, 2, N) whitened
                A = (dz / group.sigmas[:, :, None, :]).transpose(0, 2, 1, 3).reshape(len(z), 3, -1)  # (b, 3, 2N)
                D_views, g_views = A @ A.transpose(0, 2, 1), (A @ e.reshape(len(z), -1, 1))[:, :, 0]
                cost_views = np.einsum("bkn,bkn->b", e, e)
            if unique:  # each placement seen by one of these views (a photograph's own): no sum
                D[placement_of] += D_views
                g[placement_of] += g_views
                cost[placement_of] += cost_views
            else:
                np.add.at(D, placement_of, D_views)
                np.add.at(g, placement_of, g_views)
                np.add.at(cost, placement_of, cost_views)
        return D, g, cost

    def _solve(self, poses, vectors, jacobians, points: np.ndarray) -> None:
        """The eliminated placements at their optimum given the kept unknowns (module docstring; as
        ``view_eliminated.EliminatedViewStack._solve``)."""
        restart_collapsed(self._vectors, self._start)
        vectors, jacobians = dict(vectors), dict(jacobians)
        bases = self._bases(points)
        for p, v in zip(self.eliminated, self._vectors):
            vectors[p], jacobians[p] = v, IDENTITY
        prefixes = self._prefixes(poses, vectors, jacobians, bases)
        D, g, own = self._moments(poses, vectors, jacobians, bases, prefixes)
        solve_placements(self._vectors, D, g, own, lambda: self._moments(poses, vectors, jacobians, bases, prefixes))

    # --- after the optimisation -------------------------------------------------------------------

    @property
    def dimension(self) -> int:
        """The scalar unknowns solved inside the factors (3 per eliminated placement)."""
        return 3 * len(self.eliminated)

    def vectors_at(self, values: gtsam.Values) -> dict[Placement, np.ndarray]:
        """The eliminated placements' mirror vectors (owner frames, metres) at ``values``' kept unknowns."""
        self._read(values)
        return {p: v.copy() for p, v in zip(self.eliminated, self._vectors)}

    mirror_vectors = vectors_at  # as the tree's ``EliminatedEvaluator`` names it

    def covariances(self, values: gtsam.Values, marginals) -> dict[Placement, np.ndarray]:
        """Each eliminated placement's mirror-vector covariance (3x3) from ``marginals`` of the kept
        unknowns: ``D^-1 + D^-1 C Sigma_k C^T D^-1``, ``D^-1 C = R_o^-1 R_c`` (module docstring)."""
        self._compute(values, True)
        out = {}
        for s, rows in self._own_rows_of.items():
            o = len(self._own[s])
            keys = self._rest_keys[s]
            joint = marginals.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix() if keys else np.zeros((0, 0))
            R_inverse = np.linalg.inv(rows[:, :o])
            K = R_inverse @ rows[:, o:-1]
            sigma = R_inverse @ R_inverse.T + K @ joint @ K.T
            own_keys = [k for k in self._stack_keys[s] if k in self._eliminated_keys]
            for j, key in enumerate(own_keys):
                out[self._eliminated_keys[key]] = sigma[3 * j:3 * j + 3, 3 * j:3 * j + 3].copy()
        return out
