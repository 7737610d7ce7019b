"""Experiment planner: Cramér-Rao 3-sigma bounds on ``T_cam_base`` for a described setup, before any data.

A setup (number of mirrors, placements per node of the configuration tree, images, fiducial layout,
mirror distance and tilt spread, pixel sigma) is turned into ``draws`` noise-free scenes by the
simulator (random mirror placements as in the paper's Sect. 7, ``mirror_fg.simulate.tree``); the Fisher
information of each scene at its truth (``mirror_fg.solver.information.crb``) gives the best covariance any unbiased
estimator - and, in practice, the MLE - reaches with that geometry. The bounds reported are the
quadratic mean over the draws (what a Monte Carlo RMS error would show), with the spread over draws.

Assumptions: the simulator's camera (1024 x 768 px, fx = fy = 800 px, no distortion) decides which
placements keep every point in view; ``focal_px`` only rescales the noise (``pixel_sigma / focal_px``
in normalized units). Every fiducial and reconstruction point is seen in every image.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.transform import Transform
from mirror_fg.core.geometry import apply_transform
from mirror_fg.io.dataset import fiducials_from_dict
from mirror_fg.data import Dataset, Image
from mirror_fg.io.fileio import load_structured
from mirror_fg.core.camera import INTRINSIC_NAMES
from mirror_fg.solver.information.crb import (
    CramerRaoBound, IntrinsicsBound, WeakestDirection, cramer_rao_bound, intrinsics_cramer_rao_bound, weakest_direction,
)
from mirror_fg.simulate.tree import GroundTruth, default_camera, measure, simulate_base_case, visible

__all__ = ["PlanSetup", "PlanResult", "plan", "format_plan", "load_fiducials", "setup_from_files"]


@dataclass
class PlanSetup:
    """A calibration setup to evaluate.

    num_mirrors: Nv. placements: placements of each mirror but the last per node of the configuration
    tree (mirror 1's placements for two mirrors; >= 3 for the analytical solution); the last mirror
    moves in every image. num_images: images in all. fiducials: base-frame layout ``{name: (x, y, z)}``
    in metres, or None for the paper's 20 cm right triangle (``num_fiducials`` 3, or 4 with a point off
    its plane). num_points: reconstruction points within 10 cm of the fiducials. mirror_distance_m:
    camera-to-mirror distance (+/- 10 %). tilt_deg: largest tilt of a mirror normal from its nominal
    axis (placements are drawn uniformly up to it). pixel_sigma: measurement noise, pixels.
    focal_px: focal length that turns pixels into normalized units (None: the simulator's 800 px).
    estimate: intrinsics estimated through the mirrors too (``camera.estimate``, a subset of fx, fy,
    cx, cy, k1, k2, p1, p2, k3): the bounds on ``T_cam_base`` then include their uncertainty and the
    intrinsics get bounds of their own (fx, fy, cx, cy in pixels of a ``focal_px`` camera whose
    principal point is at the image centre; the lens is distortion-free).
    """

    num_mirrors: int = 2
    placements: int = 3
    num_images: int = 200
    num_fiducials: int = 3
    fiducials: Mapping[str, Sequence[float] | np.ndarray] | None = None
    num_points: int = 0
    mirror_distance_m: float = 0.5
    tilt_deg: float = 30.0
    pixel_sigma: float = 1.0
    focal_px: float | None = None
    estimate: tuple[str, ...] = ()

    def describe(self) -> str:
        layout = (f"{len(self.fiducials)} given fiducials" if self.fiducials is not None
                  else f"{self.num_fiducials} fiducials (20 cm right triangle{' + 1 off-plane' if self.num_fiducials == 4 else ''})")
        return (f"{self.num_mirrors} mirror(s), {self.placements} placements per node, {self.num_images} images, "
                f"{layout}, {self.num_points} reconstruction points, mirrors at {self.mirror_distance_m:g} m "
                f"tilted up to {self.tilt_deg:g} deg, pixel sigma {self.pixel_sigma:g} px"
                + (f", intrinsics estimated: {', '.join(self.estimate)}" if self.estimate else ""))


@dataclass
class PlanResult:
    """Cramér-Rao bounds of a setup.

    ``pose_covariance``: 6x6 of ``T_cam_base`` in docs/formats.md's ``[dtheta (rad), dt (m)]`` (camera axes),
    mean over draws. ``sigma3_rotation_deg``, ``sigma3_position_mm``: 3-sigma bounds (camera axes) from it;
    ``..._range``: (min, max) over draws per axis. ``covariance_base_cam``, ``sigma3_base_cam_rotation_deg``,
    ``sigma3_base_cam_position_mm``, ``sigma3_base_cam_range``: the same of ``T_base_cam`` (the camera's pose
    on the robot; base axes), each draw's converted at its own truth. ``point_sigma3_mm_worst``: 3-sigma of the least-constrained reconstruction point, worst axis,
    mean over draws (None without points). ``visible_fraction``: images whose given fiducials all stay in
    view (1.0 for the default layouts). ``weakest``: least-constrained direction of ``pose_covariance``.
    With ``setup.estimate``: the pose bounds include the intrinsics' uncertainty, ``intrinsics_sigma3``
    holds each intrinsic's 3-sigma (quadratic mean over draws; pixels or unitless) and
    ``sigma3_position_mm_fixed_intrinsics`` the position bound were the intrinsics known exactly.
    """

    setup: PlanSetup
    draws: int
    pose_covariance: np.ndarray
    sigma3_rotation_deg: np.ndarray
    sigma3_position_mm: np.ndarray
    sigma3_rotation_deg_range: tuple[np.ndarray, np.ndarray]
    sigma3_position_mm_range: tuple[np.ndarray, np.ndarray]
    point_sigma3_mm_worst: float | None
    visible_fraction: float
    weakest: WeakestDirection
    bounds: list[CramerRaoBound] = field(default_factory=list, repr=False)
    intrinsics_sigma3: dict[str, float] | None = None
    sigma3_position_mm_fixed_intrinsics: np.ndarray | None = None
    covariance_base_cam: np.ndarray | None = None
    sigma3_base_cam_rotation_deg: np.ndarray | None = None
    sigma3_base_cam_position_mm: np.ndarray | None = None
    #: ((rotation min, rotation max), (position min, max)) over draws per axis, degrees and millimetres.
    sigma3_base_cam_range: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None

    def to_dict(self) -> dict:
        """Plain data (JSON-able)."""
        return {
            "setup": {k: (dict((n, list(map(float, p))) for n, p in v.items()) if k == "fiducials" and v is not None
                          else v) for k, v in self.setup.__dict__.items()},
            "draws": self.draws,
            "covariance_cam_base": self.pose_covariance.tolist(),
            "sigma3_cam_base": {"rotation_deg": self.sigma3_rotation_deg.tolist(),
                                "position_mm": self.sigma3_position_mm.tolist()},
            **({"covariance_base_cam": self.covariance_base_cam.tolist(),
                "sigma3_base_cam": {"rotation_deg": self.sigma3_base_cam_rotation_deg.tolist(),
                                    "position_mm": self.sigma3_base_cam_position_mm.tolist()}}
               if self.covariance_base_cam is not None and self.sigma3_base_cam_rotation_deg is not None
               and self.sigma3_base_cam_position_mm is not None else {}),
            "sigma3_range": {"rotation_deg": [a.tolist() for a in self.sigma3_rotation_deg_range],
                             "position_mm": [a.tolist() for a in self.sigma3_position_mm_range]},
            "point_sigma3_mm_worst": self.point_sigma3_mm_worst,
            "visible_fraction": self.visible_fraction,
            "weakest_direction": self.weakest.text,
            **({"sigma3_intrinsics": self.intrinsics_sigma3,
                "sigma3_position_mm_fixed_intrinsics": self.sigma3_position_mm_fixed_intrinsics.tolist()}
               if self.intrinsics_sigma3 is not None and self.sigma3_position_mm_fixed_intrinsics is not None else {}),
        }


def _with_fiducials(
    dataset: Dataset, truth: GroundTruth, fiducials: Mapping[str, Sequence[float] | np.ndarray]
) -> tuple[Dataset, float]:
    """The same scene observing another fiducial layout (noise-free), and the fraction of images in view."""
    layout = {str(name): np.asarray(p, dtype=float).reshape(3) for name, p in fiducials.items()}
    camera = dataset.camera
    assert camera is not None  # simulated scenes are in pixels
    camera_points = apply_transform(truth.R_cam_base, truth.t_cam_base, np.array(list(layout.values())))
    images, in_view = [], 0
    for image in dataset.images:
        in_view += visible(camera, camera_points, truth.vectors(image.mirror_configs), margin_px=0.0)
        observations = measure(truth, camera, layout, image.mirror_configs)
        images.append(Image(id=image.id, mirror_configs=image.mirror_configs, observations=observations))
    scene = Dataset(num_mirrors=dataset.num_mirrors, camera=camera, pixel_sigma=dataset.pixel_sigma,
                    fiducials=layout, images=images, source="<plan>")
    return scene, in_view / max(len(images), 1)


def plan(setup: PlanSetup | None = None, draws: int = 5, seed: int = 0, **kwargs) -> PlanResult:
    """Cramér-Rao bounds of ``setup`` (or of ``PlanSetup(**kwargs)``) over ``draws`` random scenes.

    Raises ``DatasetError`` (exit status 2) for an impossible setup (fewer than 3 placements per node,
    fewer images than tree leaves, no mirror placement that keeps the points in view) and ``SolveError``
    (exit status 3) when the setup leaves an unknown unconstrained (named).
    """
    if setup is None:
        setup = PlanSetup(**kwargs)
    elif kwargs:
        raise TypeError("give either a PlanSetup or keyword arguments, not both")
    if draws < 1:
        raise DatasetError(f"plan: draws must be >= 1, got {draws}")
    if setup.pixel_sigma <= 0.0:
        raise DatasetError(f"plan: pixel_sigma must be > 0, got {setup.pixel_sigma}")
    if setup.placements < 3 and setup.num_mirrors > 1:
        raise DatasetError(
            f"plan: placements must be >= 3 per node (the analytical solution needs it), got {setup.placements}")
    if setup.focal_px is not None and setup.focal_px <= 0.0:
        raise DatasetError(f"plan: focal_px must be > 0, got {setup.focal_px}")
    unknown = [n for n in setup.estimate if n not in INTRINSIC_NAMES]
    if unknown or len(set(setup.estimate)) != len(setup.estimate):
        raise DatasetError(f"plan: estimate must name distinct intrinsics of {', '.join(INTRINSIC_NAMES)}, "
                           f"got {', '.join(setup.estimate)}")
    count = len(setup.fiducials) if setup.fiducials is not None else setup.num_fiducials
    pinhole = [n for n in ("fx", "fy", "cx", "cy") if n in setup.estimate]
    if pinhole and count < 4:  # calibrate's refusal (solver/batch/intrinsics.py check_supported), before any data
        raise SolveError(f"plan: camera.estimate: the photographs would not determine {', '.join(pinhole)}: "
                         f"{count} fiducials per image (any focal length and centre fit 3 points exactly), and "
                         "calibrate refuses it; give 4 or more fiducials (--fiducials 4, or a board's corners with "
                         "--fiducials-file), or leave them out of --estimate")
    focal = setup.focal_px if setup.focal_px is not None else default_camera().fx
    sigma_normalized = setup.pixel_sigma / focal
    # The simulator's camera (fx = fy = 800 px) with the same normalized noise: its intrinsics' bounds
    # scale to a focal_px camera by focal / 800 (fx, fy, cx, cy), distortion terms unchanged.
    sigma_sim_px = sigma_normalized * default_camera().fx
    to_focal = focal / default_camera().fx
    bounds, visible_fractions, intrinsic_bounds, poses = [], [], [], []
    for draw in range(draws):
        try:
            dataset, truth = simulate_base_case(
                num_images=setup.num_images, num_points=setup.num_points, pixel_sigma=0.0,
                mirror_distance=setup.mirror_distance_m, tilt_deg=setup.tilt_deg, mirror1_placements=setup.placements,
                seed=seed + draw, num_mirrors=setup.num_mirrors,
                num_fiducials=setup.num_fiducials if setup.fiducials is None else 3,
            )
        except (ValueError, RuntimeError) as error:  # the simulator's own checks: an impossible setup
            raise DatasetError(f"plan: {error}") from None
        fraction = 1.0
        if setup.fiducials is not None:
            dataset, fraction = _with_fiducials(dataset, truth, setup.fiducials)
        visible_fractions.append(fraction)
        poses.append(Transform(truth.R_cam_base, truth.t_cam_base))
        bounds.append(cramer_rao_bound(dataset, truth, sigma_normalized=sigma_normalized))
        if setup.estimate:
            intrinsic_bounds.append(intrinsics_cramer_rao_bound(dataset, truth, setup.estimate, sigma_px=sigma_sim_px))
    pose_bounds: list[Any] = intrinsic_bounds if setup.estimate else bounds  # each with its pose_covariance
    pose = np.mean([b.pose_covariance for b in pose_bounds], axis=0)
    sigma3 = 3.0 * np.sqrt(np.diag(pose))
    per_draw = np.array([3.0 * np.sqrt(np.diag(b.pose_covariance)) for b in pose_bounds])
    rot_range = (np.degrees(per_draw[:, :3].min(axis=0)), np.degrees(per_draw[:, :3].max(axis=0)))
    pos_range = (1000.0 * per_draw[:, 3:].min(axis=0), 1000.0 * per_draw[:, 3:].max(axis=0))
    # T_base_cam (the camera's pose on the robot, base axes), each draw's at its own truth, as calibrate prints it.
    base_cam = [T.inverse_covariance(np.asarray(b.pose_covariance)) for T, b in zip(poses, pose_bounds)]
    base_cov = np.mean(base_cam, axis=0)
    base_sigma3 = 3.0 * np.sqrt(np.diag(base_cov))
    base_draws = np.array([3.0 * np.sqrt(np.diag(P)) for P in base_cam])
    base_range = ((np.degrees(base_draws[:, :3].min(axis=0)), np.degrees(base_draws[:, :3].max(axis=0))),
                  (1000.0 * base_draws[:, 3:].min(axis=0), 1000.0 * base_draws[:, 3:].max(axis=0)))
    point_worst = None
    if setup.num_points:
        worst_var = [max(float(np.max(np.diag(P))) for P in b.point_covariances.values()) for b in bounds]
        point_worst = 3000.0 * float(np.sqrt(np.mean(worst_var)))
    return PlanResult(
        setup=setup, draws=draws, pose_covariance=pose,
        sigma3_rotation_deg=np.degrees(sigma3[:3]), sigma3_position_mm=1000.0 * sigma3[3:],
        sigma3_rotation_deg_range=rot_range, sigma3_position_mm_range=pos_range,
        point_sigma3_mm_worst=point_worst, visible_fraction=float(np.mean(visible_fractions)),
        weakest=weakest_direction(pose), bounds=bounds,
        **_intrinsics_fields(setup, intrinsic_bounds, bounds, to_focal),
        covariance_base_cam=base_cov, sigma3_base_cam_rotation_deg=np.degrees(base_sigma3[:3]),
        sigma3_base_cam_position_mm=1000.0 * base_sigma3[3:], sigma3_base_cam_range=base_range,
    )


def _intrinsics_fields(setup: PlanSetup, intrinsic_bounds: list[IntrinsicsBound], bounds: list[CramerRaoBound],
                       to_focal: float) -> dict:
    """``intrinsics_sigma3`` and ``sigma3_position_mm_fixed_intrinsics`` of a PlanResult (none without
    ``setup.estimate``)."""
    if not setup.estimate:
        return {}
    names = intrinsic_bounds[0].names
    variance = np.mean([np.diag(b.covariance) for b in intrinsic_bounds], axis=0)
    pixels = np.array([to_focal if n in ("fx", "fy", "cx", "cy") else 1.0 for n in names])
    fixed = np.mean([b.pose_covariance for b in bounds], axis=0)
    return {"intrinsics_sigma3": {n: float(3.0 * np.sqrt(v) * s) for n, v, s in zip(names, variance, pixels)},
            "sigma3_position_mm_fixed_intrinsics": 3000.0 * np.sqrt(np.diag(fixed)[3:])}


def format_plan(result: PlanResult) -> str:
    """What ``mirror-fg plan`` prints."""
    def triple(values, fmt):
        return "[" + ", ".join(format(float(v), fmt) for v in values) + "]"

    lines = [f"setup: {result.setup.describe()}",
             f"Cramér-Rao 3-sigma bounds (mean over {result.draws} random mirror placement draw(s)):"]
    if (result.sigma3_base_cam_rotation_deg is not None and result.sigma3_base_cam_position_mm is not None
            and result.sigma3_base_cam_range is not None):
        (lo_r, hi_r), (lo_p, hi_p) = result.sigma3_base_cam_range
        lines += [
            "T_base_cam  the camera's pose on the robot; bounds about and along the base axes (as calibrate prints):",
            f"  rotation  {triple(result.sigma3_base_cam_rotation_deg, '.3f')} deg   "
            f"(draws: {triple(lo_r, '.3f')} .. {triple(hi_r, '.3f')})",
            f"  camera position  {triple(result.sigma3_base_cam_position_mm, '.2f')} mm    "
            f"(draws: {triple(lo_p, '.2f')} .. {triple(hi_p, '.2f')})",
        ]
    lines += [
        f"T_cam_base  its inverse; bounds about and along the camera axes (x right, y down, z forward): rotation "
        f"±{triple(result.sigma3_rotation_deg, '.3f')} deg, base origin ±{triple(result.sigma3_position_mm, '.2f')} mm",
        f"  weakest direction: {result.weakest.text}",
    ]
    if result.intrinsics_sigma3 is not None and result.sigma3_position_mm_fixed_intrinsics is not None:
        lines.append("  intrinsics (3-sigma): " + ", ".join(
            f"{n} {v:.3g}{' px' if n in ('fx', 'fy', 'cx', 'cy') else ''}" for n, v in result.intrinsics_sigma3.items()))
        lines.append(f"  (the bounds above include the intrinsics' uncertainty; with them known exactly T_cam_base's base "
                     f"origin would be ±{triple(result.sigma3_position_mm_fixed_intrinsics, '.2f')} mm)")
    if result.point_sigma3_mm_worst is not None:
        lines.append(f"  least-constrained reconstruction point: 3-sigma {result.point_sigma3_mm_worst:.2f} mm (worst axis)")
    if result.visible_fraction < 1.0:
        lines.append(f"  warning: the given fiducials leave the image in {100 * (1 - result.visible_fraction):.0f} % "
                     "of the simulated images (bounds assume they are seen)")
    lines.append("  (bounds scale as pixel_sigma and about as 1/sqrt(images); an MLE reaches them, the analytical "
                 "solution alone does not)")
    return "\n".join(lines)


def load_fiducials(path: str | Path) -> dict[str, np.ndarray]:
    """Fiducial layout from a JSON/YAML file: ``{name: [x, y, z]}`` (metres, base frame), or a
    dataset@1 / capture@1-like mapping with a ``fiducials`` key. Read like every input (bounded, once;
    :func:`~mirror_fg.io.fileio.load_structured`) and checked like a dataset's fiducials. Raises
    ``DatasetError``."""
    source = str(path)
    data = load_structured(path)
    if isinstance(data, Mapping) and "fiducials" in data:
        data = data["fiducials"]
    if not isinstance(data, Mapping) or not data:
        raise DatasetError(f"{source}: expected a mapping of fiducial names to [x, y, z] (metres)")
    return fiducials_from_dict({str(name): value for name, value in data.items()}, source)


def setup_from_files(camera: str | Path | None = None, capture: str | Path | None = None) -> tuple[dict, str]:
    """PlanSetup fields taken from a camera calibration file (OpenCV, ROS camera_info, Kalibr: ``focal_px``,
    the mean of fx and fy) or from a capture@1 file (its camera's focal length and ``estimate``, its
    target's points in the base frame as ``fiducials``, its ``pixel_sigma`` and ``num_mirrors``; the
    images or video it lists need not exist yet), and one line saying what was taken. DatasetError."""
    if camera is not None and capture is not None:
        raise DatasetError("plan: give --camera or --capture, not both (a capture names its camera)")
    fields: dict = {}
    if camera is not None:
        from mirror_fg.io.camera_files import camera_from_file

        intrinsics, where = camera_from_file(str(camera), None, str(camera)), str(camera)
    elif capture is not None:
        from mirror_fg.io.capture import capture_from_file_data

        cap = capture_from_file_data(load_structured(capture), str(capture), media=False)
        intrinsics, where = cap.camera, str(capture)
        fields.update(fiducials=cap.fiducials(), pixel_sigma=cap.pixel_sigma, num_mirrors=cap.num_mirrors,
                      estimate=tuple(intrinsics.get("estimate") or ()))
    else:
        return {}, ""
    taken = []
    if intrinsics.get("fx") is not None and intrinsics.get("fy") is not None:
        fields["focal_px"] = 0.5 * (float(intrinsics["fx"]) + float(intrinsics["fy"]))
        taken.append(f"focal length {fields['focal_px']:.1f} px")
    if "fiducials" in fields:
        taken.append(f"{len(fields['fiducials'])} target points ({cap.target.kind}) in the base frame, "
                     f"pixel_sigma {fields['pixel_sigma']:g} px, {fields['num_mirrors']} mirror(s)")
    if fields.get("estimate"):
        taken.append(f"estimate {', '.join(fields['estimate'])}")
    return fields, f"from {where}: {', '.join(taken) or 'nothing the plan uses'}"

