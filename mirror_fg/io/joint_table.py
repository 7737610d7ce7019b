"""A joint-state CSV (docs/formats.md, "Robot arms: joint states and mounts"): a header of joint names and
either an ``image`` column (the image file's name) or a ``time`` column (seconds, any clock the images'
``time`` share), one row per recorded state; values in radians (metres for a prismatic joint).

Matching by time takes, for an image at time ``t``, the one row nearest to ``t``; it is refused where no
row lies within ``max_dt`` seconds (default 0.02 s) or where two rows are equally near (within
``TIE_S``): which state the image shows cannot then be told. Used by capture@1 (``io/robot_capture.py``)
and by live sessions reading a CSV as it grows (``live/joints.py``).
"""
from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import short

__all__ = ["JointTable", "parse_header", "parse_row", "DEFAULT_MAX_DT", "TIE_S"]

#: Largest distance (seconds) between an image's time and its joint row's, when the capture gives none.
DEFAULT_MAX_DT = 0.02
#: Two rows whose distances to an image's time differ by less than this (seconds) are equally near.
TIE_S = 1e-6


def parse_header(header: Sequence[str], name: str) -> tuple[str, list[str]]:
    """``("image" | "time", joint names)`` of a CSV header; DatasetError naming the file otherwise."""
    header = [h.strip() for h in header]
    key = "image" if "image" in header else "time" if "time" in header else None
    if key is None:
        raise DatasetError(f"{name}: no image or time column (the image file's name, or the time in seconds, on each row)")
    joints = [h for h in header if h not in ("image", "time")]
    if not joints or any(not h for h in joints):
        raise DatasetError(f"{name}: the header must name every joint column (got {short(list(header))})")
    return key, joints


def parse_row(row: Mapping[str, str | None], key: str, joints: Sequence[str], name: str,
              line: int) -> tuple[str | float, dict[str, float]]:
    """One row's key (image name, or time in seconds) and joint values; DatasetError naming the line."""
    text = (row.get(key) or "").strip()
    if key == "image":
        if not text:
            raise DatasetError(f"{name}: line {line}: empty image name")
        where = f"{name}: line {line}: image {text!r}"
        value: str | float = text
    else:
        try:
            value = float(text)
        except ValueError:
            raise DatasetError(f"{name}: line {line}: time is {short(text)}, not a number of seconds") from None
        if not math.isfinite(value):
            raise DatasetError(f"{name}: line {line}: time is {text} (not a finite number of seconds)")
        where = f"{name}: line {line} (time {text})"
    values: dict[str, float] = {}
    for joint in joints:
        cell = row.get(joint)
        try:
            values[joint] = float(cell)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: joint {joint!r} is {short(cell)}, not a number") from None
        if not math.isfinite(values[joint]):
            raise DatasetError(f"{where}: joint {joint!r} is {cell} (not a finite number)")
    return value, values


@dataclass
class JointTable:
    """The rows of a joint-state CSV, keyed by image name or kept sorted by time."""

    name: str
    key: str
    joints: list[str]
    by_image: dict[str, dict[str, float]] = field(default_factory=dict)
    times: list[float] = field(default_factory=list)
    states: list[dict[str, float]] = field(default_factory=list)

    def add(self, value: str | float, values: dict[str, float], line: int) -> None:
        """One parsed row (rows may come in any order; an image named twice is refused)."""
        if self.key == "image":
            if value in self.by_image:
                raise DatasetError(f"{self.name}: line {line}: image {value!r} has two rows")
            self.by_image[str(value)] = values
            return
        k = bisect.bisect_right(self.times, float(value))
        self.times.insert(k, float(value))
        self.states.insert(k, values)

    @property
    def last_time(self) -> float | None:
        return self.times[-1] if self.times else None

    def nearest(self, t: float, max_dt: float, image: str) -> dict[str, float]:
        """The row nearest to time ``t`` (seconds); DatasetError naming ``image`` where none lies within
        ``max_dt`` or two are equally near."""
        k = bisect.bisect_left(self.times, t)
        near = sorted((abs(self.times[j] - t), j) for j in (k - 1, k) if 0 <= j < len(self.times))
        if not near or near[0][0] > max_dt:
            gap = f"; the nearest is {near[0][0]:.3f} s away" if near else "; the file has no rows"
            raise DatasetError(f"image {image!r} (time {t:.6g} s): {self.name} has no row within max_dt {max_dt:g} s{gap}")
        if len(near) == 2 and near[1][0] - near[0][0] < TIE_S:
            a, b = sorted(self.times[j] for _, j in near)
            raise DatasetError(f"image {image!r} (time {t:.6g} s): {self.name} has two rows equally near (times {a:.6g} "
                               f"and {b:.6g} s): which joint state it shows cannot be told")
        return self.states[near[0][1]]
