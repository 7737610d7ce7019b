"""The report's screen figure: the gaze point's 3-sigma ellipses over the screen (docs/formats.md, "The answer
in the user's units"). Screen frame of :mod:`mirror_fg.core.screen`, millimetres, x right, y down, as the
viewer sees the screen."""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.gaze_error import DEFAULT_VIEWING_DISTANCE_M, gaze_error
from mirror_fg.core.screen import Screen
from mirror_fg.report.figures import new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["figure_gaze", "has_gaze_error", "gaze_screens"]

#: Points of each drawn ellipse.
_ELLIPSE_POINTS = 90


def has_gaze_error(result: Mapping[str, Any]) -> bool:
    """The result has a screen whose pose has a covariance (a gaze error to draw)."""
    return isinstance(result.get("screen"), Mapping) and result.get("covariance_cam_base") is not None


def gaze_screens(result: Mapping[str, Any]) -> list[str | None]:
    """The screens to draw: each of ``screens`` by name (several screens), else ``[None]`` (the one
    ``screen``), else none."""
    if isinstance(result.get("screens"), Mapping):
        return list(result["screens"])
    return [None] if has_gaze_error(result) else []


def ellipse_mm(covariance_mm: np.ndarray, scale: float) -> np.ndarray:
    """(K, 2) points of the 3-sigma ellipse of a 2 x 2 covariance (mm^2), magnified ``scale`` times."""
    values, vectors = np.linalg.eigh(covariance_mm)
    angle = np.linspace(0.0, 2.0 * np.pi, _ELLIPSE_POINTS)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return scale * 3.0 * circle * np.sqrt(np.clip(values, 0.0, None)) @ vectors.T


def figure_gaze(result: Mapping[str, Any], name: str | None = None) -> Figure | None:
    """The screen's active area (mm) with the 3-sigma ellipse of the gaze point at its centre and corners,
    magnified to a tenth of the screen's height, each labelled in mm and degrees; ``name``: that screen of
    a result with several."""
    if name is not None:
        from mirror_fg.io.gaze_export import one_screen

        result = {**one_screen(result, name, "result"), "covariance_cam_base": result["screens"][name]["covariance"]}
    if not has_gaze_error(result):
        return None
    screen = Screen.from_result(result)
    distance = float(result["screen"].get("viewing_distance_m", DEFAULT_VIEWING_DISTANCE_M))
    error = gaze_error(screen, distance)
    size = np.array([screen.width_mm, screen.height_mm])
    largest = float(np.max(error.sigma3_mm))
    scale = 0.1 * size[1] / largest if largest > 0 else 1.0
    fig = new_figure(7.0, 7.0 * size[1] / size[0] + 1.2)
    ax = fig.add_subplot()
    ax.plot([0, size[0], size[0], 0, 0], [0, 0, size[1], size[1], 0], color="black", lw=1.2)
    centres = error.points_px * 1000.0 * screen.metres_per_px
    for k, (centre, cov) in enumerate(zip(centres, error.covariance_mm)):
        outline = centre + ellipse_mm(cov, scale)
        ax.fill(outline[:, 0], outline[:, 1], color="tab:red", alpha=0.35, lw=0)
        ax.plot(outline[:, 0], outline[:, 1], color="tab:red", lw=1.0)
        mm, deg = error.sigma3_mm[k], error.sigma3_deg[k]
        inward = np.sign(size / 2 - centre) if k else np.array([0.0, 1.0])
        ax.annotate(f"±{mm[0]:.1f}, {mm[1]:.1f} mm\n±{deg[0]:.2f}, {deg[1]:.2f}°", centre, fontsize=8,
                    xytext=(centre + inward * np.array([0.2, 0.16]) * size), ha="center", va="center",
                    arrowprops={"arrowstyle": "-", "color": "grey", "lw": 0.6})
    ax.set_xlim(-0.08 * size[0], 1.08 * size[0])
    ax.set_ylim(1.1 * size[1], -0.1 * size[1])  # y down, as on the screen
    ax.set_aspect("equal")
    ax.set_xlabel("screen x (mm)")
    ax.set_ylabel("screen y (mm)")
    ax.set_title(f"Gaze point 3σ on {'the screen' if name is None else 'screen ' + name}, eye {100 * distance:.0f} cm in front of its centre "
                 f"(ellipses × {scale:.0f})", fontsize=10)
    return fig
