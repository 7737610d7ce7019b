"""Guided capture: the next mirror placement that shrinks the camera's position bound the most.

From the data so far and their estimate, every reachable placement of the last mirror (one more image, a
new configuration of mirror Nv under a parent placement already in the data) is scored by the
Cramér-Rao bound the estimate would have after that image (the Fisher information of eq. 23 at the
current estimate, ``mirror_fg.solver.information.crb``): the largest 3-sigma of the camera's position on the body
(``T_base_cam``, millimetres), ties broken by rotation.

One more image adds ``m`` measurements (2 per point it sees) and one unknown, its mirror vector ``v``.
With the whitened Jacobian ``[H_C | H_v]`` of those measurements (``C``: the pose, the parent placements'
vectors and the points seen; eqs. 3-9), eliminating ``v`` leaves the information ``B^T B`` with
``B = Q^T H_C``, ``Q`` an orthonormal basis of the complement of ``range(H_v)``. Woodbury's identity gives
the updated pose covariance from the current one without a new inverse:
``S'_pp = S_pp - S_pC B^T (I + B S_CC B^T)^-1 B S_Cp``.

A placement counts only if every fiducial is seen through it (on the mirror's reflective side, in
front of the camera, inside the image with a margin). Candidates cover the reachable set evenly: mirror
distances ``|v|`` in ``distance_m``, normals within ``max_tilt_deg`` of the optical axis (a Fibonacci
spiral on that spherical cap). Suggestions follow docs/formats.md's ``mirror-fg/suggestions@1``.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.geometry import householder, skew
from mirror_fg.core.transform import Transform, covariance_from_pose3
from mirror_fg.data import Dataset
from mirror_fg.solver.model.graph import Estimate, InitialEstimate
from mirror_fg.solver.information.crb import POSE_DIM, UnknownIndex, _invert, linearize

__all__ = ["Reach", "Suggestion", "Suggestions", "Estimate", "estimate_from_result", "candidate_mirror_vectors", "random_reachable_vectors",
           "suggest_next", "sees_every_fiducial", "default_reach", "SUGGESTIONS_FORMAT"]

SUGGESTIONS_FORMAT = "mirror-fg/suggestions@1"
#: Candidate placements scored per parent placement (``~300``: a greedy search over that many found
#: placements that halve the images needed, ``scripts/guided_study.py``).
NUM_CANDIDATES = 300
#: Mirror distances sampled between ``distance_m``'s ends.
DISTANCE_LEVELS = 3
#: A fiducial's image must stay this fraction of the image size inside its border.
VISIBILITY_MARGIN = 0.03
#: Parent placements (trees) under which candidates are scored, the most recent first.
MAX_PARENTS = 8
#: Candidates scored per vectorised block (bounds the memory of one block).
BLOCK = 32
#: Field of view assumed for normalized data (no camera): a 1024 x 768 image at f = 800 px.
DEFAULT_CAMERA = Camera(width=1024, height=768, fx=800.0, fy=800.0, cx=511.5, cy=383.5)
COMPASS = ("right", "lower right", "bottom", "lower left", "left", "upper left", "top", "upper right")


@dataclass(frozen=True)
class Reach:
    """The placements a user can reach: mirror distance ``|v|`` (metres) and largest tilt of the mirror
    normal from the camera's optical axis (degrees)."""

    distance_m: tuple[float, float]
    max_tilt_deg: float

    def __post_init__(self) -> None:
        low, high = self.distance_m
        if not (math.isfinite(low) and math.isfinite(high) and 0.0 < low <= high):
            raise DatasetError(f"--distance {low:g},{high:g}: give MIN,MAX in metres with 0 < MIN <= MAX")
        if not (math.isfinite(self.max_tilt_deg) and 0.0 < self.max_tilt_deg < 90.0):
            raise DatasetError(f"--max-tilt {self.max_tilt_deg:g}: give a tilt in degrees between 0 and 90")


@dataclass
class Suggestion:
    """One placement to try: mirror ``mirror`` at ``mirror_vector`` (camera frame, metres) with the
    placements ``under`` of the mirrors before it; the bound predicted after one image there."""

    mirror: int
    under: tuple[tuple[int, int], ...]
    mirror_vector: np.ndarray
    predicted_rotation_deg: np.ndarray
    predicted_position_mm: np.ndarray

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.mirror_vector))

    @property
    def tilt_deg(self) -> float:
        """Angle between the mirror normal ``v / |v|`` and the optical axis."""
        return float(np.degrees(np.arccos(np.clip(self.mirror_vector[2] / self.distance_m, -1.0, 1.0))))

    @property
    def azimuth_deg(self) -> float:
        """Direction the normal leans in the image: 0 towards +x (right), 90 towards +y (down)."""
        return float(np.degrees(np.arctan2(self.mirror_vector[1], self.mirror_vector[0])) % 360.0)

    def words(self, current_position_mm: float) -> str:
        """The suggestion as a person at the bench can follow it."""
        where = COMPASS[int(((self.azimuth_deg + 22.5) % 360.0) // 45.0)]
        under = ""
        if self.under:
            under = " with " + ", ".join(f"mirror {l} at its placement {m}" for l, m in self.under) + ","
        return (f"mirror {self.mirror}:{under} tilt it {self.tilt_deg:.0f} deg towards the {where} of the image, "
                f"keep it ~{self.distance_m:.2f} m away; expected position 3-sigma {current_position_mm:.1f} -> "
                f"{float(np.max(self.predicted_position_mm)):.1f} mm")

    def to_dict(self) -> dict:
        return {
            "mirror": self.mirror,
            "under": [list(p) for p in self.under],
            "v": [float(x) for x in self.mirror_vector],
            "distance_m": self.distance_m,
            "tilt_deg": self.tilt_deg,
            "azimuth_deg": self.azimuth_deg,
            "predicted": {"sigma3_base_cam": _sigma3(self.predicted_rotation_deg, self.predicted_position_mm)},
        }


@dataclass
class Suggestions:
    """The current bound on ``T_base_cam`` and the ranked suggestions (best first)."""

    current_rotation_deg: np.ndarray
    current_position_mm: np.ndarray
    suggestions: list[Suggestion] = field(default_factory=list)
    reach: Reach | None = None
    scored: int = 0

    def to_dict(self) -> dict:
        """``mirror-fg/suggestions@1``."""
        return {
            "format": SUGGESTIONS_FORMAT,
            "current": {"sigma3_base_cam": _sigma3(self.current_rotation_deg, self.current_position_mm)},
            "suggestions": [s.to_dict() for s in self.suggestions],
        }

    def text(self) -> str:
        """Lines for the console: the bound now, then each suggestion in words."""
        now = float(np.max(self.current_position_mm))
        lines = [f"camera position on the body now: 3-sigma [{', '.join(f'{x:.1f}' for x in self.current_position_mm)}] mm"
                 f" (base axes), rotation [{', '.join(f'{x:.2f}' for x in self.current_rotation_deg)}] deg"]
        if self.reach is not None:
            lines.append(f"scored {self.scored} reachable placements (mirror {self.reach.distance_m[0]:.2f}-"
                         f"{self.reach.distance_m[1]:.2f} m away, tilted up to {self.reach.max_tilt_deg:.0f} deg)")
        if not self.suggestions:
            lines.append("no reachable placement shows every fiducial: widen --distance or --max-tilt")
        for rank, suggestion in enumerate(self.suggestions, 1):
            lines.append(f"  {rank}. {suggestion.words(now)}")
        return "\n".join(lines)


def _sigma3(rotation_deg: np.ndarray, position_mm: np.ndarray) -> dict:
    return {"rotation_deg": [float(x) for x in rotation_deg], "position_mm": [float(x) for x in position_mm]}


# --------------------------------------------------------------------------------------------------
# Reachable placements


def default_reach(dataset: Dataset, values: InitialEstimate) -> Reach:
    """What the user has reached so far with the last mirror: its distances widened by 10 % and its
    largest tilt plus 10 deg (at most 60 deg)."""
    last = dataset.num_mirrors
    vectors = np.array([values.mirror_vectors[c] for c in dataset.configurations if c[0] == last], dtype=float)
    distances = np.linalg.norm(vectors, axis=1)
    tilts = np.degrees(np.arccos(np.clip(vectors[:, 2] / distances, -1.0, 1.0)))
    return Reach((0.9 * float(distances.min()), 1.1 * float(distances.max())), min(60.0, float(tilts.max()) + 10.0))


def candidate_mirror_vectors(reach: Reach, count: int = NUM_CANDIDATES) -> np.ndarray:
    """``count`` mirror vectors (camera frame) spread evenly over the reachable set: normals on a Fibonacci
    spiral over the cap within ``max_tilt_deg`` of +z (equal areas), each at ``DISTANCE_LEVELS`` distances."""
    directions = max(1, count // DISTANCE_LEVELS)
    k = np.arange(directions) + 0.5
    cos_tilt = 1.0 - (1.0 - math.cos(math.radians(reach.max_tilt_deg))) * k / directions
    azimuth = k * math.pi * (3.0 - math.sqrt(5.0))  # golden angle
    sin_tilt = np.sqrt(1.0 - cos_tilt**2)
    normals = np.column_stack([sin_tilt * np.cos(azimuth), sin_tilt * np.sin(azimuth), cos_tilt])
    distances = np.linspace(*reach.distance_m, DISTANCE_LEVELS)
    return (distances[:, None, None] * normals[None]).reshape(-1, 3)


def random_reachable_vectors(reach: Reach, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` mirror vectors drawn uniformly over the reachable set (normals uniform on the cap,
    distance uniform): what a user without guidance might try."""
    cos_tilt = 1.0 - (1.0 - math.cos(math.radians(reach.max_tilt_deg))) * rng.uniform(size=count)
    azimuth = rng.uniform(0.0, 2.0 * math.pi, size=count)
    sin_tilt = np.sqrt(1.0 - cos_tilt**2)
    normals = np.column_stack([sin_tilt * np.cos(azimuth), sin_tilt * np.sin(azimuth), cos_tilt])
    return rng.uniform(*reach.distance_m, size=count)[:, None] * normals


def _virtual_points(values: InitialEstimate, under: Sequence[tuple[int, int]], base_points: np.ndarray):
    """Camera-frame points (N, 3) after the parent mirrors ``under`` (eqs. 2-3), whether each stayed on
    every parent's reflective side, and the 3-D Jacobians of each point: (N, 3, 6) w.r.t. the pose
    (GTSAM's tangent ``[w, nu]``), (N, 3, 3) per parent mirror, (N, 3, 3) w.r.t. the base point."""
    R = np.asarray(values.R_cam_base, dtype=float)
    t = np.asarray(values.t_cam_base, dtype=float)
    x = base_points @ R.T + t  # eq. (2)
    n = len(base_points)
    d_pose = np.concatenate([-np.einsum("ij,njk->nik", R, np.array([skew(p) for p in base_points])),
                             np.broadcast_to(R, (n, 3, 3))], axis=2)
    d_point = np.broadcast_to(R, (n, 3, 3)).copy()
    d_mirrors: list[np.ndarray] = []
    ok = np.ones(n, dtype=bool)
    for config in under:
        v = np.asarray(values.mirror_vectors[config], dtype=float)
        M = householder(v)
        ok &= x @ v < v @ v
        d_v = _reflection_jacobian_wrt_mirror_many(x, v[None])[0]
        d_mirrors = [M @ d for d in d_mirrors] + [d_v]
        d_pose = np.einsum("ij,njk->nik", M, d_pose)
        d_point = np.einsum("ij,njk->nik", M, d_point)
        x = x @ M.T + 2.0 * v  # eq. (3)
    return x, ok, d_pose, d_mirrors, d_point


def _reflection_jacobian_wrt_mirror_many(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K, N, 3, 3) Jacobians of ``x - 2 v (v.x)/(v.v) + 2 v`` w.r.t. ``v`` (derivative of eq. 3) for
    points ``x`` (N, 3) and mirror vectors ``v`` (K, 3)."""
    vv = np.einsum("ki,ki->k", v, v)[:, None, None, None]
    vx = np.einsum("ki,ni->kn", v, x)[:, :, None, None]
    eye = np.eye(3)
    outer_vx = np.einsum("ki,nj->knij", v, x)
    outer_vv = np.einsum("ki,kj->kij", v, v)[:, None]
    return 2.0 * eye - 2.0 * ((vx / vv) * eye + outer_vx / vv - 2.0 * vx * outer_vv / vv**2)


def _reflect_many(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points ``x`` (N, 3) reflected in each mirror ``v`` (K, 3): (K, N, 3) (eq. 3)."""
    vv = np.einsum("ki,ki->k", v, v)
    vx = np.einsum("ki,ni->kn", v, x)
    return x[None] - 2.0 * (vx / vv[:, None] - 1.0)[:, :, None] * v[:, None, :]


def _in_view(camera: Camera, y: np.ndarray) -> np.ndarray:
    """Whether camera-frame points ``y`` (..., 3) are in front and image inside the margin."""
    depth_ok = y[..., 2] > 1e-6
    z = y[..., :2] / np.where(depth_ok, y[..., 2], 1.0)[..., None]
    flat = z.reshape(-1, 2)
    if camera.model == "pinhole" and not any(camera.dist):
        pixels = flat * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    else:
        pixels = camera.distort(np.clip(flat, -10.0, 10.0))
    pixels = pixels.reshape(z.shape)
    margin = VISIBILITY_MARGIN * np.array([camera.width, camera.height])
    inside = np.all((pixels >= margin - 0.5) & (pixels <= np.array([camera.width, camera.height]) - 0.5 - margin), axis=-1)
    return depth_ok & inside


def sees_every_fiducial(dataset: Dataset, values: InitialEstimate, under: Sequence[tuple[int, int]],
                        mirror_vectors: np.ndarray) -> np.ndarray:
    """Per candidate (K,): whether every fiducial is seen through the parents ``under`` and the new mirror."""
    fiducials = np.array(list(dataset.fiducials.values()), dtype=float).reshape(-1, 3)
    x, ok, *_ = _virtual_points(values, under, fiducials)
    v = np.atleast_2d(np.asarray(mirror_vectors, dtype=float))
    on_side = np.einsum("ki,ni->kn", v, x) < np.einsum("ki,ki->k", v, v)[:, None]
    seen = _in_view(dataset.camera or DEFAULT_CAMERA, _reflect_many(x, v))
    return np.all(on_side & seen, axis=1) & bool(np.all(ok))


def _pose_bounds(values: InitialEstimate, pose3_covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3-sigma rotation (deg) and position (mm) of ``T_base_cam`` (base axes) from a Pose3-tangent covariance."""
    R = np.asarray(values.R_cam_base, dtype=float)
    covariance = Transform(R, np.asarray(values.t_cam_base, dtype=float)).inverse_covariance(
        covariance_from_pose3(R, pose3_covariance))
    sigma = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return np.degrees(3.0 * sigma[:3]), 3000.0 * sigma[3:]


def _parents(dataset: Dataset) -> list[tuple[tuple[int, int], ...]]:
    """Parent placements (mirrors 1..Nv-1) of the last mirror in the data, the most recent first."""
    seen: dict[tuple[tuple[int, int], ...], None] = {}
    for image in reversed(dataset.images):
        seen.setdefault(tuple((l + 1, m) for l, m in enumerate(image.mirror_configs[:-1])), None)
    return list(seen)[:MAX_PARENTS]


def _score(dataset: Dataset, values: InitialEstimate, index: UnknownIndex, covariance: np.ndarray,
           under: tuple[tuple[int, int], ...], candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted 3-sigma (rotation deg (K, 3), position mm (K, 3)) of ``T_base_cam`` after one image through
    each candidate (K, 3) of the last mirror under ``under`` (module docstring: Woodbury on the eliminated
    mirror)."""
    names = list(dataset.fiducials) + dataset.reconstruction_point_names
    base = np.array([dataset.fiducials[n] if n in dataset.fiducials else values.points[n] for n in names], dtype=float)
    x, _, d_pose, d_mirrors, d_point = _virtual_points(values, under, base)
    # The unknowns the new image touches: the pose, the parents' vectors, the reconstruction points.
    columns = [np.arange(POSE_DIM)] + [index.mirrors[c] + np.arange(3) for c in under]
    point_columns = [index.points[n] + np.arange(3) for n in names if n not in dataset.fiducials]
    C = np.concatenate(columns + point_columns)
    G = np.zeros((len(names), 3, len(C)))  # d(virtual point)/d(unknowns in C)
    G[:, :, :POSE_DIM] = d_pose
    for k, d in enumerate(d_mirrors):
        G[:, :, POSE_DIM + 3 * k: POSE_DIM + 3 * k + 3] = d
    offset = POSE_DIM + 3 * len(under)
    for j, n in enumerate(n for n in names if n not in dataset.fiducials):
        G[len(dataset.fiducials) + j, :, offset + 3 * j: offset + 3 * j + 3] = d_point[len(dataset.fiducials) + j]
    sigma = dataset.normalized_sigma  # (2,): pixel_sigma over the focal lengths
    S_CC = covariance[np.ix_(C, C)]
    S_pC = covariance[:POSE_DIM][:, C]
    rotation = np.empty((len(candidates), 3))
    position = np.empty((len(candidates), 3))
    camera = dataset.camera or DEFAULT_CAMERA
    for start in range(0, len(candidates), BLOCK):
        v = candidates[start:start + BLOCK]
        y = _reflect_many(x, v)  # (K, N, 3)
        seen = _in_view(camera, y) & (np.einsum("ki,ni->kn", v, x) < np.einsum("ki,ki->k", v, v)[:, None])
        M = np.eye(3) - 2.0 * np.einsum("ki,kj->kij", v, v) / np.einsum("ki,ki->k", v, v)[:, None, None]
        depth = np.where(np.abs(y[..., 2]) > 1e-9, y[..., 2], 1e-9)
        J_proj = np.zeros(y.shape[:2] + (2, 3))  # eq. (9)
        J_proj[..., 0, 0] = J_proj[..., 1, 1] = 1.0 / depth
        J_proj[..., 0, 2] = -y[..., 0] / depth**2
        J_proj[..., 1, 2] = -y[..., 1] / depth**2
        J_proj = J_proj * (seen[..., None, None] / sigma[None, None, :, None])  # whitened; unseen rows zero
        H_C = np.einsum("knrj,kji,nic->knrc", J_proj, M, G).reshape(len(v), -1, len(C))
        H_v = np.einsum("knrj,knji->knri", J_proj, _reflection_jacobian_wrt_mirror_many(x, v)).reshape(len(v), -1, 3)
        U = np.linalg.svd(H_v, full_matrices=True)[0]
        B = np.einsum("kmq,kmc->kqc", U[:, :, 3:], H_C)  # Q^T H_C
        inner = np.eye(B.shape[1]) + np.einsum("kqc,cd,krd->kqr", B, S_CC, B)
        BS = np.einsum("kqc,pc->kqp", B, S_pC)  # B S_Cp
        S_pp = covariance[:POSE_DIM, :POSE_DIM] - np.einsum("kqp,kqr->kpr", BS, np.linalg.solve(inner, BS))
        for k in range(len(v)):
            rotation[start + k], position[start + k] = _pose_bounds(values, S_pp[k])
    return rotation, position


def suggest_next(dataset: Dataset, values: InitialEstimate, *, count: int = 3, reach: Reach | None = None,
                 num_candidates: int = NUM_CANDIDATES) -> Suggestions:
    """Rank the reachable placements of the last mirror by the predicted largest 3-sigma of the camera's
    position on the body after one more image there (ties by rotation); the ``count`` best.

    ``values``: the current estimate of every unknown of ``dataset`` (a ``Calibration`` will do).
    ``reach``: the placements the user can reach (default: :func:`default_reach`). Raises SolveError
    where the data so far do not determine the estimate (the Fisher information is singular).
    """
    if not dataset.fiducials:
        raise DatasetError(f"{dataset.source}: suggestions need fiducials (a known target)")
    reach = reach or default_reach(dataset, values)
    index = UnknownIndex.for_dataset(dataset)
    covariance = _invert(linearize(dataset, values).information, index, dataset.source)
    now_rotation, now_position = _pose_bounds(values, covariance[:POSE_DIM, :POSE_DIM])
    ranked: list[Suggestion] = []
    scored = 0
    candidates = candidate_mirror_vectors(reach, num_candidates)
    for under in _parents(dataset):
        usable = candidates[sees_every_fiducial(dataset, values, under, candidates)]
        scored += len(usable)
        if not len(usable):
            continue
        rotation, position = _score(dataset, values, index, covariance, under, usable)
        ranked += [Suggestion(dataset.num_mirrors, under, usable[k], rotation[k], position[k]) for k in range(len(usable))]
    ranked.sort(key=lambda s: (round(float(np.max(s.predicted_position_mm)), 6), float(np.max(s.predicted_rotation_deg))))
    return Suggestions(now_rotation, now_position, ranked[:count], reach, scored)


def estimate_from_result(result: dict, dataset: Dataset, source: str) -> tuple[Dataset, Estimate]:
    """The data a result@1 was calibrated from (without what it left out) and its estimate, to suggest from
    without calibrating again; DatasetError when the result does not belong to the data."""
    from mirror_fg.io.result import mirror_vectors, points, pose
    from mirror_fg.solver.result.calibration import Exclusion
    from mirror_fg.solver.screen.consensus import without

    excluded = [Exclusion(e["image"], e["reason"], e.get("point"), e.get("sigmas")) for e in result.get("excluded") or []]
    used = without(dataset, excluded) if excluded else dataset
    R, t = pose(result["T_cam_base"])
    vectors = mirror_vectors(result)
    point_values = {name: xyz for name, (xyz, _) in points(result).items()}
    missing = [f"placement {m} of mirror {l}" for l, m in used.configurations if (l, m) not in vectors]
    missing += [f"point {name}" for name in used.reconstruction_point_names if name not in point_values]
    if missing:
        raise DatasetError(f"{source}: holds no estimate of {missing[0]} of {dataset.source}"
                           f"{f' (and {len(missing) - 1} more)' if len(missing) > 1 else ''}: was it calibrated from them?")
    return used, Estimate(R, t, vectors, point_values)


def require_suggestions(suggestions: Suggestions, source: str) -> Suggestions:
    """The suggestions, or a SolveError where no reachable placement shows every fiducial."""
    if not suggestions.suggestions:
        raise SolveError(f"{source}: no reachable placement shows every fiducial "
                         f"(scored {suggestions.scored}): widen --distance or --max-tilt")
    return suggestions
