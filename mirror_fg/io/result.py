"""result@1 (``mirror-fg/result@1``): the one validator of a result, and its read-only accessors.

docs/formats.md (Result file) fixes the keys. :func:`validate_result` checks every key a reader uses (types,
shapes, finiteness, rotations, index ranges) and raises :class:`~mirror_fg.io.dataset.DatasetError` with
one line ``SOURCE: KEY.PATH: problem`` that quotes at most a few dozen characters of the file. Keys
beyond the documented ones are kept as they are (result@1 allows extras); ``null`` means absent for
every optional key. The accessors (:func:`transforms`, :func:`mirror_vectors`, :func:`points`,
:func:`pose_covariance`) turn a validated result into numpy values and check nothing themselves.

Frames and units as in docs/formats.md: ``T_cam_base = (R, t)`` with ``Cp = R @ Bp + t`` (metres),
``T_base_cam`` its inverse; mirror vectors in the camera frame, points in the base frame (metres);
``covariance_cam_base`` 6x6 in ``[dtheta (rad), dt (m)]``; 3-sigma bounds in degrees and millimetres.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import RESULT_FORMAT, _is_int, _is_number, _kind, _short, check_format
from mirror_fg.core.transform import quaternion_xyzw_to_rotation

__all__ = [
    "validate_result",
    "nearest_rotation",
    "transforms",
    "pose",
    "mirror_vectors",
    "points",
    "pose_covariance",
    "ORTHONORMAL_TOL",
]

#: A rotation (or a quaternion against it) may be off by rounding; beyond this it is rejected.
ORTHONORMAL_TOL = 1e-6
#: ``T_base_cam`` must be the inverse of ``T_cam_base`` to this (rotation entries, metres).
INVERSE_TOL = 1e-6
#: Covariance symmetry, relative to its largest entry.
SYMMETRY_TOL = 1e-6
#: Largest mirror, configuration or iteration count accepted (keeps indices machine integers).
MAX_INDEX = 2**31 - 1
_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class _Invalid(Exception):
    """A problem at a key path; :func:`validate_result` turns it into one DatasetError line."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(path, problem)
        self.path, self.problem = path, problem


# --------------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------------


def _quote(value: Any, limit: int = 60) -> str:
    """One-line repr of user data bounded in work and length (no alias or recursion expansion)."""
    return _short(value, limit)


def _child(path: str, key: Any) -> str:
    """Key path of ``key`` below ``path``: ``a.b``, ``a[3]``, ``points['odd name']``."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    if isinstance(key, str) and _IDENTIFIER.match(key):
        return f"{path}.{key}" if path else key
    return f"{path}[{_quote(key, 40)}]"


# --------------------------------------------------------------------------------------------------
# Checkers: each returns the plain (JSON-like) value or raises _Invalid at its path
# --------------------------------------------------------------------------------------------------


def _mapping(value: Any, path: str) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise _Invalid(path, f"expected an object, got {_kind(value)} {_quote(value)}")
    return value


def _items(value: Any, n: int | None, what: str, path: str) -> list[Any]:
    """A list (tuple, 1-D+ array) of ``n`` items (any number when ``n`` is None)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        expected = f"{n} {what}" if n is not None else f"a list of {what}"
        raise _Invalid(path, f"expected {expected}, got {_kind(value)} {_quote(value)}")
    if n is not None and len(value) != n:
        raise _Invalid(path, f"expected {n} {what}, got {len(value)}")
    return list(value)


def _number(value: Any, path: str, *, nan_ok: bool = False, minimum: float | None = None) -> float:
    """A finite real number (NaN too where ``nan_ok``: a statistic that could not be computed)."""
    if isinstance(value, np.generic):
        value = value.item()
    if not _is_number(value):
        raise _Invalid(path, f"expected a number, got {_kind(value)} {_quote(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise _Invalid(path, f"number out of range: {_quote(value)}") from None
    if nan_ok and math.isnan(x):
        return x
    if not math.isfinite(x):
        raise _Invalid(path, f"expected a finite number, got {_quote(value)}")
    if minimum is not None and x < minimum:
        raise _Invalid(path, f"expected a number >= {minimum:g}, got {_quote(value)}")
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
    if not _is_int(value):
        raise _Invalid(path, f"expected an integer, got {_kind(value)} {_quote(value)}")
    if not minimum <= value <= MAX_INDEX:
        raise _Invalid(path, f"expected an integer from {minimum} to {MAX_INDEX}, got {_quote(value)}")
    return int(value)


def _text(value: Any, path: str) -> str:
    if not isinstance(value, str) or not value:
        raise _Invalid(path, f"expected a non-empty string, got {_kind(value)} {_quote(value)}")
    return value


def _boolean(value: Any, path: str) -> bool:
    if isinstance(value, np.bool_):
        value = bool(value)
    if not isinstance(value, bool):
        raise _Invalid(path, f"expected true or false, got {_kind(value)} {_quote(value)}")
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
        raise _Invalid(path, f"negative variance on the diagonal: {_quote(np.diag(P).tolist())}")
    return P.tolist()


def _list_of(check: Callable[[Any, str], Any]) -> Callable[[Any, str], list[Any]]:
    def checked(value: Any, path: str) -> list[Any]:
        return [check(item, _child(path, k)) for k, item in enumerate(_items(value, None, "objects", path))]

    return checked


_SIGMA3 = {"rotation_deg": _sigma3, "position_mm": _sigma3}
_MIRROR = (
    {"mirror": lambda x, p: _integer(x, p, 1), "config": lambda x, p: _integer(x, p, 0), "v": _vector3},
    {"sigma3_mm": _sigma3},
)
_OUTLIER = ({"image": _text, "point": _text, "sigmas": _statistic}, {})
_OPTIMIZER = {
    "iterations": lambda x, p: _integer(x, p, 0),
    "initial_error": _statistic,
    "final_error": _statistic,
    "converged": _boolean,
}


def _mirrors(value: Any, path: str) -> list[dict[Any, Any]]:
    """Mirror vectors: one entry per configuration ``(mirror >= 1, config >= 0)``, ``v`` not zero."""
    entries = _list_of(lambda e, p: _fields(e, p, *_MIRROR))(value, path)
    seen: dict[tuple[int, int], int] = {}
    for k, entry in enumerate(entries):
        key = (entry["mirror"], entry["config"])
        if key in seen:
            raise _Invalid(_child(path, k), f"mirror {key[0]} config {key[1]} again (as in {_child(path, seen[key])})")
        seen[key] = k
        if not any(entry["v"]):
            raise _Invalid(_child(_child(path, k), "v"), "the zero vector (a mirror through the camera centre)")
    return entries


def _points(value: Any, path: str) -> dict[str, dict[Any, Any]]:
    """Reconstruction points: ``{name: {"xyz": [3] metres, "sigma3_mm": [3]}}``."""
    out: dict[str, dict[Any, Any]] = {}
    for name, entry in _mapping(value, path).items():
        where = _child(path, name)
        _text(name, f"{where} (name)")
        out[name] = _fields(entry, where, {"xyz": _vector3}, {"sigma3_mm": _sigma3})
    return out


def _residuals(value: Any, path: str) -> dict[Any, Any]:
    return _fields(
        value, path, {},
        {"rms_px": _statistic, "max_px": _statistic, "units": _text,
         "outliers": _list_of(lambda e, p: _fields(e, p, *_OUTLIER))},
    )


#: Top-level keys a reader uses, each optional except ``T_cam_base``.
_TOP = {
    "T_base_cam": _transform,
    "covariance_cam_base": _covariance,
    "sigma3_cam_base": lambda x, p: _fields(x, p, {}, _SIGMA3),
    "analytic": lambda x, p: _fields(x, p, {}, {"T_cam_base": _transform}),
    "mirrors": _mirrors,
    "points": _points,
    "optimizer": lambda x, p: _fields(x, p, {}, _OPTIMIZER),
    "residuals": _residuals,
}


def validate_result(data: Any, source: str) -> dict[str, Any]:
    """Check a parsed result@1 dictionary; return it as a plain dict (numbers as floats and ints).

    ``source`` (a file name) starts every message. Raises DatasetError, one line naming the key path
    (``mirrors[3].v[1]: expected a number, got 'abc'``). A valid result comes back equal to its input,
    with numpy values turned into plain ones and rotations within ORTHONORMAL_TOL of SO(3) made exact;
    unknown keys are kept as they are. Validating a validated result changes nothing.
    """
    check_format(data, RESULT_FORMAT, source)
    try:
        out = _fields(data, "", {"T_cam_base": _transform}, _TOP)
        if out.get("T_base_cam") is not None:
            _check_inverse(out["T_cam_base"], out["T_base_cam"])
    except _Invalid as error:
        raise DatasetError(f"{source}: {error.path}: {error.problem}") from None
    return out


def _check_inverse(T_cam_base: Mapping[str, Any], T_base_cam: Mapping[str, Any]) -> None:
    R, t = pose(T_cam_base)
    R_file, t_file = pose(T_base_cam)
    off = max(float(np.max(np.abs(R_file - R.T))), float(np.max(np.abs(t_file + R.T @ t))))
    if off > INVERSE_TOL:
        raise _Invalid("T_base_cam", f"not the inverse of T_cam_base (off by {off:.3g})")


# --------------------------------------------------------------------------------------------------
# Accessors of a validated result (numpy values; no checks)
# --------------------------------------------------------------------------------------------------


def pose(entry: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` of a validated transform ``{"R", "t"}``."""
    return np.array(entry["R"], dtype=float), np.array(entry["t"], dtype=float)


def transforms(result: Mapping[str, Any]) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``((R_cam_base, t_cam_base), (R_base_cam, t_base_cam))``.

    ``T_base_cam`` is the file's own where it has one (validated as the inverse, so the numbers match
    the result file exactly), else the inverse of ``T_cam_base``.
    """
    R, t = pose(result["T_cam_base"])
    if result.get("T_base_cam") is not None:
        return (R, t), pose(result["T_base_cam"])
    return (R, t), (R.T, -R.T @ t)


def mirror_vectors(result: Mapping[str, Any]) -> dict[tuple[int, int], np.ndarray]:
    """``(mirror l, config m) -> v`` (camera frame, metres)."""
    return {(e["mirror"], e["config"]): np.array(e["v"], dtype=float) for e in result.get("mirrors") or []}


def points(result: Mapping[str, Any]) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """``name -> (xyz metres in {B}, sigma3 mm or None)`` of the reconstruction points."""
    return {
        name: (np.array(e["xyz"], dtype=float), None if e.get("sigma3_mm") is None else np.array(e["sigma3_mm"]))
        for name, e in (result.get("points") or {}).items()
    }


def pose_covariance(result: Mapping[str, Any]) -> np.ndarray | None:
    """The 6x6 ``covariance_cam_base`` (SPEC convention), or None when the result has none."""
    cov = result.get("covariance_cam_base")
    return None if cov is None else np.array(cov, dtype=float)
