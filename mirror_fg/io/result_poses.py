"""result@1's pose blocks: one transform entry, its covariances and bounds, and (several cameras) every
camera's entry and the rig, written and checked against one another.

Conventions as docs/formats.md: ``T_cam_base = (R, t)`` with ``Cp = R Bp + t`` (metres), ``T_base_cam`` its
inverse; covariances ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) R_est`` (about the axes of the
transform's first frame) and ``t_true = t_est + dt``; 3-sigma bounds in degrees and millimetres. The rig
(docs/formats.md "Several cameras") is Kalibr's ``T_cn_cnm1`` chain: entry ``k`` maps points of camera
``k`` into camera ``k + 1`` (``x_to = R x_from + t``), i.e. ``T_to_base @ T_from_base^-1``.
:func:`mirror_fg.io.result.result_dict` writes these blocks, :func:`check_cameras` is the validator's
check of what ties them together (the per-key checkers are ``result_schema.py``'s).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.transform import Transform, rotation_to_quaternion_xyzw
from mirror_fg.io.result_checks import SYMMETRY_TOL, _child, _Invalid

__all__ = [
    "transform_entry", "base_cam_covariance", "sigma3_pose", "camera_block", "camera_entries", "rig_entries",
    "check_cameras", "POSE_TOL",
]

#: Two transforms the file states twice (an inverse, the first camera at the top level, a rig entry and
#: its cameras) must agree to this (rotation entries, metres).
POSE_TOL = 1e-6


def transform_entry(R: np.ndarray, t: np.ndarray) -> dict[str, Any]:
    """``{"R", "t", "q_xyzw"}`` of one transform (plain lists; quaternion Hamilton, scalar last)."""
    return {"R": np.asarray(R).tolist(), "t": np.asarray(t).tolist(), "q_xyzw": rotation_to_quaternion_xyzw(R).tolist()}


def base_cam_covariance(R_cam_base: np.ndarray, t_cam_base: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance (6, 6) of ``T_base_cam`` from that of ``T_cam_base``, both ``[dtheta, dt]`` (docs/formats.md);
    the inverse's rotation error is about the base axes. First order (:meth:`Transform.inverse_covariance`)."""
    return Transform(R_cam_base, t_cam_base).inverse_covariance(covariance)


def sigma3_pose(covariance: np.ndarray | None) -> dict[str, list[float]] | None:
    """``{"rotation_deg", "position_mm"}``: 3-sigma bounds of a ``[dtheta, dt]`` covariance, or None."""
    if covariance is None:
        return None
    sd3 = 3.0 * np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return {"rotation_deg": np.rad2deg(sd3[:3]).tolist(), "position_mm": (1e3 * sd3[3:]).tolist()}


def camera_block(estimated: Any) -> dict[str, Any]:
    """result@1's ``camera``: the estimated camera, the names estimated, their 3-sigma bounds, and (extras)
    their covariance and its cross-covariance with the pose ``[dtheta, dt]`` of ``T_cam_base``."""
    from mirror_fg.core.camera import camera_to_dict

    block = camera_to_dict(estimated.camera)
    block.pop("estimate", None)
    block.pop("prior_sigma", None)
    block["estimated"] = list(estimated.estimated)
    block["sigma3"] = estimated.sigma3
    P, C = estimated.covariance, estimated.pose_cross_covariance
    block["covariance"] = None if P is None else np.asarray(P, dtype=float).tolist()
    block["cross_covariance_cam_base"] = None if C is None else np.asarray(C, dtype=float).tolist()
    return block


def _kept_camera_block(camera: Any) -> dict[str, Any]:
    """A camera's block where it estimated nothing: the dataset's intrinsics, ``estimated`` empty (the
    camchain and the camera_info files need every camera's intrinsics)."""
    from mirror_fg.core.camera import camera_to_dict

    block = camera_to_dict(camera)
    block.pop("estimate", None)
    block.pop("prior_sigma", None)
    block.update({"estimated": [], "sigma3": {}, "covariance": None, "cross_covariance_cam_base": None})
    return block


def camera_entries(cameras: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """result@1's ``cameras``: per camera (a :class:`~mirror_fg.solver.result.calibration.CameraPose`, in the
    dataset's order) both transforms, both covariances and both bounds, and its ``camera`` block: the
    estimated intrinsics (as the top-level ``camera``) or, where it estimated none, the ones used."""
    out: dict[str, dict[str, Any]] = {}
    for name, pose in cameras.items():
        T = Transform(pose.R_cam_base, pose.t_cam_base)
        T_bc = T.inverse()
        P = None if pose.covariance is None else np.asarray(pose.covariance, dtype=float)
        P_bc = None if P is None else T.inverse_covariance(P)
        entry: dict[str, Any] = {
            "T_cam_base": transform_entry(T.R, T.t),
            "T_base_cam": transform_entry(T_bc.R, T_bc.t),
            "covariance_cam_base": None if P is None else P.tolist(),
            "sigma3_cam_base": sigma3_pose(P),
            "covariance_base_cam": None if P_bc is None else P_bc.tolist(),
            "sigma3_base_cam": sigma3_pose(P_bc),
        }
        if pose.estimated is not None:
            entry["camera"] = camera_block(pose.estimated)
        elif pose.camera is not None:
            entry["camera"] = _kept_camera_block(pose.camera)
        out[name] = entry
    return out


def rig_entries(cameras: Mapping[str, Any], rig: list[Any]) -> list[dict[str, Any]]:
    """result@1's ``rig``: one entry per camera after the first (``rig``: :func:`mirror_fg.solver.model.rig.rig_transforms`'
    list). ValueError when ``rig`` is not the chain of ``cameras`` (the solver did not fill it)."""
    names = list(cameras)
    chain = [(a, b) for a, b in zip(names, names[1:])]
    got = [(r.from_camera, r.to_camera) for r in rig]
    if got != chain:
        raise ValueError(f"result: the rig {got} is not the chain {chain} of the cameras "
                         "(Calibration.rig must be solver.model.rig.rig_transforms of Calibration.cameras)")
    out = []
    for r in rig:
        P = None if r.covariance is None else np.asarray(r.covariance, dtype=float)
        out.append({"from": r.from_camera, "to": r.to_camera, "T": transform_entry(r.R, r.t),
                    "covariance": None if P is None else P.tolist(), "sigma3": sigma3_pose(P)})
    return out


# --------------------------------------------------------------------------------------------------
# What ties the blocks together (the validator's checks; each block is checked by result_schema first)
# --------------------------------------------------------------------------------------------------


def _pose(entry: Mapping[str, Any]) -> Transform:
    return Transform(np.array(entry["R"], dtype=float), np.array(entry["t"], dtype=float))


def _off(a: Transform, b: Transform) -> float:
    return max(float(np.max(np.abs(a.R - b.R))), float(np.max(np.abs(a.t - b.t))))


def _check_covariance_pair(entry: Mapping[str, Any], path: str) -> None:
    P, P_bc = entry.get("covariance_cam_base"), entry.get("covariance_base_cam")
    if P is None or P_bc is None:
        return
    T = _pose(entry["T_cam_base"])
    want = base_cam_covariance(T.R, T.t, np.array(P))
    off = float(np.max(np.abs(np.array(P_bc) - want)))
    if off > SYMMETRY_TOL * max(float(np.max(np.abs(want))), 1e-300):
        raise _Invalid(_child(path, "covariance_base_cam"), f"does not match covariance_cam_base (off by {off:.3g})")


def check_cameras(result: Mapping[str, Any]) -> None:
    """``cameras``, ``rig`` and ``mirrors[].camera`` agree: each camera's ``T_base_cam`` is its ``T_cam_base``
    inverted (covariances too), the first camera is the top-level pose, ``rig`` is the chain of the cameras
    (names in order, each ``T`` = ``T_to_base T_from_base^-1``), every mirror names a declared camera.
    Raises :class:`_Invalid` at the key path."""
    cameras, rig = result.get("cameras"), result.get("rig")
    mirrors = result.get("mirrors") or []
    if cameras is None:
        if rig:
            raise _Invalid("rig", "a rig without cameras")
        for k, entry in enumerate(mirrors):
            if entry.get("camera") is not None:
                raise _Invalid(_child(_child("mirrors", k), "camera"), f"names camera {entry['camera']!r} but the "
                               "result has no cameras")
        return
    names = list(cameras)
    for name, entry in cameras.items():
        path = _child("cameras", name)
        if entry.get("T_base_cam") is not None:
            off = _off(_pose(entry["T_base_cam"]), _pose(entry["T_cam_base"]).inverse())
            if off > POSE_TOL:
                raise _Invalid(_child(path, "T_base_cam"), f"not the inverse of {_child(path, 'T_cam_base')} "
                               f"(off by {off:.3g})")
        _check_covariance_pair(entry, path)
    off = _off(_pose(cameras[names[0]]["T_cam_base"]), _pose(result["T_cam_base"]))
    if off > POSE_TOL:
        raise _Invalid(_child(_child("cameras", names[0]), "T_cam_base"),
                       f"the first camera is not the top-level T_cam_base (off by {off:.3g})")
    rig = rig or []
    if len(rig) != len(names) - 1:
        raise _Invalid("rig", f"expected {len(names) - 1} entries (one per camera after the first), got {len(rig)}")
    for k, entry in enumerate(rig):
        path = _child("rig", k)
        if (entry["from"], entry["to"]) != (names[k], names[k + 1]):
            raise _Invalid(path, f"from {entry['from']!r} to {entry['to']!r}, expected from {names[k]!r} to "
                           f"{names[k + 1]!r} (the cameras in order)")
        want = _pose(cameras[names[k + 1]]["T_cam_base"]) @ _pose(cameras[names[k]]["T_cam_base"]).inverse()
        off = _off(_pose(entry["T"]), want)
        if off > POSE_TOL:
            raise _Invalid(_child(path, "T"), f"not T_cam_base of {names[k + 1]!r} times the inverse of "
                           f"{names[k]!r}'s (off by {off:.3g})")
    for k, entry in enumerate(mirrors):
        path = _child(_child("mirrors", k), "camera")
        if entry.get("camera") is None:
            raise _Invalid(path, "missing: a result with cameras names the camera frame of every mirror vector")
        if entry["camera"] not in cameras:
            raise _Invalid(path, f"names camera {entry['camera']!r}, not one of the cameras ({', '.join(names)})")
