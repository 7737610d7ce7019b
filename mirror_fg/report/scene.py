"""The 3D scene of a general result (docs/formats.md "Views of any reflection order, and several cameras"),
drawn in the base frame {B}, metres: every camera's frustum and 3σ position ellipsoid, every mirror
placement once (a placement seen in many views, or by several cameras, is one plane), the fiducials and
reconstruction points, and which placements each camera saw.

A placement's mirror vector ``v`` is in its owner camera's frame (``mirrors[].camera``; the first camera
without ``cameras``): the plane ``n . y = |v|``, ``n = v / |v|``, whose foot point ``v`` is at
``T_base_owner v`` in {B} (Hesch et al., eq. 1). A camera's position covariance is the translation block of
its ``covariance_base_cam`` (``[dtheta, dt]``, base axes, docs/formats.md).
"""
from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np

from mirror_fg.core.transform import Transform
from mirror_fg.io.result import base_cam_covariance, base_cam_pose_covariance, mirror_vectors
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.report.figures import (
    MAX_PLACEMENTS_DRAWN,
    POSE_UNCERTAINTY_FRACTION,
    _draw_axes,
    _draw_target,
    _nice_scale,
    _orthonormal_pair,
    _set_equal_3d,
    new_figure,
)
from mirror_fg.report.views import mirror_owners, placement_ties, result_camera_names, result_camera_poses

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.data import Dataset

__all__ = ["figure_views_scene", "camera_position_covariances", "pose_is_estimated", "MAX_PLACEMENT_LABELS"]

#: Placements named one by one in the legend up to this many (beyond it, one entry per mirror).
MAX_PLACEMENT_LABELS = 10
#: Sight lines camera -> placement drawn up to this many placements.
MAX_SIGHT_LINES = 60
_MIRROR_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def pose_is_estimated(covariance: np.ndarray | None) -> TypeGuard[np.ndarray]:
    """A pose covariance that says something: present, finite and not all zero (a fixed pose, e.g. the
    base frame's camera without a known target, has a zero one)."""
    return covariance is not None and bool(np.all(np.isfinite(covariance))) and bool(np.any(covariance != 0.0))


def camera_position_covariances(result: Mapping[str, Any], dataset: Dataset | None) -> dict[Any, np.ndarray | None]:
    """``{camera: 3x3 covariance of its position in {B}}`` (m^2), None where the pose is not estimated."""
    out: dict[Any, np.ndarray | None] = {}
    if result.get("cameras"):
        for name, entry in result["cameras"].items():
            P = entry.get("covariance_base_cam")
            if P is None and entry.get("covariance_cam_base") is not None:
                R, t = (np.array(entry["T_cam_base"][k], dtype=float) for k in ("R", "t"))
                P = base_cam_covariance(R, t, np.array(entry["covariance_cam_base"], dtype=float))
            P = None if P is None else np.array(P, dtype=float)
            out[name] = P[3:, 3:] if pose_is_estimated(P) else None
        return out
    P = base_cam_pose_covariance(result)
    out[result_camera_names(result, dataset)[0]] = P[3:, 3:] if pose_is_estimated(P) else None
    return out


def _corners(camera: Any) -> np.ndarray:
    """Normalized coordinates (4, 2) of a camera's image corners (90 x 70 degrees without one)."""
    if camera is None:
        return np.array([[-1.0, -0.7], [1.0, -0.7], [1.0, 0.7], [-1.0, 0.7]])
    px = np.array([[0.0, 0.0], [camera.width, 0.0], [camera.width, camera.height], [0.0, camera.height]])
    return np.column_stack([(px[:, 0] - camera.cx) / camera.fx, (px[:, 1] - camera.cy) / camera.fy])


def _ellipsoid(centre: np.ndarray, covariance: np.ndarray, factor: float) -> np.ndarray:
    """(3, 9, 17) wireframe of the 3σ ellipsoid of ``covariance`` about ``centre``, magnified ``factor``."""
    values, vectors = np.linalg.eigh(covariance)
    semi = 3.0 * np.sqrt(np.clip(values, 0.0, None))
    u, v = np.meshgrid(np.linspace(0, 2 * math.pi, 17), np.linspace(0, math.pi, 9))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    return centre[:, None, None] + factor * np.einsum("ij,jkl->ikl", vectors * semi, unit)


@dataclass
class _Scene:
    """What the scene draws, in {B}: camera poses ``T_base_cam``, their intrinsics and 3x3 position
    covariances (None: not estimated), each placement's foot point and unit normal, who saw it, the target."""

    names: list[Any]
    base_cam: dict[Any, Transform]
    intrinsics: dict[Any, Any]
    covariances: dict[Any, np.ndarray | None]
    feet: dict[tuple[int, int], np.ndarray]
    normals: dict[tuple[int, int], np.ndarray]
    ties: dict[tuple[int, int], dict[Any, int]]
    half_side: float
    fiducials: np.ndarray
    points: dict[str, tuple[np.ndarray, np.ndarray | None]]


def _scene(result: Mapping[str, Any], dataset: Dataset | None) -> _Scene:
    names = result_camera_names(result, dataset)
    poses = result_camera_poses(result, dataset)
    base_cam = {c: Transform(R, t).inverse() for c, (R, t) in poses.items()}
    owners = mirror_owners(result, dataset)
    vectors = mirror_vectors(result)
    feet = {p: base_cam[owners[p]].apply(v) for p, v in vectors.items() if owners.get(p) in base_cam}  # eq. (1)
    intrinsics = {}
    for name in names:
        camera = (dataset.cameras or {}).get(name) if dataset is not None and name is not None else None
        intrinsics[name] = camera if camera is not None or dataset is None else dataset.camera
    distances = [float(np.linalg.norm(v)) for v in vectors.values()]
    return _Scene(
        names=[n for n in names if n in base_cam], base_cam=base_cam, intrinsics=intrinsics,
        covariances=camera_position_covariances(result, dataset), feet=feet,
        normals={p: base_cam[owners[p]].R @ (vectors[p] / np.linalg.norm(vectors[p])) for p in feet},
        ties=placement_ties(dataset) if dataset is not None else {},
        half_side=0.3 * float(np.median(distances)) if distances else 0.05,
        fiducials=np.array(list(dataset.fiducials.values())).reshape(-1, 3) if dataset is not None else np.zeros((0, 3)),
        points=reconstruction_points(result))


def _target(scene: _Scene) -> np.ndarray | None:
    parts = [scene.fiducials, *[p[None] for p, _ in scene.points.values()]]
    return np.vstack(parts) if (len(scene.fiducials) or scene.points) else None


def _draw(ax: Any, scene: _Scene, with_target: bool) -> str:
    """One panel: cameras, placements (and the target); returns what the ellipsoids' magnification is."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    target = _target(scene) if with_target else None
    centres = np.array([scene.base_cam[n].t for n in scene.names]).reshape(-1, 3)
    everything = np.vstack([np.zeros((1, 3)) if with_target else centres[:1], centres,
                            *(f[None] for f in scene.feet.values())] + ([target] if target is not None else []))
    extent = float(np.max(np.ptp(everything, axis=0))) or 1.0
    depth = 0.15 * extent
    if with_target:
        _draw_axes(ax, Transform.identity(), 0.12 * extent, lw=2)
        ax.text(0, 0, 0, " {B}", fontsize=9)
    semis = [3.0 * math.sqrt(max(float(np.linalg.eigvalsh(P).max()), 0.0))
             for n, P in scene.covariances.items() if P is not None and n in scene.base_cam]
    factor = _nice_scale(POSE_UNCERTAINTY_FRACTION * extent / max(max(semis), 1e-12)) if semis else 1.0
    drawn = [everything]
    for k, name in enumerate(scene.names):
        T = scene.base_cam[name]
        colour = f"C{k % 10}"
        corners = T.apply(np.column_stack([_corners(scene.intrinsics.get(name)) * depth, np.full(4, depth)]))
        drawn.append(corners)
        for c in corners:
            ax.plot(*np.column_stack([T.t, c]), color=colour, lw=1)
        ax.plot(*np.vstack([corners, corners[:1]]).T, color=colour, lw=1.2,
                label=f"camera {name}" if name is not None else "camera")
        _draw_axes(ax, T, 0.07 * extent, lw=1.2)
        ax.text(*T.t, f" {name}" if name is not None else " {C}", fontsize=8, color=colour)
        P = scene.covariances.get(name)
        if P is not None:
            e = _ellipsoid(T.t, P, factor)
            ax.plot_wireframe(e[0], e[1], e[2], color=colour, lw=0.5, alpha=0.8)
        for p in scene.feet if len(scene.feet) <= MAX_SIGHT_LINES else ():
            if scene.ties.get(p, {}).get(name):
                ax.plot(*np.column_stack([T.t, scene.feet[p]]), color=colour, lw=0.6, ls=":", alpha=0.9)
    per_mirror: dict[int, int] = {}
    for p in scene.feet:
        per_mirror[p[0]] = per_mirror.get(p[0], 0) + 1
    labelled: set[Any] = set()
    for p in _drawn_squares(scene):
        f = scene.feet[p]
        a, b = _orthonormal_pair(scene.normals[p])
        quad = [f + scene.half_side * (sa * a + sb * b) for sa, sb in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        colour = _MIRROR_COLOURS[(p[0] - 1) % len(_MIRROR_COLOURS)]
        shared = len(scene.ties.get(p, {})) > 1
        alpha = float(np.clip(1.0 / per_mirror[p[0]], 0.05, 0.3))
        ax.add_collection3d(Poly3DCollection([quad], facecolor=colour, alpha=alpha, lw=1.2 if shared else 0.5,
                                             edgecolor="k" if shared else colour))
        key = p if len(scene.feet) <= MAX_PLACEMENT_LABELS else p[0]
        if key not in labelled:
            labelled.add(key)
            seen = ", ".join(f"{c}" for c in scene.ties.get(p, {}) if c is not None)
            text = (f"mirror {p[0]} config {p[1]}" + (f" (seen by {seen})" if seen else "")
                    if key == p else f"mirror {p[0]} ({per_mirror[p[0]]} placements)")
            ax.plot([], [], color=colour, lw=6, alpha=0.4, label=text)
    for l in sorted(per_mirror):
        xyz = np.array([f for p, f in scene.feet.items() if p[0] == l])
        ax.scatter(*xyz.T, color=_MIRROR_COLOURS[(l - 1) % len(_MIRROR_COLOURS)], s=10 if len(xyz) <= 200 else 2,
                   depthshade=False)
    if any(n > MAX_PLACEMENTS_DRAWN for n in per_mirror.values()):
        ax.plot([], [], ls="none", marker=".", color="k",
                label=f"beyond {MAX_PLACEMENTS_DRAWN} placements of a mirror: a sample as squares, all as dots")
    if any(len(t) > 1 for t in scene.ties.values()):
        ax.plot([], [], color="k", lw=1.2, label="black edge: seen by several cameras")
    if with_target:
        _draw_target(ax, scene.fiducials, scene.points)
    _set_equal_3d(ax, np.vstack(drawn), margin=0.05 if with_target else 0.25)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    return f"3σ position ellipsoids × {factor:g}" if semis else ""


def _drawn_squares(scene: _Scene) -> list[tuple[int, int]]:
    """The placements drawn as squares: all, or MAX_PLACEMENTS_DRAWN per mirror, those seen by several
    cameras first, the rest a seeded sample (every foot point is still drawn as a dot)."""
    rng = np.random.default_rng(0)
    out: list[tuple[int, int]] = []
    for l in sorted({p[0] for p in scene.feet}):
        keys = [p for p in scene.feet if p[0] == l]
        if len(keys) > MAX_PLACEMENTS_DRAWN:
            shared = [p for p in keys if len(scene.ties.get(p, {})) > 1][:MAX_PLACEMENTS_DRAWN]
            rest = [p for p in keys if p not in set(shared)]
            extra = MAX_PLACEMENTS_DRAWN - len(shared)
            keys = shared + [rest[i] for i in sorted(rng.choice(len(rest), extra, replace=False))] if extra else shared
        out += keys
    return out


def figure_views_scene(result: Mapping[str, Any], dataset: Dataset | None) -> Figure:
    """The scene in {B} (module docstring): cameras (frusta, axes, 3σ position ellipsoids magnified by one
    common factor per panel), each placement once as a square on its plane centred on its foot point
    (black edge: seen by several cameras), dotted lines from each camera to the placements it saw,
    fiducials and points; beside it a close-up of the cameras and mirrors without the target."""
    scene = _scene(result, dataset)
    fig = new_figure(12.0, 6.8)
    close_up = bool(scene.feet) and _target(scene) is not None
    ax = fig.add_subplot(1, 2 if close_up else 1, 1, projection="3d")
    magnified = _draw(ax, scene, with_target=True)
    first = result_camera_names(result, dataset)[0]
    frame = ("" if dataset is None or dataset.fiducials else
             f" = the frame of camera {first}" if first is not None else " = the camera's frame")
    ax.set_title(f"Scene in the base frame {{B}}{frame}" + (f"\n({magnified})" if magnified else ""), fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    if close_up:
        ax2 = fig.add_subplot(1, 2, 2, projection="3d")
        magnified = _draw(ax2, scene, with_target=False)
        ax2.set_title(f"Close-up of the camera{'s' if len(scene.names) > 1 else ''} and mirrors" + (f"\n({magnified})" if magnified else ""), fontsize=10)
    notes = []
    semis = [3e3 * math.sqrt(max(float(np.linalg.eigvalsh(P).max()), 0.0)) for P in scene.covariances.values()
             if P is not None]
    if semis:
        notes.append(f"largest 3σ camera position semi-axis {max(semis):.3g} mm")
    fixed = [n for n in scene.names if scene.covariances.get(n) is None]
    if fixed:
        notes.append("pose not estimated (no ellipsoid): " + ", ".join("the camera" if n is None else str(n) for n in fixed)
                     + (" (the base frame)" if dataset is not None and not dataset.fiducials else ""))
    if notes:
        fig.suptitle("\n".join(textwrap.wrap("; ".join(notes), 120)), fontsize=9)
    return fig
