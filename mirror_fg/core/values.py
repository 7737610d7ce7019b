"""Checks of plain values read from user files, and the short quotes of them that messages carry.

Shared by every reader (dataset@1, result@1, capture@1, camera files): a JSON ``true`` is not a count,
an unknown key is refused with the key that was probably meant, and a message quotes at most a few
dozen characters of the user's data, bounded in work too (a huge integer or an aliased YAML value is
not expanded). Problems are :class:`~mirror_fg.core.errors.DatasetError` with one line.
"""
from __future__ import annotations

import difflib
import math
import numbers
import os
import reprlib
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # annotations only (``from __future__ import annotations``): no runtime dependency
    from typing_extensions import TypeIs

from mirror_fg.core.errors import DatasetError

__all__ = [
    "is_int",
    "is_index",
    "MAX_INDEX",
    "is_number",
    "finite",
    "type_name",
    "short",
    "clip",
    "short_path",
    "absolute_path",
    "check_format",
    "check_keys",
    "check_name",
    "coordinates",
    "vector",
    "named_vectors",
    "check_size",
    "check_extent",
    "MAX_TARGET_EXTENT_M",
    "MAX_FEATURE_SIZE_M",
    "MIN_LENGTH_M",
    "NAME_LIMIT",
]

#: User-given names (files, keys) are quoted in messages up to this many characters.
NAME_LIMIT = 80
#: Largest index or count of mirrors, placements (configurations) and iterations, in every file read or
#: written (dataset@1, capture@1, result@1): they stay machine integers (int32), so that what is accepted
#: on input is also a valid result.
MAX_INDEX = 2**31 - 1
#: Largest extent (metres, the diagonal of the bounding box) of a calibration target or fiducial layout
#: accepted: a size typed in millimetres into a metres field is 1000 times too large, and a target
#: wider than a room cannot be photographed whole through a mirror anyway.
MAX_TARGET_EXTENT_M = 5.0
#: Largest chessboard square, marker or tag edge (metres) accepted, for the same reason.
MAX_FEATURE_SIZE_M = 1.0
#: Smallest length (metres) a user may type for a size or distance: nothing a camera resolves through a
#: mirror is shorter than a tenth of a millimetre, and a length of 1e-100 m leaves only NaN downstream.
MIN_LENGTH_M = 1e-4


# --------------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------------


def is_int(x: Any) -> TypeIs[int | np.integer[Any]]:
    """An integer that is not a bool (JSON ``true`` is not a count)."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def is_index(x: Any, minimum: int = 0) -> bool:
    """An integer (not a bool) from ``minimum`` to :data:`MAX_INDEX`."""
    return bool(is_int(x) and minimum <= x <= MAX_INDEX)


def is_number(x: Any) -> bool:
    """A real number that is not a bool."""
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def finite(x: Any) -> float | None:
    """``x`` as a finite float; None for what is not a real number (bools, strings, null), NaN, inf, or an
    integer too large for a float (a 400-digit integer)."""
    if not is_number(x):
        return None
    try:
        value = float(x)
    except (OverflowError, ValueError, TypeError):
        return None
    return value if math.isfinite(value) else None


def coordinates(value: Any, n: int, shape: str, what: str) -> np.ndarray:
    """``value`` as a float array (n,) of finite numbers, else DatasetError starting with ``what``."""
    if value is None:
        raise DatasetError(f"{what}: missing coordinates, expected {shape}")
    if isinstance(value, np.ndarray):
        items = list(value.ravel()) if value.ndim == 1 else None
    elif isinstance(value, (list, tuple)):
        items = list(value)
    else:
        items = None
    if items is None or len(items) != n:
        got = f"{len(items)} values" if items is not None else short(value)
        raise DatasetError(f"{what}: expected {n} coordinates {shape}, got {got}")
    for k, x in enumerate(items):
        if not is_number(x):
            raise DatasetError(f"{what}: coordinate {k} is not a number: {short(x)}")
    try:
        coords = np.array([float(x) for x in items], dtype=np.float64)
    except OverflowError:
        coords = np.full(n, np.inf)
    if not np.all(np.isfinite(coords)):
        raise DatasetError(f"{what}: coordinates are not finite: {short(items)}")
    return coords


def vector(value: Any, n: int, where: str) -> np.ndarray:
    """``n`` finite numbers given as a list, as a float array (n,); DatasetError starting with ``where``."""
    if not isinstance(value, (list, tuple)) or len(value) != n or not all(is_number(x) for x in value):
        raise DatasetError(f"{where}: expected {n} numbers, got {short(value)}")
    values = [finite(x) for x in value]
    if None in values:
        raise DatasetError(f"{where}: not finite: {short(value)}")
    return np.array(values)


def named_vectors(value: Mapping[Any, Any], n: int, where: str, what: str) -> dict[str, np.ndarray]:
    """``{name: [n numbers]}`` with non-empty string names; ``what`` names an entry in messages."""
    out: dict[str, np.ndarray] = {}
    for name, v in value.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"{where}: {what} name must be a non-empty string, got {short(name)}")
        out[name] = vector(v, n, f"{where}: {what} {short(name)}")
    return out


def check_size(size_m: float, limit_m: float, where: str, quantity: str, noun: str,
               smallest_m: float | None = MIN_LENGTH_M) -> None:
    """Refuse a size (metres) above ``limit_m`` with one line naming the unit: most often millimetres
    typed into a metres field (``square: 27.5``); and one below ``smallest_m`` (no camera resolves it)."""
    if size_m > limit_m:
        raise DatasetError(f"{where}: {quantity} {size_m:g} m is not a plausible {noun} (at most {limit_m:g} m); "
                           f"sizes are in metres ({size_m:g} mm = {size_m / 1000:g})")
    if smallest_m is not None and size_m < smallest_m:
        raise DatasetError(f"{where}: {quantity} {size_m:g} m is not a plausible {noun} (at least {smallest_m:g} m); "
                           "sizes are in metres")


def check_extent(points: Iterable[np.ndarray], where: str, noun: str) -> None:
    """Refuse points (metres) whose bounding box is more than :data:`MAX_TARGET_EXTENT_M` across."""
    xyz = np.array(list(points), dtype=float).reshape(-1, 3)
    if len(xyz):
        extent = float(np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0)))
        check_size(extent, MAX_TARGET_EXTENT_M, where, "extent", noun, smallest_m=None)  # collinear: checked apart


# --------------------------------------------------------------------------------------------------
# Keys
# --------------------------------------------------------------------------------------------------


def check_format(d: Any, expected: str, source: str) -> None:
    """Refuse anything but an object whose ``format`` is ``expected`` (one line naming ``source``)."""
    if not isinstance(d, Mapping):
        raise DatasetError(f"{source}: expected an object at the top level, got {type_name(d)}")
    fmt = d.get("format")
    if fmt != expected:
        what = "missing 'format'" if fmt is None else f"unknown format {short(fmt)}"
        raise DatasetError(f"{source}: {what} (expected {expected!r})")


def check_keys(mapping: Mapping[Any, Any], allowed: Iterable[str], where: str) -> None:
    """Refuse a key of ``mapping`` outside ``allowed``, naming the key meant where one is close."""
    allowed = tuple(allowed)
    for key in mapping:
        if key not in allowed:
            check_name(key, allowed, where, "key")


def check_name(name: Any, allowed: tuple[str, ...], where: str, what: str) -> None:
    """Refuse ``name`` outside ``allowed`` (``what``: "key", "intrinsic"), with the name probably meant."""
    if name in allowed:
        return
    # Matched on its first NAME_LIMIT characters: difflib's work and memory grow with the product of
    # the lengths (a 50 MB key ended in MemoryError), and a longer name is close to none of ours.
    head = name[:NAME_LIMIT] if isinstance(name, str) else None
    close = difflib.get_close_matches(head, allowed, n=1, cutoff=0.5) if head is not None else []
    if not close and head is not None:  # "distortion" -> "dist": a known name that starts it
        close = [a for a in allowed if len(a) >= 3 and head.lower().startswith(a)][:1]
    hint = f" (did you mean {close[0]!r}?)" if close else f" (expected one of {', '.join(allowed)})"
    raise DatasetError(f"{where}: unknown {what} {short(name)}{hint}")


# --------------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------------


def type_name(x: Any) -> str:
    """JSON-ish name of a value's type, for messages."""
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    for t, name in names.items():
        if isinstance(x, t):
            return name
    return "a number" if is_number(x) else type(x).__name__


class Quoter(reprlib.Repr):
    """reprlib with small limits, and without expanding huge integers (str() of one can raise)."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 2, 6, 6, 3
        self.maxstring, self.maxother, self.maxlong = 40, 40, 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:
            return f"<integer of {int(x.bit_length() * 0.30103) + 1} digits>"
        return super().repr_int(x, level)


_QUOTER = Quoter()


def short(x: Any, limit: int = 60) -> str:
    """One-line repr of user data for messages, bounded in length and in work (an aliased or deeply
    nested value is not expanded)."""
    if isinstance(x, np.ndarray):
        x = x.tolist() if x.size <= 8 else f"<array of shape {x.shape}>"
    text = " ".join(_QUOTER.repr(x).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def clip(text: str, limit: int = NAME_LIMIT) -> str:
    """One line of at most ``limit`` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def absolute_path(path: str) -> str:
    """The absolute ``path`` for a message on one line ("where it looked"): each folder or file name in it
    quoted up to :data:`NAME_LIMIT` characters, at most the last eight of them."""
    parts = [clip(part) for part in os.path.abspath(path).split(os.sep)]
    return os.sep.join(parts) if len(parts) <= 9 else "..." + os.sep + os.sep.join(parts[-8:])


def short_path(path: str) -> str:
    """A user-given path for messages, on one line; a long one keeps its end (the file name)."""
    path = " ".join(path.split())
    return path if len(path) <= NAME_LIMIT else "..." + path[-(NAME_LIMIT - 3):]
