"""``Calibration``: the result of a calibration (batch or incremental) as a plain value.

Frames and units as docs/formats.md: ``T_cam_base = (R, t)`` maps base points into the camera
(``Cp = R Bp + t``, metres); the pose covariance is ``[dtheta (rad), dt (m)]`` with
``R_true = Exp(dtheta) R_est``, ``t_true = t_est + dt``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.fit import plausible
from mirror_fg.core.transform import Transform
from mirror_fg.solver.start.analytic import AnalyticSolution

__all__ = [
    "Calibration", "EstimatedCamera", "Exclusion", "Inconsistency", "require_converged", "POOR_FIT_RATIO",
    "MAX_BASE_DISTANCE_M",
]

#: A fit is *poor* (refused unless accepted) when its RMS whitened residual is more than this many times
#: what the noise model allows: ``sqrt(final cost / expected cost) > 3``, i.e. for one ``pixel_sigma`` an
#: RMS reprojection error above about 3 x sqrt(2) sigma. No plausible sigma explains that much (a
#: sigma three times too small is a gross mistake too); the real Takahashi photographs, with their
#: unmodelled distortion, sit at 1.3x the expected cost (a ratio of 1.14).
POOR_FIT_RATIO = 3.0
#: A camera-to-base distance above this (metres) is refused: no robot is that large, the target's
#: sizes were most likely given in millimetres (docs/formats.md).
MAX_BASE_DISTANCE_M = 20.0


@dataclass(frozen=True)
class Exclusion:
    """An image (``point`` None) or one measurement of it left out of the solve, and why.

    ``reason``: one phrase a user can act on; ``sigmas``: its whitened residual where it was measured.
    """

    image: str
    reason: str
    point: str | None = None
    sigmas: float | None = None


@dataclass(frozen=True)
class Inconsistency:
    """The images split into groups each consistent alone but disagreeing with each other.

    ``groups``: image ids per group; ``rotation_deg`` / ``position_mm``: how far apart the groups'
    ``T_cam_base`` are (for two images labelled as one placement, ``consistency.placement_disagreement``:
    the angle between their mirrors' normals and the difference of their distances from the camera);
    ``message``: one line for the user ("images 0-4 and 5-8 disagree by ...").
    """

    groups: tuple[tuple[str, ...], ...]
    rotation_deg: float
    position_mm: float
    message: str


@dataclass
class EstimatedCamera:
    """Intrinsics estimated through the mirrors (``camera.estimate``, docs/formats.md).

    ``camera``: every value as estimated (or kept); ``estimated``: the names estimated, in
    ``INTRINSIC_NAMES`` order; ``covariance`` (k, k) over them (px^2 for fx, fy, cx, cy; unitless for
    the distortion terms); ``pose_cross_covariance`` (k, 6) with the pose ``[dtheta, dt]``.
    """

    camera: Camera
    estimated: tuple[str, ...]
    covariance: np.ndarray | None
    pose_cross_covariance: np.ndarray | None

    @property
    def sigma3(self) -> dict[str, float] | None:
        """3-sigma bound of each estimated intrinsic, or None without a covariance."""
        if self.covariance is None:
            return None
        return {name: float(3.0 * np.sqrt(max(self.covariance[i, i], 0.0))) for i, name in enumerate(self.estimated)}


@dataclass
class CameraPose:
    """One camera of a dataset with several cameras (``cameras``, docs/formats.md "Several cameras").

    ``R_cam_base``, ``t_cam_base``: camera <- base. ``covariance``: its (6, 6) marginal in docs/formats.md's
    convention (the joint estimate's), None without covariances. ``camera``: the intrinsics as used (as
    estimated where the camera estimated them); ``estimated``: set where it estimated intrinsics."""

    name: str
    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    covariance: np.ndarray | None
    camera: Camera | None = None
    estimated: EstimatedCamera | None = None

    @property
    def T_cam_base(self) -> Transform:
        return Transform(self.R_cam_base, self.t_cam_base)

    @property
    def T_base_cam(self) -> Transform:
        return self.T_cam_base.inverse()

    @property
    def covariance_base_cam(self) -> np.ndarray | None:
        """Covariance (6, 6) of :attr:`T_base_cam` about the base axes (first order), or None."""
        return None if self.covariance is None else self.T_cam_base.inverse_covariance(self.covariance)


@dataclass
class Calibration:
    """Result of a calibration: MLE, its covariance, the analytical solution it started from.

    ``R_cam_base``, ``t_cam_base``: camera <- base (``Cp = R Bp + t``; metres). ``covariance``: 6x6 in
    docs/formats.md's convention ``[dtheta (rad), dt (m)]``, ``R_true = Exp(dtheta) R_est``, ``t_true = t_est + dt``.
    ``mirror_vectors``/``mirror_covariances``: per configuration ``(l, m)``, camera frame, metres / m^2.
    ``points``/``point_covariances``: reconstruction points, base frame, metres / m^2. ``residuals``:
    per measurement (N, 2), pixels when the dataset has a camera, else normalized units.
    """

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    covariance: np.ndarray | None
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    mirror_covariances: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]
    point_covariances: dict[str, np.ndarray]
    analytic: AnalyticSolution | None
    iterations: int
    initial_error: float
    final_error: float
    converged: bool
    residuals: np.ndarray
    residual_labels: list[tuple[str, str]]
    residual_units: str
    outliers: list[tuple[str, str, float]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    expected_final_error: float = float("nan")
    restarts: int = 0  # LM runs from the analytical solution's runner-up hypotheses (see calibrate)
    #: Images or measurements left out of the solve, each with its reason (none are silently dropped).
    excluded: list[Exclusion] = field(default_factory=list)
    #: Set where the images split into groups that disagree (a camera or board that moved).
    inconsistency: Inconsistency | None = None
    #: Set where intrinsics were estimated; ``covariance`` then includes their uncertainty.
    camera: EstimatedCamera | None = None
    #: Every camera of a dataset with ``cameras`` (in its order; the first is the top-level pose), else None.
    cameras: dict[str, CameraPose] | None = None
    #: The joint covariance (6C, 6C) of every camera's ``T_cam_base`` in ``cameras`` order, docs/formats.md's
    #: convention per (6, 6) block; None without covariances or without ``cameras``.
    camera_pose_covariance: np.ndarray | None = None
    #: Kalibr's ``T_cn_cnm1`` chain of ``cameras`` (``solver/model/rig.py``), empty with one camera.
    rig: list = field(default_factory=list)
    #: ``{(l, m): camera name}``: the camera frame each mirror vector is in (with ``cameras``), else empty.
    mirror_frames: dict[tuple[int, int], str] = field(default_factory=dict)
    #: Points (metres, camera frame) whose error in the base frame the result gives (``at``, ``calibrate --at``).
    at_points: list[tuple[float, float, float]] = field(default_factory=list)
    #: The held-out validation (``solver/fit/validation.py``, ``calibrate --validate``), else None.
    validation: Any = None
    #: A robot arm's result@1 entries (``mounts``, ``joint_offsets``; ``solver/batch/robot_solve.py``), else None:
    #: then ``T_cam_base`` is the camera mount's inverse and the mirror vectors are in the base link's frame.
    robot: dict | None = None
    #: The images' agreement with each other (``solver/fit/dispersion.py``), else None.
    dispersion: Any = None
    #: Each placement's ``(covariance of v, cross-covariance with the pose)`` (``solver/fit/placement_covariance.py``),
    #: else None.
    placement_covariances: Any = None

    @property
    def T_cam_base(self) -> Transform:
        """Camera <- base as a :class:`~mirror_fg.core.transform.Transform`."""
        return Transform(self.R_cam_base, self.t_cam_base)

    @property
    def T_base_cam(self) -> Transform:
        """Base <- camera (the camera's pose in the base frame, as ROS and URDF want it): the inverse of
        :attr:`T_cam_base`, as ``to_dict()["T_base_cam"]``."""
        return self.T_cam_base.inverse()

    @property
    def covariance_cam_base(self) -> np.ndarray | None:
        """Covariance (6, 6) of :attr:`T_cam_base`, ``[dtheta (rad), dt (m)]`` about the camera axes (as
        :attr:`covariance`; ``to_dict()["covariance_cam_base"]``); None without a covariance."""
        return self.covariance

    @property
    def covariance_base_cam(self) -> np.ndarray | None:
        """Covariance (6, 6) of :attr:`T_base_cam`, ``[dtheta (rad), dt (m)]`` about the base axes
        (``to_dict()["covariance_base_cam"]``, first order); None without a covariance."""
        if self.covariance is None:
            return None
        return self.T_cam_base.inverse_covariance(self.covariance)

    def point_error(self, point_cam, camera: str | None = None, *, link: str | None = None, joints=None):
        """The error at ``point_cam`` (metres, camera frame; e.g. a grasp the camera measures) in the base
        frame, from :attr:`covariance_base_cam` alone (first order, docs/formats.md "The answer in the
        user's units"): a :class:`~mirror_fg.solver.result.point_error.PointError` with ``covariance`` (3, 3, m^2,
        base axes) and ``sigma3_mm``. ``camera``: the camera of a rig whose frame ``point_cam`` is in (default
        the first). ValueError without a covariance, for an unknown camera or a malformed point.

        An arm (``calibrate_robot``): ``link=NAME, joints={joint: value}`` takes ``point_cam`` as a point fixed
        on that link (metres, the link's frame; e.g. a grasp point on the tool flange) with the arm at those
        recorded joint values, and gives the miss between where the camera sees it and where the arm puts it,
        from the camera mount's and the joint offsets' joint covariance (``solver/result/link_point_error.py``)."""
        from mirror_fg.solver.result.point_error import point_error

        if link is not None or joints is not None:
            model = (self.robot or {}).get("link_error")
            if model is None:
                raise ValueError("point_error: link and joints need an arm's calibration with covariances "
                                 "(calibrate_robot, compute_covariance=True)")
            if link is None or joints is None:
                raise ValueError("point_error: give both link (a link name) and joints ({joint: value})")
            from mirror_fg.solver.result.link_point_error import link_point_error

            return link_point_error(model, point_cam, link, joints)

        T, covariance = self.T_base_cam, self.covariance_base_cam
        if camera is not None or self.cameras:
            name = camera if camera is not None else next(iter(self.cameras or {}), None)
            if not self.cameras or name not in self.cameras:
                known = ", ".join(self.cameras or {}) or "none: one camera"
                raise ValueError(f"point_error: no camera {name!r} (cameras: {known})")
            T, covariance = self.cameras[name].T_base_cam, self.cameras[name].covariance_base_cam
        if covariance is None:
            raise ValueError("point_error: the calibration has no covariance (calibrate with compute_covariance=True)")
        return point_error(T, covariance, point_cam)

    @property
    def cost_plausible(self) -> bool:
        """Whether the final cost 0.5 chi^2 fits its distribution at the optimum (dof / 2, spread
        sqrt(dof / 2)) within 10 spreads; far above it means a local minimum or a too small sigma."""
        return plausible(self.final_error, self.expected_final_error)

    @property
    def R_base_cam(self) -> np.ndarray:
        """Rotation of the camera frame in the base frame (``T_base_cam``)."""
        return self.T_cam_base.inverse().R

    @property
    def t_base_cam(self) -> np.ndarray:
        """Camera centre in the base frame, metres."""
        return self.T_cam_base.inverse().t

    @property
    def sigma3_rotation_deg(self) -> np.ndarray | None:
        """3-sigma bounds of the rotation about the camera axes, degrees; None without a covariance
        (``calibrate(..., compute_covariance=False)``)."""
        if self.covariance is None:
            return None
        return np.degrees(3.0 * np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def sigma3_position_mm(self) -> np.ndarray | None:
        """3-sigma bounds of ``t_cam_base`` (camera axes), millimetres; None without a covariance."""
        if self.covariance is None:
            return None
        return 1000.0 * 3.0 * np.sqrt(np.diag(self.covariance)[3:])

    def _summary_rows(self) -> list[tuple[str, str]]:
        """(label, value) rows of :meth:`__repr__` and :meth:`_repr_html_`."""
        def vector(values, digits: int) -> str:
            return "n/a" if values is None else "[" + ", ".join(f"{x:.{digits}f}" for x in values) + "]"

        # An incremental estimate between images carries no residuals (IncrementalCalibrator.calibration).
        measured = len(self.residuals) > 0
        rms = f"{float(np.sqrt(np.mean(self.residual_norms**2))):.4g}" if measured else "not computed"
        measurements = f"{len(self.residuals)} measurements" if measured else "residuals not computed"
        return [
            ("R_cam_base", "; ".join(vector(row, 5) for row in self.R_cam_base)),
            ("t_cam_base (m)", vector(self.t_cam_base, 5)),
            ("3-sigma rotation (deg)", vector(self.sigma3_rotation_deg, 3)),
            ("3-sigma position (mm)", vector(self.sigma3_position_mm, 2)),
            (f"rms reprojection ({self.residual_units})", rms),
            ("iterations", f"{self.iterations} ({'converged' if self.converged else 'NOT converged'}, "
                           f"{self.restarts} restart(s))"),
            ("counts", f"{measurements}, {len(self.mirror_vectors)} mirror placements, "
                       f"{len(self.points)} points"),
        ]

    def __repr__(self) -> str:
        """A few lines: T_cam_base, its 3-sigma bounds, rms, iterations and counts (never every unknown)."""
        return "Calibration(\n" + "".join(f"  {label}: {value}\n" for label, value in self._summary_rows()) + ")"

    def _repr_html_(self) -> str:
        """The summary of :meth:`__repr__` as an HTML table (Jupyter)."""
        from html import escape

        rows = "".join(f"<tr><th style='text-align:left'>{escape(label)}</th><td>{escape(value)}</td></tr>"
                       for label, value in self._summary_rows())
        return f"<table><caption>Calibration</caption>{rows}</table>"

    @property
    def residual_norms(self) -> np.ndarray:
        """Euclidean reprojection error of each measurement (pixels or normalized units)."""
        return np.linalg.norm(self.residuals, axis=1)

    @property
    def fit_ratio(self) -> float:
        """RMS whitened residual over what the noise model allows, ``sqrt(final cost / expected cost)``
        (about 1 at the optimum; NaN where the expected cost is unknown). Above :data:`POOR_FIT_RATIO`
        the fit is poor (:func:`require_converged`)."""
        if not (self.expected_final_error > 0.0 and np.isfinite(self.final_error)):
            return float("nan")
        return float(np.sqrt(self.final_error / self.expected_final_error))

    def to_dict(self) -> dict:
        """The ``mirror-fg/result@1`` dictionary (docs/formats.md), written by ``io.result``."""
        from mirror_fg.io.result import result_dict  # the format's one writer

        return result_dict(self)


def require_converged(
    calibration: Calibration, source: str, solver: str = "Levenberg-Marquardt", accept_poor_fit: bool = False
) -> Calibration:
    """``calibration`` if it can be written: one rule for batch and incremental runs (``mirror-fg
    calibrate`` and ``calibrate-many``).

    SolveError when its solver did not converge, or when the fit is poor (:attr:`Calibration.fit_ratio`
    above :data:`POOR_FIT_RATIO`) unless ``accept_poor_fit``: the message names the likely cause (the
    images it found inconsistent, else wrong labels, pixel_sigma, distortion, a moved camera).
    DatasetError when ``T_cam_base`` puts the base more than :data:`MAX_BASE_DISTANCE_M` from the camera
    or a mirror or point is as far (sizes in millimetres where metres are expected); SolveError when an
    estimate or bound is NaN or infinite (``result_guard``).
    """
    from mirror_fg.solver.result.guard import check_finite, check_within_reach

    if not calibration.converged:
        raise SolveError(f"{source}: {solver} did not converge in {calibration.iterations} iterations "
                         "(stalled); the result was not written")
    check_finite(calibration, source)
    distance = float(np.linalg.norm(calibration.t_cam_base))
    if distance > MAX_BASE_DISTANCE_M:
        raise DatasetError(f"{source}: T_cam_base puts the base {distance:.3g} m from the camera: are the target's "
                           f"sizes in metres? (more than {MAX_BASE_DISTANCE_M:g} m is refused)")
    check_within_reach(calibration, source)
    ratio = calibration.fit_ratio
    if not accept_poor_fit and ratio > POOR_FIT_RATIO:
        cause = (calibration.inconsistency.message if calibration.inconsistency is not None else
                 "likely causes: wrong mirror_configs labels (two images given one placement), a pixel_sigma far "
                 "too small, unmodelled lens distortion, or a camera that moved")
        rms = float(np.sqrt(np.mean(calibration.residual_norms ** 2))) if len(calibration.residuals) else float("nan")
        raise SolveError(f"{source}: the fit is {ratio:.3g} times worse than the noise model allows (RMS "
                         f"{rms:.4g} {calibration.residual_units}; more than {POOR_FIT_RATIO:g}x is refused): {cause}; "
                         "the result was not written (--accept-poor-fit writes it anyway)")
    return calibration
