"""The figures of the calibration report (matplotlib on the Agg canvas, no pyplot): residual histogram,
per-image and per-point residuals, the 3D scene in the base frame, the pose covariance's correlation.

Frames (docs/formats.md): {B} base, {C} camera (OpenCV: x right, y down, z forward); the 3D scene is
drawn in the base frame, metres. Residuals as in :mod:`mirror_fg.report.residuals`; the histogram shows
the x and y coordinates, each expected N(0, pixel_sigma).
"""
from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.transform import Transform
from mirror_fg.io.result import base_cam_pose_covariance, mirror_vectors, pose_covariance, transforms
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.report.residuals import OUTLIER_FACTOR, Residuals

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.data import Dataset

__all__ = [
    "new_figure",
    "figure_histogram",
    "figure_per_image",
    "figure_per_point",
    "figure_scene",
    "figure_correlation",
    "draw_pose_uncertainty",
    "correlation",
    "draw_correlation",
    "png",
    "PNG_DPI",
    "COVARIANCE_LABELS",
]

#: Resolution of the PNG figures embedded in the HTML (dots per inch).
PNG_DPI = 100
#: Bars labelled by name up to this many (a smaller font beyond 40); beyond it, the axis says the order.
MAX_BAR_LABELS = 120
#: Mirror placements drawn per mirror in the 3D scene (a random sample beyond it, said in the legend).
MAX_PLACEMENTS_DRAWN = 60
#: The camera's 3σ position ellipsoid is drawn this fraction of the scene's extent at least (scaled, labelled).
POSE_UNCERTAINTY_FRACTION = 0.06
#: The orientation cone's half-angle is drawn at least this wide (degrees; scaled, labelled).
CONE_MIN_DEG = 6.0
#: Covariance labels in docs/formats.md's order: rotation about the camera axes, then translation.
COVARIANCE_LABELS = ("rx", "ry", "rz", "x", "y", "z")
_MIRROR_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def new_figure(width: float, height: float) -> Figure:
    """A matplotlib Figure on the Agg canvas (no pyplot, no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def figure_histogram(residuals: Residuals) -> Figure:
    """Histogram of residual coordinates with the N(0, sigma) density.

    The range is +/- 5 max(sigma, robust sigma = 1.4826 median |residual|); coordinates beyond it are
    counted in the outer bins and in the title, so that outliers do not squash the histogram.
    """
    r = residuals.residual[residuals.valid]
    fig = new_figure(8.0, 4.5)
    ax = fig.add_subplot()
    values = r.ravel()
    s = residuals.sigma
    robust = 1.4826 * float(np.median(np.abs(values))) if values.size else 0.0
    lim = 5.0 * max(s, robust)
    outside = int(np.sum(np.abs(values) > lim))
    clipped = np.clip(r, -lim, lim)
    bins = int(np.clip(np.sqrt(values.size) * 2, 15, 80))
    for k, (axis, colour) in enumerate((("x", "tab:blue"), ("y", "tab:orange"))):
        ax.hist(clipped[:, k], bins=bins, range=(-lim, lim), density=True, alpha=0.55, color=colour, label=axis)
    xs = np.linspace(-lim, lim, 400)
    ax.plot(xs, np.exp(-0.5 * (xs / s) ** 2) / (s * math.sqrt(2.0 * math.pi)), "k-", lw=2, label=f"N(0, σ={s:.3g})")
    ax.set_xlim(-lim, lim)
    ax.set_xlabel(f"residual (predicted − observed), {residuals.units}")
    ax.set_ylabel("density")
    extra = f"; {outside} beyond ±{lim:.3g} in the outer bins" if outside else ""
    coordinate_sd = float(np.sqrt(np.mean(values**2))) if values.size else float("nan")
    ax.set_title(f"Residual coordinates: {values.size}, standard deviation about 0 = {coordinate_sd:.3g} "
                 f"{residuals.units} (σ = {s:.3g} expected){extra}")
    ax.legend()
    return fig


def figure_per_image(residuals: Residuals) -> Figure:
    """Bar chart of per-image RMS; bars above OUTLIER_FACTOR x median in red."""
    per_image = residuals.per_image_rms()
    ids = list(per_image)
    values = np.array([per_image[k] for k in ids])
    median = float(np.median(values))
    flagged = values > OUTLIER_FACTOR * median
    fig = new_figure(10.0, 4.5)
    ax = fig.add_subplot()
    colours = np.where(flagged, "tab:red", "tab:blue")
    ax.bar(np.arange(len(ids)), values, color=colours, width=0.8 if len(ids) < 100 else 1.0)
    ax.axhline(median, color="k", lw=1, ls="--", label=f"median {median:.3g}")
    ax.axhline(OUTLIER_FACTOR * median, color="tab:red", lw=1, ls=":", label=f"{OUTLIER_FACTOR:g} × median")
    _finish_rms_bars(ax, residuals, ids, "image (dataset order)",
                     f"Per-image RMS residual: {int(flagged.sum())} of {len(ids)} image(s) flagged (red)")
    return fig


def _finish_rms_bars(ax: Any, residuals: Residuals, labels: list[str], order: str, title: str) -> None:
    """The expected-RMS line, bar labels (or ``order`` as the x label beyond 40 bars), title and legend."""
    ax.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    if len(labels) <= MAX_BAR_LABELS:
        size = min(7.0, 520.0 / len(labels))  # about 10 in of bars: a name per bar stays legible
        ax.set_xticks(np.arange(len(labels)), labels, rotation=90, fontsize=size)
        ax.set_xlim(-0.6, len(labels) - 0.4)
    else:
        ax.set_xlabel(order)
    ax.set_ylabel(f"RMS residual, {residuals.units}")
    ax.set_title(title)
    ax.legend(fontsize=8)


def figure_per_point(residuals: Residuals, dataset: Dataset) -> Figure:
    """Per-point RMS bars, residual vectors, and residual arrows on the image plane."""
    per_point = residuals.per_point_rms()
    names = list(per_point)
    fid = set(dataset.fiducials)
    ok = residuals.valid
    r = residuals.residual[ok]
    fig = new_figure(10.0, 8.0)
    grid = fig.add_gridspec(2, 2)
    ax = fig.add_subplot(grid[0, :])
    colours = ["tab:gray" if n in fid else "tab:purple" for n in names]
    ax.bar(np.arange(len(names)), [per_point[n] for n in names], color=colours)
    _finish_rms_bars(ax, residuals, names, "point (first-seen order)",
                     "Per-point RMS residual (grey: fiducials, purple: reconstruction points)")

    ax = fig.add_subplot(grid[1, 0])
    is_f = residuals.is_fiducial[ok]
    ax.scatter(r[is_f, 0], r[is_f, 1], s=6, c="tab:gray", label="fiducials")
    if np.any(~is_f):
        ax.scatter(r[~is_f, 0], r[~is_f, 1], s=10, c="tab:purple", label="reconstruction points")
    angles = np.linspace(0.0, 2.0 * math.pi, 200)
    ax.plot(3 * residuals.sigma * np.cos(angles), 3 * residuals.sigma * np.sin(angles), "g--", lw=1, label="3σ")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"x residual, {residuals.units}")
    ax.set_ylabel(f"y residual, {residuals.units}")
    ax.set_title("Residual vectors")
    ax.legend(fontsize=7)

    ax = fig.add_subplot(grid[1, 1])
    obs = residuals.observed[ok]
    lengths = np.linalg.norm(r, axis=1)
    if dataset.camera is not None:
        span = float(max(dataset.camera.width, dataset.camera.height))
    else:
        span = float(np.ptp(obs, axis=0).max()) if len(obs) > 1 else 1.0
    # A median residual is drawn 4 % of the image long; outliers stand out as long arrows.
    scale = 0.04 * span / max(float(np.median(lengths)) if lengths.size else 1.0, 1e-300)
    drawn = r * scale
    too_long = np.linalg.norm(drawn, axis=1) > 0.15 * span  # outliers: capped, the colour tells the length
    drawn[too_long] *= (0.15 * span / np.linalg.norm(drawn[too_long], axis=1))[:, None]
    ax.scatter(obs[:, 0], obs[:, 1], s=2, c="k")
    quiver = ax.quiver(obs[:, 0], obs[:, 1], drawn[:, 0], drawn[:, 1], lengths, angles="xy",
                       scale_units="xy", scale=1.0, cmap="plasma", width=0.005)
    fig.colorbar(quiver, ax=ax, shrink=0.8, label=f"|residual|, {residuals.units}")
    if dataset.camera is not None:
        ax.set_xlim(0, dataset.camera.width)
        ax.set_ylim(dataset.camera.height, 0)
    else:
        ax.invert_yaxis()
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"u, {residuals.units}")
    ax.set_ylabel(f"v, {residuals.units}")
    ax.set_title(f"Residuals on the image (× {scale:.3g}, long ones capped)")
    return fig


def _camera_corners(dataset: Dataset | None) -> np.ndarray:
    """Normalized coordinates (4, 2) of the image corners (a 90 x 70 degree view without a camera)."""
    if dataset is not None and dataset.camera is not None:
        c = dataset.camera
        px = np.array([[0.0, 0.0], [c.width, 0.0], [c.width, c.height], [0.0, c.height]])
        return np.column_stack([(px[:, 0] - c.cx) / c.fx, (px[:, 1] - c.cy) / c.fy])
    return np.array([[-1.0, -0.7], [1.0, -0.7], [1.0, 0.7], [-1.0, 0.7]])


def _orthonormal_pair(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to unit ``n``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _set_equal_3d(ax: Any, points: np.ndarray, margin: float = 0.05) -> None:
    """Cube limits around ``points`` (N, 3) so that the 3D axes have equal scale."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2.0
    half = max(float(np.max(hi - lo)) / 2.0, 1e-3) * (1.0 + margin)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))


def _draw_axes(ax: Any, pose: Transform, length: float, lw: float) -> None:
    """The axes of a frame whose pose in {B} is ``pose``, ``length`` metres long: x red, y green, z blue."""
    for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(*np.column_stack([pose.t, pose.t + length * pose.R[:, k]]), color=colour, lw=lw)


def _draw_target(ax: Any, fiducials: np.ndarray, points: dict[str, tuple[np.ndarray, np.ndarray | None]]) -> None:
    """Fiducials (black triangles), reconstruction points (purple) and their axis-aligned 3σ ellipsoids."""
    if len(fiducials):
        ax.scatter(*fiducials.T, marker="^", c="k", s=14, depthshade=False, label="fiducials")
    if points:
        xyz = np.array([p for p, _ in points.values()])
        ax.scatter(*xyz.T, c="tab:purple", s=14, depthshade=False, label="reconstruction points")
    u, v = np.meshgrid(np.linspace(0, 2 * math.pi, 13), np.linspace(0, math.pi, 7))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    for p, s3 in points.values():
        if s3 is None or not np.all(np.isfinite(s3)):
            continue
        e = p[:, None, None] + 1e-3 * s3[:, None, None] * unit  # semi-axes 3σ, mm -> m
        ax.plot_wireframe(e[0], e[1], e[2], color="tab:purple", lw=0.5, alpha=0.7)


def figure_scene(result: Mapping[str, Any], dataset: Dataset | None) -> Figure:
    """3D scene in the base frame: axes, camera frustum, mirror patches, fiducials, points, 3σ ellipsoids."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    T_base_cam = Transform(*transforms(result)[1])
    mirrors = mirror_vectors(result)
    points = reconstruction_points(result)
    fiducials = np.array(list(dataset.fiducials.values())).reshape(-1, 3) if dataset is not None else np.zeros((0, 3))
    target = np.vstack([fiducials, *[p[None] for p, _ in points.values()]]) if (len(fiducials) or points) else None

    feet = {k: T_base_cam.apply(v) for k, v in mirrors.items()}  # foot points in {B}
    everything = np.vstack([np.zeros((1, 3)), T_base_cam.t[None], *(f[None] for f in feet.values())]
                           + ([target] if target is not None else []))
    extent = float(np.max(np.ptp(everything, axis=0))) or 1.0
    distances = [float(np.linalg.norm(v)) for v in mirrors.values()]
    half_side = 0.3 * (float(np.median(distances)) if distances else extent)
    axis_len = 0.12 * extent

    fig = new_figure(12.0, 6.5)
    panels = 2 if target is not None else 1
    ax = fig.add_subplot(1, panels, 1, projection="3d")
    _draw_axes(ax, Transform.identity(), axis_len, lw=2)  # base frame
    ax.text(0, 0, 0, " {B}", fontsize=9)
    # Camera frustum at T_base_cam.
    depth = 0.15 * extent
    corners_c = np.column_stack([_camera_corners(dataset) * depth, np.full(4, depth)])
    corners_b = T_base_cam.apply(corners_c)
    for c in corners_b:
        ax.plot(*np.column_stack([T_base_cam.t, c]), color="k", lw=1)
    loop = np.vstack([corners_b, corners_b[:1]])
    ax.plot(*loop.T, color="k", lw=1)
    _draw_axes(ax, T_base_cam, 0.6 * axis_len, lw=1.5)  # camera frame
    ax.text(*T_base_cam.t, " {C}", fontsize=9)
    uncertainty = draw_pose_uncertainty(ax, T_base_cam, base_cam_pose_covariance(result), extent, depth)
    # Mirror placements: translucent squares centred on the foot point v, perpendicular to v; beyond
    # MAX_PLACEMENTS_DRAWN per mirror a random sample of squares (every foot point is still a dot).
    counts = {l: sum(1 for k in mirrors if k[0] == l) for l, _ in mirrors}
    for (l, m), v in _sampled(mirrors, counts):
        n = T_base_cam.R @ (v / np.linalg.norm(v))
        a, b = _orthonormal_pair(n)
        f = feet[(l, m)]
        quad = [f + half_side * (sa * a + sb * b) for sa, sb in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        colour = _MIRROR_COLOURS[(l - 1) % len(_MIRROR_COLOURS)]
        alpha = float(np.clip(1.0 / counts[l], 0.02, 0.12))  # many placements must not fill the view
        edge = colour if counts[l] <= 20 else "none"
        ax.add_collection3d(Poly3DCollection([quad], facecolor=colour, edgecolor=edge, alpha=alpha, lw=0.5))
    for l in sorted({l for l, _ in mirrors}):
        colour = _MIRROR_COLOURS[(l - 1) % len(_MIRROR_COLOURS)]
        xyz = np.array([f for (k, _), f in feet.items() if k == l])
        ax.scatter(*xyz.T, c=colour, s=8 if len(xyz) <= 200 else 1, depthshade=False)
        drawn = "" if counts[l] <= MAX_PLACEMENTS_DRAWN else f", {MAX_PLACEMENTS_DRAWN} drawn, all as dots"
        ax.plot([], [], color=colour, lw=6, alpha=0.4, label=f"mirror {l} ({counts[l]} placements{drawn})")
    _draw_target(ax, fiducials, points)
    _set_equal_3d(ax, np.vstack([everything, corners_b]))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title("Scene in the base frame {B}")
    if uncertainty:  # a suptitle: the layout keeps room for it (a long 3D-axes title is clipped)
        fig.suptitle("\n".join(textwrap.wrap(uncertainty, 110)), fontsize=9)
    if ax.get_legend_handles_labels()[0]:  # a result without mirrors or target has nothing to label
        ax.legend(fontsize=7, loc="upper left")
    if target is not None:
        ax2 = fig.add_subplot(1, 2, 2, projection="3d")
        _draw_target(ax2, fiducials, points)
        span = float(np.max(np.ptp(target, axis=0))) if len(target) > 1 else 0.1
        _draw_axes(ax2, Transform.identity(), 0.15 * span, lw=2)
        _set_equal_3d(ax2, target, margin=0.15)
        ax2.set_xlabel("x (m)")
        ax2.set_ylabel("y (m)")
        ax2.set_zlabel("z (m)")
        has_ellipsoids = any(s3 is not None for _, s3 in points.values())
        ax2.set_title("Target close-up" + (" (3σ ellipsoids to scale)" if has_ellipsoids else ""))
    return fig


def _sampled(mirrors: dict[tuple[int, int], np.ndarray], counts: dict[int, int]) -> list[tuple[tuple[int, int], np.ndarray]]:
    """The placements to draw as squares: all, or MAX_PLACEMENTS_DRAWN per mirror (seeded, reproducible)."""
    rng = np.random.default_rng(0)
    out = []
    for l in sorted(counts):
        keys = [k for k in mirrors if k[0] == l]
        if len(keys) > MAX_PLACEMENTS_DRAWN:
            keys = [keys[i] for i in sorted(rng.choice(len(keys), MAX_PLACEMENTS_DRAWN, replace=False))]
        out += [(k, mirrors[k]) for k in keys]
    return out


def _nice_scale(factor: float) -> float:
    """The smallest of 1, 2, 5 x 10^n at least ``factor`` (1 when ``factor`` <= 1)."""
    if not factor > 1.0:
        return 1.0
    exponent = math.floor(math.log10(factor))
    return next(m * 10.0**e for e in (exponent, exponent + 1) for m in (1, 2, 5) if m * 10.0**e >= factor)


def draw_pose_uncertainty(ax: Any, T_base_cam: Transform, covariance: np.ndarray | None, extent: float,
                          length: float) -> str:
    """The camera's 3σ position ellipsoid and optical-axis cone on a 3D ``ax``, magnified to be seen.

    ``covariance``: 6x6 of ``T_base_cam`` (``[dtheta, dt]``, base axes, docs/formats.md) or None. The
    ellipsoid (semi-axes 3σ) is scaled to at least POSE_UNCERTAINTY_FRACTION of ``extent``; the cone
    around the optical axis (``length`` metres long, half-angles the 3σ of the axis direction) to at
    least CONE_MIN_DEG, each by a factor 1, 2, 5 x 10^n. Returns the label naming both factors.
    """
    if covariance is None or not np.all(np.isfinite(covariance)):
        return ""
    c = T_base_cam.t
    values, vectors = np.linalg.eigh(covariance[3:, 3:])
    semi = 3.0 * np.sqrt(np.clip(values, 0.0, None))
    k_pos = _nice_scale(POSE_UNCERTAINTY_FRACTION * extent / max(float(semi.max()), 1e-12))
    u, v = np.meshgrid(np.linspace(0, 2 * math.pi, 17), np.linspace(0, math.pi, 9))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    e = c[:, None, None] + k_pos * np.einsum("ij,jkl->ikl", vectors * semi, unit)
    ax.plot_wireframe(e[0], e[1], e[2], color="tab:cyan", lw=0.6, alpha=0.9,
                      label=f"camera position 3σ ellipsoid × {k_pos:g}")
    # The optical axis a moves by dphi x a: its direction covariance is [a]x S [a]x^T (rank 2).
    a = T_base_cam.R[:, 2]
    ax_skew = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    values, vectors = np.linalg.eigh(ax_skew @ covariance[:3, :3] @ ax_skew.T)
    half = 3.0 * np.sqrt(np.clip(values[1:], 0.0, None))  # the two directions across the axis, radians
    k_rot = _nice_scale(math.radians(CONE_MIN_DEG) / max(float(half.max()), 1e-12))
    phi = np.linspace(0.0, 2.0 * math.pi, 37)
    spread = np.tan(np.clip(k_rot * half, 0.0, math.radians(80.0)))
    rim = c + length * (a[None] + np.outer(spread[0] * np.cos(phi), vectors[:, 1])
                        + np.outer(spread[1] * np.sin(phi), vectors[:, 2]))
    ax.plot(*rim.T, color="tab:red", lw=1, label=f"optical-axis 3σ cone × {k_rot:g}")
    for point in rim[:-1:9]:
        ax.plot(*np.column_stack([c, point]), color="tab:red", lw=0.7)
    ax.plot(*np.column_stack([c, c + length * a]), color="tab:red", lw=0.7, ls=":")
    return (f"camera position 3σ semi-axes {_fmt_list(1e3 * semi)} mm (ellipsoid drawn × {k_pos:g}); "
            f"optical axis 3σ {_fmt_list(np.degrees(half))}° (cone drawn × {k_rot:g})")


def _fmt_list(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{float(x):.3g}" for x in values) + "]"


def figure_correlation(result: Mapping[str, Any]) -> Figure | None:
    """Correlation matrix of ``covariance_cam_base`` ([rx, ry, rz, x, y, z], docs/formats.md convention)."""
    P = pose_covariance(result)
    if P is None:
        return None
    fig = new_figure(6.0, 5.2)
    ax = fig.add_subplot()
    im = draw_correlation(ax, correlation(P), COVARIANCE_LABELS, fontsize=8)
    ax.set_title("Correlation of T_cam_base\n(rotation about camera axes, translation)")
    fig.colorbar(im, ax=ax, shrink=0.8)
    return fig


def correlation(covariance: np.ndarray) -> np.ndarray:
    """Correlation matrix of a covariance (a zero variance is treated as 1e-300)."""
    sd = np.sqrt(np.clip(np.diag(covariance), 1e-300, None))
    return covariance / np.outer(sd, sd)


def draw_correlation(ax: Any, rho: np.ndarray, labels: Sequence[str], fontsize: float) -> Any:
    """A correlation matrix on ``ax`` (blue -1 .. red +1) with its values written in; returns the image."""
    image = ax.imshow(rho, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    for i in range(len(rho)):
        for j in range(len(rho)):
            ax.text(j, i, f"{rho[i, j]:.2f}", ha="center", va="center", fontsize=fontsize,
                    color="white" if abs(rho[i, j]) > 0.6 else "black")
    ax.set_xticks(range(len(rho)), labels)
    ax.set_yticks(range(len(rho)), labels)
    return image


def png(fig: Figure, dpi: int = PNG_DPI) -> bytes:
    """The figure as PNG bytes at ``dpi``."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
