"""The report on general data (docs/formats.md "Views of any reflection order, and several cameras"): the
residuals of every view, grouped by reflection order and by camera, and what ties cameras and placements.

A *view* is an image's camera and its ``reflections`` (the placements ``(mirror, config)`` the light meets
from the points to the camera; ``()`` a direct view). A base point ``Bp`` is predicted at
``project(F_k(... F_1(R_c Bp + t_c)))`` (Hesch et al., eqs. 2, 3, 9), each placement's plane carried from
its owner camera's frame (``mirrors[].camera``, the first camera without ``cameras``) into the viewing
camera's (:func:`mirror_fg.factors.views.view_model`), then distorted with that camera's intrinsics (the
result's estimated ones where it has them). Residuals ``predicted - observed`` in pixels (normalized image
coordinates without a camera); "RMS" is the root mean square of the Euclidean residual lengths, as
result@1's ``rms_px``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.result import estimated_camera, mirror_vectors, pose, transforms
from mirror_fg.io.result import points as reconstruction_points
from mirror_fg.report.figures import new_figure
from mirror_fg.report.residuals import Residuals

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from mirror_fg.data import Dataset

__all__ = [
    "ViewResiduals", "GroupStats", "view_residuals", "order_name", "order_stats", "camera_stats",
    "placement_ties", "figure_orders", "figure_cameras", "result_camera_names", "result_camera_poses",
    "mirror_owners", "camera_intrinsics", "MAX_CAMERA_PANELS",
]

#: Cameras drawn one panel each in the per-camera figure (the rest are in its table).
MAX_CAMERA_PANELS = 6
_ORDER_NAMES = ("direct", "first-order", "second-order", "third-order")


@dataclass
class ViewResiduals(Residuals):
    """:class:`~mirror_fg.report.residuals.Residuals` with each measurement's view: ``cameras`` (the camera
    name, None in a one-camera dataset), ``reflections`` (its image's placements in order) and ``centres``
    (N, 2) the principal point of its camera (the radial profile's centre; zeros for normalized data)."""

    cameras: list[str | None] = field(default_factory=list)
    reflections: list[tuple[tuple[int, int], ...]] = field(default_factory=list)
    centres: np.ndarray | None = None

    @property
    def orders(self) -> np.ndarray:
        """(N,) the reflection order of each measurement's view (0 = direct)."""
        return np.array([len(r) for r in self.reflections], dtype=int)

    def radial_profile(self, centre: Any = (0.0, 0.0), bins: int = 6) -> Any:
        """As :meth:`Residuals.radial_profile`, each measurement measured from its own camera's centre
        (``centre`` is used only without per-measurement centres)."""
        if self.centres is not None:
            centre = self.centres[self.valid]
        return super().radial_profile(centre, bins)


# --------------------------------------------------------------------------------------------------
# What the result says about the cameras
# --------------------------------------------------------------------------------------------------


def result_camera_names(result: Mapping[str, Any], dataset: Dataset | None) -> list[str | None]:
    """The cameras in order: the result's ``cameras``, else the dataset's (only the first has a pose then),
    else ``[None]`` (one camera, unnamed)."""
    if result.get("cameras"):
        return list(result["cameras"])
    if dataset is not None and dataset.cameras:
        return list(dataset.cameras)
    return [None]


def result_camera_poses(result: Mapping[str, Any], dataset: Dataset | None) -> dict[str | None, tuple[np.ndarray, np.ndarray]]:
    """``{camera: (R_cam_base, t_cam_base)}`` of every camera the result gives a pose (the first camera's is
    the top-level ``T_cam_base`` when the result has no ``cameras``)."""
    if result.get("cameras"):
        return {name: pose(entry["T_cam_base"]) for name, entry in result["cameras"].items()}
    return {result_camera_names(result, dataset)[0]: transforms(result)[0]}


def mirror_owners(result: Mapping[str, Any], dataset: Dataset | None) -> dict[tuple[int, int], str | None]:
    """``{placement: camera}``: the frame each mirror vector is in (``mirrors[].camera``, else the first camera)."""
    first = result_camera_names(result, dataset)[0]
    return {(e["mirror"], e["config"]): e.get("camera") or first for e in result.get("mirrors") or []}


def camera_intrinsics(result: Mapping[str, Any], dataset: Dataset, name: str | None, source: str) -> Any:
    """The intrinsics a camera's predictions are distorted with: the result's estimate for it (its
    ``cameras[name].camera`` block with ``estimated`` terms, or the top-level ``camera`` for the first
    camera), else the dataset's; None for normalized data."""
    declared = (dataset.cameras or {}).get(name) if name is not None else dataset.camera
    declared = declared if declared is not None else dataset.camera
    if declared is None:
        return None
    entry = ((result.get("cameras") or {}).get(name) or {}) if name is not None else {}
    block = entry.get("camera")
    if block is not None and block.get("estimated"):
        return estimated_camera({"camera": block}, f"{source}: cameras.{name}", declared)
    first = result_camera_names(result, dataset)[0]
    if name == first and result.get("camera") is not None and not result.get("cameras"):
        return estimated_camera(result, source, declared)
    return declared


# --------------------------------------------------------------------------------------------------
# Residuals of every view
# --------------------------------------------------------------------------------------------------


def view_residuals(result: Mapping[str, Any], dataset: Dataset, source: str) -> tuple[ViewResiduals, list[str]]:
    """Residuals of every measurement of a validated ``result`` on a general ``dataset`` (module
    docstring), in dataset order, and notes on what was left out (images of a camera the result has no
    pose for). DatasetError naming ``source`` and the dataset when the dataset is not the result's (a
    placement or point the result lacks)."""
    from mirror_fg.factors.views import view_model

    poses = result_camera_poses(result, dataset)
    owners = mirror_owners(result, dataset)
    vectors = mirror_vectors(result)
    points = {name: xyz for name, (xyz, _) in reconstruction_points(result).items()}
    mismatch = f"{source} does not belong to {dataset.source}"
    first = result_camera_names(result, dataset)[0]
    units = "px" if dataset.camera is not None or dataset.cameras else "normalized"
    rows: dict[str, list[Any]] = {k: [] for k in ("image", "name", "fid", "pred", "obs", "cam", "refl", "centre")}
    skipped: dict[str | None, int] = {}
    intrinsics: dict[str | None, Any] = {}
    for image in dataset.images:
        camera = image.camera if image.camera is not None else first
        if camera not in poses:
            skipped[camera] = skipped.get(camera, 0) + 1
            continue
        for placement in image.reflections:
            if placement not in vectors or owners.get(placement) not in poses:
                raise DatasetError(f"{mismatch}: image {image.id!r} sees mirror {placement[0]} configuration "
                                   f"{placement[1]}, which the result has no mirror vector for")
        names = list(image.observations)
        if not names:
            continue
        base = []
        for name in names:
            if name in dataset.fiducials:
                base.append(dataset.fiducials[name])
            elif name in points:
                base.append(points[name])
            else:
                raise DatasetError(f"{mismatch}: image {image.id!r} observes {name!r}, which is neither a "
                                   "fiducial nor a point of the result")
        B = np.array(base, dtype=float).reshape(-1, 3).T
        z = _predict(view_model, camera, image.reflections, poses, vectors, owners, B)
        if camera not in intrinsics:
            intrinsics[camera] = camera_intrinsics(result, dataset, camera, source)
        cam = intrinsics[camera]
        if cam is not None:
            ok = np.all(np.isfinite(z), axis=1)
            pixels = np.full_like(z, np.nan)
            if np.any(ok):
                pixels[ok] = cam.distort(z[ok])
            z = pixels
        centre = (cam.cx, cam.cy) if cam is not None else (0.0, 0.0)
        for k, name in enumerate(names):
            rows["image"].append(image.id)
            rows["name"].append(name)
            rows["fid"].append(name in dataset.fiducials)
            rows["pred"].append(z[k])
            rows["obs"].append(np.asarray(image.observations[name], dtype=float))
            rows["cam"].append(image.camera)
            rows["refl"].append(tuple(image.reflections))
            rows["centre"].append(centre)
    notes = [f"The result holds no pose for camera {c!r} (no cameras: block for it): its {n} image(s) are left "
             "out of the residuals." for c, n in skipped.items()]
    residuals = ViewResiduals(
        units=units, image_ids=rows["image"], names=rows["name"], is_fiducial=np.array(rows["fid"], dtype=bool),
        predicted=np.array(rows["pred"], dtype=float).reshape(-1, 2),
        observed=np.array(rows["obs"], dtype=float).reshape(-1, 2), sigma=float(dataset.pixel_sigma),
        cameras=rows["cam"], reflections=rows["refl"], centres=np.array(rows["centre"], dtype=float).reshape(-1, 2))
    return residuals, notes


def _predict(view_model: Any, camera: str | None, reflections: tuple, poses: dict, vectors: dict, owners: dict,
             B: np.ndarray) -> np.ndarray:
    """(N, 2) normalized predictions of base points ``B`` (3, N) in one view; NaN where the point lies
    behind the camera (or behind a mirror it must be seen through)."""
    z = view_model(camera, reflections, poses, vectors, owners, B)[0].T
    # The depth in front of the camera: the last reflected point's z (eq. 9 needs z > 0).
    R_c, t_c = poses[camera]
    x = R_c @ B + t_c[:, None]  # eq. (2)
    for placement in reflections:
        v = _in_camera(vectors[placement], camera, owners[placement], poses)
        x = x - 2.0 * v[:, None] * ((v @ x) / (v @ v) - 1.0)[None, :]  # eq. (3): M x + 2 v
    z = np.array(z, dtype=float)
    z[x[2] <= 0.0] = np.nan
    return z


def _in_camera(v_owner: np.ndarray, camera: Any, owner: Any, poses: dict) -> np.ndarray:
    """A mirror vector of the owner camera's frame in ``camera``'s frame (the plane carried over)."""
    from mirror_fg.factors.views import transfer_mirror_vector

    if owner == camera:
        return np.asarray(v_owner, dtype=float)
    return transfer_mirror_vector(np.asarray(v_owner, dtype=float), poses[camera], poses[owner])[0]


# --------------------------------------------------------------------------------------------------
# Groups: reflection order, camera; placements and the cameras they tie
# --------------------------------------------------------------------------------------------------


def order_name(order: int) -> str:
    """``direct``, ``first-order``, ``second-order``, ``third-order``, ``4th-order``, ..."""
    return _ORDER_NAMES[order] if order < len(_ORDER_NAMES) else f"{order}th-order"


@dataclass
class GroupStats:
    """Residual statistics of a group of measurements: ``label``, ``images`` (views), ``count``
    (measurements with a prediction), ``rms`` (as result@1's ``rms_px``) and ``largest`` length."""

    label: str
    images: int
    count: int
    rms: float
    largest: float
    lengths: np.ndarray


def _group(residuals: Residuals, selected: np.ndarray, label: str) -> GroupStats:
    ok = selected & residuals.valid
    lengths = np.linalg.norm(residuals.residual[ok], axis=1)
    images = len({residuals.image_ids[i] for i in np.flatnonzero(selected)})
    rms = float(np.sqrt(np.mean(lengths**2))) if lengths.size else float("nan")
    return GroupStats(label, images, int(lengths.size), rms, float(lengths.max()) if lengths.size else float("nan"),
                      lengths)


def order_stats(residuals: ViewResiduals) -> dict[int, GroupStats]:
    """``{order: statistics}`` of the measurements of each reflection order present, ascending."""
    orders = residuals.orders
    return {int(k): _group(residuals, orders == k, order_name(int(k))) for k in sorted(set(orders.tolist()))}


def camera_stats(residuals: ViewResiduals) -> dict[str | None, GroupStats]:
    """``{camera: statistics}`` in first-seen order."""
    cams = residuals.cameras
    return {c: _group(residuals, np.array([x == c for x in cams], dtype=bool), str(c)) for c in dict.fromkeys(cams)}


def placement_ties(dataset: Dataset) -> dict[tuple[int, int], dict[str | None, int]]:
    """``{placement: {camera: views of it}}`` over the dataset's images, placements sorted, cameras in the
    dataset's order: a placement seen by two cameras ties their poses together."""
    order = list(dataset.cameras or [None])
    ties: dict[tuple[int, int], dict[str | None, int]] = {}
    for image in dataset.images:
        for placement in dict.fromkeys(image.reflections):
            seen = ties.setdefault(placement, {})
            seen[image.camera] = seen.get(image.camera, 0) + 1
    return {p: dict(sorted(ties[p].items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))
            for p in sorted(ties)}


# --------------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------------


def _rayleigh_cdf(r: np.ndarray, sigma: float) -> np.ndarray:
    """P(|e| <= r) for e ~ N(0, sigma^2 I_2): the residual length's distribution under the noise model."""
    return 1.0 - np.exp(-0.5 * (r / sigma) ** 2)


def figure_orders(residuals: ViewResiduals) -> Figure:
    """Residuals by reflection order: RMS and largest length per order (bars, with counts), and each
    order's distribution of residual lengths against the noise model's (Rayleigh, sigma = pixel_sigma)."""
    stats = order_stats(residuals)
    fig = new_figure(11.0, 4.6)
    bars, cdf = fig.subplots(1, 2, width_ratios=(1.0, 1.4))
    x = np.arange(len(stats))
    colours = [f"C{k % 10}" for k in stats]
    rms = np.array([s.rms for s in stats.values()])
    largest = np.array([s.largest for s in stats.values()])
    bars.bar(x, rms, color=colours, width=0.6, label="RMS")
    bars.scatter(x, largest, marker="v", c="k", zorder=3, label="largest")
    for position, s in zip(x, stats.values()):
        bars.annotate(f"n={s.count}\n{s.images} view(s)", (position, s.rms), textcoords="offset points", xytext=(0, 4),
                      ha="center", fontsize=7)
    bars.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    bars.set_xticks(x, [f"{s.label}\n({k} mirror{'s' if k != 1 else ''})" for k, s in stats.items()], fontsize=8)
    top = float(np.nanmax(np.concatenate([largest, [residuals.expected_rms]])))
    bars.set_ylim(0.0, 1.25 * top if top > 0 else 1.0)
    bars.set_ylabel(f"reprojection error length, {residuals.units}")
    bars.set_title("RMS and largest residual by reflection order", fontsize=10)
    bars.legend(fontsize=7, loc="upper left")
    upper = max(float(np.nanmax(largest)) if largest.size else 0.0, 4.0 * residuals.sigma, 1e-12)
    r = np.linspace(0.0, upper, 200)
    if residuals.sigma > 0:
        cdf.plot(r, _rayleigh_cdf(r, residuals.sigma), "k--", lw=1.5, label=f"noise model (σ = {residuals.sigma:.3g})")
    for (k, s), colour in zip(stats.items(), colours):
        if s.count:
            lengths = np.sort(s.lengths)
            cdf.step(lengths, np.arange(1, len(lengths) + 1) / len(lengths), where="post", color=colour, lw=1.5,
                     label=f"{s.label}: RMS {s.rms:.3g}, n={s.count}")
    cdf.set_xlim(0.0, upper)
    cdf.set_ylim(0.0, 1.02)
    cdf.set_xlabel(f"reprojection error length, {residuals.units}")
    cdf.set_ylabel("fraction of measurements at most this long")
    cdf.set_title("Distribution of residual lengths by reflection order", fontsize=10)
    cdf.legend(fontsize=7, loc="lower right")
    return fig


def figure_cameras(residuals: ViewResiduals) -> Figure:
    """Residuals per camera: the RMS of each camera (bars), and each camera's residual vectors with the
    3σ circle (a panel each, the first MAX_CAMERA_PANELS cameras)."""
    stats = camera_stats(residuals)
    shown = list(stats)[:MAX_CAMERA_PANELS]
    fig = new_figure(11.0, 7.5)
    grid = fig.add_gridspec(2, max(len(shown), 2))
    bars = fig.add_subplot(grid[0, :])
    x = np.arange(len(stats))
    bars.bar(x, [s.rms for s in stats.values()], color=[f"C{k % 10}" for k in range(len(stats))], width=0.6)
    for position, s in zip(x, stats.values()):
        bars.annotate(f"RMS {s.rms:.3g}, largest {s.largest:.3g}\nn={s.count}, {s.images} image(s)", (position, s.rms),
                      textcoords="offset points", xytext=(0, 3), ha="center", fontsize=7)
    bars.axhline(residuals.expected_rms, color="tab:green", lw=1, label=f"expected √2·σ = {residuals.expected_rms:.3g}")
    bars.set_xticks(x, [s.label for s in stats.values()])
    top = max([s.rms for s in stats.values() if math.isfinite(s.rms)] + [residuals.expected_rms])
    bars.set_ylim(0.0, 1.4 * top if top > 0 else 1.0)
    bars.set_ylabel(f"RMS residual, {residuals.units}")
    bars.set_title("RMS reprojection error of each camera", fontsize=10)
    bars.legend(fontsize=7, loc="upper right")
    angles = np.linspace(0.0, 2.0 * math.pi, 200)
    valid = residuals.valid
    r_all = residuals.residual[valid]
    lim = max(float(np.max(np.abs(r_all))) if r_all.size else 0.0, 3.2 * residuals.sigma, 1e-12) * 1.05
    for k, name in enumerate(shown):
        ax = fig.add_subplot(grid[1, k])
        sel = valid & np.array([c == name for c in residuals.cameras], dtype=bool)
        r = residuals.residual[sel]
        orders = residuals.orders[sel]
        for order in sorted(set(orders.tolist())):
            ax.scatter(r[orders == order, 0], r[orders == order, 1], s=5, c=f"C{order % 10}", label=order_name(order))
        ax.plot(3 * residuals.sigma * np.cos(angles), 3 * residuals.sigma * np.sin(angles), "g--", lw=1, label="3σ")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(f"x residual, {residuals.units}", fontsize=8)
        if k == 0:
            ax.set_ylabel(f"y residual, {residuals.units}", fontsize=8)
        ax.set_title(f"{name}: RMS {stats[name].rms:.3g}", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="upper right")
    return fig
