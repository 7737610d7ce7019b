"""The gaze-point error a screen calibration costs (docs/formats.md, "The answer in the user's units").

A gaze tracker gives the eye and the gaze direction in the camera frame; the calibration puts the screen
there. The point of regard is the ray's hit on the screen, in screen millimetres (screen frame of
:mod:`mirror_fg.core.screen`: origin at the top-left corner of the active area, x right, y down). With
the ray held (the camera measures it) and the screen pose uncertain, the hit moves on the screen by the
first-order propagation of the pose covariance (6 x 6 ``[dtheta, dt]``, ``R_true = Exp(dtheta) R``,
``t_true = t + dt``, camera axes): :meth:`Screen.pixel_of_ray`'s Jacobian.

The eye is placed on the screen's normal through the centre of the active area, ``viewing_distance_m``
(metres) in front of it, and looks at the centre and at the four corners (top-left, top-right,
bottom-right, bottom-left). Each hit's 3-sigma is given along the screen's x and y in millimetres and as
the angle it subtends at the eye (degrees): the component of that on-screen error across the line of
sight over the eye's distance to the point.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.screen import Screen

__all__ = ["DEFAULT_VIEWING_DISTANCE_M", "GazeError", "gaze_error", "gaze_block", "gaze_summary_lines"]

#: The viewer's distance in front of the screen's centre, metres (a desk monitor).
DEFAULT_VIEWING_DISTANCE_M = 0.6


@dataclass(frozen=True)
class GazeError:
    """The gaze points' errors: ``eye_cam`` (3,) metres; ``points_px`` (5, 2) the centre then the four
    corners (pixel-edge coordinates); ``covariance_mm`` (5, 2, 2) of each hit, screen axes, mm^2;
    ``sigma3_mm`` (5, 2); ``sigma3_deg`` (5, 2) as seen from the eye."""

    viewing_distance_m: float
    eye_cam: np.ndarray
    points_px: np.ndarray
    covariance_mm: np.ndarray
    sigma3_mm: np.ndarray
    sigma3_deg: np.ndarray


def eye_in_front(screen: Screen, viewing_distance_m: float) -> np.ndarray:
    """The eye (3,) in the camera frame: ``viewing_distance_m`` along the normal from the screen's centre."""
    centre = screen.camera_point([screen.width_px / 2.0, screen.height_px / 2.0])
    return centre + viewing_distance_m * screen.normal_cam


def gaze_error(screen: Screen, viewing_distance_m: float = DEFAULT_VIEWING_DISTANCE_M) -> GazeError:
    """The on-screen error (module docstring) of a gaze at the centre and the corners; ValueError without
    a covariance or with a viewing distance that is not > 0."""
    if screen.covariance is None:
        raise ValueError("the screen's pose has no covariance: no gaze error")
    if not viewing_distance_m > 0:
        raise ValueError(f"the viewing distance must be > 0 metres, got {viewing_distance_m}")
    w, h = float(screen.width_px), float(screen.height_px)
    points = np.array([[w / 2, h / 2], [0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    eye = eye_in_front(screen, viewing_distance_m)
    mm_per_px = 1000.0 * screen.metres_per_px
    R = screen.T_cam_screen.R
    covariances, degrees = [], []
    for pixel in points:
        target = screen.camera_point(pixel)
        hit = screen.pixel_of_ray(eye, target - eye, inside=False)  # the ray through it: it hits there
        assert hit is not None and hit.covariance_px is not None
        cov_mm = hit.covariance_px * np.outer(mm_per_px, mm_per_px)
        covariances.append(cov_mm)
        distance = float(np.linalg.norm(target - eye))
        line = (target - eye) / distance
        across = R[:, :2] - np.outer(line, line @ R[:, :2])  # a screen axis' step, across the line of sight
        # a step of s mm along screen axis k turns the line of sight by |across_k| s / distance (radians)
        per_mm = np.linalg.norm(across, axis=0) / (1000.0 * distance)
        degrees.append(np.degrees(3.0 * np.sqrt(np.diag(cov_mm)) * per_mm))
    covariance = np.array(covariances)
    return GazeError(float(viewing_distance_m), eye, points, covariance,
                     3.0 * np.sqrt(np.diagonal(covariance, axis1=1, axis2=2)), np.array(degrees))


def gaze_block(screen: Screen, viewing_distance_m: float = DEFAULT_VIEWING_DISTANCE_M) -> dict[str, Any]:
    """The keys the result@1 ``screen`` block gains (docs/formats.md, "The answer in the user's units"):
    ``sigma3_on_screen_mm`` and ``sigma3_on_screen_deg`` (``{"centre": [2], "corners": [[2] x 4]}``) and
    ``viewing_distance_m``; empty without a covariance."""
    if screen.covariance is None:
        return {}
    error = gaze_error(screen, viewing_distance_m)
    return {
        "sigma3_on_screen_mm": {"centre": error.sigma3_mm[0].tolist(), "corners": error.sigma3_mm[1:].tolist()},
        "sigma3_on_screen_deg": {"centre": error.sigma3_deg[0].tolist(), "corners": error.sigma3_deg[1:].tolist()},
        "viewing_distance_m": error.viewing_distance_m,
    }


def gaze_summary_lines(block: dict[str, Any]) -> list[str]:
    """The console's lines for a result's ``screen`` block (none without the gaze keys)."""
    if "sigma3_on_screen_mm" not in block:
        return []
    mm, deg = block["sigma3_on_screen_mm"], block["sigma3_on_screen_deg"]
    corners_mm = np.max(np.array(mm["corners"]), axis=0)
    corners_deg = np.max(np.array(deg["corners"]), axis=0)
    return [
        f"gaze point 3-sigma on the screen (eye {100 * block['viewing_distance_m']:.0f} cm in front of its centre, "
        "screen x, y):",
        f"  centre  ±[{mm['centre'][0]:.2f}, {mm['centre'][1]:.2f}] mm  ±[{deg['centre'][0]:.3f}, {deg['centre'][1]:.3f}] deg",
        f"  corners ±[{corners_mm[0]:.2f}, {corners_mm[1]:.2f}] mm  ±[{corners_deg[0]:.3f}, {corners_deg[1]:.3f}] deg "
        "(the largest of the four)",
    ]
