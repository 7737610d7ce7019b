"""The configuration tree of mirror placements (Sect. 4.2, Fig. 3): whether some images form a complete one,
and, where they do not, what it still lacks in the user's words.

A placement is a prefix of an image's ``mirror_configs``; ``(l, m)`` names placement ``m`` of mirror
``l`` (the key of ``Calibration.mirror_vectors``). Bottom-up, a placement of mirror l is *complete* when
>= ``MIN_CHILDREN`` complete placements of mirror l+1 were seen under it (a placement of the last mirror
when seen); the tree is complete when >= ``MIN_CHILDREN`` placements of mirror 1 are.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

from mirror_fg.data import Image

__all__ = ["MIN_CHILDREN", "complete_tree", "tree_shortfall"]

#: Complete placements of mirror l+1 a placement of mirror l (the root: of mirror 1) needs (eqs. 13-17).
MIN_CHILDREN = 3

Prefix = tuple[int, ...]


def _complete_prefixes(leaves: set[Prefix], num_mirrors: int) -> dict[int, set[Prefix]]:
    """The complete placements per level (``0``: the root ``()`` when the tree is complete)."""
    kept = set(leaves)  # level Nv: every leaf seen
    complete = {num_mirrors: kept}
    for level in range(num_mirrors, 0, -1):
        children: dict[Prefix, set[int]] = defaultdict(set)
        for prefix in kept:
            children[prefix[:-1]].add(prefix[-1])
        kept = {parent for parent, c in children.items() if len(c) >= MIN_CHILDREN}
        complete[level - 1] = kept
    return complete


def complete_tree(images: Iterable[Image], num_mirrors: int) -> list[Image]:
    """The images that form a complete configuration tree (Fig. 3), or ``[]`` if there is none; those
    whose every placement is complete, in their order."""
    images = list(images)
    complete = _complete_prefixes({im.mirror_configs for im in images}, num_mirrors)
    if () not in complete[0]:
        return []
    return [im for im in images
            if all(im.mirror_configs[:level] in complete[level] for level in range(num_mirrors + 1))]


def tree_shortfall(images: Iterable[Image], num_mirrors: int) -> str | None:
    """What keeps ``images`` from a complete tree, as one phrase ("mirror 1 has 1 complete placement(s),
    needs 3; mirror 2 has 2 placement(s) under (1, 0), needs 3": along the placement nearest to complete),
    or None when the tree is complete."""
    leaves = {im.mirror_configs for im in images}
    if not leaves:
        return "no image yet"
    complete = _complete_prefixes(leaves, num_mirrors)
    if () in complete[0]:
        return None
    seen = {level: {leaf[:level] for leaf in leaves} for level in range(num_mirrors + 1)}

    def children(parent: Prefix, of: set[Prefix]) -> list[Prefix]:
        return [p for p in of if p[:-1] == parent]

    parts: list[str] = []
    parent: Prefix = ()
    for level in range(1, num_mirrors + 1):
        count = len(children(parent, complete[level]))
        what = "placement(s)" if level == num_mirrors else "complete placement(s)"
        where = f" under ({len(parent)}, {parent[-1]})" if parent else ""
        parts.append(f"mirror {level} has {count} {what}{where}, needs {MIN_CHILDREN}")
        incomplete = [p for p in children(parent, seen[level]) if p not in complete[level]]
        if not incomplete:
            break
        # Follow the incomplete placement with the most complete children: the one nearest to complete.
        parent = max(sorted(incomplete), key=lambda p: len(children(p, complete[level + 1])))
    return "; ".join(parts)
