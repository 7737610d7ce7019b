"""Robot arms (docs/formats.md, "Robot arms: joint states and mounts"): forward kinematics from a URDF
through Pinocchio (:mod:`mirror_fg.robot.kinematics`, imported lazily: the ``[robot]`` extra) and the
test arms shipped with the package (``urdf/arm6.urdf``, ``urdf/panda.urdf``)."""
from __future__ import annotations

import os

__all__ = ["ARMS", "arm_urdf"]

#: The test arms ``simulate --robot`` knows: a UR5-like six-axis arm and a Panda-like seven-axis arm.
ARMS = ("arm6", "panda")


def arm_urdf(name: str) -> str:
    """The path of a shipped test arm's URDF (kinematics only: no meshes)."""
    if name not in ARMS:
        raise ValueError(f"unknown test arm {name!r} (one of {', '.join(ARMS)})")
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "urdf", f"{name}.urdf")
