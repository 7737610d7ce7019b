"""The files of ``mirror-fg verify`` (docs/formats.md, "Has it moved?"): verification@1 and the updated
result@1 of ``--update``.

The updated result is the stored one with the camera's transform and covariance replaced by the stored
estimate combined with the new data (``Verification.fused``) and every block derived from them written
again (``T_base_cam``, its covariances, the 3-sigma bounds); conventions as docs/formats.md (metres,
``[dtheta, dt]`` covariances).
"""
from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import Transform
from mirror_fg.io.output import json_text
from mirror_fg.io.result import ros_pose_covariance, validate_result
from mirror_fg.io.result_poses import sigma3_pose, transform_entry

__all__ = ["VERIFICATION_FORMAT", "verification_text", "updated_result"]

VERIFICATION_FORMAT = "mirror-fg/verification@1"
#: Blocks of a result that ``--update`` cannot carry over (they hang on more than the camera's transform).
_NOT_UPDATED = ("cameras", "mounts", "screen", "screens")


def verification_text(document: Mapping[str, Any]) -> str:
    """verification@1 as JSON text (a number that is not finite is written as null)."""
    return json_text(document, allow_nan=False) if _finite(document) else json_text(_nulls(document), allow_nan=False)


def _finite(value: Any) -> bool:
    if isinstance(value, float):
        return bool(np.isfinite(value))
    if isinstance(value, Mapping):
        return all(_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    return True


def _nulls(value: Any) -> Any:
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _nulls(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nulls(v) for v in value]
    return value


def check_updatable(result: Mapping[str, Any], source: str) -> None:
    """DatasetError (exit 2) where ``--update`` cannot write this result again (one camera only)."""
    for key in _NOT_UPDATED:
        if result.get(key):
            raise DatasetError(f"{source}: --update writes single-camera results only (this one has {key!r}); "
                               "calibrate again with the old and new images together")


def updated_result(result: Mapping[str, Any], fused: tuple[np.ndarray, np.ndarray, np.ndarray], source: str,
                   data_source: str, images: int) -> dict[str, Any]:
    """The stored result with the fused transform ``(R_cam_base, t_cam_base, covariance)`` (a validated
    result@1 dictionary); ``update`` records where the new images came from."""
    check_updatable(result, source)
    R, t, P = fused
    T = Transform(R, t)
    T_bc = T.inverse()
    P_bc = T.inverse_covariance(P)
    out = copy.deepcopy(dict(result))
    for stale in ("at", "validation"):  # derived from the old transform and data
        out.pop(stale, None)
    out.update({
        "T_cam_base": transform_entry(T.R, T.t), "T_base_cam": transform_entry(T_bc.R, T_bc.t),
        "covariance_cam_base": P.tolist(), "sigma3_cam_base": sigma3_pose(P),
        "covariance_base_cam": P_bc.tolist(), "sigma3_base_cam": sigma3_pose(P_bc),
        "covariance_base_cam_ros": ros_pose_covariance(P_bc).tolist(),
        "update": {"result": source, "data": data_source, "images": images},
    })
    return validate_result(out, f"{source} (updated)")
