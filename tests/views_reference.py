"""Independent reference MLE for the general view model (docs/formats.md "Views of any reflection order, and several
cameras"): scipy.optimize.least_squares on the whitened pixel residuals, its covariance the inverse Fisher
information, in docs/formats.md's conventions. Imports nothing from mirror_fg.

Model (Hesch et al. 2010): camera c sees base point Bp as x = R_c Bp + t_c (eq. 2), then for each
placement of the image's ``reflections`` in order x <- M x + 2 v (eq. 3, v that placement's mirror vector
in camera c's frame), z = (x1/x3, x2/x3) (eq. 9), pixels = K z. A placement's unknown is its v in the
frame of its owner camera o (the first camera in ``cameras`` order with an image seeing it); for c != o
the plane n.x = d (n = v/|v|, d = |v|) goes o -> base -> c.

Parameters (perturbations about a reference state, re-centred at the optimum so that the covariance of
the parameters *is* docs/formats.md's): per estimated camera ``[dtheta, dt]`` with R = Exp(dtheta) R0, t = t0 + dt;
per placement dv (3) with v = v0 + dv, or for the ``scale`` placement a (2) with v = d unit(u0 + B a)
(|v| = d exactly); per reconstruction point dp (3), or for the second ``scale`` point a (2) with
P1 = P0 + d unit(u0 + B a). Without fiducials the first camera is the base frame and is not estimated.
The Jacobian is by complex step (every operation below is analytic in the parameters), checked against
central differences in test_views_reference.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from views_scenes import CASES, Truth  # noqa: F401 - re-exported for the tests
from views_scenes import (kaleidoscope_three_mirrors_one_point, kaleidoscope_two_mirrors,  # noqa: F401
                          mixed_one_mirror_gives_pose, mixed_two_handheld, rig_three_cameras, rig_two_cameras)

COMPLEX_STEP = 1e-30
SINGLE = "camera"  # the camera's name in a dataset with one `camera`


def skew(w):
    return np.array([[0 * w[0], -w[2], w[1]], [w[2], 0 * w[0], -w[0]], [-w[1], w[0], 0 * w[0]]])


def exp_so3(w):
    """Rodrigues' formula, analytic in w (complex step safe: theta^2 = w.w, no abs)."""
    th2 = w @ w
    W = skew(w)
    if abs(th2.real) < 1e-8:
        a, b = 1 - th2 / 6 + th2 * th2 / 120, 0.5 - th2 / 24 + th2 * th2 / 720
    else:
        th = np.sqrt(th2)
        a, b = np.sin(th) / th, (1 - np.cos(th)) / th2
    return np.eye(3) + a * W + b * (W @ W)


def log_so3(R) -> np.ndarray:
    """Rotation vector of R (real; angles below pi - 1e-6)."""
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis * (0.5 + angle**2 / 12 if angle < 1e-6 else angle / (2 * np.sin(angle)))


def pose_error(R_ref, t_ref, R, t) -> np.ndarray:
    """docs/formats.md's ``[dtheta, dt]`` from (R_ref, t_ref) to (R, t): R = Exp(dtheta) R_ref, t = t_ref + dt."""
    return np.r_[log_so3(np.asarray(R) @ np.asarray(R_ref).T), np.asarray(t) - np.asarray(t_ref)]


def unit(u):
    return u / np.sqrt(u @ u)


def tangent_basis(u) -> np.ndarray:
    """(3, 2): two orthonormal vectors orthogonal to the unit vector u."""
    a = np.eye(3)[np.argmin(np.abs(u))]
    b1 = unit(np.cross(u, a))
    return np.c_[b1, np.cross(u, b1)]


@dataclass
class Problem:
    """A dataset@1 dict read for the reference: cameras (name -> dict, in order), images as
    (camera, reflections, names, observed pixels (N, 2)), fiducials, point names, owners, scale."""

    cameras: dict
    images: list
    fiducials: dict
    point_names: list
    owners: dict
    sigma: float
    scale: dict | None
    fixed_first: bool


def read_problem(d: dict) -> Problem:
    cameras = dict(d["cameras"]) if "cameras" in d else {SINGLE: d["camera"]}
    images = []
    for im in d["images"]:
        refl = im.get("reflections")
        if refl is None:  # docs/formats.md: mirror_configs [m1..mNv] means [[1, m1], ..., [Nv, mNv]]
            refl = [[l + 1, m] for l, m in enumerate(im["mirror_configs"])]
        names = list(im["observations"])
        images.append((im.get("camera", SINGLE), [tuple(p) for p in refl], names,
                       np.array([im["observations"][n] for n in names], float)))
    owners: dict = {}
    for cam in cameras:
        for c, refl, _, _ in images:
            if c == cam:
                for p in refl:
                    owners.setdefault(p, cam)
    fiducials = {n: np.array(x, float) for n, x in d["fiducials"].items()}
    points = sorted({n for _, _, names, _ in images for n in names if n not in fiducials})
    return Problem(cameras, images, fiducials, points, dict(sorted(owners.items())), float(d["pixel_sigma"]),
                   d.get("scale"), not fiducials)


class Model:
    """The parametrisation (module docstring) about a reference state; ``residuals(x)`` whitened."""

    def __init__(self, problem: Problem, poses: dict, mirrors: dict, points: dict):
        self.pb = problem
        self.poses = {c: (np.array(R, float), np.array(t, float)) for c, (R, t) in poses.items()}
        self.mirrors = {p: np.array(v, float) for p, v in mirrors.items()}
        self.points = {n: np.array(x, float) for n, x in points.items()}
        scale = problem.scale or {}
        self.scale_mirror = (scale["mirror"], scale["config"]) if "mirror" in scale else None
        self.scale_points = tuple(scale["points"]) if "points" in scale else None
        self.distance = float(scale.get("distance", 0.0))
        self.slices: dict = {}
        k = 0
        for i, c in enumerate(problem.cameras):
            if not (problem.fixed_first and i == 0):
                self.slices[("pose", c)] = slice(k, k + 6)
                k += 6
        for p in problem.owners:
            size = 2 if p == self.scale_mirror else 3
            self.slices[("mirror", p)] = slice(k, k + size)
            k += size
        for n in problem.point_names:
            size = 2 if self.scale_points and n == self.scale_points[1] else 3
            self.slices[("point", n)] = slice(k, k + size)
            k += size
        self.size = k
        self._bases = {}
        if self.scale_mirror:
            self._bases["mirror"] = tangent_basis(unit(self.mirrors[self.scale_mirror]))
        if self.scale_points:
            a, b = self.scale_points
            self._bases["point"] = tangent_basis(unit(self.points[b] - self.points[a]))

    # --- the unknowns as functions of x ---
    def pose(self, x, c):
        R0, t0 = self.poses[c]
        s = self.slices.get(("pose", c))
        if s is None:
            return R0 + 0 * x[0], t0 + 0 * x[0]
        return exp_so3(x[s][:3]) @ R0, t0 + x[s][3:]

    def mirror(self, x, p):
        s, v0 = self.slices[("mirror", p)], self.mirrors[p]
        if p == self.scale_mirror:
            return self.distance * unit(unit(v0) + self._bases["mirror"] @ x[s])
        return v0 + x[s]

    def point(self, x, n):
        s = self.slices[("point", n)]
        if self.scale_points and n == self.scale_points[1]:
            a = self.point(x, self.scale_points[0])
            u0 = unit(self.points[n] - self.points[self.scale_points[0]])
            return a + self.distance * unit(u0 + self._bases["point"] @ x[s])
        return self.points[n] + x[s]

    def state(self, x):
        """(poses, mirrors, points) at x (real)."""
        return ({c: self.pose(x, c) for c in self.pb.cameras}, {p: self.mirror(x, p) for p in self.pb.owners},
                {n: self.point(x, n) for n in self.pb.point_names})

    def plane_in(self, x, p, c, poses):
        """(n, d) of placement p in camera c's frame (owner frame -> base -> c)."""
        v = self.mirror(x, p)
        d = np.sqrt(v @ v)
        n = v / d
        o = self.pb.owners[p]
        if o == c:
            return n, d
        Ro, to = poses[o]
        Rc, tc = poses[c]
        n_b, d_b = Ro.T @ n, d - n @ to  # plane in base: (Ro^T n) . Bx = d - n . to
        n_c = Rc @ n_b
        return n_c, d_b + n_c @ tc

    def residuals(self, x):
        poses = {c: self.pose(x, c) for c in self.pb.cameras}
        pts = {n: self.point(x, n) for n in self.pb.point_names}
        out = []
        for cam, refl, names, obs in self.pb.images:
            R, t = poses[cam]
            X = np.array([self.pb.fiducials[n] + 0 * x[0] if n in self.pb.fiducials else pts[n] for n in names])
            p = X @ R.T + t  # eq. (2)
            for pl in refl:
                n, d = self.plane_in(x, pl, cam, poses)
                p = p - 2.0 * np.outer(p @ n - d, n)  # eq. (3): M p + 2 v with v = d n
            z = p[:, :2] / p[:, 2:3]  # eq. (9)
            K = self.pb.cameras[cam]
            pix = np.c_[K["fx"] * z[:, 0] + K["cx"], K["fy"] * z[:, 1] + K["cy"]]
            out.append(((pix - obs) / self.pb.sigma).ravel())
        return np.concatenate(out)

    def jacobian(self, x):
        """Complex-step Jacobian of :meth:`residuals` (exact to rounding)."""
        x = np.asarray(x, float)
        cols = []
        for k in range(self.size):
            xc = x.astype(complex)
            xc[k] += 1j * COMPLEX_STEP
            cols.append(self.residuals(xc).imag / COMPLEX_STEP)
        return np.array(cols).T

    def quantities(self, x):
        """Every reported quantity as one vector: per camera [dtheta, dt] about the reference state (0 for a
        fixed one), per placement v, per point p; with the labels of its blocks."""
        blocks, labels = [], []
        for c in self.pb.cameras:
            s = self.slices.get(("pose", c))
            blocks.append(x[s] if s is not None else np.zeros(6) + 0 * x[0])
            labels.append(("pose", c))
        for p in self.pb.owners:
            blocks.append(self.mirror(x, p))
            labels.append(("mirror", p))
        for n in self.pb.point_names:
            blocks.append(self.point(x, n))
            labels.append(("point", n))
        return np.concatenate(blocks), labels


@dataclass
class Reference:
    """The reference MLE and its covariances in docs/formats.md's conventions (module docstring)."""

    poses: dict
    pose_cov: dict
    joint_pose_cov: np.ndarray
    mirrors: dict
    mirror_cov: dict
    points: dict
    point_cov: dict
    cost: float
    owners: dict
    num_measurements: int
    num_unknowns: int
    #: The joint covariance of every reported quantity, and each block's slice in it (("pose", c),
    #: ("mirror", (l, m)), ("point", name)).
    covariance: np.ndarray | None = None
    blocks: dict | None = None

    def rig(self, frm: str, to: str):
        """T_to_from = T_to_base T_from_base^-1 (x_to = R x_from + t) and its (6, 6) covariance."""
        return rig_transform(self.poses, self.joint_pose_cov, list(self.poses), frm, to)


def rig_transform(poses: dict, joint_cov: np.ndarray, order: list, frm: str, to: str, step: float = 1e-6):
    """(R, t, cov) of T_to_from from the camera poses and their joint covariance (docs/formats.md's convention) (6C, 6C) in ``order``;
    cov in docs/formats.md's convention about the ``to`` camera's axes, by central differences of the 12 pose
    perturbations (each R = Exp(dtheta) R, t = t + dt)."""
    (Rf, tf), (Rt, tt) = poses[frm], poses[to]

    def compose(e):
        Rf_, tf_ = exp_so3(e[:3]) @ Rf, tf + e[3:6]
        Rt_, tt_ = exp_so3(e[6:9]) @ Rt, tt + e[9:12]
        R = Rt_ @ Rf_.T
        return R, tt_ - R @ tf_

    R0, t0 = compose(np.zeros(12))
    G = np.zeros((6, 12))
    for k in range(12):
        e = np.zeros(12)
        e[k] = step
        Rp, tp = compose(e)
        Rm, tm = compose(-e)
        G[:, k] = (pose_error(R0, t0, Rp, tp) - pose_error(R0, t0, Rm, tm)) / (2 * step)
    i, j = order.index(frm), order.index(to)
    idx = np.r_[6 * i:6 * i + 6, 6 * j:6 * j + 6]
    return R0, t0, G @ joint_cov[np.ix_(idx, idx)] @ G.T


def start_state(problem: Problem, truth: Truth, perturbation: float = 0.0, seed: int = 0):
    """Truth (optionally perturbed: rotations by ``perturbation`` rad, translations, mirror vectors and
    points by ``perturbation`` m x 0.1, each component N(0, .)), keeping the scale constraint."""
    rng = np.random.default_rng(seed)
    poses, mirrors, points = {}, {}, {}
    for i, c in enumerate(problem.cameras):
        R, t = truth.T_cam_base[c]
        if perturbation and not (problem.fixed_first and i == 0):
            R, t = exp_so3(rng.normal(0, perturbation, 3)) @ R, t + rng.normal(0, 0.1 * perturbation, 3)
        poses[c] = (R, t)
    for p in problem.owners:
        if truth.owners[p] != problem.owners[p]:
            raise AssertionError(f"truth owner of {p} is {truth.owners[p]}, docs/formats.md's is {problem.owners[p]}")
        v = truth.mirrors[p]
        mirrors[p] = v + (rng.normal(0, 0.1 * perturbation, 3) if perturbation else 0)
    for n in problem.point_names:
        points[n] = truth.points[n] + (rng.normal(0, 0.1 * perturbation, 3) if perturbation else 0)
    scale = problem.scale or {}
    if "mirror" in scale:
        p = (scale["mirror"], scale["config"])
        mirrors[p] = scale["distance"] * unit(mirrors[p])
    if "points" in scale:
        a, b = scale["points"]
        points[b] = points[a] + scale["distance"] * unit(points[b] - points[a])
    return poses, mirrors, points


def reference_mle(dataset_dict: dict, truth: Truth, perturbation: float = 0.0, seed: int = 0,
                  passes: int = 3) -> Reference:
    """The MLE of ``dataset_dict`` started from ``truth`` (or from it perturbed, see :func:`start_state`)
    and its covariance (inverse of J^T J of the whitened residuals) in docs/formats.md's conventions. ``passes``:
    solves, each re-centred at the previous optimum."""
    problem = read_problem(dataset_dict)
    model = Model(problem, *start_state(problem, truth, perturbation, seed))
    for _ in range(passes):  # solve, re-centre at the optimum, solve again (the last pass moves ~nothing)
        fit = least_squares(model.residuals, np.zeros(model.size), jac=model.jacobian, method="lm",
                            xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
        model = Model(problem, *model.state(fit.x))
    x0 = np.zeros(model.size)
    r = model.residuals(x0)
    J = model.jacobian(x0)
    cov_x = np.linalg.inv(J.T @ J)
    q, labels = model.quantities(x0)
    G = np.array([model.quantities(x0 + 1j * COMPLEX_STEP * e)[0].imag / COMPLEX_STEP
                  for e in np.eye(model.size)]).T
    cov_q = G @ cov_x @ G.T
    blocks, k = {}, 0
    for label in labels:
        blocks[label] = slice(k, k + 6 if label[0] == "pose" else k + 3)
        k = blocks[label].stop
    cams = list(problem.cameras)
    pose_idx = np.r_[tuple(np.arange(blocks[("pose", c)].start, blocks[("pose", c)].stop) for c in cams)]
    poses, mirrors, points = model.state(x0)
    return Reference(
        poses={c: (np.real(R), np.real(t)) for c, (R, t) in poses.items()},
        pose_cov={c: cov_q[blocks[("pose", c)], blocks[("pose", c)]] for c in cams},
        joint_pose_cov=cov_q[np.ix_(pose_idx, pose_idx)],
        mirrors={p: np.real(v) for p, v in mirrors.items()},
        mirror_cov={p: cov_q[blocks[("mirror", p)], blocks[("mirror", p)]] for p in problem.owners},
        points={n: np.real(x) for n, x in points.items()},
        point_cov={n: cov_q[blocks[("point", n)], blocks[("point", n)]] for n in problem.point_names},
        cost=0.5 * float(r @ r), owners=dict(problem.owners), num_measurements=r.size, num_unknowns=model.size,
        covariance=cov_q, blocks=blocks,
    )


@dataclass
class Comparison:
    """``worst_sigmas``: max |estimate - reference| / reference sigma over every component with a
    nonzero reference variance (``worst_label`` names it); ``ratio_min`` / ``ratio_max``: range of
    sqrt(diag(calibration cov)) / sqrt(diag(reference cov)) over them; ``gauge_error``: the largest
    |difference| in a zero-variance (gauge) component; ``rows``: (label, z, ratio) per block."""

    worst_sigmas: float
    worst_label: str
    ratio_min: float
    ratio_max: float
    gauge_error: float
    rows: list


GAUGE_VARIANCE = 1e-24


def compare(calibration, reference: Reference, dataset_dict: dict) -> Comparison:
    """The calibration's estimates and covariances against the reference's (attributes as in the
    module docstring of test_views_mle.py: single camera R_cam_base/t_cam_base/covariance, several
    cameras cameras[name]; mirror_vectors, mirror_covariances, points, point_covariances)."""
    rows, gauge = [], 0.0
    several = "cameras" in dataset_dict

    def add(label, diff, ref_cov, cal_cov):
        nonlocal gauge
        var = np.diag(ref_cov)
        live = var > GAUGE_VARIANCE
        if (~live).any():
            gauge = max(gauge, float(np.abs(diff[~live]).max()))
        z = np.abs(diff[live]) / np.sqrt(var[live])
        ratio = (np.sqrt(np.clip(np.diag(cal_cov)[live], 0, None)) / np.sqrt(var[live])) if cal_cov is not None \
            else np.full(live.sum(), np.nan)
        rows.append((label, z, ratio))

    for c, (R, t) in reference.poses.items():
        pose = calibration.cameras[c] if several else calibration
        cov = pose.covariance
        add(f"pose {c}", pose_error(R, t, pose.R_cam_base, pose.t_cam_base), reference.pose_cov[c],
            None if cov is None else np.asarray(cov))
    for p, v in reference.mirrors.items():
        add(f"mirror {p}", np.asarray(calibration.mirror_vectors[p]) - v, reference.mirror_cov[p],
            np.asarray(calibration.mirror_covariances[p]))
    for n, x in reference.points.items():
        add(f"point {n}", np.asarray(calibration.points[n]) - x, reference.point_cov[n],
            np.asarray(calibration.point_covariances[n]))
    zs = [(float(z.max()), label) for label, z, _ in rows if z.size]
    ratios = np.concatenate([r for _, _, r in rows])
    worst = max(zs)
    return Comparison(worst[0], worst[1], float(np.nanmin(ratios)), float(np.nanmax(ratios)), gauge, rows)
