"""What the registry keeps of a document: one row per camera of a result@1 or verification@1, as plain values.

Frames and units (docs/formats.md): ``T_base_cam`` is the camera's pose on the robot (``Bp = R Cp + t``),
its translation in metres and rotation as a unit quaternion ``[x, y, z, w]``; its 3-sigma is the result's
``sigma3_base_cam`` (``position_mm`` along the base axes, ``rotation_deg`` in the uncertainty convention).
A single-camera result's camera is named ``camera``; a rig's cameras keep their names. A verification
carries no pose: its rows hold the verdict of each camera it judged.
"""
from __future__ import annotations

import hashlib
import math
import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from mirror_fg.registry.schema import RegistryError

__all__ = ["CameraRow", "HistoryRecord", "camera_rows", "document_kind", "input_sha256", "SINGLE_CAMERA",
           "RESULT_FORMAT", "VERIFICATION_FORMAT"]

RESULT_FORMAT = "mirror-fg/result@1"
VERIFICATION_FORMAT = "mirror-fg/verification@1"
#: The camera name of a single-camera result.
SINGLE_CAMERA = "camera"


@dataclass(slots=True)
class CameraRow:
    """The query columns of one camera of a document (None where the document has no pose)."""

    camera: str
    verdict: str | None
    t_m: tuple[float, float, float] | None
    q_xyzw: tuple[float, float, float, float] | None
    sigma3_position_mm: tuple[float, float, float] | None
    sigma3_rotation_deg: tuple[float, float, float] | None


@dataclass(slots=True)
class HistoryRecord(CameraRow):
    """One stored record: a camera of a run, with its run's identity (``document`` only from ``latest``)."""

    id: int = 0
    run_id: int = 0
    robot: str = ""
    kind: str = ""
    time: datetime | None = None
    mirror_fg_version: str = ""
    input_sha256: str | None = None
    host: str | None = None
    document: Any = None


def document_kind(document: Mapping[str, Any]) -> str:
    """``calibration`` for a result@1, ``verification`` for a verification@1, else a RegistryError."""
    kind = {RESULT_FORMAT: "calibration", VERIFICATION_FORMAT: "verification"}.get(str(document.get("format")))
    if kind is None:
        raise RegistryError(f"the registry records {RESULT_FORMAT} and {VERIFICATION_FORMAT} documents, "
                            f"not {str(document.get('format'))[:60]!r}")
    return kind


def camera_rows(document: Mapping[str, Any]) -> list[CameraRow]:
    """One row per camera of ``document`` (a rig: each camera; a single camera: ``camera``)."""
    if document_kind(document) == "verification":
        cameras = document.get("cameras") or {}
        if not isinstance(cameras, Mapping) or not cameras:
            raise RegistryError("a verification@1 document without cameras cannot be recorded")
        return [CameraRow(str(name), _verdict(entry.get("verdict") if isinstance(entry, Mapping) else None),
                          None, None, None, None) for name, entry in cameras.items()]
    verdict = _calibration_verdict(document)
    rig = document.get("cameras")
    if isinstance(rig, Mapping) and rig:
        return [_pose_row(str(name), entry, verdict) for name, entry in rig.items()]
    return [_pose_row(SINGLE_CAMERA, document, verdict)]


def _pose_row(name: str, entry: Mapping[str, Any], verdict: str | None) -> CameraRow:
    pose = entry.get("T_base_cam") or {}
    sigma3 = entry.get("sigma3_base_cam") or {}
    return CameraRow(name, verdict, _vector(pose.get("t"), 3), _vector(pose.get("q_xyzw"), 4),
                     _vector(sigma3.get("position_mm"), 3), _vector(sigma3.get("rotation_deg"), 3))


def _vector(values: Any, size: int) -> Any:
    """``values`` as a tuple of ``size`` finite floats, or None (a missing or unusable entry)."""
    try:
        numbers = tuple(float(x) for x in values)
    except (TypeError, ValueError):
        return None
    return numbers if len(numbers) == size and all(math.isfinite(x) for x in numbers) else None


def _verdict(value: Any) -> str | None:
    return None if value is None else str(value)[:32]


def _calibration_verdict(document: Mapping[str, Any]) -> str | None:
    """The console's verdict on a result (``looks right``, ``check``; None when there is no cost to judge)."""
    from mirror_fg.report.summary import verdict_line
    from mirror_fg.report.verdict import stored_verdict

    stored = stored_verdict(document)  # the one verdict calibrate stored, as printed
    if stored is not None:
        return {"good": "looks right", "check": "check"}.get(stored.level)
    try:
        line = verdict_line(document)
    except (KeyError, TypeError, ValueError):  # a result without what the verdict reads: no verdict to store
        return None
    if line.startswith("verdict: looks right"):
        return "looks right"
    if line.startswith("verdict: CHECK"):
        return "check"
    return None


def input_sha256(path: str | os.PathLike[str] | None) -> str | None:
    """The sha256 of an input file; None for a pipe or device (read once, it cannot be read again)."""
    if path is None:
        return None
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        digest = hashlib.sha256()
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()
