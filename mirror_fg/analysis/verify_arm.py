"""Has an arm's mount moved? (docs/formats.md, "Has it moved? `mirror-fg verify`"): the likelihood-ratio
test of ``analysis/verify.py`` for each unknown mount of an arm's result@1 (``mounts``), from new images
with joint states.

Frames and units as docs/formats.md, "Robot arms": {B} the base link; a mount ``T_link_cam`` /
``T_link_target`` = ``(R, t)``, ``x_link = R x_mount + t`` (metres), its stored covariance
``[dtheta (rad), dt (m)]`` about and along the link's axes (``R_true = Exp(dtheta) R``,
``t_true = t + dt``); GTSAM's Pose3 tangent inside (``covariance_to_pose3``), as the arm's own solve
(``solver/model/robot_views.py``: the mount key's right perturbation).

The model is the arm's view model as it is (``RobotProblem``: ``factors/robot.py`` with forward
kinematics, eq. 23). What cannot have moved comes from the result: the target's reconstruction points
(held at their stored positions, target frame), the intrinsics (its values), the joint offsets (encoder
zeros: unknowns under their stored marginal in every fit, a Gaussian of the stored ``sigma3 / 3`` about the
stored offset, written as the recorded joints shifted by the stored offset and a zero-mean prior on what
is left). Each new mirror placement is a new unknown plane in {B}, started from the stored mounts: an
image's PnP map ``x_cam = A p + b`` through the plane's reflection ``x -> M x + 2 v`` (eq. 3) with
``C = FK_cam(q) T_link_cam`` and ``D = FK_target(q) T_link_target`` gives ``M = R_C A R_D^T`` and
``2 v = R_C b + t_C - M t_D``; the normal is ``M``'s -1 eigenvector.

For mount ``m``: ``cost_free`` with every mount free (verify's weak prior: :data:`~verdicts.FREE_WEIGHT`
of the stored information where the new data see, :data:`~verdicts.UNSEEN_WEIGHT` where they do not),
``cost_held`` with ``m`` under its stored prior (its stored marginal: result@1 holds no cross-covariance
with the joint offsets) and the other mounts free; ``d2 = 2 (cost_held - cost_free)`` against chi-square
(or verify's F-test where the result holds ``dispersion``) with ``k`` the directions of ``m`` the new data
see (its information with the planes, the other mounts and the offsets marginalised, relative to the
stored covariance). One placement seen from several arm poses hides three directions of the mount on the
base link (the plane and that mount compose into one virtual frame) and none of the mount on the moving
link. Verdicts, exit codes and verification@1 as verify's, one entry per unknown mount named by its role
(``camera``, ``target``).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import gtsam
import numpy as np
from scipy import stats

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.core.transform import covariance_to_pose3
from mirror_fg.factors.robot import compose
from mirror_fg.data import Dataset
from mirror_fg.io.result import estimated_camera, pose
from mirror_fg.io.robot_fields import Mount
from mirror_fg.solver.model.optimizer import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params
from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem
from mirror_fg.solver.start.pnp import lowest_reprojection, pnp_candidates
from mirror_fg.analysis import verdicts as base

__all__ = ["verify_arm", "stored_mounts"]

_MOUNT_KEYS = {"camera": "T_link_cam", "target": "T_link_target"}


def stored_mounts(result: Mapping[str, Any], source: str = "result") -> dict[str, tuple[str, np.ndarray, np.ndarray,
                                                                                         np.ndarray]]:
    """``{role: (link, R, t, covariance)}`` of each unknown mount of an arm's result@1; DatasetError (one
    line) where a mount lacks a covariance or its covariance is not positive definite."""
    out = {}
    for role, entry in (result.get("mounts") or {}).items():
        R, t = pose(entry[_MOUNT_KEYS[role]])
        covariance = entry.get("covariance")
        if covariance is None:
            raise DatasetError(f"{source}: the {role} mount has no covariance: verify needs the stored uncertainty "
                               "(calibrate again)")
        C = np.array(covariance, dtype=float)
        if not np.all(np.isfinite(C)) or np.linalg.eigvalsh(0.5 * (C + C.T))[0] <= 0:
            raise DatasetError(f"{source}: the {role} mount's covariance is not positive definite")
        out[role] = (entry["link"], R, t, 0.5 * (C + C.T))
    return out


def _stored_offsets(result: Mapping[str, Any], dataset: Dataset, source: str) -> tuple[dict[str, float], dict[str, float]]:
    """The stored joint offsets ``{joint: value}`` and their sigmas (radians, metres for prismatic joints)."""
    kinematics = dataset.robot.kinematics  # type: ignore[union-attr]
    values, sigmas = {}, {}
    for joint, entry in (result.get("joint_offsets") or {}).items():
        if joint not in kinematics.joints:
            raise DatasetError(f"{source}: joint offset {joint!r} is not a joint of {dataset.source}'s URDF: the result "
                               "and the data are from different arms")
        if "offset_mm" in entry:
            values[joint], sigmas[joint] = 1e-3 * float(entry["offset_mm"]), 1e-3 * float(entry["sigma3_mm"]) / 3.0
        else:
            values[joint] = math.radians(float(entry["offset_deg"]))
            sigmas[joint] = math.radians(float(entry["sigma3_deg"])) / 3.0
        if not sigmas[joint] > 0:
            raise DatasetError(f"{source}: joint offset {joint!r} has no positive sigma3: verify needs the stored "
                               "uncertainty (calibrate again)")
    return values, sigmas


def _verification_dataset(result: Mapping[str, Any], dataset: Dataset, source: str) -> Dataset:
    """``dataset`` with the result's mounts (the tested ones unknown), intrinsics, points and joint offsets
    (module docstring); one line (DatasetError) where the result and the data cannot be from one set-up."""
    setup = dataset.robot
    if setup is None:
        raise DatasetError(f"{source}: an arm's result (mounts) needs new images with joint states (robot), and "
                           f"{dataset.source} has none")
    if not result.get("mounts"):
        raise DatasetError(f"{dataset.source}: images with joint states, but {source} is not an arm's result (no "
                           "mounts): verify them against an arm's calibration")
    if dataset.cameras is not None:
        raise DatasetError(f"{dataset.source}: verify tests an arm with one camera")
    stored = stored_mounts(result, source)
    mounts = {}
    for role, mount in setup.mounts.items():
        if role in stored:
            link = stored[role][0]
            if mount.link != link:
                raise DatasetError(f"{dataset.source}: the {role} rides link {mount.link!r} but {source} has it on "
                                   f"{link!r}: the result and the data are from different set-ups")
            mounts[role] = Mount(link, None)
        elif mount.known is None:
            raise DatasetError(f"{dataset.source}: the {role} mount is unknown but {source} does not hold it: the "
                               "result and the data are from different set-ups")
        else:
            mounts[role] = mount
    points = base.stored_points(result, dataset, source)  # a camera per image counts as pixels too
    camera = dataset.camera
    found = estimated_camera(result, source, camera)
    if found is not None:
        if camera is not None and (found.width, found.height) != (camera.width, camera.height):
            raise DatasetError(f"{source}: its camera is {found.width}x{found.height} px but the new images' camera is "
                               f"{camera.width}x{camera.height}: the result and the data are from different set-ups")
        camera = replace(found, estimate=(), prior_sigma=())
    offsets, sigmas = _stored_offsets(result, dataset, source)
    images = [replace(im, joints={j: x + offsets.get(j, 0.0) for j, x in (im.joints or {}).items()}) for im in dataset.images]
    used = {n: points[n] for n in dataset.reconstruction_point_names}
    return replace(dataset, camera=camera, fiducials={**dataset.fiducials, **used}, images=images,
                   robot=replace(setup, mounts=mounts, offsets=tuple(offsets), offset_sigma=sigmas))


class _ArmFits:
    """The new data's graph (``RobotProblem``'s, with the offsets' stored prior) and LM on it; the same
    interface as verify's ``_Fits`` for its verdict."""

    def __init__(self, dataset: Dataset, stored: dict[str, tuple[str, np.ndarray, np.ndarray, np.ndarray]],
                 max_iterations: int):
        self.problem = RobotProblem(dataset)
        self.data = self.problem.graph()
        self.source = dataset.source
        self.stored = {role: (R, t, C) for role, (_, R, t, C) in stored.items()}
        self.stored_pose = {role: gtsam.Pose3(gtsam.Rot3(R), t) for role, (R, t, _) in self.stored.items()}
        self.stored_tangent = {role: covariance_to_pose3(R, C) for role, (R, _, C) in self.stored.items()}
        self.params = lm_params(max_iterations, cost_scale(dataset), GENERAL_LAMBDA_UPPER_BOUND)
        self.noun = "mount"

    def pose_key(self, role: str) -> int:
        return self.problem.mount_keys[role]

    def start(self) -> gtsam.Values:
        """The stored mounts, offsets at the stored ones, each new plane from its images' PnP (module
        docstring)."""
        problem = self.problem
        mounts = {role: (R, t) for role, (R, t, _) in self.stored.items()}
        mounts.update(problem.known)
        planes: dict[tuple[int, int], list[np.ndarray]] = {}
        dataset = problem.dataset
        for image, factor, observed in zip(dataset.images, problem.factors, problem.normalized):
            if len(image.reflections) != 1:
                continue
            names = [n for n in image.observations if n in dataset.fiducials]
            if len(names) < 4:
                continue
            points = np.array([dataset.fiducials[n] for n in names], float)
            normalized = np.array([observed[:, list(image.observations).index(n)] for n in names], float)
            found = lowest_reprojection(pnp_candidates(points, normalized, 1), points, normalized)
            if found is None:
                continue
            A, b = found
            (F_c, _), (F_t, _) = factor.fk(np.zeros(len(problem.offsets)))
            R_C, t_C = compose((F_c[:3, :3], F_c[:3, 3]), mounts["camera"])
            R_D, t_D = compose((F_t[:3, :3], F_t[:3, 3]), mounts["target"])
            M = R_C @ A @ R_D.T  # eq. (3): the reflection in {B}
            normal = np.linalg.eigh(0.5 * (M + M.T))[1][:, 0]
            planes.setdefault(image.reflections[0], []).append(
                0.5 * np.outer(normal, normal) @ (R_C @ b + t_C - M @ t_D))
        missing = [p for p in problem.placements if p not in planes]
        if missing:
            raise DatasetError(f"{self.source}: mirror {missing[0][0]} placement {missing[0][1]} has no image through it "
                               "alone with 4 or more fiducials: verify cannot place its plane")
        estimate = RobotEstimate(mounts, {p: np.mean(v, axis=0) for p, v in planes.items()}, {},
                                 np.zeros(len(problem.offsets)))
        return problem.values(estimate)

    def prior(self, role: str, information: np.ndarray | None = None) -> gtsam.NonlinearFactor:
        """Mount ``role`` at its stored transform: with its stored covariance, or ``information`` (tangent)."""
        noise = (gtsam.noiseModel.Gaussian.Information(information) if information is not None
                 else gtsam.noiseModel.Gaussian.Covariance(self.stored_tangent[role]))
        return gtsam.PriorFactorPose3(self.pose_key(role), self.stored_pose[role], noise)

    def fit(self, priors: list, starts: list[gtsam.Values]) -> tuple[gtsam.Values, float]:
        """LM on the data and ``priors`` from each start: the lowest ``(values, cost)``."""
        return base.lowest_fit(self.data, priors, starts, self.params, self.source,
                               lambda error: f"the new images do not determine the unknowns ({error})")

    def pose_information(self, role: str, values: gtsam.Values) -> np.ndarray:
        """What the new data (and the offsets' stored prior) say about mount ``role``, the planes, the other
        mounts and the offsets marginalised (Schur complement; tangent at ``values``)."""
        H, columns = self.problem.information(self.data, values)
        c = columns[self.pose_key(role)]
        own = np.zeros(H.shape[0], dtype=bool)
        own[c] = True
        H_co = H[own][:, ~own]
        return H[c, c] - H_co @ np.linalg.pinv(H[~own][:, ~own], rcond=1e-12, hermitian=True) @ H_co.T


def verify_arm(result: Mapping[str, Any], dataset: Dataset, alpha: float, tolerance_mm: float, tolerance_deg: float,
               source: str, max_iterations: int) -> base.Verification:
    """Whether each unknown mount of an arm's ``result`` is still where it puts it (module docstring);
    verify's :class:`~mirror_fg.analysis.verify.Verification`, its entries named by the mounts' roles
    (``fused`` empty: ``--update`` writes single-camera results)."""
    stored = stored_mounts(result, source)
    fits = _ArmFits(_verification_dataset(result, dataset, source), stored, max_iterations)
    tested = list(stored)
    start = fits.start()
    held_all, _ = fits.fit([fits.prior(r) for r in tested], [start])
    seen = {r: base.seen_directions(fits.stored_tangent[r], fits.pose_information(r, held_all)) for r in tested}
    free_priors = {r: fits.prior(r, base.free_information(*seen[r])) for r in tested}
    free, cost_free = fits.fit(list(free_priors.values()), [held_all, start])
    data_cost = float(fits.data.error(free))
    expected = expected_cost(fits.problem.size, 3 * len(fits.problem.mirror_keys), min_dof=1)
    if not plausible(data_cost, expected):  # not even moved mounts explain them
        raise DatasetError(f"{dataset.source}: the new images do not fit {source}'s target, points and joint offsets even "
                           f"with the mounts free (cost {data_cost:.3g}, expected about {expected:.3g}): the result and "
                           "the data are from different set-ups, or the target or its points moved")
    dispersion = base.stored_dispersion(result)
    checked = dispersion is not None and dispersion[1] > 0.5 and math.isfinite(dispersion[0]) and dispersion[0] > 0
    scale, nu = (max(1.0, dispersion[0]), dispersion[1]) if checked else (1.0, None)  # type: ignore[index]
    ncp = {k: base.detectable_noncentrality(k, alpha, denominator_dof=nu) for k in range(1, 7)}
    verdicts: dict[str, base.CameraVerdict] = {}
    for role in tested:
        priors = [fits.prior(role)] + [f for r, f in free_priors.items() if r != role]
        _, cost_held = fits.fit(priors, [held_all, free])
        d2 = max(0.0, 2.0 * (cost_held - cost_free))
        dof = int(np.sum(seen[role][0] > base.SEEN))
        if dof == 0:
            p = 1.0
        elif nu is not None:
            p = float(stats.f.sf(d2 / (dof * scale), dof, nu))
        else:
            p = float(stats.chi2.sf(d2, dof))
        answer = base.verdict_of(role, d2, dof, p, free, fits, ncp.get(dof, math.inf), alpha, tolerance_mm,
                               tolerance_deg, scale)
        if dispersion is not None:
            answer = replace(answer, dispersion=dispersion[0], dispersion_dof=dispersion[1])
            if not checked and answer.verdict == base.NOT_MOVED:
                answer = replace(answer, verdict=base.CANNOT_TELL, advice=base.UNCHECKED)
        verdicts[role] = answer
    return base.Verification(verdicts, alpha, tolerance_mm, tolerance_deg, {})
