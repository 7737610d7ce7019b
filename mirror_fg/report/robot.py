"""The report of a robot arm's calibration (docs/formats.md, "Robot arms: joint states and mounts"): its
residuals through the view model with forward kinematics, and the arm drawn at its poses with the camera,
the mirrors and the target.

Frames: {B} the base link, metres. The result's mounts (``mounts``, else the dataset's known ones), mirror
vectors in {B} and joint offsets (degrees, or millimetres for a prismatic joint) give the prediction.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.data import Dataset
from mirror_fg.report.figures import new_figure
from mirror_fg.report.residuals import Residuals

__all__ = ["robot_residuals", "figure_arm", "ARM_POSES_DRAWN"]

#: Arm poses drawn at most (evenly spread over the images).
ARM_POSES_DRAWN = 12


def _estimate(result: Mapping[str, Any], dataset: Dataset, source: str):
    from mirror_fg.io.result import mirror_vectors
    from mirror_fg.io.robot_fields import pose_from_dict
    from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem, camera_name, is_camera, mount_words

    problem = RobotProblem(dataset)
    mounts = dict(problem.known)
    given = result.get("mounts") or {}
    for role in problem.mount_keys:
        name = camera_name(role)
        entry = given.get(role) if name is None else (given.get("cameras") or {}).get(name)
        where = f"mounts.{role}" if name is None else f"mounts.cameras.{name}"
        if entry is None:
            raise DatasetError(f"{source} has no {mount_words(role)} for {dataset.source} ({where})")
        key = "T_link_cam" if is_camera(role) else "T_link_target"
        mounts[role] = pose_from_dict(entry.get(key) if isinstance(entry, Mapping) else entry, f"{source}: {where}.{key}")
    vectors = {p: v for p, v in mirror_vectors(result).items()}
    missing = [p for p in problem.placements if p not in vectors]
    if missing:
        raise DatasetError(f"{source} does not belong to {dataset.source}: no mirror {missing[0][0]} placement "
                           f"{missing[0][1]}")
    offsets = []
    for name in problem.offsets:
        entry = (result.get("joint_offsets") or {}).get(name, {})
        offsets.append(math.radians(entry["offset_deg"]) if "offset_deg" in entry else entry.get("offset_mm", 0.0) / 1000)
    points = {n: np.array(e["xyz"], float) for n, e in (result.get("points") or {}).items()}
    estimate = RobotEstimate(mounts, vectors, {n: points[n] for n in problem.point_names if n in points},
                             np.array(offsets, float))
    return problem, estimate


def robot_residuals(result: Mapping[str, Any], dataset: Dataset, source: str) -> Residuals:
    """Residuals (pixels with a camera) of every measurement, in dataset order."""
    problem, estimate = _estimate(result, dataset, source)
    values = problem.values(estimate)
    image_ids: list[str] = []
    names: list[str] = []
    fiducial, predicted, observed = [], [], []
    for image, factor in zip(dataset.images, problem.factors):
        z = factor.predict(values).T
        camera = dataset.camera_of(image)
        if camera is not None:
            z = camera.distort(z)
        for k, name in enumerate(image.observations):
            image_ids.append(image.id)
            names.append(name)
            fiducial.append(name in dataset.fiducials)
            predicted.append(z[k])
            observed.append(np.asarray(image.observations[name], float))
    units = "px" if dataset.camera is not None else "normalized"
    return Residuals(units, image_ids, names, np.array(fiducial), np.array(predicted), np.array(observed),
                     float(dataset.pixel_sigma))


def figure_arm(result: Mapping[str, Any], dataset: Dataset) -> Any:
    """The arm at up to :data:`ARM_POSES_DRAWN` of its poses (links joined through the URDF's joints), the
    camera's axes and the target's points at each, and each mirror placement as a square on its plane."""
    problem, estimate = _estimate(result, dataset, "result")
    kin = problem.kinematics
    fig = new_figure(7.0, 6.0)
    ax = fig.add_subplot(projection="3d")
    count = len(dataset.images)
    drawn = sorted(set(np.linspace(0, count - 1, min(count, ARM_POSES_DRAWN)).round().astype(int).tolist()))
    everything = []
    for k in drawn:
        image, factor = dataset.images[k], problem.factors[k]
        state = factor.poses(problem.values(estimate))
        for role in (problem.role_of(image), "target"):
            chain = kin.chain_links(problem.links[role])
            placed = kin.placements(image.joints, chain)
            xyz = np.array([placed[link][0][:3, 3] for link in chain])
            ax.plot(*xyz.T, "-o", color="0.35", lw=1.5, ms=2.5, alpha=0.6)
            everything.append(xyz)
        R_c, t_c = state["C"]
        for axis, colour in zip(R_c.T, ("r", "g", "b")):
            ax.plot(*np.column_stack([t_c, t_c + 0.1 * axis]), color=colour, lw=2.0)
        R_t, t_t = state["D"]
        points = R_t @ factor.target_points[:, np.all(np.isfinite(factor.target_points), axis=0)] + t_t[:, None]
        ax.scatter(*points, s=2, color="tab:orange")
        everything += [t_c[None], points.T]
    centre = np.mean(np.vstack(everything), axis=0)
    for (l, m), v in sorted(estimate.mirror_vectors.items()):
        n, d = v / np.linalg.norm(v), float(np.linalg.norm(v))
        foot = centre - (n @ centre - d) * n  # the plane's point nearest the scene
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(n, u)
        corners = np.array([foot + 0.15 * (a * u + b * w) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))])
        ax.plot(*corners.T, color="tab:cyan", lw=1.2)
        ax.text(*foot, f"{l}:{m}", fontsize=7, color="tab:cyan")
        everything.append(corners)
    span = np.vstack(everything)
    mid, half = span.mean(axis=0), 0.55 * float(np.max(span.max(axis=0) - span.min(axis=0)))
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"{len(drawn)} of {count} arm poses in {kin.base_link}")
    return fig
