"""The result@1 schema: which key holds what, each block's checker (``mirrors``, ``points``, ``residuals``,
``excluded``, ``inconsistency``, the estimated ``camera``, ...) built from the low-level checkers of
``result_checks.py``. :func:`mirror_fg.io.result.validate_result` applies :data:`REQUIRED` and
:data:`OPTIONAL` to a parsed file, then checks what ties keys together (``T_base_cam`` the inverse of
``T_cam_base``, the covariances of one another). Units as in docs/formats.md: metres, 3-sigma bounds in
degrees and millimetres.
"""
from __future__ import annotations

from typing import Any

from mirror_fg.core.values import short
from mirror_fg.io.result_checks import (
    Checker,
    _boolean,
    _child,
    _covariance,
    _fields,
    _integer,
    _Invalid,
    _list_of,
    _mapping,
    _matrix,
    _number,
    _sigma3,
    _statistic,
    _text,
    _transform,
    _vector,
    _vector3,
)
from mirror_fg.io.screen_result import check_screen_block

__all__ = ["REQUIRED", "OPTIONAL"]

#: The key every result has.
REQUIRED: dict[str, Checker] = {"T_cam_base": _transform}

_SIGMA3: dict[str, Checker] = {"rotation_deg": _sigma3, "position_mm": _sigma3}
_MIRROR: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"mirror": lambda x, p: _integer(x, p, 1), "config": lambda x, p: _integer(x, p, 0), "v": _vector3},
    {"sigma3_mm": _sigma3, "camera": _text,  # camera: the frame of v (a result with cameras)
     # v's covariance and its cross-covariance with the pose (docs/formats.md "Has it moved?")
     "covariance": lambda x, p: _matrix(x, 3, p).tolist(),
     "cross_covariance_cam_base": lambda x, p: _list_of(lambda row, q: _vector(row, 6, q))(_items3(x, p), p)},
)


def _items3(value: Any, path: str) -> Any:
    """Three rows (the cross-covariance of ``v`` with the pose)."""
    if not isinstance(value, list) or len(value) != 3:
        raise _Invalid(path, "expected 3 rows of 6 numbers")
    return value
_OUTLIER: tuple[dict[str, Checker], dict[str, Checker]] = ({"image": _text, "point": _text, "sigmas": _statistic}, {})
_OPTIMIZER: dict[str, Checker] = {
    "iterations": lambda x, p: _integer(x, p, 0),
    "initial_error": _statistic,
    "final_error": _statistic,
    "expected_final_error": _statistic,
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
        {"rms_px": _statistic, "max_px": _statistic, "mean_px": _statistic, "units": _text,
         "outliers": _list_of(lambda e, p: _fields(e, p, *_OUTLIER))},
    )


_EXCLUDED: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"image": _text, "reason": _text}, {"point": _text, "sigmas": _statistic},
)


def _inconsistency(value: Any, path: str) -> dict[Any, Any]:
    """``{"groups": [[image ids]] (at least two), "rotation_deg", "position_mm", "message"}``."""
    out = _fields(value, path, {"groups": _list_of(_list_of(_text)), "message": _text},
                  {"rotation_deg": _statistic, "position_mm": _statistic})
    if len(out["groups"]) < 2:
        raise _Invalid(_child(path, "groups"), f"expected at least two groups, got {len(out['groups'])}")
    return out


def _camera(value: Any, path: str) -> dict[Any, Any]:
    """The estimated camera: fx, fy > 0, cx, cy, ``dist``, ``estimated`` names with their ``sigma3``."""
    from mirror_fg.core.camera import INTRINSIC_NAMES

    def name(x: Any, p: str) -> str:
        if x not in INTRINSIC_NAMES:
            raise _Invalid(p, f"expected one of {', '.join(INTRINSIC_NAMES)}, got {short(x)}")
        return x

    def square(x: Any, p: str) -> list[list[float]]:
        rows = _list_of(lambda row, q: _vector(row, len(x), q))(x, p)
        return rows

    positive = lambda x, p: _number(x, p, minimum=1e-300)  # noqa: E731
    out = _fields(value, path, {"fx": positive, "fy": positive, "cx": _number, "cy": _number,
                                "estimated": _list_of(name)},
                  {"dist": lambda x, p: _vector(x, len(x) if isinstance(x, (list, tuple)) else 0, p),
                   "width": lambda x, p: _integer(x, p, 1), "height": lambda x, p: _integer(x, p, 1),
                   "model": _text, "covariance": square,
                   "cross_covariance_cam_base": _list_of(lambda row, q: _vector(row, 6, q)),
                   "sigma3": lambda x, p: {k: _number(v, _child(p, k), nan_ok=True, minimum=0.0)
                                           for k, v in _mapping(x, p).items()}})
    k = len(out["estimated"])
    if out.get("covariance") is not None and len(out["covariance"]) != k:
        raise _Invalid(_child(path, "covariance"), f"expected {k} x {k} (one row per name in {_child(path, 'estimated')})")
    if out.get("cross_covariance_cam_base") is not None and len(out["cross_covariance_cam_base"]) != k:
        raise _Invalid(_child(path, "cross_covariance_cam_base"), f"expected {k} x 6 (one row per name in {_child(path, 'estimated')})")
    if out.get("sigma3") is not None and set(out["sigma3"]) != set(out["estimated"]):
        raise _Invalid(_child(path, "sigma3"), f"expected a bound for each name in {_child(path, 'estimated')}")
    return out


def _camera_pose(value: Any, path: str) -> dict[Any, Any]:
    """One camera of ``cameras``: its transforms, covariances, bounds and (optional) ``camera`` block."""
    return _fields(value, path, {"T_cam_base": _transform}, {
        "T_base_cam": _transform, "covariance_cam_base": _covariance, "covariance_base_cam": _covariance,
        "sigma3_cam_base": lambda x, p: _fields(x, p, {}, _SIGMA3),
        "sigma3_base_cam": lambda x, p: _fields(x, p, {}, _SIGMA3), "camera": _camera})


def _cameras(value: Any, path: str) -> dict[str, dict[Any, Any]]:
    """``{name: camera pose}`` of a result with several cameras, at least one, in the dataset's order."""
    entries = _mapping(value, path)
    if not entries:
        raise _Invalid(path, "expected at least one camera, got none")
    out: dict[str, dict[Any, Any]] = {}
    for name, entry in entries.items():
        where = _child(path, name)
        _text(name, f"{where} (name)")
        out[name] = _camera_pose(entry, where)
    return out


_RIG: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"from": _text, "to": _text, "T": _transform},
    {"covariance": _covariance, "sigma3": lambda x, p: _fields(x, p, {}, _SIGMA3)},
)


#: The error at a point (docs/formats.md "The answer in the user's units"); covariance 3 x 3, m^2.
_AT: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"point_cam": _vector3, "point_base": _vector3},
    {"covariance": lambda x, p: _matrix(x, 3, p).tolist(), "sigma3_mm": _sigma3, "camera": _text},
)
#: The held-out validation: images held out, the RMS of their ratios, the worst.
_VALIDATION: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"images": lambda x, p: _integer(x, p, 0), "ratio": _statistic},
    {"worst": lambda x, p: _fields(x, p, {"image": _text, "ratio": _statistic}, {}), "not_held_out": _list_of(_text)},
)

#: The images' agreement with each other (solver/fit/dispersion.py): B / nu, nu, B, images counted.
_DISPERSION: tuple[dict[str, Checker], dict[str, Checker]] = (
    {"dof": lambda x, p: _number(x, p, minimum=0.0), "cost": lambda x, p: _number(x, p, minimum=0.0),
     "images": lambda x, p: _integer(x, p, 0)},
    {"factor": lambda x, p: _number(x, p, minimum=0.0)},
)

#: Top-level keys a reader uses, each optional except ``T_cam_base`` (:data:`REQUIRED`).
OPTIONAL: dict[str, Checker] = {
    "T_base_cam": _transform,
    "covariance_cam_base": _covariance,
    "sigma3_cam_base": lambda x, p: _fields(x, p, {}, _SIGMA3),
    "covariance_base_cam": _covariance,
    "sigma3_base_cam": lambda x, p: _fields(x, p, {}, _SIGMA3),
    "covariance_base_cam_ros": _covariance,
    "analytic": lambda x, p: _fields(x, p, {}, {"T_cam_base": _transform}),
    "mirrors": _mirrors,
    "points": _points,
    "optimizer": lambda x, p: _fields(x, p, {}, _OPTIMIZER),
    "residuals": _residuals,
    "excluded": _list_of(lambda e, p: _fields(e, p, *_EXCLUDED)),
    "inconsistency": _inconsistency,
    "camera": _camera,
    "cameras": _cameras,  # several cameras (docs/formats.md "Several cameras"); tied together by result_poses
    "rig": _list_of(lambda e, p: _fields(e, p, *_RIG)),
    "screen": check_screen_block,  # a screen capture's screen (io.screen_result)
    "at": _list_of(lambda e, p: _fields(e, p, *_AT)),
    "validation": lambda x, p: _fields(x, p, *_VALIDATION),
    "dispersion": lambda x, p: _fields(x, p, *_DISPERSION),
}
