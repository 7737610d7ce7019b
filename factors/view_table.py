"""The views of a problem as arrays, a block per shape, instead of one ``ViewFactor`` per image (the model of
``views.py``; Hesch et al., eqs. 2, 3, 9): what the stacked and eliminated factors are built from.

Why: the views of one shape (one camera, the same owner camera at each reflection, the same pattern of
repeated placements, the same points seen, sigmas, kernel and intrinsics) differ only in their placements
and their observations. A block holds those of all its views as arrays, ``(b, U)`` placement indices and
``(b, 2, N)`` observations, beside one ``ViewFactor`` of the shape (its *template*, the block's first
view), so that building a problem of thousands of images is a few array operations per block, not an
object and its dictionaries per image. The per-image ``ViewFactor`` s are made only where something asks for
them (:meth:`ViewTable.factors`), sharing the template's arrays (read only).

The stacks (``view_stack.stacks_by_placements``), the placements a stack alone sees
(``view_eliminated.private_placements``) and the groups of one shape (``view_stack.groups_by_shape``) are
computed here from the arrays: the same views in the same order as those functions give of the per-image
factors (``tests/test_view_table.py``).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.factors.views import ViewFactor, ViewSlots

if TYPE_CHECKING:
    from mirror_fg.factors.view_stack import _Group

__all__ = [
    "ViewBlock",
    "ViewTable",
    "collected_keys",
    "groups_by_shape",
    "merged_sets",
    "placement_indices",
    "stacks_by_placements",
    "unique_rows",
    "view_factor_like",
]

Placement = tuple[int, int]


def view_factor_like(template: ViewFactor, reflections: tuple, placements: list, mirror_keys: dict,
                     owners: dict, observed: np.ndarray) -> ViewFactor:
    """The ``ViewFactor`` of a view of the same shape as ``template`` (camera, owners at each reflection,
    pattern of repeated placements, points seen, intrinsics, kernel) through other placements: its own
    reflections, owners, columns, keys and observations, the rest shared with the template (read only).
    ``placements``: the reflections' placements in order of first reflection."""
    factor = object.__new__(type(template))  # a shallow copy (copy.copy's generic protocol costs more here)
    factor.__dict__.update(template.__dict__)
    factor.reflections = tuple(reflections)
    factor.owners = {p: owners[p] for p in factor.reflections}
    slots = template.slots
    offset = 6 * len(slots.pose_cols)
    factor.slots = ViewSlots(slots.pose_cols, {p: offset + 3 * k for k, p in enumerate(placements)}, slots.size)
    factor.mirror_keys = {p: mirror_keys[p] for p in placements}
    factor.base_points = template.base_points.copy()
    factor.observed = np.asarray(observed, dtype=float)
    factor.keys = [*template.pose_keys.values(), *factor.mirror_keys.values(), *template.unique_landmarks,
                   *([template.intrinsics[1]] if template.intrinsics is not None else [])]
    return factor


@dataclass
class ViewBlock:
    """Views of one shape (module docstring): ``template`` the first one's factor, ``members`` (b,) their
    positions in the table, ``placements`` (b, U) their placements (indices into ``ViewTable.placements``)
    in order of first reflection, ``observed`` (b, 2, N) their observations (the factor's ``observed``)."""

    template: ViewFactor
    members: np.ndarray
    placements: np.ndarray
    observed: np.ndarray

    @property
    def local(self) -> list[int]:
        """The position among the view's placements of each reflection (the shape's pattern)."""
        order = list(dict.fromkeys(self.template.reflections))
        return [order.index(p) for p in self.template.reflections]

    @property
    def owners(self) -> tuple[str, ...]:
        """The owner camera at each reflection."""
        return tuple(self.template.owners[p] for p in self.template.reflections)

    @property
    def eliminable(self) -> bool:
        """Whether its views can be in an eliminated stack: fiducials only, intrinsics known, no kernel."""
        t = self.template
        return t.intrinsics is None and not t.unique_landmarks and t.robust is None


def collected_keys(view_factors: Sequence[ViewFactor]) -> tuple[dict, dict[str, int], dict[Placement, int]]:
    """The fixed poses, the pose keys and the plane keys of ``view_factors`` (each in order first seen)."""
    fixed: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    pose_keys: dict[str, int] = {}
    mirror_keys: dict[Placement, int] = {}
    for f in view_factors:
        fixed.update(f.fixed)
        pose_keys.update(f.pose_keys)
        mirror_keys.update(f.mirror_keys)
    return fixed, pose_keys, mirror_keys


def groups_by_shape(view_factors: Sequence[ViewFactor], extra: Any = None) -> list[list[int]]:
    """The views (indices) of each shape, in order first seen: one camera, the same owner and placement
    position at each reflection, the same pose keys, as many points, one kernel (and the same
    ``extra(view)``, where given): what a :class:`_Group` evaluates at once."""
    shapes: dict[tuple, list[int]] = {}
    for i, f in enumerate(view_factors):
        order = list(f.mirror_keys)  # the placements in order of first reflection
        owners = tuple(f.owners[p] for p in f.reflections)
        local = tuple(range(len(order))) if len(order) == len(f.reflections) else tuple(map(order.index, f.reflections))
        shape = (f.camera, owners, local, tuple(f.pose_keys), f.base_points.shape[1], f.robust, f.robust_k,
                 None if extra is None else extra(f))
        shapes.setdefault(shape, []).append(i)
    return list(shapes.values())


def stacks_by_placements(view_factors: Sequence[ViewFactor], placements_per_factor: int) -> list[list[int]]:
    """The views (indices) of each stack: views with the same placements, in the order first seen;
    consecutive ones merged up to ``placements_per_factor`` placements (fewer factor calls, each of which
    copies the Values)."""
    same: dict[frozenset, list[int]] = {}
    for i, f in enumerate(view_factors):
        same.setdefault(frozenset(f.mirror_keys), []).append(i)
    merged: list[tuple[set, list[int]]] = []
    for placements, members in same.items():
        if merged and len(merged[-1][0]) + sum(p not in merged[-1][0] for p in placements) <= placements_per_factor:
            merged[-1][0].update(placements)
            merged[-1][1].extend(members)
        else:
            merged.append((set(placements), list(members)))
    return [members for _, members in merged]


def placement_indices(placements: list[Placement], rows: list) -> np.ndarray:
    """Each row's placements (b, U) (rows of one length) as indices into ``placements`` (sorted, as
    ``ViewProblem.placements``)."""
    if not placements or not rows or not rows[0]:
        return np.zeros((len(rows), 0), dtype=np.intp)
    known = np.array(placements, dtype=np.int64).reshape(-1, 2)
    low, span = known.min(axis=0), int(np.ptp(known[:, 1])) + 1  # (l, m) -> (l - l0) span + m - m0: as the tuples
    asked = np.array(rows, dtype=np.int64).reshape(len(rows), -1, 2)
    codes = (known[:, 0] - low[0]) * span + (known[:, 1] - low[1])
    return np.searchsorted(codes, (asked[..., 0] - low[0]) * span + (asked[..., 1] - low[1])).astype(np.intp)


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_index=True, return_inverse=True)`` of integer rows (n, w) without the
    rows themselves, by one lexicographic sort of the columns (``np.unique`` sorts the rows as opaque records:
    several times slower): each distinct row's first index, and each row's distinct row (in sorted order)."""
    count = len(rows)
    order = np.lexsort(rows.T[::-1]) if rows.shape[1] else np.arange(count)  # (stable: the first of equal rows first)
    ordered = rows[order]
    new = np.ones(count, dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    which = np.empty(count, dtype=np.intp)
    which[order] = np.cumsum(new) - 1
    return order[new], which


def merged_sets(sets: np.ndarray, limit: int) -> np.ndarray:
    """Each set's stack: ``sets`` (S, w) (placements, -1 pads) in order, consecutive ones merged while their
    union has at most ``limit`` placements, the next set starting a new stack (``view_stack.stacks_by_placements``).
    A stack's union after each of its sets is the number of its placements not seen since it began: a
    cumulative sum, so each stack is found by one search (over a window that doubles until the stack ends)."""
    count, width = sets.shape
    flat = sets.reshape(-1)
    mine = flat >= 0
    set_of, flat = np.repeat(np.arange(count), width)[mine], flat[mine]
    by_placement = np.lexsort((np.arange(len(flat)), flat))
    previous = np.full(len(flat), -1, dtype=np.intp)  # each pair's previous pair of the same placement
    same = flat[by_placement[1:]] == flat[by_placement[:-1]]
    previous[by_placement[1:][same]] = by_placement[:-1][same]
    starts = np.searchsorted(set_of, np.arange(count + 1))  # each set's first pair
    stack = np.zeros(count, dtype=np.intp)
    begin, k, window = 0, 0, max(4 * limit, 16)
    while begin < count:
        end = min(count, begin + window)
        q0 = starts[begin]
        union = np.concatenate([[0], np.cumsum(previous[q0:starts[end]] < q0)])[starts[begin + 1:end + 1] - q0]
        fits = int(np.searchsorted(union, limit, side="right"))  # the union only grows
        if fits == end - begin and end < count:
            window *= 2  # the stack may go on past the window
            continue
        stop = begin + max(fits, 1)  # (a set alone beyond the limit is a stack of its own)
        stack[begin:stop] = k
        k, begin = k + 1, stop
    return stack


class ViewTable:
    """Views as blocks of one shape (module docstring). ``placements``: every placement, indexed by the
    blocks' ``placements``; ``mirror_keys``, ``owners``: each placement's plane key and owner camera;
    ``count``: the number of views (positions 0..count-1 over the blocks' ``members``)."""

    def __init__(self, blocks: list[ViewBlock], placements: list[Placement], mirror_keys: dict[Placement, int],
                 owners: dict[Placement, str], count: int):
        self.blocks, self.placements, self.count = blocks, placements, count
        self.mirror_keys, self.owners = mirror_keys, owners
        self._pairs_cache: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    @classmethod
    def of_factors(cls, view_factors: Sequence[ViewFactor]) -> ViewTable:
        """The table of per-image factors, a block per factor."""
        placements = sorted({p for f in view_factors for p in f.mirror_keys})
        index = {p: i for i, p in enumerate(placements)}
        mirror_keys: dict[Placement, int] = {}
        owners: dict[Placement, str] = {}
        blocks = []
        for i, f in enumerate(view_factors):
            mirror_keys.update(f.mirror_keys)
            owners.update(f.owners)
            blocks.append(ViewBlock(f, np.array([i], dtype=np.intp),
                                    np.array([[index[p] for p in f.mirror_keys]], dtype=np.intp).reshape(1, -1),
                                    f.observed[None]))
        return cls(blocks, placements, mirror_keys, owners, len(view_factors))

    def subset(self, keep: Callable[[ViewBlock], bool]) -> ViewTable:
        """The table of the blocks ``keep`` accepts, their views renumbered in the same order."""
        blocks = [block for block in self.blocks if keep(block)]
        position = np.full(self.count, -1, dtype=np.intp)
        members = np.sort(np.concatenate([b.members for b in blocks])) if blocks else np.zeros(0, dtype=np.intp)
        position[members] = np.arange(len(members))
        return ViewTable([ViewBlock(b.template, position[b.members], b.placements, b.observed) for b in blocks],
                         self.placements, self.mirror_keys, self.owners, len(members))

    # --- the per-image factors, where asked ------------------------------------------------------

    def factors(self) -> list[ViewFactor]:
        """Every view's ``ViewFactor``, in order."""
        out: list[ViewFactor | None] = [None] * self.count
        for block in self.blocks:
            local = block.local
            template = block.template
            for row, i in enumerate(block.members.tolist()):
                if row == 0:
                    out[i] = template
                    continue
                placements = [self.placements[u] for u in block.placements[row].tolist()]
                out[i] = view_factor_like(template, tuple(placements[u] for u in local), placements,
                                          self.mirror_keys, self.owners, block.observed[row])
        return out  # type: ignore[return-value]

    # --- the layout of the stacked factors -------------------------------------------------------

    def _pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every (view, its u-th placement) pair, in view order then ``u``: views, ``u``, placements and
        each pair's block (computed once: the blocks are not changed)."""
        if self._pairs_cache is None:
            self._pairs_cache = self._pairs_of_blocks()
        return self._pairs_cache

    def _pairs_of_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        views, us, ids, blocks = [], [], [], []
        for k, block in enumerate(self.blocks):
            b, U = block.placements.shape
            views.append(np.repeat(block.members, U))
            us.append(np.tile(np.arange(U, dtype=np.intp), b))
            ids.append(block.placements.reshape(-1))
            blocks.append(np.full(b * U, k, dtype=np.intp))
        if not views:
            empty = np.zeros(0, dtype=np.intp)
            return empty, empty, empty, empty
        views_, us_, ids_, blocks_ = (np.concatenate(a) for a in (views, us, ids, blocks))
        order = np.lexsort((us_, views_))
        return views_[order], us_[order], ids_[order], blocks_[order]

    def stacks(self, placements_per_factor: int) -> list[np.ndarray]:
        """The views of each stack: ``view_stack.stacks_by_placements`` (views with the same placements in
        the order first seen, consecutive ones merged up to ``placements_per_factor`` placements)."""
        width = max((b.placements.shape[1] for b in self.blocks), default=0)
        sets = np.full((self.count, max(width, 1)), -1, dtype=np.intp)  # each view's placements, sorted, padded
        for block in self.blocks:
            U = block.placements.shape[1]
            sets[block.members, :U] = np.sort(block.placements, axis=1)
        if width > 1:  # a placement twice in a view counts once (a set)
            repeated = np.zeros_like(sets, dtype=bool)
            repeated[:, 1:] = sets[:, 1:] == sets[:, :-1]
            sets[repeated] = -1
            sets = np.sort(sets, axis=1)
        first, which = unique_rows(sets)
        rank = np.empty(len(first), dtype=np.intp)  # each set's rank in order first seen
        rank[np.argsort(first, kind="stable")] = np.arange(len(first))
        in_order = sets[np.sort(first)]
        stack_of_set = merged_sets(in_order, placements_per_factor)
        set_rank = rank[which]
        order = np.lexsort((np.arange(self.count), set_rank))  # by set (first seen), then view
        stack_of_view = stack_of_set[set_rank[order]]
        bounds = np.flatnonzero(np.diff(stack_of_view)) + 1
        return np.split(order, bounds) if self.count else []

    def collected_keys(self) -> tuple[dict, dict[str, int], dict[Placement, int]]:
        """``view_stack.collected_keys`` of the views: the fixed poses, the pose keys and the plane keys, each
        in order first seen."""
        fixed: dict = {}
        pose_keys: dict[str, int] = {}
        for block in sorted(self.blocks, key=lambda b: int(b.members[0])):
            fixed.update(block.template.fixed)
            pose_keys.update(block.template.pose_keys)
        _, _, ids, _ = self._pairs()
        unique, first = np.unique(ids, return_index=True)
        in_order = unique[np.argsort(first, kind="stable")]
        return fixed, pose_keys, {self.placements[u]: self.mirror_keys[self.placements[u]] for u in in_order.tolist()}

    def private_placements(self, stacks: list[np.ndarray], keep: set) -> list[Placement]:
        """``view_eliminated.private_placements``: the placements seen by one stack's views only, not in
        ``keep``, last in every view's reflections and seen by their owner camera only (the paper's last
        mirror). Each view has one last reflection, so no view has two of them."""
        stack_of_view = np.zeros(self.count, dtype=np.intp)
        for s, members in enumerate(stacks):
            stack_of_view[members] = s
        views, us, ids, blocks = self._pairs()
        # as the paper's last mirror: seen by its owner camera only and last in every view's reflections (in
        # other places its cost in v alone is far from quadratic: Gauss-Newton on it crawled or diverged on a
        # rig's two-mirror views, where the placements stay variables); a pair is "transferred" unless its
        # placement is the view's last reflection, owned by its camera
        last_u = np.array([b.local[-1] if b.local else -1 for b in self.blocks], dtype=np.intp)
        own_last = np.array([bool(b.local) and b.template.owners[b.template.reflections[-1]] == b.template.camera
                             for b in self.blocks], dtype=bool)
        transferred = (us != last_u[blocks]) | ~own_last[blocks]
        count = len(self.placements)
        seen = np.bincount(ids, minlength=count) > 0
        stack = stack_of_view[views]
        low = np.full(count, np.iinfo(np.intp).max, dtype=np.intp)
        high = np.full(count, -1, dtype=np.intp)
        np.minimum.at(low, ids, stack)
        np.maximum.at(high, ids, stack)
        bad = np.zeros(count, dtype=bool)
        bad[ids[transferred]] = True
        kept = np.array([p in keep for p in self.placements], dtype=bool)
        chosen = seen & (low == high) & ~bad & ~kept
        return [self.placements[u] for u in np.flatnonzero(chosen).tolist()]

    def groups(self, eliminated: np.ndarray | None = None
               ) -> list[tuple[ViewFactor, np.ndarray, list[tuple[ViewBlock, np.ndarray]]]]:
        """The views of each shape (``view_stack.groups_by_shape``; with ``eliminated``, a mask over the
        placements, also the same placements eliminated): ``(first view's block template, members (sorted),
        [(block, its rows in the group)])`` in order first seen."""
        shapes: dict[tuple, list[tuple[ViewBlock, np.ndarray]]] = {}
        for block in self.blocks:
            t = block.template
            shape = (t.camera, block.owners, tuple(block.local), tuple(t.pose_keys), t.base_points.shape[1],
                     t.robust, t.robust_k)
            if eliminated is None:
                shapes.setdefault(shape, []).append((block, np.arange(len(block.members))))
                continue
            pattern = eliminated[block.placements]  # (b, U)
            firsts, which = unique_rows(pattern.astype(np.intp))
            for k, row in enumerate(pattern[firsts]):
                shapes.setdefault((*shape, tuple(row.tolist())), []).append((block, np.flatnonzero(which == k)))
        out = []
        for parts in shapes.values():
            members = np.concatenate([block.members[rows] for block, rows in parts])
            out.append((int(members.min()), np.sort(members), parts))
        out.sort(key=lambda g: g[0])
        return [(min(parts, key=lambda part: int(part[0].members[part[1][0]]))[0].template, members, parts)
                for _, members, parts in out]

    def stack_keys(self, stacks: list[np.ndarray], eliminated: np.ndarray) -> tuple[list[list[int]], list[list[int]]]:
        """Each stack's pose keys and its placements not ``eliminated`` (a mask over the placements, as
        indices), each in order first seen over the stack's views (their placements in order of first
        reflection), as ``view_eliminated`` lays its factors out."""
        position = np.zeros(self.count, dtype=np.intp)  # each view's place in the stacks' order
        stack_of_view = np.zeros(self.count, dtype=np.intp)
        block_of_view = np.zeros(self.count, dtype=np.intp)
        at = 0
        for s, members in enumerate(stacks):
            position[members] = np.arange(at, at + len(members))
            stack_of_view[members] = s
            at += len(members)
        for k, block in enumerate(self.blocks):
            block_of_view[block.members] = k
        poses: list[list[int]] = []
        for members in stacks:  # the shapes' pose keys (a few shapes per stack)
            blocks, first = np.unique(block_of_view[members], return_index=True)
            ordered = blocks[np.argsort(first, kind="stable")].tolist()
            poses.append(list(dict.fromkeys(k for b in ordered for k in self.blocks[b].template.pose_keys.values())))
        views, us, ids, _ = self._pairs()
        kept = ~eliminated[ids]
        order = np.lexsort((us[kept], position[views[kept]]))
        code = stack_of_view[views[kept]][order] * len(self.placements) + ids[kept][order]
        unique, first = np.unique(code, return_index=True)
        code = unique[np.argsort(first, kind="stable")]  # (stack, placement) in order first seen
        stack = code // max(len(self.placements), 1)
        placements: list[list[int]] = [[] for _ in stacks]
        bounds = np.searchsorted(stack, np.arange(len(stacks) + 1))
        for s in range(len(stacks)):
            placements[s] = (code[bounds[s]:bounds[s + 1]] % len(self.placements)).tolist()
        return poses, placements

    def group_of(self, first: ViewFactor, parts: list[tuple[ViewBlock, np.ndarray]]) -> _Group:
        """The ``view_stack._Group`` of one of :meth:`groups`' groups (its views in order)."""
        from mirror_fg.factors.view_stack import (
            _Group,  # (view_stack builds its stacks of tables)
        )

        members = np.concatenate([block.members[rows] for block, rows in parts])
        order = np.argsort(members, kind="stable")

        def stacked(arrays: list[np.ndarray]) -> np.ndarray:
            return (arrays[0] if len(arrays) == 1 else np.concatenate(arrays))[order]

        def shared(array: np.ndarray, rows: np.ndarray) -> np.ndarray:
            return np.broadcast_to(array, (len(rows), *array.shape))

        return _Group.of_arrays(first, stacked([block.placements[rows] for block, rows in parts]), self.placements,
                                stacked([shared(block.template.base_points, rows) for block, rows in parts]),
                                stacked([block.observed[rows] for block, rows in parts]),
                                stacked([shared(block.template.sigmas, rows) for block, rows in parts]),
                                stacked([shared(block.template.landmark_keys, rows) for block, rows in parts]))
