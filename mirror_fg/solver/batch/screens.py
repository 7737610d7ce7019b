"""Several screens seen by one camera through mirrors, in one graph (docs/formats.md, "The answer in the
user's units": several screens; "Screens" for each screen's frame).

Each screen ``s`` has its own frame (origin at the top-left corner of its active area, x right, y down,
z into it, metres) and an unknown ``T_cam_screen_s`` (a GTSAM ``Pose3`` ``X(s)``, camera <- screen). A
mirror placement ``(l, m)`` is one plane in the camera frame whichever screen its images show (an
``OrientedPlane3`` ``V(i)``, as in the general view model, ``factors/views.py``): a photograph that shows
two screens in one mirror ties them. An image of screen ``s`` through placements ``p_1..p_k`` sees its
fiducial ``q`` (screen frame) at ``project(F_k(... F_1(R_s q + t_s)))`` (Hesch et al., eqs. 2, 3, 9):
the view factor of ``factors/views.py`` with the screen's pose in the role of the camera's pose and
every placement in the one camera's frame (so no plane is carried between frames).

The start: each screen calibrated alone (``mirror_fg.calibrate`` on its own images: the analytical
solution, LM, its checks and what it leaves out); a placement seen with several screens starts from the
first screen's estimate. Then LM over the joint graph, and the joint covariance of every ``T_cam_screen``
from GTSAM's ``Marginals`` (right-perturbation ``[w, nu]`` converted to the uncertainty convention
``[dtheta, dt]``, ``R_true = Exp(dtheta) R``, ``t_true = t + dt``, camera axes).

The screens' relative poses (:func:`relative_pose`): ``T_to_from = T_cam_to^-1 T_cam_from`` maps points
of screen ``from`` into screen ``to``'s frame, its covariance ``[dtheta, dt]`` about ``to``'s axes
propagated (first order) from the joint covariance.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import Transform
from mirror_fg.factors.views import ViewFactor, plane_of, vector_of_plane
from mirror_fg.data import Dataset
from mirror_fg.io.point_sigma import normalized_sigmas
from mirror_fg.solver.result.calibration import Calibration

__all__ = ["ScreensCalibration", "calibrate_screens", "relative_pose"]

Placement = tuple[int, int]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def relative_pose(T_cam_to: Transform, T_cam_from: Transform, joint: np.ndarray) -> tuple[Transform, np.ndarray]:
    """``(T_to_from, covariance)``: points of screen ``from`` into screen ``to``'s frame, and its (6, 6)
    covariance about ``to``'s axes from the joint (12, 12) covariance of ``[to, from]`` (module docstring).

    With ``R' = Exp(a) R_to``, ``t' = t_to + e``, ``R_from' = Exp(b) R_from``, ``t_from' = t_from + f``:
    ``dtheta = R_to^T (b - a)``, ``dt = R_to^T [t_from - t_to]x a - R_to^T e + R_to^T f``."""
    Ra, ta = T_cam_to.R, T_cam_to.t
    Rb, tb = T_cam_from.R, T_cam_from.t
    T = Transform(Ra.T @ Rb, Ra.T @ (tb - ta))
    zero = np.zeros((3, 3))
    J = np.block([[-Ra.T, zero, Ra.T, zero],
                  [Ra.T @ _skew(tb - ta), -Ra.T, zero, Ra.T]])
    return T, J @ joint @ J.T


@dataclass
class ScreensCalibration:
    """The joint solution: ``names`` (screens, in the capture's order), ``poses`` ``{name: T_cam_screen}``,
    ``joint_covariance`` (6S, 6S) in that order (uncertainty convention per block), the placements'
    mirror vectors (camera frame, metres), the optimizer's figures, the residuals (pixels, per
    measurement, with ``(screen, image, point)`` labels) and each screen's own calibration (the start)."""

    names: list[str]
    poses: dict[str, Transform]
    joint_covariance: np.ndarray
    mirror_vectors: dict[Placement, np.ndarray]
    mirror_covariances: dict[Placement, np.ndarray]
    iterations: int
    initial_error: float
    final_error: float
    expected_final_error: float
    residuals: np.ndarray
    residual_labels: list[tuple[str, str, str]]
    alone: dict[str, Calibration]

    def covariance(self, name: str) -> np.ndarray:
        """(6, 6) marginal of ``T_cam_screen`` of screen ``name``."""
        k = 6 * self.names.index(name)
        return self.joint_covariance[k:k + 6, k:k + 6].copy()

    def relative(self, to: str, from_: str) -> tuple[Transform, np.ndarray]:
        """``T_to_from`` and its covariance (:func:`relative_pose`)."""
        i, j = 6 * self.names.index(to), 6 * self.names.index(from_)
        rows = np.r_[i:i + 6, j:j + 6]
        return relative_pose(self.poses[to], self.poses[from_], self.joint_covariance[np.ix_(rows, rows)])

    def first_calibration(self) -> Calibration:
        """The first screen's pose as a :class:`Calibration` (its own solve's diagnostics, the joint
        estimate's pose, covariance, placements, cost and residuals): the top level of the result."""
        first = self.names[0]
        T = self.poses[first]
        labels = [(f"{screen}/{image}", point) for screen, image, point in self.residual_labels]
        return dataclasses.replace(
            self.alone[first], R_cam_base=T.R, t_cam_base=T.t, covariance=self.covariance(first),
            mirror_vectors=dict(self.mirror_vectors), mirror_covariances=dict(self.mirror_covariances),
            iterations=self.iterations, initial_error=self.initial_error, final_error=self.final_error,
            expected_final_error=self.expected_final_error, residuals=self.residuals, residual_labels=labels,
            outliers=[], restarts=0)


def calibrate_screens(datasets: Mapping[str, Dataset], alone: Mapping[str, Calibration] | None = None) -> ScreensCalibration:
    """Every screen's ``T_cam_screen`` in one graph (module docstring). ``datasets``: ``{screen name:
    its images}``, each with its screen's fiducials (screen frame) and the one camera; ``alone``: each
    screen's own calibration where already made (else made here). Raises DatasetError (the cameras differ,
    fewer than two screens) or CalibrationError (a screen that cannot be calibrated on its own)."""
    from mirror_fg.solver.calibrate import calibrate

    names = list(datasets)
    if len(names) < 2:
        raise DatasetError("several screens: give at least two screens (one screen is an ordinary screen target)")
    cameras = {name: ds.camera for name, ds in datasets.items()}
    first_camera = cameras[names[0]]
    if first_camera is None or any(c != first_camera for c in cameras.values()):
        raise DatasetError("several screens: every screen's images must come from the one camera, with pixels")
    alone = {name: (alone or {}).get(name) or calibrate(datasets[name]) for name in names}
    left_out = {name: {(e.image, e.point) for e in cal.excluded} for name, cal in alone.items()}

    pose_keys = {name: X(k) for k, name in enumerate(names)}
    placements: dict[Placement, np.ndarray] = {}
    for name in names:  # the first screen's estimate of a shared placement
        for p, v in alone[name].mirror_vectors.items():
            placements.setdefault(p, np.asarray(v, float))
    mirror_keys = {p: V(i) for i, p in enumerate(sorted(placements))}

    graph = gtsam.NonlinearFactorGraph()
    factors: list[tuple[str, str, list[str], ViewFactor]] = []
    for name in names:
        ds = datasets[name]
        for image in ds.images:
            if (image.id, None) in left_out[name]:
                continue
            normalized = ds.normalized(image)
            points = [n for n in image.observations if n in ds.fiducials and (image.id, n) not in left_out[name]]
            if not points or any(p not in mirror_keys for p in image.reflections):
                continue
            base = np.array([ds.fiducials[n] for n in points], float).T
            observed = np.array([normalized[n] for n in points], float).T
            sigmas = normalized_sigmas(ds.camera, ds.pixel_sigma, ds.point_sigma, points).T
            owners = {p: name for p in image.reflections}  # every plane in the one camera's frame
            factor = ViewFactor(name, image.reflections, {name: pose_keys[name]}, {}, mirror_keys, owners, base,
                                [-1] * len(points), observed, sigmas)
            graph.add(factor.factor())
            factors.append((name, image.id, points, factor))

    values = gtsam.Values()
    for name in names:
        cal = alone[name]
        values.insert(pose_keys[name], gtsam.Pose3(gtsam.Rot3(cal.R_cam_base), np.asarray(cal.t_cam_base, float)))
    for p, key in mirror_keys.items():
        values.insert(key, plane_of(placements[p]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(100)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_error = float(graph.error(values))
    values = optimizer.optimize()

    poses = {name: Transform(values.atPose3(key).rotation().matrix(), np.asarray(values.atPose3(key).translation(), float))
             for name, key in pose_keys.items()}
    marginals = gtsam.Marginals(graph, values)
    kv = gtsam.KeyVector()
    for key in pose_keys.values():
        kv.append(key)
    block = marginals.jointMarginalCovariance(kv).fullMatrix()
    J = np.zeros((6 * len(names), 6 * len(names)))  # [w, nu] -> [R w, R nu] per screen
    for k, name in enumerate(names):
        J[6 * k:6 * k + 6, 6 * k:6 * k + 6] = np.kron(np.eye(2), poses[name].R)
    joint = J @ block @ J.T
    mirrors, mirror_covariances = {}, {}
    for p, key in mirror_keys.items():
        v, dv = vector_of_plane(values.atOrientedPlane3(key))
        mirrors[p], mirror_covariances[p] = v, dv @ marginals.marginalCovariance(key) @ dv.T

    residuals, labels = [], []
    camera = first_camera
    for name, image_id, points, factor in factors:
        z = factor.predict(values)
        observed = np.array([datasets[name].images[_index(datasets[name], image_id)].observations[n] for n in points])
        residuals.append(camera.distort(z.T) - observed)
        labels += [(name, image_id, n) for n in points]
    measurements = sum(2 * len(f[2]) for f in factors)
    unknowns = 6 * len(names) + 3 * len(mirror_keys)
    return ScreensCalibration(names, poses, joint, mirrors, mirror_covariances, int(optimizer.iterations()),
                              initial_error, float(graph.error(values)), (measurements - unknowns) / 2.0,
                              np.vstack(residuals), labels, dict(alone))


def _index(dataset: Dataset, image_id: str) -> int:
    return next(k for k, image in enumerate(dataset.images) if image.id == image_id)

