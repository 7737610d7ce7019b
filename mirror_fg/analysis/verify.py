"""Has it moved? (docs/formats.md, "Has it moved? `mirror-fg verify`"): a likelihood-ratio test, per
camera, of a few new images against the transform and covariance a stored result@1 holds.

Frames and units as docs/formats.md: ``T_cam_base = (R, t)``, ``Cp = R Bp + t`` (metres); covariances
``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) R_est`` and ``t_true = t_est + dt``. GTSAM's
Pose3 tangent ``[w, nu]`` (right perturbation) is used inside, converted at the edges
(``core.transform.covariance_to_pose3`` / ``covariance_from_pose3``).

The model is the general view model (``solver/model/views.py``, one ``factors/views.py`` factor per image): the
target, the reconstruction points and the intrinsics are the stored ones (they cannot have moved; the
points are held at their stored positions; intrinsics the result estimated are unknowns under their
stored covariance, in both fits), every mirror placement of the new data is a new unknown (started by
``solver/start/propagation.py``'s rule 3 from the stored pose). For camera ``c``:

- ``cost_free``: the new images with every camera free;
- ``cost_held``: the same with camera ``c`` under a prior at its stored transform with its stored
  covariance ``S`` (jointly with its estimated intrinsics, their stored cross-covariance, where the result
  estimated them: the pose's error and theirs are correlated);
- ``d2 = 2 (cost_held - cost_free)``; under "not moved" (linearised) ``d2 ~ chi2_k``, ``p = 1 - chi2_k(d2)``.

``k``: the new data's information ``N`` about the pose after marginalising the placements and the other
cameras (a Schur complement), in the stored covariance's units: the eigenvalues ``lambda_i`` of
``L^T N L`` (``S = L L^T``). A direction with ``lambda_i`` below :data:`SEEN` is one the new data cannot
see (one mirror placement absorbs any rotation about a line in its plane: three of six); there the
"free" fit holds the camera by :data:`UNSEEN_WEIGHT` of the stored prior (under 1 % of a degree of freedom
in ``d2``), and ``k`` counts the others. Not by all of it: the poses the images cannot tell apart are a
curved family (turned about the placements' common line) that leaves the stored tangent, and after a large
move the whole prior there keeps the free camera off it (no pose it allows fits the images). Where
``k = 6`` the move ``delta`` (new minus stored) has the combined covariance ``C = S + N^-1``. The
smallest move detectable at ``alpha`` with power 0.9 has non-centrality ``lambda*``
(``P(ncx2_k(lambda*) > chi2_k^-1(1 - alpha)) = 0.9``); in the worst direction it is
``sqrt(lambda* max eig C_rr)`` in rotation and ``sqrt(lambda* max eig C_tt)`` in position (infinite
where ``k < 6``).

Bounds too narrow for the data (``solver/fit/dispersion.py``): a per-image systematic error (corner bias,
unmodelled distortion) moves each image's virtual camera while its own mirror placement hides it from the
residuals, so ``S`` and ``N^-1`` are too small by a factor the residuals do not show. Where the result
stores its images' agreement with each other, ``dispersion`` (``s2 = B / nu``, ``nu`` degrees of freedom;
about 1 when the noise model holds), both are scaled by ``f = max(1, s2)`` and the test is an F-test, the
noise level estimated from the image-level redundancy: ``F = d2 / (k f)``, ``p = 1 - F_{k,nu}(F)`` (exact
size alpha where ``s2 >= 1``, below it otherwise: the bounds are only ever widened); ``C = f (S + N^-1)``
and ``lambda*`` the non-centrality of power 0.9 of ``F_{k,nu}`` (times ``f`` in ``d2``). Where ``nu = 0`` (every stored image was needed to determine the solution: its
bounds cannot be checked) the test is the chi-square one and `not moved` becomes `cannot tell`; a
result without ``dispersion`` (written before it existed) is tested with the chi-square as stored.
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
from mirror_fg.data import Dataset
from mirror_fg.io.result import estimated_camera, pose
from mirror_fg.solver.model.optimizer import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params
from mirror_fg.solver.model.marginals import unconstrained_message
from mirror_fg.solver.options import SolveOptions
from mirror_fg.solver.start.propagation import Unsolvable, propagate
from mirror_fg.analysis.verdicts import (  # noqa: F401 (the verdicts' names, public here too)
    CANNOT_TELL,
    MOVED,
    NOT_MOVED,
    POWER,
    SEEN,
    UNCHECKED,
    CameraVerdict,
    Verification,
    detectable_noncentrality,
    free_information,
    lowest_fit,
    seen_directions,
    stored_dispersion,
    stored_points,
    verdict_of,
)
from mirror_fg.analysis.verify_fused import fused_estimate
from mirror_fg.analysis.verify_plane import StoredPlane, standing_plane
from mirror_fg.analysis.verify_priors import StoredIntrinsics, joint_prior, stored_intrinsics
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewProblem, camera_names, tangent_dimension

__all__ = ["Verification", "CameraVerdict", "verify", "MOVED", "NOT_MOVED", "CANNOT_TELL", "POWER", "stored_cameras",
           "detectable_noncentrality"]

#: LM iterations of each fit.
MAX_ITERATIONS = 100


# --------------------------------------------------------------------------------------------------
# The stored result


def stored_cameras(result: Mapping[str, Any]) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """``{camera: (R_cam_base, t_cam_base, covariance_cam_base or None)}`` of a validated result@1 (one
    camera is :data:`~mirror_fg.solver.model.views.SINGLE_CAMERA`)."""
    entries = result.get("cameras") or {SINGLE_CAMERA: result}
    out = {}
    for name, entry in entries.items():
        R, t = pose(entry["T_cam_base"])
        cov = entry.get("covariance_cam_base")
        out[name] = (R, t, None if cov is None else np.array(cov, dtype=float))
    return out


def _stored_intrinsics(result: Mapping[str, Any], name: str, given, source: str):
    """The camera the result used for ``name`` (its estimated block where it has one), else ``given``."""
    if result.get("cameras"):
        block = result["cameras"][name].get("camera")
        found = estimated_camera({"camera": block}, source, given) if block is not None else None
    else:
        found = estimated_camera(result, source, given)
    if found is None:
        return given
    if given is not None and (found.width, found.height) != (given.width, given.height):
        raise DatasetError(f"{source}: camera {name!r} is {found.width}x{found.height} px but the new images' camera "
                           f"is {given.width}x{given.height}: the result and the data are from different set-ups")
    return found


def _verification_dataset(result: Mapping[str, Any], dataset: Dataset,
                          source: str) -> tuple[Dataset, dict[str, StoredIntrinsics]]:
    """``dataset`` with the stored intrinsics (their values; none left to estimate) and the stored
    reconstruction points as known points, and the intrinsics the result estimated with their stored
    covariances; one line (DatasetError) where the result and the data cannot be from one set-up."""
    stored = stored_cameras(result)
    names = camera_names(dataset)
    unknown = [n for n in names if n not in stored]
    if unknown:
        have = ", ".join(repr(n) for n in stored)
        what = "the data have one camera" if dataset.cameras is None else f"camera {unknown[0]!r} of the data"
        raise DatasetError(f"{source}: {what} is not in the result (its cameras: {have}): the result and the data "
                           "are from different set-ups")
    for name in names:
        covariance = stored[name][2]
        if covariance is None:
            raise DatasetError(f"{source}: camera {name!r} has no covariance_cam_base: verify needs the stored "
                               "uncertainty (calibrate again)")
        if not np.all(np.isfinite(covariance)) or np.linalg.eigvalsh(0.5 * (covariance + covariance.T))[0] <= 0:
            raise DatasetError(f"{source}: camera {name!r}: covariance_cam_base is not positive definite (a camera "
                               "whose frame is the base frame cannot have moved against it)")
    points = stored_points(result, dataset, source)

    def fixed(camera):
        return None if camera is None else replace(camera, estimate=(), prior_sigma=())

    if dataset.cameras is not None:
        cameras = {n: fixed(_stored_intrinsics(result, n, c, source)) for n, c in dataset.cameras.items()}
        camera = None
    else:
        cameras, camera = None, fixed(_stored_intrinsics(result, SINGLE_CAMERA, dataset.camera, source))
    used = {n: points[n] for n in dataset.reconstruction_point_names}
    verification = replace(dataset, camera=camera, cameras=cameras, fiducials={**dataset.fiducials, **used})
    intrinsics = {}
    for name in names:
        found = stored_intrinsics(result, name, verification.cameras[name] if verification.cameras else camera, source)
        if found is not None:
            intrinsics[name] = found
    return verification, intrinsics


# --------------------------------------------------------------------------------------------------
# The fits


class _Fits:
    """The new data's graph and the priors of the test, and LM on them."""

    def __init__(self, dataset: Dataset, stored: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                 intrinsics: dict[str, StoredIntrinsics], max_iterations: int = MAX_ITERATIONS):
        self.problem = ViewProblem(dataset, intrinsics={n: i.model for n, i in intrinsics.items()})
        self.intrinsics = intrinsics
        self.data = self.problem.graph()
        for name, stored_k in intrinsics.items():  # in every fit: the intrinsics cannot have moved
            self.data.add(stored_k.marginal_prior(self.problem.intrinsics_keys[name]))
        self.stored = stored
        self.params = lm_params(max_iterations, cost_scale(dataset), GENERAL_LAMBDA_UPPER_BOUND)
        self.source = dataset.source
        self.stored_pose = {n: gtsam.Pose3(gtsam.Rot3(R), t) for n, (R, t, _) in stored.items()}
        #: The stored covariance in GTSAM's tangent at the stored pose.
        self.stored_tangent = {n: covariance_to_pose3(R, C) for n, (R, _, C) in stored.items()}
        self.noun = "camera"
        #: A stored placement held at its plane in {B} (``verify_plane.py``), else None.
        self.plane: StoredPlane | None = None

    def hold_plane(self, plane: StoredPlane | None) -> None:
        """Hold ``plane`` (the single camera's): its marginal in every fit, the held pose given it."""
        self.plane = plane
        if plane is not None:
            self.data.add(plane.marginal_prior(self.pose_key(SINGLE_CAMERA), self.problem.mirror_keys[plane.placement]))

    def pose_key(self, name: str) -> int:
        return self.problem.pose_keys[name]

    def start(self) -> gtsam.Values:
        """The stored poses and every new placement from them (propagation rule 3)."""
        problem = self.problem
        poses = {n: (R, t) for n, (R, t, _) in self.stored.items() if n in problem.pose_keys}
        try:
            known = propagate(problem.views, problem.dataset.fiducials, problem.cameras, poses)
        except Unsolvable as error:
            raise DatasetError(f"{self.source}: {error}") from None
        return problem.values(problem.estimate_from(known))

    def prior(self, name: str, information: np.ndarray | None = None) -> gtsam.NonlinearFactor:
        """Camera ``name`` at its stored transform: with its stored covariance (and, where the result
        estimated them, its intrinsics' cross-covariance), or ``information`` (tangent)."""
        key = self.problem.pose_keys[name]
        if information is not None:
            return gtsam.PriorFactorPose3(key, self.stored_pose[name], gtsam.noiseModel.Gaussian.Information(information))
        if self.plane is not None:
            return self.plane.conditional(key, self.problem.mirror_keys[self.plane.placement], self.stored_pose[name])
        if name in self.intrinsics:
            return joint_prior(key, self.problem.intrinsics_keys[name], self.stored_pose[name], self.intrinsics[name],
                               self.stored_tangent[name])
        return gtsam.PriorFactorPose3(key, self.stored_pose[name],
                                      gtsam.noiseModel.Gaussian.Covariance(self.stored_tangent[name]))

    def fit(self, priors: list, starts: list[gtsam.Values]) -> tuple[gtsam.Values, float]:
        """LM on the data and ``priors`` from each start: the lowest ``(values, cost)``."""
        return lowest_fit(self.data, priors, starts, self.params, self.source,
                          lambda error: unconstrained_message(error, self.problem))

    def information(self, values: gtsam.Values) -> tuple[np.ndarray, dict[int, slice]]:
        """The data's Gauss-Newton information over every unknown (tangent) and each key's columns."""
        ordering, columns, start = gtsam.Ordering(), {}, 0
        for key in self.problem.keys:
            ordering.push_back(key)
            dim = tangent_dimension(key, values)
            columns[key] = slice(start, start + dim)
            start += dim
        A, _ = self.data.linearize(values).jacobian(ordering)
        return A.T @ A, columns

    def pose_information(self, name: str, values: gtsam.Values) -> np.ndarray:
        """What the new data say about camera ``name``'s pose, the placements and the other cameras
        marginalised (Schur complement; tangent at ``values``)."""
        H, columns = self.information(values)
        c = columns[self.problem.pose_keys[name]]
        own = np.zeros(H.shape[0], dtype=bool)
        own[c] = True
        H_oo = H[~own][:, ~own]
        H_co = H[own][:, ~own]
        return H[c, c] - H_co @ np.linalg.pinv(H_oo, rcond=1e-12, hermitian=True) @ H_co.T


# --------------------------------------------------------------------------------------------------
# The test


def verify(result: Mapping[str, Any] | Any, dataset: Dataset, alpha: float = 0.01, tolerance_mm: float = 2.0,
           tolerance_deg: float = 0.2, source: str = "result", options: SolveOptions | None = None,
           standing: bool = False) -> Verification:
    """Whether each camera of ``dataset``'s images is still where ``result`` (a validated result@1
    dictionary, or a :class:`~mirror_fg.solver.result.calibration.Calibration`) puts it (module docstring).
    ``source`` names the result in messages; ``options``: its ``max_iterations`` bounds each LM fit;
    ``standing``: the new images' placements the result holds (the same labels) are the same mirrors, standing
    where they stood (``verify_plane.py``: one of them is held at its stored plane).
    DatasetError (exit 2) where the result and the data cannot be from one set-up."""
    if not 0.0 < alpha < 1.0:
        raise DatasetError(f"alpha must be between 0 and 1, got {alpha}")
    if hasattr(result, "to_dict"):
        result = result.to_dict()
    if standing and (dataset.robot is not None or result.get("mounts")):
        raise DatasetError(f"{source}: a standing mirror is held for a camera fixed in the base frame, not an arm")
    if dataset.robot is not None or result.get("mounts"):  # the target or the camera rides the arm's joints
        from mirror_fg.analysis.verify_arm import verify_arm

        return verify_arm(result, dataset, alpha, tolerance_mm, tolerance_deg, source,
                          options.max_iterations if options is not None else MAX_ITERATIONS)
    verification_data, intrinsics = _verification_dataset(result, dataset, source)
    stored_all = stored_cameras(result)
    fits = _Fits(verification_data, {n: c for n, c in stored_all.items() if n in camera_names(dataset)},  # type: ignore[misc]
                 intrinsics, options.max_iterations if options is not None else MAX_ITERATIONS)
    problem = fits.problem
    tested = list(problem.pose_keys)
    if standing:  # a mirror that still stands (verify_plane.py)
        fits.hold_plane(standing_plane(result, verification_data, bool(intrinsics) or tested != [SINGLE_CAMERA],
                                       fits.stored_tangent, source))
    start = fits.start()
    held_all, _ = fits.fit([fits.prior(n) for n in tested], [start])  # every camera held: also the fused estimate
    seen = {n: seen_directions(fits.stored_tangent[n], fits.pose_information(n, held_all)) for n in tested}
    free_priors = {n: fits.prior(n, free_information(*seen[n])) for n in tested}
    free, cost_free = fits.fit(list(free_priors.values()), [held_all, start])
    expected = expected_cost(problem.size, free.dim() - 6 * len(tested), min_dof=1)
    if not plausible(float(fits.data.error(free)), expected):  # not even a moved camera explains them
        raise DatasetError(f"{dataset.source}: the new images do not fit {source}'s target and points even with the "
                           f"camera free (cost {fits.data.error(free):.3g}, expected about {expected:.3g}): the result and "
                           "the data are from different set-ups, or the target or its points moved")
    dispersion = stored_dispersion(result)
    checked = dispersion is not None and dispersion[1] > 0.5 and math.isfinite(dispersion[0]) and dispersion[0] > 0
    # only ever widened: bounds narrower than the noise model gives are not trusted (s2 < 1 is chance)
    scale, nu = (max(1.0, dispersion[0]), dispersion[1]) if checked else (1.0, None)  # type: ignore[index]
    ncp = {k: detectable_noncentrality(k, alpha, denominator_dof=nu) for k in range(1, 7)}
    verdicts: dict[str, CameraVerdict] = {}
    for name in camera_names(dataset):
        if name not in problem.pose_keys:
            verdicts[name] = CameraVerdict(name, CANNOT_TELL, 1.0, 0.0, 0, None, None, math.inf, math.inf,
                                           "no new image of this camera")
            continue
        priors = [fits.prior(name)] + [f for n, f in free_priors.items() if n != name]
        _, cost_held = fits.fit(priors, [held_all, free])
        d2 = max(0.0, 2.0 * (cost_held - cost_free))
        dof = int(np.sum(seen[name][0] > SEEN))
        if dof == 0:
            p = 1.0
        elif nu is not None:  # the F-test: d2 / k over the image-level variance factor (module docstring)
            p = float(stats.f.sf(d2 / (dof * scale), dof, nu))
        else:
            p = float(stats.chi2.sf(d2, dof))
        answer = verdict_of(name, d2, dof, p, free, fits, ncp.get(dof, math.inf), alpha, tolerance_mm, tolerance_deg,
                          scale)
        if dispersion is not None:
            answer = replace(answer, dispersion=dispersion[0], dispersion_dof=dispersion[1])
            if not checked and answer.verdict == NOT_MOVED:  # nu = 0: the stored bounds cannot be checked
                answer = replace(answer, verdict=CANNOT_TELL, advice=UNCHECKED)
        verdicts[name] = answer
    fused = fused_estimate(fits, held_all, tested)
    return Verification(verdicts, alpha, tolerance_mm, tolerance_deg, fused)
