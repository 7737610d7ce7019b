"""The analytical solution's placement rule in the user's words (docs/formats.md "Frames and symbols"; paper Sect. 5).

Every placement of mirrors 1..l-1 needs at least three different placements of mirror l seen with it
(the paper's ternary tree, Fig. 3, with >= 3 children per node); the root needs three of mirror 1.
:func:`too_few_placements` says which node falls short, in placements and mirrors rather than tree
nodes, and whether the labels would satisfy the rule with the mirrors in the reverse order (the most
common mix-up: ``mirror_configs`` lists the mirrors from the target to the camera).
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

__all__ = ["MIN_PLACEMENTS", "too_few_placements", "satisfies_placement_rule"]

#: Placements of mirror l needed under every placement of mirrors 1..l-1 (eqs. 13-18 need three).
MIN_PLACEMENTS = 3
_WORDS = ("none", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


def satisfies_placement_rule(configs: Sequence[tuple[int, ...]]) -> bool:
    """True when, at every level l, every placement of mirrors 1..l-1 among ``configs`` (one
    ``mirror_configs`` tuple per image) has at least :data:`MIN_PLACEMENTS` placements of mirror l."""
    if not configs:
        return False
    for level in range(1, len(configs[0]) + 1):
        children: dict[tuple[int, ...], set[int]] = defaultdict(set)
        for c in configs:
            children[c[: level - 1]].add(c[level - 1])
        if any(len(placed) < MIN_PLACEMENTS for placed in children.values()):
            return False
    return True


def too_few_placements(source: str, configs: Sequence[tuple[int, ...]], prefix: tuple[int, ...], level: int,
                       placed: Sequence[int]) -> str:
    """One line: under ``prefix`` (placements of mirrors 1..level-1) mirror ``level`` has only ``placed``.

    ``configs``: the ``mirror_configs`` of the images the analytical solution uses.
    """
    count = len(placed)
    gave = _WORDS[count] if count < len(_WORDS) else str(count)
    listed = ", ".join(str(m) for m in placed[:8]) + (", ..." if count > 8 else "")
    under = ""
    if prefix:
        pairs = ", ".join(f"({l + 1}, {m})" for l, m in enumerate(prefix))  # docs/formats.md: placement m of mirror l is (l, m)
        words = " and ".join(f"mirror {l + 1} at placement {m}" for l, m in enumerate(prefix))
        under = f"under placement {pairs} ({words}), "
    line = (f"{source}: {under}mirror {level} needs at least {_WORDS[MIN_PLACEMENTS]} placements, you gave {gave}"
            + (f" ({listed})" if count else ""))
    num_mirrors = len(configs[0]) if configs else 0
    if num_mirrors > 1 and satisfies_placement_rule([tuple(reversed(c)) for c in configs]):
        line += (f"; with the mirrors in the other order the placements would suffice: mirror_configs lists the "
                 f"mirrors from the target to the camera (mirror 1 is the one the light meets first, mirror "
                 f"{num_mirrors} the one the camera looks into)")
    return line
