"""The summary lines of a robot arm's result@1 (docs/formats.md, "Robot arms: joint states and mounts"): each
estimated mount on its link with its 3-sigma, and each estimated joint offset."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["mount_lines"]

KEYS = {"camera": "T_link_cam", "target": "T_link_target"}


def _numbers(values, digits: int) -> str:
    return "[" + ", ".join(f"{float(v):.{digits}f}" for v in values) + "]"


def mount_lines(result: Mapping[str, Any]) -> list[str]:
    """Lines for ``mounts`` and ``joint_offsets`` (none without them)."""
    lines = []
    mounts = dict(result.get("mounts") or {})
    cameras = mounts.pop("cameras", None) or {}
    if cameras:  # several cameras: each under its name (mounts.camera repeats the first's)
        mounts.pop("camera", None)
    entries = [(f"the camera {name!r}", "camera", entry) for name, entry in cameras.items()]
    entries += [(f"the {role}", role, entry) for role, entry in mounts.items()]
    for words, role, entry in entries:
        pose = entry[KEYS[role]]
        lines.append(f"{KEYS[role]}  {words} on link {entry['link']}: t {_numbers(pose['t'], 5)} m, "
                     f"q_xyzw {_numbers(pose['q_xyzw'], 6)}")
        sigma3 = entry.get("sigma3")
        if sigma3:
            lines.append(f"  3-sigma bounds in {entry['link']} axes: rotation ±{_numbers(sigma3['rotation_deg'], 3)} deg, "
                         f"position ±{_numbers(sigma3['position_mm'], 2)} mm")
    for joint, entry in (result.get("joint_offsets") or {}).items():
        if "offset_deg" in entry:
            lines.append(f"joint offset {joint}: {entry['offset_deg']:.3f} ± {entry['sigma3_deg']:.3f} deg (3 sigma)")
        else:
            lines.append(f"joint offset {joint}: {entry['offset_mm']:.3f} ± {entry['sigma3_mm']:.3f} mm (3 sigma)")
    return lines
