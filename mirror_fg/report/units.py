"""The answer in the user's units, for the console and the report (docs/formats.md, "The answer in the
user's units"): the error at the user's points (result@1 ``at``), a map of the largest 3-sigma over the
image at 0.5, 1 and 2 m, and the held-out validation (``solver/fit/validation.py``) with its ratio per image.

Frames: a point ``p_cam`` in the camera frame (OpenCV axes, metres) maps into {B} by ``T_base_cam``; its
3-sigma (millimetres, base axes) comes from ``covariance_base_cam`` alone (``solver/result/point_error.py``).
A pixel ``(u, v)`` at depth ``z`` (metres along the optical axis) is the point ``z (x, y, 1)`` with
``(x, y)`` its undistorted normalized coordinates. Figures: matplotlib on the Agg canvas, as the report's.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.transform import Transform
from mirror_fg.io.result import base_cam_pose_covariance, transforms

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.data import Dataset
    from mirror_fg.solver.fit.validation import Validation

__all__ = ["units_lines", "largest_sigma3_map", "figure_point_error_map", "figure_validation", "units_blocks",
           "MAP_DEPTHS_M"]

#: Depths (metres along the optical axis) of the report's map of the largest 3-sigma over the image.
MAP_DEPTHS_M = (0.5, 1.0, 2.0)
#: Grid of the map (columns; rows follow the image's aspect ratio).
MAP_COLUMNS = 48
#: Above this ratio an image is drawn red in the validation figure (a point about 6 sigma off).
RATIO_FLAG = 2.0


def _v(values: Any, fmt: str) -> str:
    return "[" + ", ".join(format(float(x), fmt) for x in values) + "]"


def units_lines(result: Mapping[str, Any]) -> list[str]:
    """Console lines of result@1's ``at`` (each point's 3-sigma in {B}) and ``validation``."""
    lines: list[str] = []
    for entry in result.get("at") or []:
        camera = f" (camera {entry['camera']})" if entry.get("camera") else ""
        sigma = entry.get("sigma3_mm")
        bound = "not computed (no covariance)" if sigma is None else (
            f"3-sigma ±{_v(sigma, '.2f')} mm along base x, y, z (worst direction "
            f"{3000.0 * math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(entry['covariance']))[-1]), 0.0)):.2f} mm)")
        lines.append(f"at p_cam {_v(entry['point_cam'], '.3f')} m{camera}: p_base {_v(entry['point_base'], ' .4f')} m, "
                     f"{bound}")
    validation = result.get("validation")
    if validation:
        worst = validation.get("worst") or {}
        lines.append(f"held-out validation over {validation['images']} image(s): ratio {validation['ratio']:.3g} "
                     f"(1 when the noise model and the bounds hold)"
                     + (f", worst image {worst['image']} at {worst['ratio']:.3g}" if worst else ""))
        if validation.get("not_held_out"):
            lines.append("  not held out (the others alone leave an unknown undetermined): "
                         + ", ".join(validation["not_held_out"][:10]))
    return lines


def _pixel_grid(camera: Any) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Pixel centres ``(u, v)`` of the map's grid, their undistorted normalized coordinates (N, 2) and the
    image size; without a camera a normalized square of half-width 0.5."""
    if camera is None:
        xs = np.linspace(-0.5, 0.5, MAP_COLUMNS)
        u, v = np.meshgrid(xs, xs)
        return np.stack([u.ravel(), v.ravel()], axis=1), np.stack([u.ravel(), v.ravel()], axis=1), (1.0, 1.0)
    rows = max(2, round(MAP_COLUMNS * camera.height / camera.width))
    u, v = np.meshgrid(np.linspace(0.5, camera.width - 0.5, MAP_COLUMNS), np.linspace(0.5, camera.height - 0.5, rows))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    return pixels, np.asarray(camera.normalize(pixels), dtype=float).reshape(-1, 2), (camera.width, camera.height)


def largest_sigma3_map(T_base_cam: Transform, covariance_base_cam: np.ndarray, normalized: np.ndarray,
                       depth_m: float) -> np.ndarray:
    """The 3-sigma along the worst direction (mm) of each point ``depth (x, y, 1)`` in {B}."""
    points = depth_m * np.column_stack([normalized, np.ones(len(normalized))])
    a = points @ np.asarray(T_base_cam.R, float).T  # R p_cam: the lever arm of a rotation error
    J = np.zeros((len(points), 3, 6))  # solver/point_error.point_jacobian of every point: [-[a]x, I]
    J[:, 0, 1], J[:, 0, 2], J[:, 1, 0] = a[:, 2], -a[:, 1], -a[:, 2]
    J[:, 1, 2], J[:, 2, 0], J[:, 2, 1] = a[:, 0], a[:, 1], -a[:, 0]
    J[:, :, 3:] = np.eye(3)
    C = J @ np.asarray(covariance_base_cam, float) @ J.transpose(0, 2, 1)
    return 3000.0 * np.sqrt(np.clip(np.linalg.eigvalsh(C)[:, -1], 0.0, None))


def figure_point_error_map(result: Mapping[str, Any], camera: Any) -> Figure:
    """Three panels: the largest 3-sigma (mm, {B}) of a point seen at each pixel at 0.5, 1 and 2 m."""
    from mirror_fg.report.figures import new_figure

    (_, _), (R_bc, t_bc) = transforms(result)
    covariance = base_cam_pose_covariance(result)
    assert covariance is not None
    pixels, normalized, (width, height) = _pixel_grid(camera)
    maps = [largest_sigma3_map(Transform(R_bc, t_bc), covariance, normalized, z) for z in MAP_DEPTHS_M]
    low, high = min(float(m.min()) for m in maps), max(float(m.max()) for m in maps)
    fig = new_figure(10.0, 3.4)
    columns = MAP_COLUMNS
    rows = len(pixels) // columns
    for k, (z, values) in enumerate(zip(MAP_DEPTHS_M, maps)):
        ax = fig.add_subplot(1, 3, k + 1)
        extent = (0, width, height, 0) if camera is not None else (-0.5, 0.5, 0.5, -0.5)
        image = ax.imshow(values.reshape(rows, columns), extent=extent, vmin=low, vmax=high, cmap="viridis",
                          aspect="equal")
        levels = ax.contour(values.reshape(rows, columns), extent=extent, colors="white", linewidths=0.6, origin="upper")
        ax.clabel(levels, fontsize=6, fmt="%.1f")
        ax.set_title(f"depth {z:g} m: {values.min():.1f}–{values.max():.1f} mm", fontsize=9)
        ax.set_xlabel("u, px" if camera is not None else "x (normalized)", fontsize=8)
        if k == 0:
            ax.set_ylabel("v, px" if camera is not None else "y (normalized)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.colorbar(image, ax=fig.axes, shrink=0.85, label="largest 3σ in {B}, mm")
    return fig


def figure_validation(validation: Validation) -> Figure:
    """Each held-out image's ratio (file order) with 1 (the model holds) and the flag line."""
    from mirror_fg.report.figures import new_figure

    fig = new_figure(8.0, 3.0)
    ax = fig.add_subplot(1, 1, 1)
    ratios = np.asarray(validation.ratios)
    x = np.arange(len(ratios))
    colours = np.where(ratios > RATIO_FLAG, "tab:red", "tab:blue")
    ax.bar(x, ratios, color=colours, width=0.9 if len(ratios) < 80 else 1.0)
    ax.axhline(1.0, color="k", lw=0.8, label="1: noise model and bounds hold")
    ax.axhline(RATIO_FLAG, color="tab:red", lw=0.8, ls="--", label=f"{RATIO_FLAG:g}")
    worst = validation.worst
    if worst is not None:
        k = validation.images.index(worst[0])
        ax.annotate(worst[0], (k, worst[1]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("held-out image (file order)", fontsize=8)
    ax.set_ylabel("ratio √(cost / expected)", fontsize=8)
    ax.set_title(f"{len(ratios)} image(s), RMS ratio {validation.ratio:.3g}", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.set_ylim(0.0, max(float(ratios.max(initial=0.0)), RATIO_FLAG) * 1.3)
    ax.legend(fontsize=7, loc="upper center", ncol=2)
    return fig


def units_blocks(result: Mapping[str, Any], dataset: Dataset | None) -> list[Any]:
    """The report's section: the error at the result's points, the map, the held-out validation (computed
    from the dataset, the result's own summary without it)."""
    from mirror_fg.report.pages import Block, RenderedFigure

    blocks: list[Any] = [Block("h2", "The answer in the user's units")]
    lines = units_lines({"at": result.get("at")})
    if lines:
        blocks.append(Block("pre", "\n".join(lines), id="point-error"))
    camera = None
    if dataset is not None:
        camera = dataset.camera if dataset.cameras is None else next(iter(dataset.cameras.values()))
    covariance = base_cam_pose_covariance(result)
    if covariance is not None and np.any(covariance):
        estimated = result.get("camera")
        if estimated is not None and camera is not None:
            from mirror_fg.io.result import estimated_camera

            camera = estimated_camera(result, "result", camera) or camera
        blocks.append(Block("figure", "The largest 3σ (mm, along the worst direction in the base frame) of a point the "
                            "camera sees at each pixel, at 0.5, 1 and 2 m along the optical axis: the pose's "
                            "uncertainty alone (T_base_cam's covariance, first order)"
                            + (", first camera" if result.get("cameras") else "") + ".",
                            figure=RenderedFigure(figure_point_error_map(result, camera))))
    else:
        blocks.append(Block("p", "No pose covariance (or the pose is the base frame itself): no error map.", css="note"))
    validation, note = None, ""
    if dataset is not None:
        from mirror_fg.solver.fit.validation import validate_result_file

        try:
            validation = validate_result_file(dataset, result)
        except (ValueError, KeyError, np.linalg.LinAlgError, RuntimeError) as error:
            note = f"Held-out validation not computed: {error}"
    if validation is not None and len(validation.images):
        summary = units_lines({"validation": validation.to_dict()})
        blocks.append(Block("pre", "\n".join(summary), id="validation"))
        blocks.append(Block("figure", "Held-out validation: each image left out of the solve in turn (one Gauss–Newton "
                            "step from the full solution), its own mirror placements fitted to it, its whitened cost "
                            "against what the others' covariance predicts, as √(cost / expected): about 1 when the "
                            "noise model and the 3σ bounds hold; red above 2 (a point about 6σ off).",
                            figure=RenderedFigure(figure_validation(validation))))
    elif result.get("validation"):
        blocks.append(Block("pre", "\n".join(units_lines({"validation": result["validation"]})), id="validation"))
    else:
        blocks.append(Block("p", note or "No dataset given: no held-out validation.", css="note"))
    return blocks
