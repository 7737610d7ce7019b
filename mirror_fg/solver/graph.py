"""Factor graph from a dataset, Levenberg-Marquardt MLE (eq. 23) and Marginals -> ``Calibration``.

Unknowns (eq. 21): one ``Pose3`` node ``X(0)`` for ``T_cam_base`` (camera <- base), one ``Point3`` node
``V(i)`` per mirror configuration (mirror vector, camera frame, metres) and one ``Point3`` node ``L(j)``
per reconstruction point (base frame, metres).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, V, X

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import RESULT_FORMAT, Dataset, dataset_from_dict
from mirror_fg.solver.analytic import AnalyticSolution, reconstruct_points, solve_analytic
from mirror_fg.factors.batched import batched_factors
from mirror_fg.factors.reflection import ReflectionFactor, noise_model
from mirror_fg.core.geometry import nested_transform, project
from mirror_fg.core.transform import rotation_to_quaternion_xyzw, spec_covariance_from_pose3

__all__ = ["Calibration", "InitialEstimate", "GraphLayout", "build_graph", "calibrate", "initial_estimate", "OUTLIER_SIGMAS"]

#: Measurements whose whitened residual exceeds this many sigmas after the solve are reported.
OUTLIER_SIGMAS = 5.0


class InitialEstimate(Protocol):
    """Anything with the unknowns' values: an ``AnalyticSolution`` or a ground truth."""

    R_cam_base: np.ndarray
    t_cam_base: np.ndarray
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray]


@dataclass
class GraphLayout:
    """Which key holds which unknown."""

    pose_key: int
    mirror_keys: dict[tuple[int, int], int]
    point_keys: dict[str, int]

    @classmethod
    def for_dataset(cls, dataset: Dataset) -> "GraphLayout":
        return cls(
            pose_key=X(0),
            mirror_keys={config: V(i) for i, config in enumerate(dataset.configurations)},
            point_keys={name: L(j) for j, name in enumerate(dataset.reconstruction_point_names)},
        )

    def name_of(self, key: int) -> str:
        """Human name of the unknown behind a key."""
        if key == self.pose_key:
            return "T_cam_base"
        for (l, m), k in self.mirror_keys.items():
            if k == key:
                return f"mirror {l} placement {m}"
        for name, k in self.point_keys.items():
            if k == key:
                return f"point '{name}'"
        return gtsam.DefaultKeyFormatter(key)


@dataclass
class Measurement:
    """One observation: image, point name, normalized coordinates (2,), the image's mirror configs."""

    image_id: str
    point: str
    normalized: np.ndarray
    mirror_configs: tuple[int, ...]


def measurements_of(dataset: Dataset) -> list[Measurement]:
    """Every observation of the dataset in normalized coordinates, in file order."""
    result = []
    for image in dataset.images:
        normalized = dataset.normalized(image)
        for name in image.observations:
            result.append(Measurement(image.id, name, normalized[name], image.mirror_configs))
    return result


def measurement_factor(
    dataset: Dataset, layout: GraphLayout, meas: Measurement, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """The reflection factor of one measurement (fiducial constant, or landmark node)."""
    mirror_keys = [layout.mirror_keys[(l + 1, m)] for l, m in enumerate(meas.mirror_configs)]
    if meas.point in dataset.fiducials:
        return ReflectionFactor(noise, layout.pose_key, mirror_keys, meas.normalized, fiducial=dataset.fiducials[meas.point])
    return ReflectionFactor(noise, layout.pose_key, mirror_keys, meas.normalized, landmark_key=layout.point_keys[meas.point])


def build_graph(
    dataset: Dataset, initial: InitialEstimate, robust: str | None = None, fast: bool = True
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, GraphLayout, list[Measurement]]:
    """Factor graph of every measurement and the initial values of every unknown.

    fast: stacked, vectorised factors (``factors/batched.py``, same model and Jacobians, per-measurement
    robust weights); otherwise one reference ``ReflectionFactor`` per measurement.
    """
    layout = GraphLayout.for_dataset(dataset)
    graph = gtsam.NonlinearFactorGraph()
    measurements = measurements_of(dataset)
    if fast:
        for factor in batched_factors(dataset, layout, measurements, dataset.normalized_sigma, robust):
            graph.add(factor)
    else:
        noise = noise_model(dataset.normalized_sigma, robust)
        for meas in measurements:
            graph.add(measurement_factor(dataset, layout, meas, noise))
    values = gtsam.Values()
    values.insert(layout.pose_key, gtsam.Pose3(gtsam.Rot3(initial.R_cam_base), np.asarray(initial.t_cam_base, dtype=float)))
    for config, key in layout.mirror_keys.items():
        values.insert(key, np.asarray(initial.mirror_vectors[config], dtype=float))
    for name, key in layout.point_keys.items():
        values.insert(key, np.asarray(initial.points[name], dtype=float))
    return graph, values, layout, measurements


@dataclass
class Calibration:
    """Result of a calibration: MLE, its covariance, the analytical solution it started from.

    ``R_cam_base``, ``t_cam_base``: camera <- base (``Cp = R Bp + t``; metres). ``covariance``: 6x6 in
    SPEC's convention ``[dtheta (rad), dt (m)]``, ``R_true = Exp(dtheta) R_est``, ``t_true = t_est + dt``.
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

    @property
    def cost_plausible(self) -> bool:
        """Whether the final cost 0.5 chi^2 fits its distribution at the optimum (dof / 2, spread
        sqrt(dof / 2)) within 10 spreads; far above it means a local minimum or a too small sigma."""
        return _plausible(self.final_error, self.expected_final_error)

    @property
    def R_base_cam(self) -> np.ndarray:
        """Rotation of the camera frame in the base frame (``T_base_cam``)."""
        return self.R_cam_base.T

    @property
    def t_base_cam(self) -> np.ndarray:
        """Camera centre in the base frame, metres."""
        return -self.R_cam_base.T @ self.t_cam_base

    @property
    def sigma3_rotation_deg(self) -> np.ndarray:
        """3-sigma bounds of the rotation about the camera axes, degrees."""
        return np.degrees(3.0 * np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def sigma3_position_mm(self) -> np.ndarray:
        """3-sigma bounds of ``t_cam_base`` (camera axes), millimetres."""
        return 1000.0 * 3.0 * np.sqrt(np.diag(self.covariance)[3:])

    @property
    def residual_norms(self) -> np.ndarray:
        """Euclidean reprojection error of each measurement (pixels or normalized units)."""
        return np.linalg.norm(self.residuals, axis=1)

    def to_dict(self) -> dict:
        """The ``mirror-fg/result@1`` dictionary (docs/formats.md)."""

        def transform(R: np.ndarray, t: np.ndarray) -> dict:
            return {"R": R.tolist(), "t": np.asarray(t).tolist(), "q_xyzw": rotation_to_quaternion_xyzw(R).tolist()}

        norms = self.residual_norms
        result = {
            "format": RESULT_FORMAT,
            "T_cam_base": transform(self.R_cam_base, self.t_cam_base),
            "T_base_cam": transform(self.R_base_cam, self.t_base_cam),
            "covariance_cam_base": None if self.covariance is None else self.covariance.tolist(),
            "sigma3_cam_base": None
            if self.covariance is None
            else {"rotation_deg": self.sigma3_rotation_deg.tolist(), "position_mm": self.sigma3_position_mm.tolist()},
            "analytic": None
            if self.analytic is None
            else {"T_cam_base": transform(self.analytic.R_cam_base, self.analytic.t_cam_base)},
            "mirrors": [
                {
                    "mirror": l,
                    "config": m,
                    "v": self.mirror_vectors[(l, m)].tolist(),
                    "sigma3_mm": _sigma3_mm(self.mirror_covariances.get((l, m))),
                }
                for l, m in sorted(self.mirror_vectors)
            ],
            "points": {
                name: {"xyz": self.points[name].tolist(), "sigma3_mm": _sigma3_mm(self.point_covariances.get(name))}
                for name in sorted(self.points)
            },
            "optimizer": {
                "iterations": self.iterations,
                "initial_error": self.initial_error,
                "final_error": self.final_error,
                "expected_final_error": self.expected_final_error,
                "converged": self.converged,
            },
            "residuals": {
                "rms_px": float(np.sqrt(np.mean(norms**2))) if len(norms) else 0.0,
                "max_px": float(np.max(norms)) if len(norms) else 0.0,
                "mean_px": float(np.mean(norms)) if len(norms) else 0.0,
                "units": self.residual_units,
                "outliers": [
                    {"image": image, "point": point, "sigmas": sigmas} for image, point, sigmas in self.outliers
                ],
            },
        }
        return result


def _sigma3_mm(covariance: np.ndarray | None) -> list[float] | None:
    if covariance is None:
        return None
    return (1000.0 * 3.0 * np.sqrt(np.diag(covariance))).tolist()


def predicted_normalized(
    dataset: Dataset, measurements: list[Measurement], R: np.ndarray, t: np.ndarray,
    mirror_vectors: dict[tuple[int, int], np.ndarray], points: dict[str, np.ndarray],
) -> np.ndarray:
    """Predicted normalized coordinates (N, 2) of every measurement (eqs. 5, 9), one (A, b) per image."""
    base_points = np.array(
        [dataset.fiducials[m.point] if m.point in dataset.fiducials else points[m.point] for m in measurements]
    ).reshape(-1, 3)
    transforms: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}
    A = np.empty((len(measurements), 3, 3))
    b = np.empty((len(measurements), 3))
    for i, meas in enumerate(measurements):
        transform = transforms.get(meas.mirror_configs)
        if transform is None:
            vectors = [mirror_vectors[(l + 1, m)] for l, m in enumerate(meas.mirror_configs)]
            transform = transforms[meas.mirror_configs] = nested_transform(R, t, vectors)
        A[i], b[i] = transform
    return project(np.einsum("iab,ib->ia", A, base_points) + b)


def residual_statistics(
    dataset: Dataset, measurements: list[Measurement], predicted: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 2) predicted minus observed, in pixels (through the distortion) where the dataset
    has a camera, else normalized; and each measurement's whitened residual norm in sigmas."""
    observed_normalized = np.array([m.normalized for m in measurements]).reshape(-1, 2)
    whitened = np.linalg.norm((predicted - observed_normalized) / dataset.normalized_sigma, axis=1)
    if dataset.camera is None:
        return predicted - observed_normalized, whitened
    by_id = {image.id: image for image in dataset.images}
    observed_pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements]).reshape(-1, 2)
    return dataset.camera.distort(predicted) - observed_pixels, whitened


def extract_values(values: gtsam.Values, layout: GraphLayout) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """``(R_cam_base, t_cam_base, mirror_vectors, points)`` read from GTSAM values."""
    pose = values.atPose3(layout.pose_key)
    mirror_vectors = {config: np.array(values.atPoint3(key)) for config, key in layout.mirror_keys.items()}
    points = {name: np.array(values.atPoint3(key)) for name, key in layout.point_keys.items()}
    return pose.rotation().matrix(), np.array(pose.translation()), mirror_vectors, points


def marginal_covariances(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: GraphLayout, source: str
) -> tuple[np.ndarray, dict, dict]:
    """Pose covariance (SPEC convention), mirror and point covariances at ``values``.

    The information matrix ``J^T J`` of the linearised graph is split into the last mirror's
    placements, which never share a measurement (so their block is block-diagonal), and everything
    else; the Schur complement gives every marginal exactly, far faster than per-key
    ``gtsam.Marginals`` queries. Should a factor ever couple two of those placements, this falls back
    to ``gtsam.Marginals``.
    """
    last_mirror = max(l for l, _ in layout.mirror_keys) if layout.mirror_keys else 0
    diagonal_keys = [k for (l, _), k in layout.mirror_keys.items() if l == last_mirror]
    diagonal_index = {k: i for i, k in enumerate(diagonal_keys)}
    rest_keys = [layout.pose_key] + [k for (l, _), k in layout.mirror_keys.items() if l != last_mirror]
    rest_keys += list(layout.point_keys.values())
    rest_offset, size = {}, 0
    for key in rest_keys:
        rest_offset[key] = size
        size += 6 if key == layout.pose_key else 3
    A = np.zeros((size, size))  # rest-rest information
    B = np.zeros((len(diagonal_keys), size, 3))  # rest-placement information
    D = np.zeros((len(diagonal_keys), 3, 3))  # placement information (block-diagonal)
    linear = graph.linearize(values)
    for f in range(linear.size()):
        factor = linear.at(f)
        J = factor.jacobian()[0]  # whitened, columns in the factor's key order
        rest_columns, rest_index, diagonal_blocks = [], [], []
        column = 0
        for key in factor.keys():
            width = 6 if key == layout.pose_key else 3
            if key in diagonal_index:
                diagonal_blocks.append((diagonal_index[key], J[:, column : column + width]))
            else:
                rest_columns.extend(range(column, column + width))
                rest_index.extend(range(rest_offset[key], rest_offset[key] + width))
            column += width
        J_rest = J[:, rest_columns]
        A[np.ix_(rest_index, rest_index)] += J_rest.T @ J_rest
        for n, (i, block) in enumerate(diagonal_blocks):
            B[i][rest_index] += J_rest.T @ block
            D[i] += block.T @ block
            for _, other in diagonal_blocks[n + 1 :]:
                if np.any(block.T @ other != 0.0):
                    return _marginals_from_gtsam(graph, values, layout, source)
    try:
        D_inv = np.linalg.inv(D)
        BD = B @ D_inv  # B_i D_i^-1, (n, size, 3)
        schur = A - BD.transpose(1, 0, 2).reshape(size, -1) @ B.transpose(1, 0, 2).reshape(size, -1).T
        rest_covariance = np.linalg.inv(schur)
    except np.linalg.LinAlgError:
        return _marginals_from_gtsam(graph, values, layout, source)
    if not np.all(np.isfinite(rest_covariance)) or np.min(np.linalg.eigvalsh(schur)) <= 1e-12 * np.max(np.diag(schur)):
        return _marginals_from_gtsam(graph, values, layout, source)
    DB = BD.transpose(0, 2, 1)  # D_i^-1 B_i^T (D symmetric)
    diagonal_covariances = D_inv + (DB @ rest_covariance) @ BD
    pose = values.atPose3(layout.pose_key)
    covariance = spec_covariance_from_pose3(pose.rotation().matrix(), rest_covariance[:6, :6])

    def block(key: int) -> np.ndarray:
        if key in diagonal_index:
            return diagonal_covariances[diagonal_index[key]]
        o = rest_offset[key]
        return rest_covariance[o : o + 3, o : o + 3]

    mirrors = {config: block(key) for config, key in layout.mirror_keys.items()}
    points = {name: block(key) for name, key in layout.point_keys.items()}
    return covariance, mirrors, points


def _marginals_from_gtsam(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, layout: GraphLayout, source: str
) -> tuple[np.ndarray, dict, dict]:
    """The same marginals from ``gtsam.Marginals`` (also names unconstrained unknowns)."""
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as error:  # IndeterminantLinearSystemException surfaces as RuntimeError
        raise SolveError(f"{source}: {unconstrained_message(error, layout)}") from None
    pose = values.atPose3(layout.pose_key)
    covariance = spec_covariance_from_pose3(pose.rotation().matrix(), marginals.marginalCovariance(layout.pose_key))
    mirrors = {config: marginals.marginalCovariance(key) for config, key in layout.mirror_keys.items()}
    points = {name: marginals.marginalCovariance(key) for name, key in layout.point_keys.items()}
    return covariance, mirrors, points


def unconstrained_message(error: Exception, layout: GraphLayout) -> str:
    """Name the unknown GTSAM found unconstrained in an indeterminant linear system."""
    text = str(error)
    for key in [layout.pose_key, *layout.mirror_keys.values(), *layout.point_keys.values()]:
        if gtsam.DefaultKeyFormatter(key) in text:
            return f"the data do not constrain {layout.name_of(key)} (indeterminant system near it)"
    return "the data leave some unknowns unconstrained (indeterminant linear system)"


#: Normalized measurement noise at which the LM settings below were chosen: 1 px at fx = 800 px
#: (the paper's base case).
REFERENCE_NORMALIZED_SIGMA = 1.0 / 800.0


def cost_scale(dataset: Dataset) -> float:
    """How many times larger every whitened cost, gradient and Hessian are than at the reference noise.

    With a uniform ``pixel_sigma`` the MLE does not depend on it, but the cost scales as
    ``1 / sigma^2``: every absolute threshold of LM (its damping, its absolute tolerance, the stall
    test) is multiplied by this factor so that LM takes the same steps whatever the sigma.
    """
    sigma = float(np.sqrt(np.prod(dataset.normalized_sigma)))
    return (REFERENCE_NORMALIZED_SIGMA / sigma) ** 2


def lm_params(max_iterations: int, scale: float = 1.0) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt settings of the MLE (eq. 23): tight tolerances, at most ``max_iterations``.

    ``scale``: :func:`cost_scale` of the data; the damping and the absolute tolerance scale with it
    (GTSAM's defaults, 1e-5 and 1e5 for the damping, hold at the reference noise).
    """
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12 * scale)
    params.setlambdaInitial(1e-5 * scale)
    params.setlambdaUpperBound(1e5 * scale)
    return params


def _stationary(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, error: float, scale: float) -> bool:
    """Whether the Gauss-Newton step at ``values`` promises (almost) no decrease of the error
    (relative to the error, or to ``scale`` (:func:`cost_scale`) near a zero error)."""
    linear = graph.linearize(values)
    try:
        step = linear.optimize()
    except RuntimeError:  # indeterminant: not a well-defined optimum
        return False
    zero = step.scale(0.0)
    predicted_decrease = linear.error(zero) - linear.error(step)
    return predicted_decrease <= 1e-6 * max(error, scale)


def _plausible(final_error: float, expected_final_error: float) -> bool:
    """Whether a final cost 0.5 chi^2 is within 10 spreads (sqrt(dof / 2)) above its mean dof / 2."""
    spread = np.sqrt(max(expected_final_error, 1.0))
    return not final_error > expected_final_error + 10.0 * spread


#: At most this many restarts of LM from the analytical solution's runner-up hypotheses.
MAX_RESTARTS = 4


@dataclass
class _Run:
    """One Levenberg-Marquardt run of :func:`calibrate`."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    result: gtsam.Values
    layout: GraphLayout
    measurements: list[Measurement]
    initial_error: float
    final_error: float
    iterations: int
    converged: bool


def _levenberg_marquardt(
    dataset: Dataset, initial: InitialEstimate, robust: str | None, fast: bool, max_iterations: int,
    on_iteration: Callable[[int, float, float], None] | None, timings: dict[str, float],
) -> _Run:
    """Build the graph from ``initial`` and run LM (eq. 23); times added to ``timings``."""
    start = time.perf_counter()
    graph, values, layout, measurements = build_graph(dataset, initial, robust, fast=fast)
    timings["build"] = timings.get("build", 0.0) + time.perf_counter() - start

    start = time.perf_counter()
    scale = cost_scale(dataset)
    params = lm_params(max_iterations, scale)
    if on_iteration is not None:
        params.iterationHook = on_iteration
    initial_error = graph.error(values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    try:
        result = optimizer.optimize()
    except RuntimeError as error:
        raise SolveError(f"{dataset.source}: {unconstrained_message(error, layout)}") from None
    final_error = graph.error(result)
    iterations = optimizer.iterations()
    # LM also stops when its damping hits the upper bound: a stall unless a Gauss-Newton step
    # would no longer lower the error (then it is at a stationary point, e.g. noise-free data).
    stalled = optimizer.lambda_() >= params.getlambdaUpperBound() and not _stationary(graph, result, final_error, scale)
    converged = bool(np.isfinite(final_error)) and iterations < max_iterations and not stalled
    timings["optimize"] = timings.get("optimize", 0.0) + time.perf_counter() - start
    return _Run(graph, values, result, layout, measurements, float(initial_error), float(final_error), iterations,
                converged)


#: LM iterations allowed when refining one subtree hypothesis of the initial estimate.
SUBTREE_MAX_ITERATIONS = 50
#: Relative decrease of the cost below which a subtree refinement stops.
SUBTREE_RELATIVE_TOLERANCE = 1e-4


def _refine_subtree(subtree: Dataset, closed_form: AnalyticSolution) -> tuple[float, AnalyticSolution] | None:
    """The MLE (eq. 23) of one subtree's own images from its closed-form hypothesis: its cost and values."""
    try:
        graph, values, layout, _ = build_graph(subtree, closed_form, None)
        params = lm_params(SUBTREE_MAX_ITERATIONS, cost_scale(subtree))
        params.setRelativeErrorTol(SUBTREE_RELATIVE_TOLERANCE)  # a start and a ranking: no need for the last digits
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except (RuntimeError, SolveError):  # an under-determined subtree: no refinement, no score
        return None
    R, t, mirror_vectors, _ = extract_values(result, layout)
    return float(graph.error(result)), AnalyticSolution(R, t, mirror_vectors)


def initial_estimate(dataset: Dataset, seed: int = 0) -> AnalyticSolution:
    """The initial guess of :func:`calibrate`: the analytical solution (Sects. 4-5) with every P3P
    hypothesis of a mirror placement below the root refined on its own images by LM before the
    levels above choose between them (``analytic.solve_analytic(refine_subtree=...)``).

    The closed form alone weights every PnP pose equally, so under noise (2 px, or a mirror 0.25 m
    away) a mirror placement whose images mostly took the wrong P3P twin can look better than the
    right one and start LM in another minimum; refined, the right hypothesis is the cheaper one.
    Frames and units as :class:`~mirror_fg.solver.analytic.AnalyticSolution`.
    """
    return solve_analytic(dataset, seed, refine_subtree=_refine_subtree)


def as_dataset(data: Dataset | Mapping[str, Any], what: str = "calibrate()") -> Dataset:
    """``data`` as a :class:`Dataset` (a dataset@1 dictionary is validated) that the solver can take.

    Raises DatasetError on anything else, or where the dataset asks for what this version cannot do
    (intrinsics estimated through the mirrors, ``camera.estimate``).
    """
    if isinstance(data, Mapping):
        data = dataset_from_dict(data, source="<dataset dict>")
    if not isinstance(data, Dataset):
        raise DatasetError(f"{what}: expected a mirror_fg.Dataset or a dataset@1 dictionary, got {type(data).__name__}")
    if data.camera is not None and data.camera.estimate:
        raise DatasetError(f"{data.source}: camera.estimate ({', '.join(data.camera.estimate)}): estimating "
                           "intrinsics through the mirrors is not supported by this version")
    return data


def require_converged(calibration: Calibration, source: str, solver: str = "Levenberg-Marquardt") -> Calibration:
    """``calibration`` if its solver converged, else SolveError: one rule for batch and incremental runs."""
    if not calibration.converged:
        raise SolveError(f"{source}: {solver} did not converge in {calibration.iterations} iterations "
                         "(stalled); the result was not written")
    return calibration


def calibrate(
    dataset: Dataset | Mapping[str, Any],
    *,
    initial: InitialEstimate | None = None,
    robust: str | None = None,
    compute_covariance: bool = True,
    max_iterations: int = 100,
    on_iteration: Callable[[int, float, float], None] | None = None,
    fast: bool = True,
) -> Calibration:
    """Analytical solution (Sects. 4-5), then the MLE by Levenberg-Marquardt (eq. 23) and Marginals.

    initial: start the MLE from these values instead of the analytical solution (e.g. the ground truth).
    robust: ``None``, ``"huber"`` or ``"cauchy"`` kernel on every measurement. on_iteration: called with
    ``(iteration, error_before, error_after)`` after each LM iteration. fast: stacked vectorised
    factors (default) or the per-measurement reference factors (same estimates).
    """
    dataset = as_dataset(dataset)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    analytic = None
    if initial is None:
        analytic = initial_estimate(dataset)
        initial = analytic
    timings["analytic"] = time.perf_counter() - start

    run = _levenberg_marquardt(dataset, initial, robust, fast, max_iterations, on_iteration, timings)
    graph, result, layout, measurements, values = run.graph, run.result, run.layout, run.measurements, run.values
    expected_final_error = 0.5 * max(2 * len(measurements) - values.dim(), 0)
    restarts = 0
    if analytic is not None and not (run.converged and _plausible(run.final_error, expected_final_error)):
        # A cost far above its chi-square range: LM stopped in another minimum. Start again from the
        # root's runner-up hypotheses (best fiducial reprojection first); keep the lowest cost.
        for alternative in analytic.alternatives[:MAX_RESTARTS]:
            if not alternative.points and layout.point_keys:
                alternative.points = reconstruct_points(dataset, alternative)
            restarts += 1
            try:
                other = _levenberg_marquardt(dataset, alternative, robust, fast, max_iterations, None, timings)
            except SolveError:
                continue
            if (other.converged, -other.final_error) > (run.converged, -run.final_error):
                run, analytic = other, alternative
            if run.converged and _plausible(run.final_error, expected_final_error):
                break
        graph, result, layout, measurements, values = run.graph, run.result, run.layout, run.measurements, run.values
    initial_error, final_error, iterations, converged = run.initial_error, run.final_error, run.iterations, run.converged

    start = time.perf_counter()
    covariance, mirror_covs, point_covs = (None, {}, {})
    if compute_covariance:
        covariance, mirror_covs, point_covs = marginal_covariances(graph, result, layout, dataset.source)
    timings["marginals"] = time.perf_counter() - start

    start = time.perf_counter()
    R, t, mirror_vectors, points = extract_values(result, layout)
    predicted = predicted_normalized(dataset, measurements, R, t, mirror_vectors, points)
    residuals, whitened = residual_statistics(dataset, measurements, predicted)
    outliers = [
        (meas.image_id, meas.point, float(w)) for meas, w in zip(measurements, whitened) if w > OUTLIER_SIGMAS
    ]
    timings["residuals"] = time.perf_counter() - start
    return Calibration(
        R_cam_base=R,
        t_cam_base=t,
        covariance=covariance,
        mirror_vectors=mirror_vectors,
        mirror_covariances=mirror_covs,
        points=points,
        point_covariances=point_covs,
        analytic=analytic,
        iterations=iterations,
        initial_error=float(initial_error),
        expected_final_error=expected_final_error,
        restarts=restarts,
        final_error=float(final_error),
        converged=converged,
        residuals=residuals,
        residual_labels=[(m.image_id, m.point) for m in measurements],
        residual_units="px" if dataset.camera is not None else "normalized",
        outliers=outliers,
        timings=timings,
    )
