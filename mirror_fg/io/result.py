"""result@1 (``mirror-fg/result@1``): its writer, its reader and one validator, and read-only accessors.

:func:`result_dict` makes the result@1 dictionary of a calibration; :func:`write_result` /
:func:`result_text` write it (JSON, or YAML where the file ends in .yaml/.yml) and :func:`load_result`
reads one back through :func:`validate_result`. docs/formats.md (Result file) fixes the keys.
:func:`validate_result` checks every key a reader uses (types, shapes, finiteness, rotations, index
ranges) and raises :class:`~mirror_fg.core.errors.DatasetError` with one line ``SOURCE: KEY.PATH:
problem`` that quotes at most a few dozen characters of the file. Keys beyond the documented ones are
kept as they are (result@1 allows extras); ``null`` means absent for every optional key. The accessors (:func:`transforms`, :func:`mirror_vectors`, :func:`points`,
:func:`pose_covariance`) turn a validated result into numpy values and check nothing themselves.

Frames and units as in docs/formats.md: ``T_cam_base = (R, t)`` with ``Cp = R @ Bp + t`` (metres),
``T_base_cam`` its inverse; mirror vectors in the camera frame, points in the base frame (metres);
``covariance_cam_base`` 6x6 in ``[dtheta (rad), dt (m)]`` (camera axes), ``covariance_base_cam`` the same for
``T_base_cam`` (base axes) and ``covariance_base_cam_ros`` that one in ROS ``PoseWithCovariance`` order
``(x, y, z, rot x, rot y, rot z)``; 3-sigma bounds in degrees and millimetres.
The schema (which key holds what, each block's checker) is ``result_schema.py``, built from the low-level
checkers (numbers, vectors, rotations, objects key by key) of ``result_checks.py``; this module applies it
and checks what ties keys together.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_format, short
from mirror_fg.io.fileio import parse_json, parse_yaml, read_text
from mirror_fg.io.output import atomic_write, is_yaml, json_text
from mirror_fg.io.result_checks import ORTHONORMAL_TOL, SYMMETRY_TOL, _fields, _Invalid, nearest_rotation
from mirror_fg.io.result_poses import (
    base_cam_covariance,
    camera_block,
    camera_entries,
    check_cameras,
    rig_entries,
    sigma3_pose,
    transform_entry,
)
from mirror_fg.io.result_schema import OPTIONAL, REQUIRED
from mirror_fg.io.screen_result import check_screen_pose

RESULT_FORMAT = "mirror-fg/result@1"

__all__ = [
    "RESULT_FORMAT",
    "CalibrationLike",
    "result_dict",
    "write_result",
    "result_text",
    "load_result",
    "validate_result",
    "nearest_rotation",
    "transforms",
    "pose",
    "mirror_vectors",
    "points",
    "pose_covariance",
    "base_cam_pose_covariance",
    "base_cam_covariance",
    "ros_pose_covariance",
    "sigma3_pose",
    "estimated_camera",
    "ORTHONORMAL_TOL",
]

#: ``T_base_cam`` must be the inverse of ``T_cam_base`` to this (rotation entries, metres).
INVERSE_TOL = 1e-6


# --------------------------------------------------------------------------------------------------
# Writing and reading result@1
# --------------------------------------------------------------------------------------------------


class _Pose(Protocol):
    R_cam_base: np.ndarray
    t_cam_base: np.ndarray


class CalibrationLike(Protocol):
    """What :func:`result_dict` reads of a calibration (:class:`mirror_fg.solver.result.calibration.Calibration`).

    ``R_cam_base``, ``t_cam_base`` (metres): ``Cp = R Bp + t``; ``covariance`` 6x6 ``[dtheta, dt]`` or
    None; mirror vectors ``(l, m) -> v`` (camera frame, metres) and points (base frame, metres) with
    their 3x3 covariances; ``analytic``: the analytical solution's pose or None. A calibration of several
    cameras also has ``cameras`` (name -> CameraPose), ``rig`` (solver.model.rig.rig_transforms of them) and
    ``mirror_frames`` ((l, m) -> camera name), read where present (``cameras`` None: one camera).
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    covariance: np.ndarray | None
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    mirror_covariances: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]
    point_covariances: dict[str, np.ndarray]
    iterations: int
    initial_error: float
    final_error: float
    expected_final_error: float
    converged: bool
    residual_units: str
    outliers: list[tuple[str, str, float]]
    excluded: list[Any]  # Exclusion: image, reason, point, sigmas
    inconsistency: Any  # Inconsistency or None: groups, rotation_deg, position_mm, message
    camera: Any  # EstimatedCamera or None: camera, estimated, covariance, pose_cross_covariance, sigma3

    @property
    def analytic(self) -> _Pose | None: ...  # read-only: any object with a pose (an AnalyticSolution)

    @property
    def R_base_cam(self) -> np.ndarray: ...

    @property
    def t_base_cam(self) -> np.ndarray: ...

    @property
    def residual_norms(self) -> np.ndarray: ...


def analytic_entry(analytic: Any) -> dict[str, Any] | None:
    """The result's ``analytic``: the analytical solution's (or the propagation's start's) ``T_cam_base``, and
    with several cameras every camera's under ``cameras`` (docs/formats.md); None without one."""
    if analytic is None:
        return None
    entry: dict[str, Any] = {"T_cam_base": transform_entry(analytic.R_cam_base, analytic.t_cam_base)}
    poses = getattr(analytic, "camera_poses", None)
    if poses:
        entry["cameras"] = {name: {"T_cam_base": transform_entry(R, t)} for name, (R, t) in poses.items()}
    return entry


def result_dict(calibration: CalibrationLike) -> dict:
    """The ``mirror-fg/result@1`` dictionary of ``calibration`` (docs/formats.md)."""

    transform = transform_entry
    c = calibration
    cameras = getattr(c, "cameras", None)
    frames = getattr(c, "mirror_frames", None) or {}
    norms = c.residual_norms
    P = None if c.covariance is None else np.asarray(c.covariance, dtype=float)
    P_bc = None if P is None else base_cam_covariance(c.R_cam_base, c.t_cam_base, P)
    result = {
        "format": RESULT_FORMAT,
        "T_cam_base": transform(c.R_cam_base, c.t_cam_base),
        "T_base_cam": transform(c.R_base_cam, c.t_base_cam),
        "covariance_cam_base": None if P is None else P.tolist(),
        "sigma3_cam_base": sigma3_pose(P),
        "covariance_base_cam": None if P_bc is None else P_bc.tolist(),
        "sigma3_base_cam": sigma3_pose(P_bc),
        "covariance_base_cam_ros": None if P_bc is None else ros_pose_covariance(P_bc).tolist(),
        "analytic": analytic_entry(c.analytic),
        "mirrors": [
            {
                "mirror": l,
                "config": m,
                "v": c.mirror_vectors[(l, m)].tolist(),
                "sigma3_mm": _sigma3_mm(c.mirror_covariances.get((l, m))),
                **({} if cameras is None else {"camera": _mirror_frame(frames, l, m)}),
            }
            for l, m in sorted(c.mirror_vectors)
        ],
        "points": {
            name: {"xyz": c.points[name].tolist(), "sigma3_mm": _sigma3_mm(c.point_covariances.get(name))}
            for name in sorted(c.points)
        },
        "optimizer": {
            "iterations": c.iterations,
            "initial_error": c.initial_error,
            "final_error": c.final_error,
            "expected_final_error": c.expected_final_error,
            "converged": c.converged,
        },
        "residuals": {
            "rms_px": float(np.sqrt(np.mean(norms**2))) if len(norms) else 0.0,
            "max_px": float(np.max(norms)) if len(norms) else 0.0,
            "mean_px": float(np.mean(norms)) if len(norms) else 0.0,
            "units": c.residual_units,
            "outliers": [
                {"image": image, "point": point, "sigmas": sigmas} for image, point, sigmas in c.outliers
            ],
        },
        "excluded": [
            {"image": e.image, "point": e.point, "reason": e.reason, "sigmas": e.sigmas} for e in c.excluded
        ],
    }
    if c.inconsistency is not None:
        i = c.inconsistency
        result["inconsistency"] = {
            "groups": [list(group) for group in i.groups], "rotation_deg": float(i.rotation_deg),
            "position_mm": float(i.position_mm), "message": i.message,
        }
    if c.camera is not None:
        result["camera"] = camera_block(c.camera)
    if cameras is not None:  # several cameras (docs/formats.md "Several cameras"); absent, the file is as before
        result["cameras"] = camera_entries(cameras)
        result["rig"] = rig_entries(cameras, list(getattr(c, "rig", None) or []))
    at_points = getattr(c, "at_points", None)
    if at_points:  # the error at the user's points (docs/formats.md "The answer in the user's units")
        from mirror_fg.solver.result.point_error import at_entries, calibration_poses

        result["at"] = at_entries(calibration_poses(c), at_points)
    validation = getattr(c, "validation", None)
    if validation is not None:
        result["validation"] = validation.to_dict()
    robot = getattr(c, "robot", None)
    if robot:  # a robot arm (docs/formats.md "Robot arms"): mounts, joint offsets, planes in the base link's frame
        result.update({k: robot[k] for k in ("mounts", "joint_offsets") if k in robot})
        mirrors: list[dict[str, Any]] = result["mirrors"]  # type: ignore[assignment]
        for entry in mirrors:
            entry["frame"] = robot["mirror_frame"]
    dispersion = getattr(c, "dispersion", None)
    if dispersion is not None:  # docs/formats.md "Has it moved?"
        result["dispersion"] = dispersion.to_dict()
    joint = getattr(c, "placement_covariances", None)
    if joint:  # docs/formats.md "Has it moved?": a mirror that stands still, jointly with the camera
        for entry in result["mirrors"]:  # type: ignore[union-attr,assignment]
            found = joint.get((entry["mirror"], entry["config"]))
            if found is not None:
                entry["covariance"], entry["cross_covariance_cam_base"] = found[0].tolist(), found[1].tolist()
    return result


def _mirror_frame(frames: Mapping[tuple[int, int], str], l: int, m: int) -> str:
    """The camera whose frame placement ``(l, m)``'s mirror vector is in; ValueError where the solver gave none."""
    if (l, m) not in frames:
        raise ValueError(f"result: mirror {l} config {m} has no camera frame (Calibration.mirror_frames)")
    return frames[(l, m)]


def ros_pose_covariance(covariance: np.ndarray) -> np.ndarray:
    """``[dtheta, dt]`` covariance reordered as ROS ``PoseWithCovariance``: ``(x, y, z, rot x, rot y, rot z)``,
    rotations about the parent's fixed axes (which ``R_true = Exp(dtheta) R`` is)."""
    order = [3, 4, 5, 0, 1, 2]
    return np.asarray(covariance, dtype=float)[np.ix_(order, order)]


def _sigma3_mm(covariance: np.ndarray | None) -> list[float] | None:
    """3-sigma bounds (mm) of a 3x3 covariance (m^2), or None."""
    if covariance is None:
        return None
    return (1000.0 * 3.0 * np.sqrt(np.diag(covariance))).tolist()


def write_result(path: str | os.PathLike[str], result: Mapping[str, Any]) -> None:
    """Write a ``mirror-fg/result@1`` dictionary: JSON (indent 2), or YAML where ``path`` ends in .yaml/.yml.

    numpy arrays and scalars become lists and plain numbers first. The write is atomic: the text goes
    to a temporary file in the same directory that replaces ``path`` only when complete, so any
    failure (a value that cannot be serialised, a full disk) leaves an existing file as it was and no
    temporary file behind. Raises TypeError naming the key of a value that cannot be written.
    """
    target = os.fspath(path)
    atomic_write(target, result_text(result, target))


def result_text(result: Mapping[str, Any], path: str | os.PathLike[str]) -> str:
    """The text of a result@1 file: YAML where ``path`` ends in .yaml/.yml, else JSON (indent 2)."""
    plain = _plain(result, "result")
    if is_yaml(os.fspath(path)):
        import yaml

        return yaml.safe_dump(plain, default_flow_style=None, sort_keys=False, allow_unicode=True)
    return json_text(plain, allow_nan=True)


def load_result(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a result@1 file (JSON, or YAML where the name ends in .yaml/.yml). Raises DatasetError."""
    source = os.fspath(path)
    text = read_text(source)
    data = parse_yaml(text, source) if is_yaml(source) else parse_json(text, source)
    return validate_result(data, source)


def _plain(value: Any, where: str) -> Any:
    """``value`` with numpy arrays/scalars and tuples turned into lists, floats, ints, bools."""
    if isinstance(value, np.ndarray):
        if value.ndim == 0:
            return _plain(value[()], where)
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Mapping):
        out: dict[Any, Any] = {}
        for key, v in value.items():
            k = key.item() if isinstance(key, np.generic) else key
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"{where}: cannot write a key of type {type(key).__name__}: {short(key)}")
            out[k] = _plain(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where}: cannot write a value of type {type(value).__name__}")


def validate_result(data: Any, source: str) -> dict[str, Any]:
    """Check a parsed result@1 dictionary; return it as a plain dict (numbers as floats and ints).

    ``source`` (a file name) starts every message. Raises DatasetError, one line naming the key path
    (``mirrors[3].v[1]: expected a number, got 'abc'``). A valid result comes back equal to its input,
    with numpy values turned into plain ones and rotations within ORTHONORMAL_TOL of SO(3) made exact;
    unknown keys are kept as they are. Validating a validated result changes nothing.
    """
    check_format(data, RESULT_FORMAT, source)
    try:
        out = _fields(data, "", REQUIRED, OPTIONAL)
        if out.get("T_base_cam") is not None:
            _check_inverse(out["T_cam_base"], out["T_base_cam"])
        _check_base_cam_covariances(out)
        check_cameras(out)
        if out.get("screen") is not None:
            check_screen_pose(out)
    except _Invalid as error:
        raise DatasetError(f"{source}: {error.path}: {error.problem}") from None
    return out


def _check_inverse(T_cam_base: Mapping[str, Any], T_base_cam: Mapping[str, Any]) -> None:
    R, t = pose(T_cam_base)
    R_file, t_file = pose(T_base_cam)
    off = max(float(np.max(np.abs(R_file - R.T))), float(np.max(np.abs(t_file + R.T @ t))))
    if off > INVERSE_TOL:
        raise _Invalid("T_base_cam", f"not the inverse of T_cam_base (off by {off:.3g})")


def _check_base_cam_covariances(result: Mapping[str, Any]) -> None:
    """``covariance_base_cam`` is that of ``covariance_cam_base`` inverted, ``..._ros`` it reordered."""
    P_bc, P_ros = result.get("covariance_base_cam"), result.get("covariance_base_cam_ros")
    expected = {
        "covariance_base_cam": None if result.get("covariance_cam_base") is None
        else base_cam_covariance(*pose(result["T_cam_base"]), np.array(result["covariance_cam_base"])),
        "covariance_base_cam_ros": None if P_bc is None else ros_pose_covariance(np.array(P_bc)),
    }
    for key, got in (("covariance_base_cam", P_bc), ("covariance_base_cam_ros", P_ros)):
        want = expected[key]
        if got is not None and want is not None:
            off = float(np.max(np.abs(np.array(got) - want)))
            if off > SYMMETRY_TOL * max(float(np.max(np.abs(want))), 1e-300):
                source = "covariance_cam_base" if key == "covariance_base_cam" else "covariance_base_cam"
                raise _Invalid(key, f"does not match {source} (off by {off:.3g})")


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
    """The 6x6 ``covariance_cam_base`` (docs/formats.md's convention), or None when the result has none."""
    cov = result.get("covariance_cam_base")
    return None if cov is None else np.array(cov, dtype=float)


def base_cam_pose_covariance(result: Mapping[str, Any]) -> np.ndarray | None:
    """The 6x6 ``covariance_base_cam`` (rotation error about the base axes): the file's own, else computed
    from ``covariance_cam_base`` (results written before it was added); None without a covariance."""
    if result.get("covariance_base_cam") is not None:
        return np.array(result["covariance_base_cam"], dtype=float)
    P = pose_covariance(result)
    return None if P is None else base_cam_covariance(*pose(result["T_cam_base"]), P)


def estimated_camera(result: Mapping[str, Any], source: str = "result", dataset_camera: Any = None) -> Any:
    """The :class:`~mirror_fg.core.camera.Camera` a validated result estimated (its ``camera`` block), or
    None where the intrinsics were not estimated (the dataset's camera holds then). Model and image size
    the block lacks come from ``dataset_camera``. DatasetError naming ``source`` where the block is not a
    usable camera."""
    block = result.get("camera")
    if block is None:
        return None
    from mirror_fg.core.camera import CAMERA_KEYS, camera_from_dict

    plain = {key: value for key, value in block.items()
             if key in CAMERA_KEYS and key not in ("estimate", "prior_sigma") and value is not None}
    if dataset_camera is not None:
        for key in ("model", "width", "height"):
            plain.setdefault(key, getattr(dataset_camera, key))
    return camera_from_dict(plain, f"{source}: camera")


def base_cam_sigma3(result: Mapping[str, Any]) -> dict[str, list[float]] | None:
    """3-sigma bounds of ``T_base_cam`` (base axes) of a validated result, from its covariance (the
    file's ``covariance_base_cam``, else ``covariance_cam_base``); None without a covariance."""
    return sigma3_pose(base_cam_pose_covariance(result))
