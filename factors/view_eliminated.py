"""View factors with the placements that one factor alone sees eliminated inside it (Schur complement), as the
paper's tree factors eliminate the last mirror's placements (``eliminated.py``) and GTSAM's
``SmartProjectionFactor`` its landmark (Hesch et al., eqs. 2, 3, 9, 23; the model of ``views.py``).

Why: in the general view model every placement is an unknown of the graph; a photograph's own placement (a
hand-held mirror, the paper's last mirror) is seen by its views only. With one plane variable per
photograph each Python factor call copies a ``Values`` that grows with the images (``batched.py``'s
docstring), and GTSAM eliminates every plane from a factor's dense rows: 15-30 s for 10,000 tree images
against the tree pipeline's 1 s. Here those placements never enter the ``Values``:

* views are stacked by the set of placements they see (``view_stack.py``'s groups and merging, at most
  :data:`PLACEMENTS_PER_FACTOR` placements per factor); a placement all of whose views are in one factor,
  and no other eliminated placement in any of those views, is eliminated: the factor's keys are the camera
  poses and the other placements only;
* evaluated at those values, each eliminated placement's mirror vector ``v`` is first optimised on its own
  measurements (Gauss-Newton, vectorised over every placement, warm-started; variable projection), so a
  factor's cost is ``min_v`` of the cost of eq. (23): the same minimiser as the joint graph;
* where a view's eliminated placement is its last reflection (and no earlier one), the points as they reach
  that mirror are computed once per evaluation and each inner iteration is that one reflection and the
  projection in closed form (``view_last_reflection.py``, as the tree's factors do); the general model
  (``view_stack._Group.model``) otherwise;
* linearised, each placement is eliminated from its views' normal equations
  (``N_kk - C^T D^-1 C``, ``D = J_v^T J_v``, ``C = J_v^T [J_k | e]``) and the factor's rows compressed to
  ``d + 1`` (``view_points._rows_of``): the same Levenberg-Marquardt steps as the joint graph with those
  placements eliminated first.

The placements and their covariances are recovered afterwards (:meth:`EliminatedViewStack.vectors_at`,
:meth:`EliminatedViewStack.covariances`: ``Sigma_v = D^-1 + D^-1 C Sigma_k C^T D^-1``). Fiducials only,
intrinsics known, no robust kernel (the other views keep ``view_stack.py`` / ``view_points.py``). Not
thread-safe (GTSAM calls Python factors one at a time). ``tests/test_view_eliminated.py`` checks cost,
reduced system and whole calibrations against the per-view factors.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import gtsam
import numpy as np

import mirror_fg.factors.view_last_reflection as last
from mirror_fg.factors.schur import inverses, one_blas_thread
from mirror_fg.factors.view_points import _rows_of, compressed_rows
from mirror_fg.factors.view_stack import _Group, read_poses_and_planes
from mirror_fg.factors.view_table import ViewTable
from mirror_fg.factors.views import ViewFactor

__all__ = ["EliminatedViewStack", "IDENTITY", "eliminable", "private_placements", "PLACEMENTS_PER_FACTOR", "collapsed", "COLLAPSED_FRACTION",
           "collapsed_placements", "halved_placements", "newton_steps", "solve_placements"]

Placement = tuple[int, int]
IDENTITY = np.eye(3)  # an eliminated placement's Jacobian (its variable is its vector): read only
IDENTITY.flags.writeable = False
_THIRTEEN = np.arange(13)
#: Placements of one factor at most: its width is its poses and kept placements only, so a factor can hold
#: many photographs (few Python calls per iteration).
PLACEMENTS_PER_FACTOR = 256
#: Gauss-Newton iterations allowed per evaluation for the eliminated placements, and the step (metres)
#: below which a placement is at its optimum (``eliminated.py``'s).
INNER_MAX_ITERATIONS = 20
INNER_STEP_TOLERANCE = 1e-12
#: A Gauss-Newton step of every placement below this (metres) is taken without evaluating the cost again:
#: Gauss-Newton converges linearly here (rate ~0.02-0.05, ``lm.polished``), so the next would be below
#: :data:`INNER_STEP_TOLERANCE`, and the cost it leaves changes by O(step^2).
FINAL_STEP = 1e-10


#: An eliminated placement nearer the camera centre than this fraction of the median placement's distance
#: has collapsed (:func:`collapsed`). Each placement's solve keeps it on its side of the camera centre (a
#: step moves it by at most half its distance), so from poor values of the rest it can run towards the
#: centre (a mirror seen edge-on); if its later solves started there they would crawl back at most 1.5x
#: per step and Levenberg-Marquardt would settle around it. Measured on test_point_sigma's 27-image scene
#: cut to 21 images: six placements at |v| ~ 1e-8 m, cost 130 against 77 with every placement an
#: unknown. So a collapsed warm start starts again from the placement's initial vector, and callers that
#: still find a collapsed solution solve again with every placement an unknown (``view_stack.py``).
COLLAPSED_FRACTION = 0.1


def collapsed_placements(mirror_vectors: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Which of ``mirror_vectors`` (eliminated placements) have collapsed into the camera centre: nearer it
    than :data:`COLLAPSED_FRACTION` of their median distance (a mask)."""
    distances = np.linalg.norm(np.asarray(mirror_vectors, dtype=float).reshape(-1, 3), axis=1)
    return distances < COLLAPSED_FRACTION * np.median(distances) if len(distances) else np.zeros(0, dtype=bool)


def collapsed(mirror_vectors: Sequence[np.ndarray]) -> bool:
    """Whether some of ``mirror_vectors`` (the eliminated placements at a solution) has collapsed into the
    camera centre (:func:`collapsed_placements`)."""
    return bool(collapsed_placements(mirror_vectors).any())


def eliminable(factor: ViewFactor) -> bool:
    """Whether a view can be in an eliminated stack: fiducials only, intrinsics known, no robust kernel."""
    return factor.intrinsics is None and not factor.unique_landmarks and factor.robust is None



def private_placements(view_factors: Sequence[ViewFactor], stacks: list[list[int]], keep: set) -> list[Placement]:
    """The placements to eliminate: seen by one stack's views only, not in ``keep``, and at most one per
    view: those with the fewest views first (a photograph's own placement before a mirror placement that
    many photographs share, which stays a variable). Of views given one by one (``view_points_eliminated.py``);
    ``ViewTable.private_placements`` chooses the same of a view problem's arrays."""
    first_stack: dict[Placement, int] = {}
    views_of: dict[Placement, list[int]] = {}
    shared: set[Placement] = set()  # seen in more than one stack
    # as the paper's last mirror: seen by its owner camera only and last in every view's reflections (in
    # other places its cost in v alone is far from quadratic: Gauss-Newton on it crawled or diverged on a
    # rig's two-mirror views, where the placements stay variables)
    transferred: set[Placement] = set()
    for s, members in enumerate(stacks):
        for i in members:
            f = view_factors[i]
            if not f.reflections:  # a direct view
                continue
            last, camera, owners = f.reflections[-1], f.camera, f.owners
            for p in f.mirror_keys:
                if p in views_of:
                    views_of[p].append(i)
                    if first_stack[p] != s:
                        shared.add(p)
                else:
                    views_of[p], first_stack[p] = [i], s
                if p != last or owners[p] != camera:
                    transferred.add(p)
    candidates = sorted((p for p in views_of if p not in shared and p not in keep and p not in transferred),
                        key=lambda p: (len(views_of[p]), p))
    taken: set[int] = set()  # views that have their eliminated placement
    chosen = []
    for p in candidates:
        if not taken.intersection(views_of[p]):
            chosen.append(p)
            taken.update(views_of[p])
    return sorted(chosen)

def restart_collapsed(vectors: np.ndarray, start: np.ndarray) -> None:
    """Placements (E, 3) whose warm start ran into the camera centre (a tenth of their start's distance)
    start again from ``start``, in place."""
    collapsed = np.linalg.norm(vectors, axis=1) < 0.1 * np.linalg.norm(start, axis=1)
    vectors[collapsed] = start[collapsed]


def newton_steps(D: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Each placement's Gauss-Newton step ``-D^-1 g`` (E, 3) from its symmetric information ``D`` (E, 3, 3)
    and gradient ``g`` (E, 3) (``schur.inverses`` of the upper triangles)."""
    return -np.einsum("eij,ej->ei", inverses(D[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]].T), g)


def solve_placements(vectors: np.ndarray, D: np.ndarray, g: np.ndarray, own: np.ndarray,
                     moments: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """The eliminated placements ``vectors`` (E, 3, updated in place) at their optimum given the kept
    unknowns: Gauss-Newton per placement from its information ``D`` (E, 3, 3), gradient ``g`` and own cost
    ``own`` (E,), a step that raises its views' cost refused and the placement damped (Levenberg-Marquardt
    on each placement alone: their costs are separate); ``moments()`` gives ``(D, g, own)`` again at the
    moved ``vectors``. Returns each placement's cost there."""
    E = len(vectors)
    damping = np.zeros(E)
    for _ in range(INNER_MAX_ITERATIONS if E else 0):
        step = newton_steps(D + damping[:, None, None] * (D * IDENTITY), g)
        if not np.all(np.isfinite(step)):
            raise RuntimeError("an eliminated mirror placement has no finite optimum at these values")
        length = np.linalg.norm(step, axis=1)
        if float(length.max(initial=0.0)) < INNER_STEP_TOLERANCE:
            break  # (the step would change the cost by O(step^2): nothing)
        if float(length.max(initial=0.0)) < FINAL_STEP:  # taken without evaluating again (module docstring)
            vectors += step
            break
        limit = 0.5 * np.linalg.norm(vectors, axis=1)  # stay on its side of the camera centre
        before = vectors.copy()
        vectors += step * np.minimum(1.0, limit / np.maximum(length, 1e-300))[:, None]
        D_new, g_new, own_new = moments()
        better = own_new <= own * (1.0 + 1e-12) + 1e-300
        vectors[~better] = before[~better]
        D[better], g[better], own[better] = D_new[better], g_new[better], own_new[better]
        damping = np.where(better, damping * 0.1, np.maximum(damping * 10.0, 1e-3))
        damping[damping < 1e-8] = 0.0
    return own


def halved_placements(vectors: np.ndarray, D: np.ndarray, g: np.ndarray, own: np.ndarray,
                      moments: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """:func:`solve_placements` as the tree's eliminated factors solve (``eliminated.py``): Gauss-Newton per
    placement, each step at most half the placement's distance, halved up to four times where it raises the
    placement's cost and else not taken. Returns each placement's cost at ``vectors`` (updated in place)."""
    E = len(vectors)
    for _ in range(INNER_MAX_ITERATIONS if E else 0):
        step = newton_steps(D, g)
        step[~np.isfinite(step)] = 0.0
        active = np.max(np.abs(step), axis=1) > INNER_STEP_TOLERANCE
        if not active.any():
            break
        step[~active] = 0.0
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, 0.5 * np.linalg.norm(vectors, axis=1) / np.maximum(length, 1e-300))[:, None]
        base, cost = vectors.copy(), own.copy()
        for _halving in range(4):
            vectors[:] = base + step
            D, g, own = moments()
            worse = own > cost * (1.0 + 1e-12)
            if not worse.any():
                break
            step[worse] *= 0.5
        else:
            vectors[worse] = base[worse]
            D, g, own = moments()
    return own


class EliminatedViewStack:
    """Views (all :func:`eliminable`: their per-image factors, or a ``view_table.ViewTable``) in factors with
    their own placements eliminated (module docstring).

    ``start``: every eliminated placement's mirror vector to start from (owner frame, metres); ``keep``:
    placements that stay variables whatever sees them (e.g. the scale's); ``tree_like``: the placements solved
    as the tree's factors solve them (:attr:`tree_like`); ``closed_form``: the last reflection
    in closed form where it is the eliminated placement's (``view_last_reflection.py``; else the general
    model everywhere, as a reference). ``eliminated``: the placements
    solved inside; ``kept_mirror_keys``: the plane keys the factors see; ``factors``: the
    ``gtsam.CustomFactor`` objects."""

    def __init__(self, view_factors: Sequence[ViewFactor] | ViewTable, start: dict[Placement, np.ndarray],
                 keep: frozenset | set = frozenset(),
                 placements_per_factor: int = PLACEMENTS_PER_FACTOR, closed_form: bool = True, tree_like: bool = False):
        table = view_factors if isinstance(view_factors, ViewTable) else ViewTable.of_factors(view_factors)
        stacks = table.stacks(placements_per_factor)
        self.eliminated = table.private_placements(stacks, set(keep))
        index = {p: e for e, p in enumerate(self.eliminated)}
        # each placement's eliminated index (-1: kept), by the table's placement indices
        eliminated_of = np.array([index.get(p, -1) for p in table.placements], dtype=np.intp)
        self._start = np.array([start[p] for p in self.eliminated], dtype=float).reshape(-1, 3)
        self._vectors = self._start.copy()
        self.fixed, self.pose_keys, mirror_keys = table.collected_keys()
        self.kept_mirror_keys: dict[Placement, int] = {p: k for p, k in mirror_keys.items() if p not in index}
        pose_set = set(self.pose_keys.values())
        self._keys, self._widths, self._offsets, columns_of = [], [], [], []
        stack_of_view = np.zeros(table.count, dtype=np.intp)
        size = 0
        kept_columns: list[int] = []  # of each (stack, kept placement), in the order of kept_codes
        kept_codes: list[int] = []
        for s, (members, pose_keys, kept) in enumerate(zip(stacks, *table.stack_keys(stacks, eliminated_of >= 0))):
            keys = pose_keys + [table.mirror_keys[table.placements[u]] for u in kept]
            columns, width = {}, 0
            for key in keys:
                columns[key] = width
                width += 6 if key in pose_set else 3
            kept_codes.extend(s * len(table.placements) + u for u in kept)
            kept_columns.extend(6 * len(pose_keys) + 3 * np.arange(len(kept)))
            self._keys.append(keys)
            self._widths.append(width)
            self._offsets.append(size)
            columns_of.append(columns)
            size += (width + 1) ** 2
            stack_of_view[members] = s
        self._normal_size = size
        order = np.argsort(np.array(kept_codes, dtype=np.intp), kind="stable")
        kept_lookup = (np.array(kept_codes, dtype=np.intp)[order], np.array(kept_columns, dtype=np.intp)[order])
        # each eliminated placement: its stack, and where its C = J_v^T [J_k | e] (3 x (d+1)) starts
        stack_of_placement = np.zeros(len(self.eliminated), dtype=np.intp)
        for block in table.blocks:
            at = eliminated_of[block.placements]  # (b, U)
            mine = at >= 0
            stack_of_placement[at[mine]] = np.broadcast_to(stack_of_view[block.members][:, None], at.shape)[mine]
        self._stack_of_placement = stack_of_placement
        widths = np.array(self._widths)
        c_sizes = 3 * (widths[stack_of_placement] + 1)
        self._c_offsets = size + np.concatenate([[0], np.cumsum(c_sizes)[:-1]]).astype(np.intp)
        self._d_offset = size + int(c_sizes.sum())
        d_of = widths[stack_of_placement]
        self._gradient_at = (self._c_offsets[:, None] + np.arange(3)[None, :] * (d_of[:, None] + 1)
                             + d_of[:, None]).astype(np.intp)  # C[:, d] = J_v^T e of each placement
        self._total = self._d_offset + 9 * len(self.eliminated)
        # views of one shape and the same placement eliminated (in order of first reflection)
        shapes = table.groups(eliminated_of >= 0)
        self.groups = [table.group_of(first, parts) for first, _, parts in shapes]
        self._targets, self._placement_of_view, self._elim_cols, self._elim_local = [], [], [], []
        for group, (_, members, _) in zip(self.groups, shapes):
            targets, placement_of, elim_cols = self._layout(group, members, eliminated_of, stack_of_view, columns_of,
                                                            kept_lookup, len(table.placements))
            self._targets.append(targets)
            self._placement_of_view.append(placement_of)
            self._elim_cols.append(elim_cols)
            ids = group.placement_ids  # the group's eliminated placement, if any (one local position for all)
            assert ids is not None
            self._elim_local.append(next((u for u in range(ids.shape[1]) if eliminated_of[ids[0, u]] >= 0), None))
        # the closed form of the last reflection (``view_last_reflection.py``) where a group's eliminated
        # placement is its last reflection and not an earlier one too (always its own camera's: see
        # ViewTable.private_placements); the general model with ``wrt`` elsewhere
        self._fast = [closed_form and u is not None and group.steps[-1][1] == u and [w for _, w in group.steps].count(u) == 1
                      for group, u in zip(self.groups, self._elim_local)]
        self._observed_soa = [np.ascontiguousarray(group.observed.transpose(1, 2, 0)) for group in self.groups]
        self._sigmas_soa = [np.ascontiguousarray(group.sigmas.transpose(1, 2, 0)) for group in self.groups]
        seen = np.bincount(np.concatenate([np.zeros(0, dtype=np.intp)] + [
            placement_of for placement_of, u in zip(self._placement_of_view, self._elim_local) if u is not None]),
            minlength=len(self.eliminated))  # each eliminated placement's views
        # the closed-form groups of as many points, evaluated as one (the inner solve calls their moments a
        # few dozen times per linearisation; a call per group was most of its cost): each merge's groups,
        # observations and sigmas (2, N, b) and eliminated placement of each view (b,)
        by_count: dict[int, list[int]] = {}
        for i, (group, fast) in enumerate(zip(self.groups, self._fast)):
            if fast:
                by_count.setdefault(group.base.shape[2], []).append(i)
        # each merge's placements seen by its views alone, one each (``one_view``); None for the placements:
        # the only views, placement k seen by view k alone (no gather, no scatter: _moments)
        self._merged: list[tuple[list[int], np.ndarray, np.ndarray, np.ndarray | None, bool]] = []
        for merge in by_count.values():
            placement_of = np.concatenate([self._placement_of_view[i] for i in merge])
            one_view = bool(np.all(seen[placement_of] == 1))
            only = (len(by_count) == 1 and all(self._fast) and one_view
                    and np.array_equal(placement_of, np.arange(len(self.eliminated))))
            self._merged.append((merge, np.concatenate([self._observed_soa[i] for i in merge], axis=2),
                                 np.concatenate([self._sigmas_soa[i] for i in merge], axis=2),
                                 None if only else placement_of, one_view))
        self._mine = [np.flatnonzero(stack_of_placement == s) for s in range(len(stacks))]
        self._c_index = [self._c_offsets[m][:, None] + np.arange(3 * (w + 1))[None] for m, w in zip(self._mine, self._widths)]
        self._all_targets = (self._targets[0].ravel() if len(self._targets) == 1
                             else np.concatenate([target.ravel() for target in self._targets]))
        self._work: list[dict] = [{} for _ in self.groups]  # buffers of each group's normals
        self._prefix_work: list[dict] = [{} for _ in self.groups]  # and of its points' derivatives
        self._pose_set = pose_set
        self._order = {p: i for i, p in enumerate([*self.kept_mirror_keys, *self.eliminated])}
        self._rows = [group.placement_index(self._order) for group in self.groups]
        self._stack_rows = [stack_of_view[members] for _, members, _ in shapes]  # each group's views' stacks
        self.factors = [gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(width + 1), keys, self._error_function(s))
                        for s, (keys, width) in enumerate(zip(self._keys, self._widths))]
        self._state: dict[int, bytes] = {}
        self._valid = self._linearized = False
        self._cost = np.zeros(len(stacks))
        self._systems: list = []
        self._D_inv = np.zeros((len(self.eliminated), 3, 3))
        self._C: list[tuple[np.ndarray, np.ndarray]] = []  # per stack: its placements, their C
        self.batches = 0
        #: Solve the placements as the tree's eliminated factors do (:func:`halved_placements`, each solve
        #: from the optimum of the last linearisation): the analytic start's ranking (``start/initial.py``),
        #: whose choice among wrong hypotheses must not depend on the model's inner solve.
        self.tree_like = tree_like
        self._anchor = self._start.copy()

    def restart(self, start: dict[Placement, np.ndarray]) -> None:
        """The state of a new stack of the same views whose eliminated placements start at ``start``: one
        subtree refined from several hypotheses builds its arrays and factors once (``start/initial.py``)."""
        self._start = np.array([start[p] for p in self.eliminated], dtype=float).reshape(-1, 3)
        self._vectors = self._start.copy()
        self._anchor = self._start.copy()
        self._state, self._valid, self._linearized = {}, False, False
        self._cost = np.zeros_like(self._cost)

    # --- layout -----------------------------------------------------------------------------------

    def _layout(self, group: _Group, members: np.ndarray, eliminated_of: np.ndarray, stack_of_view: np.ndarray,
                columns_of: list[dict[int, int]], kept_lookup: tuple[np.ndarray, np.ndarray], placements: int):
        """Where each entry of a view's local augmented normal matrix ``[A | e]^T [A | e]`` ((P+1)^2) goes:
        kept x kept (and e) to its stack's normal, eliminated x kept (and e) to its placement's ``C``,
        eliminated x eliminated to its ``D``, kept x eliminated nowhere (the last slot, dropped).
        ``kept_lookup``: the codes ``stack * placements + placement`` of each stack's kept placements (sorted)
        and their first columns in the stack."""
        P = group.slots.size
        b = len(members)
        stacks = stack_of_view[members]
        stack_col = np.full((b, P + 1), -1, dtype=np.intp)  # each local column's column in its stack
        placement_of = np.full(b, -1, dtype=np.intp)
        elim_col = -1
        first = group.first  # a group's views share their cameras and the local order of placements
        for name, c in first.slots.pose_cols.items():
            key = first.pose_keys[name]
            in_stack = np.array([columns.get(key, -1) for columns in columns_of])  # its column in each stack
            stack_col[:, c:c + 6] = in_stack[stacks][:, None] + np.arange(6)
        offset = 6 * len(first.slots.pose_cols)
        ids = group.placement_ids
        assert ids is not None
        for u in range(group.placement_count):
            c = offset + 3 * u  # (views.ViewSlots: the placements' columns in their order of first reflection)
            if eliminated_of[ids[0, u]] >= 0:  # (the group's shape says which local placement is eliminated)
                placement_of[:], elim_col = eliminated_of[ids[:, u]], c
            else:
                codes, columns = kept_lookup
                stack_col[:, c:c + 3] = columns[np.searchsorted(codes, stacks * placements + ids[:, u])][:, None] + np.arange(3)
        stack_col[:, P] = np.array(self._widths)[stacks]  # e
        stride = np.array(self._widths)[stacks] + 1  # (b,)
        base = np.array(self._offsets)[stacks]
        kept = stack_col >= 0
        # (one array of this size written in place: a fresh one costs its pages, more than the arithmetic)
        targets = np.empty((b, P + 1, P + 1), dtype=np.intp)
        np.add((base[:, None] + stack_col * stride[:, None])[:, :, None], stack_col[:, None, :], out=targets)
        np.copyto(targets, self._total, where=~(kept[:, :, None] & kept[:, None, :]))  # (rows and columns of the
        # eliminated placement: below)
        elim_cols = np.zeros((b, 3), dtype=np.intp)
        if elim_col >= 0:  # the group's eliminated placement (one local position for all its views)
            rows = elim_col + np.arange(3)
            elim_cols[:] = rows
            c_off = self._c_offsets[placement_of]
            C = c_off[:, None, None] + np.arange(3)[None, :, None] * stride[:, None, None] + stack_col[:, None, :]
            targets[:, rows, :] = np.where(kept[:, None, :], C, self._total)
            targets[:, rows[:, None], rows[None, :]] = (self._d_offset + 9 * placement_of[:, None, None]
                                                        + np.arange(9).reshape(3, 3)[None])
        return targets, placement_of, elim_cols

    # --- evaluation -------------------------------------------------------------------------------

    def _read(self, values: gtsam.Values):
        return read_poses_and_planes(values, self.fixed, self.pose_keys, self.kept_mirror_keys)

    def _arrays(self, vectors, jacobians) -> tuple[np.ndarray, np.ndarray]:
        """Every placement's vector and plane Jacobian (kept ones, then the eliminated at their current
        vectors, whose variable is ``v`` itself) as arrays in ``self._order``."""
        kept = list(self.kept_mirror_keys)
        V = np.concatenate([np.array([vectors[p] for p in kept]).reshape(-1, 3), self._vectors])
        J = np.concatenate([np.array([jacobians[p] for p in kept]).reshape(-1, 3, 3),
                            np.broadcast_to(IDENTITY, (len(self.eliminated), 3, 3))])
        return V, J

    def _prefixes(self, poses, vectors, jacobians, derivatives: bool) -> list:
        """Each fast group's points before its last mirror ``y`` (3, b, N) and, with ``derivatives``, their
        derivative in the local columns (3, P, b, N) (``view_last_reflection.py``); None for the others."""
        V, J = self._arrays(vectors, jacobians)
        return [group.reflected_soa(poses, (V[at], J[at]), group.steps[:-1], derivatives, work) if fast else None
                for group, at, fast, work in zip(self.groups, self._rows, self._fast, self._prefix_work)]

    def _normals(self, poses, vectors, jacobians, prefixes: list) -> np.ndarray:
        """Every entry of the stacks' normals, the placements' ``C`` and ``D`` at the current vectors."""
        V, J = self._arrays(vectors, jacobians)
        weights = []
        for i, (group, at) in enumerate(zip(self.groups, self._rows)):
            if prefixes[i] is not None:
                y, dy = prefixes[i]
                normals = last.augmented_normals(y, dy, self._vectors[self._placement_of_view[i]], int(self._elim_cols[i][0, 0]),
                                                 self._observed_soa[i], self._sigmas_soa[i], self._work[i])
                weights.append(normals.ravel())
                continue
            z, dz, _ = group.model(poses, vectors, jacobians, True, arrays=(V[at], J[at]))
            e = (z - group.observed) / group.sigmas  # (b, 2, N) whitened
            A = dz / group.sigmas[:, :, None, :]  # (b, 2, P, N)
            b, _, P, n = A.shape
            Ae = np.concatenate([A.transpose(0, 1, 3, 2).reshape(b, 2 * n, P), e.reshape(b, 2 * n, 1)], axis=2)
            weights.append((Ae.transpose(0, 2, 1) @ Ae).ravel())
        return np.bincount(self._all_targets, weights[0] if len(weights) == 1 else np.concatenate(weights),
                           minlength=self._total + 1)

    def _moments(self, poses, vectors, jacobians, prefixes: list, merged: list,
                 rest_too: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``D = J_v^T J_v`` (E, 3, 3), ``J_v^T e`` (E, 3) and the cost ``||e||^2`` (E,) of every eliminated
        placement's views, the rest held; and (``rest_too``) each stack's cost of its views without one.
        ``merged``: the closed-form groups' points before their last mirror, merged as ``self._merged``."""
        V, J = self._arrays(vectors, jacobians) if not all(self._fast) else (None, None)
        E = len(self.eliminated)
        D, g, own = np.zeros((E, 3, 3)), np.zeros((E, 3)), np.zeros(E)
        rest = np.zeros(len(self._keys))
        for (_, observed, sigmas, placement_of, one_view), y in zip(self._merged, merged):
            if placement_of is None:  # the only views: placement k seen by view k alone (the tree's last mirror)
                D, g, own = last.moments(y, self._vectors, observed, sigmas)
                continue
            D_views, g_views, cost = last.moments(y, self._vectors[placement_of], observed, sigmas)
            if one_view:  # each placement seen by one of these views alone
                D[placement_of] += D_views
                g[placement_of] += g_views
                own[placement_of] += cost
                continue
            # each placement's sums over its views, in one pass: D's 9 entries, g's 3, the cost
            rows = np.concatenate([D_views.reshape(-1, 9), g_views, cost[:, None]], axis=1)
            sums = np.bincount((placement_of[:, None] * 13 + _THIRTEEN).ravel(), rows.ravel(),
                               minlength=13 * E).reshape(E, 13)
            D += sums[:, :9].reshape(E, 3, 3)
            g += sums[:, 9:12]
            own += sums[:, 12]
        for i, (group, placement_of, wrt, at, members) in enumerate(zip(
                self.groups, self._placement_of_view, self._elim_local, self._rows, self._stack_rows)):
            if prefixes[i] is not None:  # (in a merge above)
                continue
            if wrt is None and not rest_too:
                continue
            assert V is not None and J is not None  # (a group not in closed form)
            if wrt is None:
                z = group.model(poses, vectors, jacobians, False, arrays=(V[at], J[at]))[0]
            else:
                z, dz, _ = group.model(poses, vectors, jacobians, True, wrt=wrt, arrays=(V[at], J[at]))
            e = ((z - group.observed) / group.sigmas).transpose(0, 2, 1).reshape(len(z), -1, 1)  # (b, 2N, 1)
            cost = np.einsum("bki,bki->b", e, e)
            if wrt is None:
                rest += np.bincount(members, cost, minlength=len(rest))
                continue
            A = (dz / group.sigmas[:, :, None, :]).transpose(0, 3, 1, 2).reshape(len(z), -1, 3)  # (b, 2N, 3)
            At = A.transpose(0, 2, 1)
            np.add.at(D, placement_of, At @ A)
            np.add.at(g, placement_of, (At @ e)[:, :, 0])
            own += np.bincount(placement_of, cost, minlength=E)
        return D, g, own, rest

    def _solve(self, poses, vectors, jacobians, prefixes: list) -> np.ndarray:
        """The eliminated placements at their optimum given the rest (module docstring): Gauss-Newton per
        placement, a step that raises its views' cost refused and the placement damped (Levenberg-Marquardt
        on each placement alone: their costs are separate); each stack's cost there."""
        if self.tree_like:  # from the last linearisation's optimum; a collapsed one from its start (eliminated.py)
            self._vectors[:] = np.where(collapsed_placements(self._anchor)[:, None], self._start, self._anchor)
        else:
            restart_collapsed(self._vectors, self._start)
        merged = [prefixes[members[0]][0] if len(members) == 1
                  else np.concatenate([prefixes[i][0] for i in members], axis=2) for members, *_ in self._merged]
        D, g, own, rest = self._moments(poses, vectors, jacobians, prefixes, merged, True)
        again = lambda: self._moments(poses, vectors, jacobians, prefixes, merged, False)[:3]  # noqa: E731
        own = (halved_placements if self.tree_like else solve_placements)(self._vectors, D, g, own, again)
        return rest + np.bincount(self._stack_of_placement, own, minlength=len(rest))

    def _evaluate(self, values: gtsam.Values, jacobians: bool) -> None:
        same = self._valid and all(self._bytes(key, values) == self._state[key] for key in self._state)
        if same and (self._linearized or not jacobians):
            return
        self.batches += 1
        poses, vectors, plane_jacobians, state = self._read(values)
        # the points before each eliminated mirror: they depend on the kept unknowns only
        prefixes = self._prefixes(poses, vectors, plane_jacobians, jacobians)
        if not same:  # the placements are already at their optimum for these values otherwise
            self._cost = self._solve(poses, vectors, plane_jacobians, prefixes)
        self._state, self._valid, self._linearized = state, True, False
        if not jacobians:
            return
        normal = self._normals(poses, vectors, plane_jacobians, prefixes)
        E = len(self.eliminated)
        D = normal[self._d_offset:self._d_offset + 9 * E].reshape(E, 3, 3)
        self._D_inv = inverses(D[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]].T) if E else np.zeros((0, 3, 3))
        systems, C_all = [], []
        with one_blas_thread():
            for s, (base, width) in enumerate(zip(self._offsets, self._widths)):
                N = normal[base:base + (width + 1) ** 2].reshape(width + 1, width + 1).copy()
                mine = self._mine[s]
                if len(mine):
                    C = normal[self._c_index[s]].reshape(len(mine), 3, width + 1)  # (m, 3, d+1)
                    N -= C.reshape(-1, width + 1).T @ (self._D_inv[mine] @ C).reshape(-1, width + 1)  # the Schur complement
                    N = 0.5 * (N + N.T)
                    C_all.append((mine, C))
                R = _rows_of(N)
                blocks, at = [], 0
                for key in self._keys[s]:
                    dim = 6 if key in self._pose_set else 3
                    blocks.append(np.asfortranarray(R[:, at:at + dim]))
                    at += dim
                systems.append((np.ascontiguousarray(R[:, width]), blocks))
        self._C = C_all
        self._systems = systems
        self._linearized = True
        self._anchor = self._vectors.copy()

    def _bytes(self, key: int, values: gtsam.Values) -> bytes:
        if key in self._pose_set:
            return values.atPose3(key).matrix().tobytes()
        return values.atOrientedPlane3(key).planeCoefficients().tobytes()

    def _error_function(self, s: int):
        width = self._widths[s]

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            self._evaluate(values, H is not None)
            return compressed_rows(self._cost[s], width, None if H is None else self._systems[s], H)

        return error

    # --- after the optimisation -------------------------------------------------------------------

    @property
    def dimension(self) -> int:
        """The scalar unknowns solved inside the factors (3 per eliminated placement)."""
        return 3 * len(self.eliminated)

    def vectors_at(self, values: gtsam.Values) -> dict[Placement, np.ndarray]:
        """The eliminated placements' mirror vectors (owner frames, metres) at ``values``' kept unknowns."""
        self._evaluate(values, False)
        return {p: v.copy() for p, v in zip(self.eliminated, self._vectors)}

    mirror_vectors = vectors_at  # as the tree's ``EliminatedEvaluator`` names it

    def covariances(self, values: gtsam.Values, marginals) -> dict[Placement, np.ndarray]:
        """Each eliminated placement's mirror-vector covariance (3x3), from ``marginals`` of the kept
        unknowns (``jointMarginalCovariance``): ``D^-1 + D^-1 C Sigma_k C^T D^-1`` (module docstring)."""
        self._evaluate(values, True)
        out = {}
        for mine, C in self._C:
            s = int(self._stack_of_placement[mine[0]])
            width = self._widths[s]
            keys = gtsam.KeyVector(self._keys[s])
            joint = marginals.jointMarginalCovariance(keys).fullMatrix() if self._keys[s] else np.zeros((0, 0))
            K = self._D_inv[mine] @ C[:, :, :width]  # (m, 3, d)
            sigma = self._D_inv[mine] + K @ joint @ K.transpose(0, 2, 1)
            for e, block in zip(mine, sigma):
                out[self.eliminated[e]] = block
        return out
