"""The analytical solution's result (Sects. 4-5 of the paper): every unknown in closed form, the PnP
transform chosen per image and the root's runner-up hypotheses. Frames and units: camera <- base, metres."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["AnalyticSolution"]


@dataclass
class AnalyticSolution:
    """Closed-form estimate of every unknown.

    ``R_cam_base``, ``t_cam_base``: camera <- base (``Cp = R Bp + t``, metres). ``mirror_vectors``:
    ``(l, m) -> v`` (camera frame, metres). ``points``: reconstruction points, base frame, metres.
    ``image_transforms``: the PnP ``(A_Nv, b_Nv)`` chosen for each image that had one.
    ``alternatives``: the root's runner-up hypotheses (other P3P choices), best first, without points.
    ``camera_poses``: with several cameras, every camera's start ``name -> (R_cam_base, t_cam_base)``
    (the first is ``R_cam_base``, ``t_cam_base``); empty for one camera.
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray] = field(default_factory=dict)
    image_transforms: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    alternatives: list[AnalyticSolution] = field(default_factory=list, repr=False)
    camera_poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def __repr__(self) -> str:
        """One bounded line (a dataclass repr printed every image's PnP transform: 54,000 characters)."""
        R = "; ".join(" ".join(f"{x:.5g}" for x in row) for row in np.asarray(self.R_cam_base))
        return (f"AnalyticSolution(R_cam_base=[{R}], t_cam_base=[{' '.join(f'{x:.5g}' for x in self.t_cam_base)}] m, "
                f"{len(self.mirror_vectors)} mirror placements, {len(self.points)} points, {len(self.image_transforms)} "
                f"image transforms, {len(self.alternatives)} alternatives)")
