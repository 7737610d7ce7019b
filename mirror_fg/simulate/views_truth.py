"""Ground truth of simulations with views of any reflection order and several cameras
(``mirror-fg/truth@1``, extended compatibly: docs/formats.md "Views of any reflection order, and several cameras").

A single-camera truth file is the one :mod:`mirror_fg.simulate.tree` writes. A rig's adds
``cameras: {name: {"T_cam_base": {"R", "t"}}}`` (dataset order) and, per mirror placement, ``camera``:
the frame its ``v`` is in (the first camera in ``cameras`` order with an image of it, as result@1's
``mirrors[].camera``). The top-level ``T_cam_base`` is the first camera's.
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.core.geometry import nested_transform
from mirror_fg.simulate.tree import TRUTH_FORMAT, GroundTruth

__all__ = ["ViewsTruth", "views_truth_from_dict", "load_views_truth", "plane_in_camera", "Camera_name"]

#: A camera's name in a rig; None for the one camera of a single-camera dataset.
Camera_name = str | None


def _floats(x) -> list:
    return np.asarray(x, dtype=float).tolist()


# --------------------------------------------------------------------------------------------------
# Ground truth with several cameras and placements in any camera's frame


@dataclass
class ViewsTruth:
    """True unknowns of a views simulation (``mirror-fg/truth@1``, extended compatibly).

    ``poses``: ``{camera: (R, t)}`` camera-to-base transforms (eq. 2) in the dataset's camera order; the
    one key is None for a single-camera dataset. ``mirror_vectors[(l, m)]`` (metres) is in the frame of
    ``mirror_cameras[(l, m)]``: the first camera (in ``poses`` order) with an image of that placement
    (docs/formats.md "Result", ``mirrors[].camera``). ``points``: base-frame reconstruction points.
    """

    poses: dict[Camera_name, tuple[np.ndarray, np.ndarray]]
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    mirror_cameras: dict[tuple[int, int], Camera_name] = field(default_factory=dict)
    points: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def first_camera(self) -> Camera_name:
        return next(iter(self.poses))

    def vector(self, placement: tuple[int, int], camera: Camera_name = None) -> np.ndarray:
        """Mirror vector of ``placement`` in ``camera``'s frame (the first camera's when None)."""
        camera = self.first_camera if camera is None else camera
        owner = self.mirror_cameras.get(placement, self.first_camera)
        v = self.mirror_vectors[placement]
        if owner == camera:
            return np.asarray(v, dtype=float)
        return plane_in_camera(v, self.poses[owner], self.poses[camera])

    def transform(self, reflections: Sequence[Sequence[int]], camera: Camera_name = None) -> tuple[np.ndarray, np.ndarray]:
        """``(A, b)`` of a view: the camera sees base point ``Bp`` at ``A Bp + b`` (eqs. 5-8)."""
        camera = self.first_camera if camera is None else camera
        R, t = self.poses[camera]
        return nested_transform(R, t, [self.vector((int(l), int(m)), camera) for l, m in reflections])

    def ground_truth(self) -> GroundTruth:
        """The first camera's unknowns as a :class:`GroundTruth` (every mirror vector in its frame)."""
        R, t = self.poses[self.first_camera]
        return GroundTruth(R_cam_base=R, t_cam_base=t, points=dict(self.points),
                           mirror_vectors={p: self.vector(p) for p in self.mirror_vectors})

    def to_dict(self) -> dict:
        """JSON-able ``mirror-fg/truth@1``: a single-camera file reads with
        :func:`mirror_fg.simulate.tree.ground_truth_from_dict` too; a rig adds ``cameras`` and each
        mirror's ``camera`` (the frame of its ``v``)."""
        R, t = self.poses[self.first_camera]
        rig = self.first_camera is not None
        mirrors = []
        for (l, m), v in sorted(self.mirror_vectors.items()):
            entry = {"mirror": int(l), "config": int(m), "v": _floats(v)}
            if rig:
                entry["camera"] = self.mirror_cameras.get((l, m), self.first_camera)
            mirrors.append(entry)
        data: dict[str, Any] = {"format": TRUTH_FORMAT, "T_cam_base": {"R": _floats(R), "t": _floats(t)},
                                "mirrors": mirrors, "points": {name: _floats(p) for name, p in self.points.items()}}
        if rig:
            data["cameras"] = {name: {"T_cam_base": {"R": _floats(R_c), "t": _floats(t_c)}}
                               for name, (R_c, t_c) in self.poses.items()}
        return data


def views_truth_from_dict(data: Mapping) -> ViewsTruth:
    """Inverse of :meth:`ViewsTruth.to_dict` (also reads a plain single-camera truth@1)."""
    fmt = data.get("format", TRUTH_FORMAT)
    if fmt != TRUTH_FORMAT:
        raise ValueError(f"ground truth: format is {fmt!r}, expected {TRUTH_FORMAT!r}")

    def pose(T: Mapping) -> tuple[np.ndarray, np.ndarray]:
        return np.array(T["R"], dtype=float).reshape(3, 3), np.array(T["t"], dtype=float).reshape(3)

    poses: dict[Camera_name, tuple[np.ndarray, np.ndarray]]
    if "cameras" in data:
        poses = {str(name): pose(entry["T_cam_base"]) for name, entry in data["cameras"].items()}
    else:
        poses = {None: pose(data["T_cam_base"])}
    first = next(iter(poses))
    vectors, owners = {}, {}
    for entry in data.get("mirrors", []):
        key = (int(entry["mirror"]), int(entry["config"]))
        vectors[key] = np.array(entry["v"], dtype=float).reshape(3)
        owners[key] = entry.get("camera", first)
        if owners[key] not in poses:
            raise ValueError(f"ground truth: mirror {key[0]} config {key[1]} is in camera {owners[key]!r}, "
                             f"which is not in cameras")
    points = {name: np.array(p, dtype=float).reshape(3) for name, p in data.get("points", {}).items()}
    return ViewsTruth(poses=poses, mirror_vectors=vectors, mirror_cameras=owners, points=points)


def load_views_truth(path: str | Path) -> ViewsTruth:
    """Read a ``<stem>.truth.json`` written by :func:`write_views_simulation` (or by ``simulate``)."""
    return views_truth_from_dict(json.loads(Path(path).read_text(encoding="utf-8")))


def plane_in_camera(v: np.ndarray, pose_from: tuple[np.ndarray, np.ndarray],
                    pose_to: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Mirror vector ``v`` (frame of the camera with T_cam_base ``pose_from``) in another camera's frame:
    its plane carried into the base frame and out again (``solver.start.propagation``)."""
    from mirror_fg.solver.start.propagation import mirror_vector_in, plane_from_camera

    return mirror_vector_in(plane_from_camera(np.asarray(v, dtype=float), pose_from), pose_to)
