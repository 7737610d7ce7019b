"""Fisher information and Cramér-Rao bound of the MLE (Hesch et al., eq. 23), NEES, weakest direction.

Unknowns (eq. 21), stacked in this order: ``T_cam_base`` (6, GTSAM's ``Pose3`` tangent ``[w, nu]``,
``R Exp(w)``, ``t + R nu``), one mirror vector per configuration (3 each, camera frame, metres, in
``dataset.configurations`` order) and one base-frame point per reconstruction point (3 each, metres,
in ``dataset.reconstruction_point_names`` order). With iid Gaussian noise of standard deviation
``sigma`` (normalized image units) on every coordinate, the Fisher information at the truth is
``J^T Sigma^-1 J`` with ``J`` the stacked Jacobian of eq. (9) (``geometry.measurement_jacobians``), and
its inverse is the Cramér-Rao bound on the covariance of any unbiased estimator.

Covariances that leave this module follow docs/formats.md: the pose block as ``[dtheta (rad), dt (m)]`` with
``R_true = Exp(dtheta) R_est``, ``t_true = t_est + dt``; errors likewise, "true minus estimate".
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.geometry import measurement_jacobians
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.data import Dataset
from mirror_fg.io.point_sigma import normalized_sigmas
from mirror_fg.solver.model.graph import InitialEstimate as Unknowns  # any values of every unknown (truth, analytic, MLE)

__all__ = [
    "UnknownIndex",
    "Linearization",
    "CramerRaoBound",
    "WeakestDirection",
    "linearize",
    "fisher_information",
    "cramer_rao_bound",
    "pose_error",
    "nees",
    "nees_band",
    "chi2_quantile",
    "weakest_direction",
    "IntrinsicsBound",
    "intrinsics_cramer_rao_bound",
]

POSE_DIM = 6
AXIS_NAMES = (
    "rotation about camera x", "rotation about camera y", "rotation about camera z",
    "translation along camera x", "translation along camera y", "translation along camera z",
)


@dataclass
class UnknownIndex:
    """Column of each unknown in the stacked state: pose at 0..5, then mirrors, then points."""

    mirrors: dict[tuple[int, int], int]
    points: dict[str, int]
    size: int

    @classmethod
    def for_dataset(cls, dataset: Dataset) -> "UnknownIndex":
        mirrors = {config: POSE_DIM + 3 * i for i, config in enumerate(dataset.configurations)}
        start = POSE_DIM + 3 * len(mirrors)
        points = {name: start + 3 * j for j, name in enumerate(dataset.reconstruction_point_names)}
        return cls(mirrors=mirrors, points=points, size=start + 3 * len(points))

    def name_of(self, column: int) -> str:
        """Human name of the unknown that owns a column."""
        if column < POSE_DIM:
            return f"T_cam_base ({AXIS_NAMES[column]})"
        for (l, m), start in self.mirrors.items():
            if start <= column < start + 3:
                return f"mirror {l} placement {m}"
        for name, start in self.points.items():
            if start <= column < start + 3:
                return f"point '{name}'"
        raise IndexError(column)


@dataclass
class Linearization:
    """Whitened normal equations at a linearization point.

    ``information``: ``J^T Sigma^-1 J`` (n x n). ``score``: ``J^T Sigma^-1 (z - h(x))`` (n,), present when
    asked for; one Gauss-Newton step from ``x`` is ``information^-1 score``. ``num_measurements``: number
    of 2-D observations.
    """

    information: np.ndarray
    index: UnknownIndex
    num_measurements: int
    score: np.ndarray | None = None


def _observation_blocks(dataset: Dataset, values: Unknowns, with_residuals: bool):
    """Per observation: local Jacobian (2, 6 + 3 Nv + 3), its columns, and the residual z - h (2,)."""
    index = UnknownIndex.for_dataset(dataset)
    Nv = dataset.num_mirrors
    width = POSE_DIM + 3 * Nv + 3
    dummy = index.size  # column of the absent point block of a fiducial; dropped afterwards
    num_obs = sum(len(image.observations) for image in dataset.images)
    H = np.zeros((num_obs, 2, width))
    columns = np.empty((num_obs, width), dtype=np.int64)
    residuals = np.zeros((num_obs, 2))
    pose_cols = np.arange(POSE_DIM)
    row = 0
    R = np.asarray(values.R_cam_base, dtype=float)
    t = np.asarray(values.t_cam_base, dtype=float)
    for image in dataset.images:
        configs = [(l + 1, m) for l, m in enumerate(image.mirror_configs)]
        vectors = [np.asarray(values.mirror_vectors[c], dtype=float) for c in configs]
        mirror_cols = np.concatenate([index.mirrors[c] + np.arange(3) for c in configs])
        observed = dataset.normalized(image) if with_residuals else None
        for name in image.observations:
            fiducial = dataset.fiducials.get(name)
            base_point = fiducial if fiducial is not None else np.asarray(values.points[name], dtype=float)
            z, H_pose, H_mirrors, H_point = measurement_jacobians(R, t, vectors, base_point)  # eqs. (3)-(9)
            H[row, :, :POSE_DIM] = H_pose
            for k in range(Nv):
                H[row, :, POSE_DIM + 3 * k : POSE_DIM + 3 * k + 3] = H_mirrors[k]
            columns[row, :POSE_DIM] = pose_cols
            columns[row, POSE_DIM : POSE_DIM + 3 * Nv] = mirror_cols
            if fiducial is None:
                H[row, :, -3:] = H_point
                columns[row, -3:] = index.points[name] + np.arange(3)
            else:
                columns[row, -3:] = dummy
            if observed is not None:
                residuals[row] = observed[name] - z
            row += 1
    return index, H, columns, residuals


def _sigma(dataset: Dataset, sigma_normalized: float | Sequence[float] | None) -> np.ndarray:
    """Each observation's sigma (N, 2), in :func:`_observation_blocks`' row order: the given one for all,
    else the dataset's (``point_sigma`` where given, else ``pixel_sigma``, over the focal lengths)."""
    names = [name for image in dataset.images for name in image.observations]
    if sigma_normalized is None:
        return normalized_sigmas(dataset.camera, dataset.pixel_sigma, dataset.point_sigma, names)
    return np.broadcast_to(np.asarray(sigma_normalized, dtype=float), (len(names), 2)).copy()


def linearize(
    dataset: Dataset,
    values: Unknowns,
    sigma_normalized: float | Sequence[float] | None = None,
    with_score: bool = False,
) -> Linearization:
    """Fisher information ``J^T Sigma^-1 J`` of every observation of ``dataset`` at ``values``.

    sigma_normalized: noise standard deviation per image coordinate in normalized units (scalar or
    (x, y)); default the dataset's (``pixel_sigma / f``, ``point_sigma / f`` for the points that have
    one), the same noise model as ``mirror_fg.calibrate``.
    with_score: also form ``J^T Sigma^-1 (z - h(values))`` from the dataset's observations.
    """
    sigma = _sigma(dataset, sigma_normalized)
    index, H, columns, residuals = _observation_blocks(dataset, values, with_score)
    H = H / sigma[:, :, None]  # whiten each image coordinate
    n = index.size + 1
    local = np.einsum("kri,krj->kij", H, H)
    flat = (columns[:, :, None] * n + columns[:, None, :]).ravel()
    information = np.bincount(flat, weights=local.ravel(), minlength=n * n).reshape(n, n)[:-1, :-1]
    score = None
    if with_score:
        local_score = np.einsum("kri,kr->ki", H, residuals / sigma)
        score = np.bincount(columns.ravel(), weights=local_score.ravel(), minlength=n)[:-1]
    return Linearization(information=information, index=index, num_measurements=len(H), score=score)


def fisher_information(
    dataset: Dataset, values: Unknowns, sigma_normalized: float | Sequence[float] | None = None
) -> np.ndarray:
    """``J^T Sigma^-1 J`` (n x n) at ``values``; column order as in :class:`UnknownIndex`."""
    return linearize(dataset, values, sigma_normalized).information


def _invert(information: np.ndarray, index: UnknownIndex, source: str) -> np.ndarray:
    """Inverse of a symmetric positive-definite information matrix, or a SolveError naming the gap."""
    scale = 1.0 / np.sqrt(np.maximum(np.diag(information), np.finfo(float).tiny))
    scaled = information * scale[:, None] * scale[None, :]  # Jacobi scaling: unit diagonal
    try:
        L = np.linalg.cholesky(scaled)
    except np.linalg.LinAlgError:
        L = None
    # Cholesky also succeeds on nearly singular matrices: check the conditioning too.
    if L is not None and (np.min(np.diag(L)) / np.max(np.diag(L))) ** 2 > 1e-13:
        inverse_L = np.linalg.solve(L, np.eye(len(scaled)))
        return (inverse_L.T @ inverse_L) * scale[:, None] * scale[None, :]
    eigenvalues, vectors = np.linalg.eigh(scaled)
    weakest = vectors[:, 0]
    column = int(np.argmax(np.abs(weakest)))
    raise SolveError(
        f"{source}: the measurements do not constrain {index.name_of(column)} "
        f"(Fisher information singular, smallest scaled eigenvalue {eigenvalues[0]:.1e})"
    )


@dataclass
class CramerRaoBound:
    """Inverse Fisher information at the truth: the smallest covariance an unbiased estimator can reach.

    ``pose_covariance``: 6x6 in docs/formats.md's ``[dtheta (rad), dt (m)]`` (camera axes). ``mirror_covariances``
    (camera frame, m^2) and ``point_covariances`` (base frame, m^2) per unknown. ``covariance``: the full
    inverse in the stacked state of :class:`UnknownIndex` (pose block in GTSAM's ``[w, nu]``).
    """

    pose_covariance: np.ndarray
    mirror_covariances: dict[tuple[int, int], np.ndarray]
    point_covariances: dict[str, np.ndarray]
    covariance: np.ndarray
    linearization: Linearization
    R_cam_base: np.ndarray
    _first_order_step: np.ndarray | None = field(default=None, repr=False)

    @property
    def sigma_pose(self) -> np.ndarray:
        """1-sigma of ``[dtheta (rad), dt (m)]``."""
        return np.sqrt(np.diag(self.pose_covariance))

    @property
    def sigma3_rotation_deg(self) -> np.ndarray:
        """3-sigma bounds of the rotation about the camera axes, degrees (as in the paper's Sect. 8)."""
        return np.degrees(3.0 * self.sigma_pose[:3])

    @property
    def sigma3_position_mm(self) -> np.ndarray:
        """3-sigma bounds of ``t_cam_base`` along the camera axes, millimetres."""
        return 3000.0 * self.sigma_pose[3:]

    def first_order_errors(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Errors, true minus estimate, of the first-order (one Gauss-Newton step from the truth) estimator.

        That estimator, ``x_true + I^-1 J^T Sigma^-1 (z - h(x_true))``, is efficient by construction: its
        covariance is this bound. Comparing the MLE's error with it, on the same noise, measures the
        MLE's efficiency without the Monte Carlo sampling error. Needs ``with_score=True``. Returns the
        pose error ``[dtheta, dt]`` (6,) in docs/formats.md's convention and the point errors (base frame, metres).
        """
        if self._first_order_step is None:
            raise ValueError("first_order_errors: build the bound with with_score=True")
        step = self._first_order_step
        R = self.R_cam_base
        pose = -np.concatenate([R @ step[:3], R @ step[3:6]])  # estimate = truth (+) step; docs/formats.md: true - est
        index = self.linearization.index
        points = {name: -step[start : start + 3] for name, start in index.points.items()}
        return pose, points


def cramer_rao_bound(
    dataset: Dataset,
    truth: Unknowns,
    sigma_normalized: float | Sequence[float] | None = None,
    with_score: bool = False,
) -> CramerRaoBound:
    """Cramér-Rao bound of every unknown of ``dataset``, the Fisher information evaluated at ``truth``.

    sigma_normalized: measurement noise in normalized units (default the dataset's, as in
    ``mirror_fg.calibrate``). with_score: also keep the first-order estimator's step (needs the dataset's
    observations; see :meth:`CramerRaoBound.first_order_errors`). Raises ``SolveError`` naming an
    unknown the measurements leave unconstrained.
    """
    lin = linearize(dataset, truth, sigma_normalized, with_score=with_score)
    covariance = _invert(lin.information, lin.index, dataset.source)
    R = np.asarray(truth.R_cam_base, dtype=float)
    pose = covariance_from_pose3(R, covariance[:POSE_DIM, :POSE_DIM])
    mirrors = {c: covariance[s : s + 3, s : s + 3].copy() for c, s in lin.index.mirrors.items()}
    points = {p: covariance[s : s + 3, s : s + 3].copy() for p, s in lin.index.points.items()}
    step = covariance @ lin.score if with_score else None
    return CramerRaoBound(pose, mirrors, points, covariance, lin, R, step)


# --- errors and consistency ----------------------------------------------------------------------


def pose_error(R_true: np.ndarray, t_true: np.ndarray, R_est: np.ndarray, t_est: np.ndarray) -> np.ndarray:
    """docs/formats.md's ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) R_est``, ``t_true = t_est + dt``."""
    dtheta = gtsam.Rot3.Logmap(gtsam.Rot3(np.asarray(R_true, dtype=float) @ np.asarray(R_est, dtype=float).T))
    return np.concatenate([np.asarray(dtheta, dtype=float), np.asarray(t_true, float) - np.asarray(t_est, float)])


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Normalized estimation error squared ``e^T P^-1 e`` of each run.

    errors: (n, d) or (d,); covariances: (n, d, d) or (d, d), one per run (or one shared). For a
    consistent estimator each value is chi-square with d degrees of freedom (mean d).
    """
    e = np.atleast_2d(np.asarray(errors, dtype=float))
    P = np.asarray(covariances, dtype=float)
    P = np.broadcast_to(P, (len(e), e.shape[1], e.shape[1]))
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])


def _regularized_gamma_p(a: float, x: float) -> float:
    """Lower regularized incomplete gamma ``P(a, x)`` (series below a+1, continued fraction above)."""
    if x <= 0.0:
        return 0.0
    log_prefix = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        ap = a
        for _ in range(100_000):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * 1e-15:
                break
        return total * math.exp(log_prefix)
    # Lentz's continued fraction for Q(a, x).
    tiny = 1e-300
    b = x + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    for i in range(1, 100_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return 1.0 - math.exp(log_prefix) * h


def chi2_quantile(probability: float, dof: float) -> float:
    """Quantile of the chi-square distribution (bisection on the regularized incomplete gamma)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability}")
    z = NormalDist().inv_cdf(probability)
    guess = dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3  # Wilson-Hilferty
    lo, hi = 0.0, max(guess, 1e-8)
    while _regularized_gamma_p(dof / 2.0, hi / 2.0) < probability:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _regularized_gamma_p(dof / 2.0, mid / 2.0) < probability:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * max(hi, 1.0):
            break
    return 0.5 * (lo + hi)


def nees_band(num_runs: int, dof: int = POSE_DIM, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided ``confidence`` band of the *mean* NEES over ``num_runs`` independent consistent runs.

    ``num_runs * mean`` is chi-square with ``num_runs * dof`` degrees of freedom.
    """
    if num_runs < 1:
        raise ValueError("nees_band: need at least one run")
    k = num_runs * dof
    tail = (1.0 - confidence) / 2.0
    return chi2_quantile(tail, k) / num_runs, chi2_quantile(1.0 - tail, k) / num_runs


# --- weakest direction -------------------------------------------------------------------------------


@dataclass
class WeakestDirection:
    """Least-constrained direction of a 6x6 docs/formats.md pose covariance (eigenvector of the smallest information).

    Rotations are scaled by ``lever_arm_m`` (a rotation of 1 mrad moves a point that far away by
    ``lever_arm_m`` mm) so that both halves are in metres. ``vector``: unit eigenvector in the scaled
    ``[dtheta * lever_arm, dt]``; ``shares``: its squared components (sum 1); ``sigma_m``: 1-sigma along
    it in scaled metres; ``text``: one sentence.
    """

    vector: np.ndarray
    shares: np.ndarray
    sigma_m: float
    lever_arm_m: float
    text: str


def weakest_direction(pose_covariance: np.ndarray, lever_arm_m: float = 1.0) -> WeakestDirection:
    """The eigenvector of the smallest information (largest covariance) of ``T_cam_base``, in words."""
    scale = np.array([lever_arm_m] * 3 + [1.0] * 3)
    scaled = np.asarray(pose_covariance, dtype=float) * scale[:, None] * scale[None, :]
    eigenvalues, vectors = np.linalg.eigh(scaled)
    u = vectors[:, -1]
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    shares = u**2
    order = [int(i) for i in np.argsort(shares)[::-1]]
    main = order[0]
    sigma = math.sqrt(max(eigenvalues[-1], 0.0))
    sigma_text = (
        f"{math.degrees(sigma / lever_arm_m):.3g} deg" if main < 3 else f"{1000.0 * sigma:.3g} mm"
    )
    text = f"{AXIS_NAMES[main]} is the weakest ({100 * shares[main]:.0f} % of the direction, 1-sigma {sigma_text}"
    partners = [i for i in order[1:] if shares[i] >= 0.10]
    if partners:
        text += "; coupled with " + ", ".join(f"{AXIS_NAMES[i]} ({100 * shares[i]:.0f} %)" for i in partners)
    text += f"; rotations weighed at a {lever_arm_m:g} m lever arm)"
    return WeakestDirection(vector=u, shares=shares, sigma_m=sigma, lever_arm_m=lever_arm_m, text=text)


# --- with the intrinsics among the unknowns -----------------------------------------------


@dataclass
class IntrinsicsBound:
    """Cramér-Rao bound with the intrinsics ``names`` (INTRINSIC_NAMES order) estimated too.

    ``covariance``: (k, k) over the intrinsics (px^2 for fx, fy, cx, cy; unitless for k1..).
    ``pose_covariance``: 6x6 docs/formats.md ``[dtheta (rad), dt (m)]`` of ``T_cam_base`` with the intrinsics'
    uncertainty included. ``cross``: (k, 6) between the intrinsics and that pose error.
    """

    names: tuple[str, ...]
    covariance: np.ndarray
    pose_covariance: np.ndarray
    cross: np.ndarray

    @property
    def sigma3(self) -> dict[str, float]:
        """3-sigma of each intrinsic (pixels or unitless)."""
        return {n: float(3.0 * np.sqrt(self.covariance[i, i])) for i, n in enumerate(self.names)}


def intrinsics_cramer_rao_bound(
    dataset: Dataset, truth: Unknowns, estimate: Sequence[str], sigma_px: float | None = None
) -> IntrinsicsBound:
    """Cramér-Rao bound of ``T_cam_base`` and of the intrinsics ``estimate`` of ``dataset.camera``.

    The Fisher information of the one model's views in pixels (``model/views.py`` through
    ``factors/intrinsics.py``: eqs. 2-9, then OpenCV's lens and ``K``) at ``truth`` and the camera's values
    (the pose's and the intrinsics' bounds do not depend on the planes' coordinates), iid noise ``sigma_px`` pixels (default the dataset's
    ``pixel_sigma``). Raises ``SolveError`` naming an unknown the measurements leave unconstrained.
    """
    from dataclasses import replace

    from mirror_fg.factors.intrinsics import IntrinsicsModel
    from mirror_fg.solver.batch.intrinsics import camera_intrinsics
    from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem, tangent_dimension

    camera = dataset.camera
    if camera is None:
        raise SolveError(f"{dataset.source}: intrinsics need pixel data (a camera)")
    sigma = dataset.pixel_sigma if sigma_px is None else float(sigma_px)
    model = IntrinsicsModel(camera_intrinsics(camera), estimate)
    # the one model's views in pixels, every measurement at ``sigma``, no prior: the images' information alone
    problem = ViewProblem(replace(dataset, camera=replace(camera, prior_sigma=()), pixel_sigma=sigma, point_sigma={}),
                          intrinsics={SINGLE_CAMERA: model})
    graph = problem.graph()
    values = problem.values(ViewEstimate(
        {SINGLE_CAMERA: (np.asarray(truth.R_cam_base, float), np.asarray(truth.t_cam_base, float))},
        {p: np.asarray(truth.mirror_vectors[p], float) for p in problem.placements},
        {n: np.asarray(truth.points[n], float) for n in problem.point_names}, {SINGLE_CAMERA: model.fixed.copy()}))
    keys = [problem.pose_keys[SINGLE_CAMERA], problem.intrinsics_keys[SINGLE_CAMERA],
            *problem.mirror_keys.values(), *problem.point_keys.values()]
    ordering = gtsam.Ordering()
    for key in keys:
        ordering.push_back(key)
    information, _ = graph.linearize(values).hessian(ordering)
    k = len(model.estimated)
    scale = 1.0 / np.sqrt(np.maximum(np.diag(information), np.finfo(float).tiny))
    eigenvalues, vectors = np.linalg.eigh(information * scale[:, None] * scale[None, :])
    if not eigenvalues[0] > 1e-13 * eigenvalues[-1]:
        column = int(np.argmax(np.abs(vectors[:, 0])))
        key_of_column = [key for key in keys for _ in range(tangent_dimension(key, values))]
        name = (model.estimated[column - POSE_DIM] if POSE_DIM <= column < POSE_DIM + k
                else problem.name_of(key_of_column[column]))
        raise SolveError(f"{dataset.source}: the measurements do not constrain {name} "
                         f"(Fisher information singular, smallest scaled eigenvalue {eigenvalues[0]:.1e})")
    covariance = (vectors / eigenvalues) @ vectors.T * scale[:, None] * scale[None, :]
    R = np.asarray(truth.R_cam_base, dtype=float)
    to_spec = np.zeros((6, 6))
    to_spec[:3, :3] = R
    to_spec[3:, 3:] = R
    return IntrinsicsBound(
        names=model.estimated,
        covariance=covariance[POSE_DIM : POSE_DIM + k, POSE_DIM : POSE_DIM + k],
        pose_covariance=covariance_from_pose3(R, covariance[:POSE_DIM, :POSE_DIM]),
        cross=covariance[POSE_DIM : POSE_DIM + k, :POSE_DIM] @ to_spec.T,
    )
