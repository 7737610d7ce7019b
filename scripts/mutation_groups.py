"""The mutation study's groups for the newest code: verify, registry, robot, units, verdict (with the input
guards) and incremental. Each is a list of :class:`mutation_study.Mutant` (passed in as ``Mutant`` so that
this module does not import the study back); see ``scripts/mutation_study.py`` for how they run.

A mutant whose line a later change rewrote is reported as "line not found" by the study, not run.
"""
from __future__ import annotations

from typing import Any

VERIFY_PY = "mirror_fg/analysis/verify.py"
VERIFY = ("tests/test_verify.py",)
VERIFY_FAST = tuple(f"tests/test_verify.py::{t}" for t in (
    "test_degrees_of_freedom_seen", "test_detectable_noncentrality_against_monte_carlo", "test_verdicts_follow_the_tolerance",
    "test_power_fast", "test_estimated_intrinsics_fast", "test_cannot_tell_whenever_the_detectable_move_exceeds_the_tolerance",
    "test_update_narrows_every_bound", "test_cli_not_moved_writes_verification_and_update",
    "test_cli_moved_and_cannot_tell_exit_codes")) + ("tests/test_verify_mutants.py",)
REGISTRY = ("tests/test_registry.py", "tests/test_registry_cli.py", "tests/test_registry_mutants.py")
ROBOT_FACTOR = ("tests/test_robot_factor.py",)
ROBOT_KIN = ("tests/test_robot_kinematics.py",)
ROBOT_INPUTS = ("tests/test_robot_inputs.py",)
ROBOT_AXES = ("tests/test_robot_axes.py", "tests/test_robot_calibrate.py::test_one_rotation_axis_is_said_in_words_exit_3")
ROBOT_MLE = ("tests/test_robot_mle.py", "tests/test_robot_start.py")
POINT = ("tests/test_point_error.py",)
GAZE = ("tests/test_gaze_error.py", "tests/test_gaze_export.py")
SCREEN = ("tests/test_screen.py",)
VALIDATION = ("tests/test_validation.py", "tests/test_units_mutants.py::test_validation_from_an_estimate_near_the_optimum_equals_the_optimum_s")
VERDICT = ("tests/test_verdict.py", "tests/test_verdict_mutants.py")
GUARDS = "tests/test_input_guard_mutants.py"
INCREMENTAL = ("tests/test_incremental_views.py", "tests/test_incremental_mutants.py")
TREE = ("tests/test_incremental.py",)


def groups(Mutant: Any) -> dict[str, list]:
    """``{group: [Mutant, ...]}`` for the study's :func:`register`."""
    M = Mutant
    out: dict[str, list] = {}
    out["verify"] = [
        M(VERIFY_PY, "            p = float(stats.chi2.sf(d2, dof))", "            p = float(stats.chi2.sf(d2, 6))",
          VERIFY_FAST, "the p-value with 6 degrees of freedom whatever the new images see"),
        M(VERIFY_PY, "dof = int(np.sum(seen[name][0] > SEEN))", "dof = int(np.sum(seen[name][0] > SEEN)) - 1",
          VERIFY_FAST, "the seen degrees of freedom off by one"),
        M(VERIFY_PY, "d2 = max(0.0, 2.0 * (cost_held - cost_free))", "d2 = max(0.0, cost_held - cost_free)",
          VERIFY_FAST, "the statistic without GTSAM's factor 1/2 (half the chi-square)"),
        M(VERIFY_PY, "return float(stats.ncx2.sf(critical, dof, ncp)) - power",
          "return float(stats.ncx2.cdf(critical, dof, ncp)) - power", VERIFY_FAST,
          "the power as the probability of not rejecting"),
        M(VERIFY_PY, "critical = stats.chi2.isf(alpha, dof)", "critical = stats.chi2.ppf(alpha, dof)", VERIFY_FAST,
          "the critical value from the wrong tail"),
        M(VERIFY_PY, "move = np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R @ R_s.T)), t - t_s])",
          "move = np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R @ R_s.T)), t_s - t])", VERIFY_FAST,
          "the move's position stored minus new"),
        M(VERIFY_PY, "move = np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R @ R_s.T)), t - t_s])",
          "move = np.concatenate([gtsam.Rot3.Logmap(gtsam.Rot3(R_s @ R.T)), t - t_s])", VERIFY_FAST,
          "the move's rotation stored relative to new"),
        M(VERIFY_PY, "combined = S + 0.5 * (new + new.T)", "combined = S", VERIFY_FAST,
          "the combined covariance without the new data's term"),
        M(VERIFY_PY, "detectable_m = math.sqrt(ncp * float(np.linalg.eigvalsh(combined[3:, 3:])[-1]))",
          "detectable_m = math.sqrt(ncp * float(np.linalg.eigvalsh(combined[3:, 3:])[0]))", VERIFY_FAST,
          "the detectable move in the best, not the worst, direction"),
        M(VERIFY_PY, "elif math.degrees(detectable_rad) <= tolerance_deg and 1e3 * detectable_m <= tolerance_mm:",
          "elif math.degrees(detectable_rad) <= tolerance_deg and detectable_m <= tolerance_mm:", VERIFY_FAST,
          "the detectable move in metres against a tolerance in millimetres"),
        M(VERIFY_PY, "return {MOVED: 4, NOT_MOVED: 0, CANNOT_TELL: 5}[self.verdict]",
          "return {MOVED: 5, NOT_MOVED: 0, CANNOT_TELL: 4}[self.verdict]", VERIFY_FAST,
          "the whole verification's exit codes of moved and cannot tell swapped", occurrence=1),
        M(VERIFY_PY, "return MOVED if MOVED in verdicts else CANNOT_TELL if CANNOT_TELL in verdicts else NOT_MOVED",
          "return CANNOT_TELL if CANNOT_TELL in verdicts else MOVED if MOVED in verdicts else NOT_MOVED", VERIFY_FAST,
          "a rig with one camera that cannot tell hides another that moved"),
        M(VERIFY_PY, "    weights = np.where(lam > SEEN, FREE_WEIGHT, UNSEEN_WEIGHT)",
          "    weights = np.where(lam > SEEN, 1.0, UNSEEN_WEIGHT)",
          VERIFY_FAST, "the free fit held at the stored pose where the new images see"),
        M(VERIFY_PY, "    weights = np.where(lam > SEEN, FREE_WEIGHT, UNSEEN_WEIGHT)",
          "    weights = np.where(lam > SEEN, FREE_WEIGHT, 1.0)",
          ("tests/test_verify.py::test_takahashi_fiducials_shifted_say_moved",),
          "the free fit held by the whole stored prior where the new images see nothing (a large move is refused)"),
        M("mirror_fg/analysis/verify_priors.py", "covariance = pose_tangent - B @ cross_tangent.T",
          "covariance = pose_tangent + B @ cross_tangent.T", VERIFY_FAST,
          "the conditional covariance adds what the intrinsics explain"),
        M("mirror_fg/analysis/verify_priors.py", "B = cross_tangent @ np.linalg.inv(self.covariance)",
          "B = cross_tangent @ self.covariance", VERIFY_FAST, "the regression with the covariance, not its inverse"),
        M("mirror_fg/io/verification.py", "P_bc = T.inverse_covariance(P)", "P_bc = P", VERIFY_FAST,
          "--update writes the camera-base covariance as the base-camera one"),
    ]
    history = "mirror_fg/registry/history.py"
    store = "mirror_fg/registry/store.py"
    schema = "mirror_fg/registry/schema.py"
    out["registry"] = [
        M(history, "position_sigma3 = np.hypot(np.array(before.sigma3_position_mm), np.array(after.sigma3_position_mm))",
          "position_sigma3 = np.array(before.sigma3_position_mm) + np.array(after.sigma3_position_mm)", REGISTRY,
          "the combined 3-sigma as a sum, not in quadrature"),
        M(history, "rotation_sigma3 = np.hypot(np.array(before.sigma3_rotation_deg), np.array(after.sigma3_rotation_deg))",
          "rotation_sigma3 = np.array(after.sigma3_rotation_deg)", REGISTRY,
          "the rotation change against the newer calibration's 3-sigma only"),
        M(history, "if np.any(np.abs(position) > position_sigma3) or np.any(np.abs(rotation) > rotation_sigma3):",
          "if np.any(position > position_sigma3) or np.any(np.abs(rotation) > rotation_sigma3):", REGISTRY,
          "a change flagged only when it is positive"),
        M(history, "position = 1000.0 * (np.array(after.t_m) - np.array(before.t_m))",
          "position = np.array(after.t_m) - np.array(before.t_m)", REGISTRY, "the position change in metres against mm"),
        M(history, "    if w < 0:  # the same rotation, the short way round", "    if w > 0:  # the same rotation, the short way round",
          REGISTRY, "the rotation taken the long way round"),
        M(history, "return np.degrees(2.0 * math.atan2(norm, w) / norm * v)", "return np.degrees(math.atan2(norm, w) / norm * v)",
          REGISTRY, "the quaternion's half angle as the angle"),
        M(history, "x2, y2, z2, w2 = (-float(q_before[0]), -float(q_before[1]), -float(q_before[2]), float(q_before[3]))",
          "x2, y2, z2, w2 = (float(q_before[0]), float(q_before[1]), float(q_before[2]), float(q_before[3]))", REGISTRY,
          "the change composed with the earlier rotation, not its inverse"),
        M(store, "if self.engine.dialect.name != \"sqlite\" or not _locked(error) or _time.monotonic() > deadline:",
          "if self.engine.dialect.name != \"sqlite\" or _time.monotonic() > deadline:", REGISTRY,
          "every SQLite error retried for two minutes as if locked"),
        M(store, "if self.engine.dialect.name != \"sqlite\" or not _locked(error) or _time.monotonic() > deadline:",
          "if self.engine.dialect.name != \"sqlite\" or _locked(error) or _time.monotonic() > deadline:", REGISTRY,
          "a locked database not retried"),
        M(store, "            with Session(self.engine) as session, session.begin():\n                run = Run(",
          "            with Session(self.engine) as session:\n                run = Run(", REGISTRY,
          "the run written without a transaction (never committed)"),
        M(store, "record = session.scalars(query.order_by(CameraRecord.time.desc(), CameraRecord.id.desc())",
          "record = session.scalars(query.order_by(CameraRecord.time, CameraRecord.id.desc())", REGISTRY,
          "latest gives the oldest record"),
        M(schema, "    if revision is None:\n        return True", "    if revision is None:\n        return False", REGISTRY,
          "an empty database taken for a newer schema"),
        M(schema, "    if current == head:\n        return", "    if current is not None:\n        return", REGISTRY,
          "an old schema not migrated"),
    ]
    kin = "mirror_fg/robot/kinematics.py"
    factor = "factors/robot.py"
    out["robot"] = [
        M(factor, "    A[3:, :3] = _skew(t) @ R\n", "    A[3:, :3] = R @ _skew(t)\n", ROBOT_FACTOR,
          "the adjoint's translation block in the wrong order"),
        M(factor, "    A[3:, :3] = _skew(t) @ R\n", "    A[3:, :3] = -_skew(t) @ R\n", ROBOT_FACTOR,
          "the adjoint's translation block with the wrong sign"),
        M(factor, "    return a[0].T, -a[0].T @ a[1]", "    return a[0].T, -a[1]", ROBOT_FACTOR,
          "the inverse's translation not rotated"),
        M(factor, "dC = dT @ -adjoint(inverse(state[\"T\"]))", "dC = dT @ -adjoint(state[\"T\"])", ROBOT_FACTOR,
          "C's perturbation carried through T, not its inverse"),
        M(factor, "a = adjoint(inverse(mounts[\"camera\"])) @ state[\"J_c\"]", "a = adjoint(mounts[\"camera\"]) @ state[\"J_c\"]",
          ROBOT_FACTOR, "the joint-offset chain through the camera mount, not its inverse"),
        M(factor, "jacobians[k] = dC @ a + dT @ b", "jacobians[k] = dC @ a - dT @ b", ROBOT_FACTOR,
          "the target side of the joint-offset Jacobian with the wrong sign"),
        M(factor, "d_c = d - float(n @ t_C)", "d_c = d + float(n @ t_C)", ROBOT_FACTOR,
          "a mirror plane moved to the camera with the wrong sign"),
        M(kin, "out[link] = (np.asarray(bMl.homogeneous, float), np.vstack([J[3:], J[:3]]))  # [v, w] -> [w, nu]",
          "out[link] = (np.asarray(bMl.homogeneous, float), J)  # [v, w] -> [w, nu]", ROBOT_FACTOR + ROBOT_KIN,
          "Pinocchio's [v, w] Jacobian taken as GTSAM's [w, nu]"),
        M(kin, "J = J - bMl.inverse().action @ J_base", "J = J - bMl.action @ J_base", ROBOT_FACTOR + ROBOT_KIN,
          "the moving base's velocity carried the wrong way"),
        M(kin, "q[info.index_q:info.index_q + 2] = np.cos(value), np.sin(value)",
          "q[info.index_q:info.index_q + 2] = np.sin(value), np.cos(value)", ROBOT_FACTOR + ROBOT_KIN,
          "a continuous joint's angle as (sin, cos)"),
        M("mirror_fg/io/robot_fields.py",
          "if info.lower is not None and not info.lower - LIMIT_SLACK <= x <= info.upper + LIMIT_SLACK:",
          "if info.lower is not None and not info.lower - LIMIT_SLACK <= x:", ROBOT_INPUTS, "the upper joint limit unchecked"),
        M("mirror_fg/io/robot_fields.py",
          "setup.offset_sigma[n] = sigmas[\"prior_sigma_mm\"] / 1000.0 if prismatic else math.radians(sigmas[\"prior_sigma_deg\"])",
          "setup.offset_sigma[n] = sigmas[\"prior_sigma_mm\"] / 1000.0 if prismatic else sigmas[\"prior_sigma_deg\"]",
          ROBOT_INPUTS + ("tests/test_robot_mle.py",), "the joint offsets' prior sigma in degrees taken as radians"),
        M("mirror_fg/solver/batch/robot_solve.py", "if s[0] > 0 and s[1] > ONE_AXIS_RATIO * s[0]:",
          "if s[0] > 0 and s[2] > ONE_AXIS_RATIO * s[0]:", ROBOT_AXES,
          "the one-axis check on the third singular value (a planar motion refused)"),
        M("mirror_fg/solver/batch/robot_solve.py", "ONE_AXIS_RATIO = 0.02", "ONE_AXIS_RATIO = 0.0002", ROBOT_AXES,
          "the one-axis threshold a hundred times lower"),
        M("mirror_fg/solver/model/robot_views.py", "return inv, covariance_from_pose3(inv[0], Ad @ pose3_covariance @ Ad.T)",
          "return inv, covariance_from_pose3(inv[0], Ad.T @ pose3_covariance @ Ad)", ("tests/test_robot_axes.py", "tests/test_robot_mle.py"),
          "the mount's covariance carried by the transposed adjoint"),
    ]
    out["units"] = [
        M("mirror_fg/solver/result/point_error.py", "return np.hstack([-skew, np.eye(3)])", "return np.hstack([skew, np.eye(3)])",
          POINT, "the point Jacobian's rotation term with the wrong sign"),
        M("mirror_fg/solver/result/point_error.py", "a = np.asarray(R_base_cam, float) @ np.asarray(point_cam, float)",
          "a = np.asarray(point_cam, float)", POINT, "the lever arm in camera axes, not base axes"),
        M("mirror_fg/solver/result/point_error.py", "return PointError(p, T_base_cam.apply(p), C, 3000.0 * np.sqrt(np.clip(np.diag(C), 0.0, None)))",
          "return PointError(p, T_base_cam.apply(p), C, 3.0 * np.sqrt(np.clip(np.diag(C), 0.0, None)))", POINT,
          "sigma3_mm in metres"),
        M("mirror_fg/core/gaze_error.py", "mm_per_px = 1000.0 * screen.metres_per_px", "mm_per_px = screen.metres_per_px",
          GAZE, "the gaze error in metres where mm are written"),
        M("mirror_fg/core/gaze_error.py", "per_mm = np.linalg.norm(across, axis=0) / (1000.0 * distance)",
          "per_mm = np.linalg.norm(across, axis=0) / distance", GAZE, "the angle per mm off by a thousand"),
        M("mirror_fg/core/gaze_error.py", "return centre + viewing_distance_m * screen.normal_cam",
          "return centre - viewing_distance_m * screen.normal_cam", GAZE, "the eye behind the screen"),
        M("mirror_fg/io/gaze_export.py", "return np.array(T[\"R\"], dtype=float), 1000.0 * np.array(T[\"t\"], dtype=float), dict(block)",
          "return np.array(T[\"R\"], dtype=float), np.array(T[\"t\"], dtype=float), dict(block)", GAZE,
          "the gaze exports' translation in metres, not mm"),
        M("mirror_fg/io/gaze_export.py", "return np.array(T[\"R\"], dtype=float), 1000.0 * np.array(T[\"t\"], dtype=float), dict(block)",
          "return np.array(T[\"R\"], dtype=float).T, 1000.0 * np.array(T[\"t\"], dtype=float), dict(block)", GAZE,
          "the gaze exports' rotation transposed"),
        M("mirror_fg/core/screen.py", "        lam = -o_s[2] / d_s[2]\n", "        lam = o_s[2] / d_s[2]\n", GAZE + SCREEN,
          "the ray's hit on the far side"),
        M("mirror_fg/core/screen.py", "J_q = (np.eye(3) - np.outer(d_s, [0.0, 0.0, 1.0]) / d_s[2]) @ G",
          "J_q = G", GAZE + SCREEN, "the hit's Jacobian without the ray's slide along itself"),
        M("mirror_fg/solver/fit/validation.py", "ratios = np.sqrt(costs / expected) if len(costs) else np.zeros(0)",
          "ratios = costs / expected if len(costs) else np.zeros(0)", VALIDATION, "the held-out ratio without its root"),
        M("mirror_fg/solver/fit/validation.py", "step = -covariance @ gradient  # one Gauss-Newton step",
          "step = covariance @ gradient  # one Gauss-Newton step", VALIDATION, "the Gauss-Newton step uphill"),
        M("mirror_fg/solver/batch/screens.py", "(measurements - unknowns) / 2.0,", "(measurements - unknowns),",
          ("tests/test_screens.py", "tests/test_units_mutants.py"), "the screens' expected cost twice the chi-square's half"),
    ]
    out["verdict"] = [
        M("mirror_fg/report/verdict.py", "low = math.sqrt(float(chdtri(dof, 1.0 - tail)) / dof)",
          "low = math.sqrt(float(chdtri(dof, tail)) / dof)", VERDICT, "the noise band's low end at the upper quantile"),
        M("mirror_fg/report/verdict.py", "tail = (1.0 - confidence) / 2.0", "tail = 1.0 - confidence", VERDICT,
          "the noise band one-sided"),
        M("mirror_fg/report/verdict.py", "high = math.sqrt(float(chdtri(dof, tail)) / dof)",
          "high = math.sqrt(float(chdtri(dof, tail)) / (dof + 1))", VERDICT, "the band's degrees of freedom off by one"),
        M("mirror_fg/report/verdict.py", "return min(low, NOISE_BAND[0]), max(high, NOISE_BAND[1])",
          "return max(low, NOISE_BAND[0]), min(high, NOISE_BAND[1])", VERDICT, "the band narrowed, not widened"),
        M("mirror_fg/report/verdict.py", "LINEAR_LIMIT_DEG = 10.0", "LINEAR_LIMIT_DEG = 100.0", VERDICT,
          "the linearisation limit ten times looser"),
        M("mirror_fg/report/verdict.py", "        if size_mm > 0 and position_mm > limit_mm:",
          "        if size_mm > 0 and position_mm > size_mm:", VERDICT, "the position bound against the whole scene"),
        M("mirror_fg/report/verdict.py", "        if measurements > 0 and spare / measurements < MIN_MEAN_REDUNDANCY:",
          "        if measurements > 0 and spare / measurements > MIN_MEAN_REDUNDANCY:", VERDICT, "the redundancy test inverted"),
        M("mirror_fg/report/verdict.py", "spare = 2.0 * float(expected) if", "spare = float(expected) if", VERDICT,
          "spare measurements as GTSAM's half chi-square"),
        M("mirror_fg/solver/result/guard.py", "MAX_SCENE_DISTANCE_M = 20.0", "MAX_SCENE_DISTANCE_M = 20000.0",
          ("tests/test_result_validation.py", GUARDS), "the scene-distance guard in mm"),
        M("mirror_fg/solver/screen/camera_labels.py", "if rms is not None and rms > LABEL_CONFLICT_SIGMAS * np.sqrt(2.0) * sigma:",
          "if rms is not None and rms < LABEL_CONFLICT_SIGMAS * np.sqrt(2.0) * sigma:", ("tests/test_consensus_guards.py", GUARDS),
          "a camera label conflict when the two agree"),
        M("mirror_fg/solver/screen/camera_labels.py", "if len(images) == 1 and others:", "if len(images) == 0 and others:",
          ("tests/test_consensus_guards.py", GUARDS), "a lone mislabelled image never suspected"),
        M("mirror_fg/io/dataset_fields.py",
          "if not is_number(distance) or not MIN_LENGTH_M <= float(distance) <= MAX_TARGET_EXTENT_M:",
          "if not is_number(distance) or not MIN_LENGTH_M <= float(distance):", ("tests/test_dataset.py", GUARDS),
          "a scale distance in millimetres accepted"),
    ]
    inc = "mirror_fg/solver/incremental/calibrator.py"
    views = "mirror_fg/solver/incremental/views.py"
    state = "mirror_fg/solver/incremental/state.py"
    out["incremental"] = [
        M(inc, "            for earlier in self._given:\n", "            for earlier in self._given[1:]:\n", INCREMENTAL,
          "the hand-over forgets the first image"),
        M(inc, "            estimate = self.backend.add_image(image)\n        self._given",
          "            estimate = None\n        self._given", INCREMENTAL, "the image that leaves the tree dropped at the hand-over"),
        M(inc, "        self._given.append(image)  # as it came", "        self._given = [image]  # as it came", INCREMENTAL,
          "only the last image kept for a hand-over"),
        M(views, "            if not fit <= POOR_FIT_RATIO:", "            if not fit <= 10 * POOR_FIT_RATIO:", INCREMENTAL,
          "a start that fits ten times worse accepted"),
        M(views, "SETTLE_UPDATES = 1", "SETTLE_UPDATES = 0", INCREMENTAL, "no settling update after new unknowns"),
        M(views, "FINAL_LM_ITERATIONS = 100", "FINAL_LM_ITERATIONS = 3", INCREMENTAL, "the final LM cut short"),
        M(views, "return values, int(optimizer.iterations()) < FINAL_LM_ITERATIONS",
          "return values, int(optimizer.iterations()) <= FINAL_LM_ITERATIONS", INCREMENTAL,
          "an LM that ran out of iterations called converged"),
        M(views, "            everything.insert(self._isam.calculateEstimate())  # type: ignore[union-attr]",
          "            pass", INCREMENTAL, "new unknowns judged without the current estimate"),
        M(state, "    params.relinearizeSkip = 1", "    params.relinearizeSkip = 10", INCREMENTAL + TREE,
          "relinearisation checked every tenth update"),
        M(state, "params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))",
          "params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(1.0))", INCREMENTAL + TREE,
          "wildfire back-substitution: the estimate lags the linear solution"),
        M(state, "params.setRelinearizeThreshold((thresholds or RelinearizeThresholds()).threshold_map())",
          "params.setRelinearizeThreshold(1.0)", INCREMENTAL + TREE, "a relinearisation threshold of 1 on every variable"),
    ]
    return out
