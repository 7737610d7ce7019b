"""Documents for the registry tests: result@1 and verification@1 with only what the registry reads, built from
poses given here (an independent reference for what history must show)."""
from __future__ import annotations

import math

import numpy as np


def quaternion_xyzw(rotation_vector_deg) -> list[float]:
    """The unit quaternion [x, y, z, w] of a rotation vector in degrees."""
    w = np.radians(np.asarray(rotation_vector_deg, dtype=float))
    angle = float(np.linalg.norm(w))
    if angle == 0.0:
        return [0.0, 0.0, 0.0, 1.0]
    axis = w / angle
    return [*(axis * math.sin(angle / 2)).tolist(), math.cos(angle / 2)]


def pose_entry(position_mm, rotation_deg, sigma3_mm=(3.0, 3.0, 3.0), sigma3_deg=(0.3, 0.3, 0.3)) -> dict:
    return {"T_base_cam": {"t": [x / 1000.0 for x in position_mm], "q_xyzw": quaternion_xyzw(rotation_deg)},
            "sigma3_base_cam": {"position_mm": list(sigma3_mm), "rotation_deg": list(sigma3_deg)}}


def result_document(position_mm=(100.0, 0.0, 50.0), rotation_deg=(0.0, 0.0, 0.0), tag: str = "", cameras=None,
                    **sigma) -> dict:
    """A result@1 of one camera (or a rig: ``cameras`` = {name: (position_mm, rotation_deg)})."""
    document = {"format": "mirror-fg/result@1", **pose_entry(position_mm, rotation_deg, **sigma)}
    if cameras:
        document["cameras"] = {name: pose_entry(p, r, **sigma) for name, (p, r) in cameras.items()}
    if tag:
        document["test_tag"] = tag  # result@1 may carry extra keys
    return document


def verification_document(verdicts: dict[str, str]) -> dict:
    return {"format": "mirror-fg/verification@1", "result": "result.json", "data": "new.json", "alpha": 0.01,
            "cameras": {name: {"verdict": v, "p_value": 0.5} for name, v in verdicts.items()}}
