"""The result@1 validator's low-level checkers (:func:`mirror_fg.io.result.validate_result` uses them).

Each checker takes a parsed value and its key path (``mirrors[3].v``) and returns the plain (JSON-like)
value, numpy values turned into plain ones, or raises :class:`_Invalid` at that path; the validator
turns that into one :class:`~mirror_fg.core.errors.DatasetError` line. The schema itself (which key
holds what) is ``result_schema.py``. Units as there: metres, 3-sigma bounds in degrees and millimetres.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.transform import quaternion_xyzw_to_rotation
from mirror_fg.core.values import MAX_INDEX, is_index, is_int, is_number, short, type_name

#: A checker: ``(value, key path) -> plain value``, raising :class:`_Invalid`.
Checker = Callable[[Any, str], Any]

#: A rotation (or a quaternion against it) may be off by rounding; beyond this it is rejected.
ORTHONORMAL_TOL = 1e-6
#: Covariance symmetry, relative to its largest entry.
SYMMETRY_TOL = 1e-6
_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class _Invalid(Exception):
    """A problem at a key path; :func:`~mirror_fg.io.result.validate_result` turns it into one DatasetError line."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(path, problem)
        self.path, self.problem = path, problem


# --------------------------------------------------------------------------------------------------
# Key paths
# --------------------------------------------------------------------------------------------------


def _child(path: str, key: Any) -> str:
    """Key path of ``key`` below ``path``: ``a.b``, ``a[3]``, ``points['odd name']``."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    if isinstance(key, str) and _IDENTIFIER.match(key):
        return f"{path}.{key}" if path else key
    return f"{path}[{short(key, 40)}]"


# --------------------------------------------------------------------------------------------------
# Checkers: each returns the plain (JSON-like) value or raises _Invalid at its path
# --------------------------------------------------------------------------------------------------


def _mapping(value: Any, path: str) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise _Invalid(path, f"expected an object, got {type_name(value)} {short(value)}")
    return value


def _items(value: Any, n: int | None, what: str, path: str) -> list[Any]:
    """A list (tuple, 1-D+ array) of ``n`` items (any number when ``n`` is None)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        expected = f"{n} {what}" if n is not None else f"a list of {what}"
        raise _Invalid(path, f"expected {expected}, got {type_name(value)} {short(value)}")
    if n is not None and len(value) != n:
        raise _Invalid(path, f"expected {n} {what}, got {len(value)}")
    return list(value)


def _number(value: Any, path: str, *, nan_ok: bool = False, minimum: float | None = None) -> float:
    """A finite real number (NaN too where ``nan_ok``: a statistic that could not be computed)."""
    if isinstance(value, np.generic):
        value = value.item()
    if not is_number(value):
        raise _Invalid(path, f"expected a number, got {type_name(value)} {short(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise _Invalid(path, f"number out of range: {short(value)}") from None
    if nan_ok and math.isnan(x):
        return x
    if not math.isfinite(x):
        raise _Invalid(path, f"expected a finite number, got {short(value)}")
    if minimum is not None and x < minimum:
        raise _Invalid(path, f"expected a number >= {minimum:g}, got {short(value)}")
    return x


def _vector(value: Any, n: int, path: str, **number: Any) -> list[float]:
    out = []
    for k, x in enumerate(_items(value, n, "numbers", path)):
        try:
            out.append(_number(x, "", **number))
        except _Invalid as error:  # the element's path only on failure: vectors are many
            raise _Invalid(_child(path, k), error.problem) from None
    return out


def _matrix(value: Any, n: int, path: str) -> np.ndarray:
    rows = _items(value, n, "rows", path)
    return np.array([_vector(row, n, _child(path, i)) for i, row in enumerate(rows)])


def _integer(value: Any, path: str, minimum: int) -> int:
    if isinstance(value, np.generic):
        value = value.item()
    if not is_int(value):
        raise _Invalid(path, f"expected an integer, got {type_name(value)} {short(value)}")
    if not is_index(value, minimum):
        raise _Invalid(path, f"expected an integer from {minimum} to {MAX_INDEX}, got {short(value)}")
    return int(value)


def _text(value: Any, path: str) -> str:
    if not isinstance(value, str) or not value:
        raise _Invalid(path, f"expected a non-empty string, got {type_name(value)} {short(value)}")
    return value


def _boolean(value: Any, path: str) -> bool:
    if isinstance(value, np.bool_):
        value = bool(value)
    if not isinstance(value, bool):
        raise _Invalid(path, f"expected true or false, got {type_name(value)} {short(value)}")
    return value


def _fields(
    value: Any, path: str, required: Mapping[str, Callable[[Any, str], Any]],
    optional: Mapping[str, Callable[[Any, str], Any]],
) -> dict[Any, Any]:
    """An object checked key by key; extra keys kept; an optional key may be absent or null."""
    entry = _mapping(value, path)
    out = dict(entry)
    for key, check in required.items():
        if entry.get(key) is None:
            raise _Invalid(_child(path, key), "missing" if key not in entry else "null, expected a value")
        out[key] = check(entry[key], _child(path, key))
    for key, check in optional.items():
        if entry.get(key) is not None:
            out[key] = check(entry[key], _child(path, key))
    return out


def nearest_rotation(R: np.ndarray) -> np.ndarray | None:
    """A finite 3x3 ``R`` as a proper rotation, or None when it is not one within ORTHONORMAL_TOL.

    ``R`` itself when orthonormal to rounding (the file's numbers bit for bit), else the nearest
    rotation (SVD; det stays +1 this close to SO(3)).
    """
    error = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if error > ORTHONORMAL_TOL or np.linalg.det(R) <= 0.0:
        return None
    if error <= 1e-13:
        return R
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def _rotation(value: Any, path: str) -> list[list[float]]:
    R = nearest_rotation(_matrix(value, 3, path))
    if R is None:
        raise _Invalid(path, "not a rotation matrix (R^T R != I or det R != +1)")
    return R.tolist()


def _transform(value: Any, path: str) -> dict[Any, Any]:
    """``{"R": 3x3 rotation, "t": [3] metres, "q_xyzw": [4] (optional, the same rotation)}``."""
    out = _fields(value, path, {"R": _rotation, "t": _vector3}, {"q_xyzw": lambda q, p: _vector(q, 4, p)})
    if out.get("q_xyzw") is not None:
        q = np.array(out["q_xyzw"])
        if abs(float(np.linalg.norm(q)) - 1.0) > ORTHONORMAL_TOL:
            raise _Invalid(_child(path, "q_xyzw"), f"not a unit quaternion (norm {np.linalg.norm(q):.6g})")
        if np.max(np.abs(quaternion_xyzw_to_rotation(q) - np.array(out["R"]))) > ORTHONORMAL_TOL:
            raise _Invalid(_child(path, "q_xyzw"), f"is not the rotation {_child(path, 'R')}")
    return out


def _vector3(value: Any, path: str) -> list[float]:
    return _vector(value, 3, path)


def _sigma3(value: Any, path: str) -> list[float]:
    """3-sigma bounds: 3 numbers >= 0, NaN where not computed."""
    return _vector(value, 3, path, nan_ok=True, minimum=0.0)


def _statistic(value: Any, path: str) -> float:
    return _number(value, path, nan_ok=True)


def _covariance(value: Any, path: str) -> list[list[float]]:
    """6x6 finite, symmetric (to SYMMETRY_TOL of its largest entry), non-negative variances."""
    P = _matrix(value, 6, path)
    if np.max(np.abs(P - P.T)) > SYMMETRY_TOL * max(float(np.max(np.abs(P))), 1e-300):
        raise _Invalid(path, "not symmetric")
    if np.any(np.diag(P) < 0.0):
        raise _Invalid(path, f"negative variance on the diagonal: {short(np.diag(P).tolist())}")
    return P.tolist()


def _list_of(check: Callable[[Any, str], Any]) -> Callable[[Any, str], list[Any]]:
    def checked(value: Any, path: str) -> list[Any]:
        return [check(item, _child(path, k)) for k, item in enumerate(_items(value, None, "objects", path))]

    return checked

