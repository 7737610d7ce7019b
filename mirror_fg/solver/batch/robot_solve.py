"""The batch solve of an arm's data (docs/formats.md, "Robot arms: joint states and mounts"): analytical
start (``robot_start.py``: PnP, robot-world hand-eye per placement, peeling eqs. 13-18) -> Levenberg-
Marquardt over the view model with forward kinematics (``robot_views.py``, eq. 23) -> the motion's
observability (a mount's translation along the one axis every arm pose rotates about is not determined:
SolveError naming it) -> covariances (dense: the unknowns are few) -> :class:`Calibration` with the
mounts and joint offsets (``Calibration.robot``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import gtsam
import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.core.fit import expected_cost, plausible
from mirror_fg.core.transform import rotation_to_quaternion_xyzw
from mirror_fg.factors.robot import compose
from mirror_fg.data import Dataset
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.model.lm import GENERAL_LAMBDA_UPPER_BOUND, cost_scale, lm_params, run_optimizer
from mirror_fg.solver.options import STAGES, SolveOptions
from mirror_fg.solver.pipeline import run_pipeline
from mirror_fg.solver.screen.rechecks import Checked, Rechecked
from mirror_fg.solver.result.builder import Label, build_calibration
from mirror_fg.solver.start.robot_start import arm_start, camera_from_planes, triangulate
from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem, camera_base_pose, camera_name, is_camera, mount_words

__all__ = ["calibrate_robot", "solve_robot", "RobotSolution", "start_estimate", "UNDETERMINED_RATIO"]

logger = logging.getLogger("mirror_fg")
#: Starts tried at most where LM from the first ends implausibly (the first, then triples of placements).
MAX_STARTS = 8
#: Smallest eigenvalue of the information, relative to its largest over the unknown's own scale, below which
#: a direction is taken as undetermined (a well-posed arm scene measures 1e-9 and more).
UNDETERMINED_RATIO = 1e-12


def _pose(T: np.ndarray):
    return T[:3, :3], T[:3, 3]


def _reflection(v: np.ndarray) -> np.ndarray:
    """eq. (3) as a 4x4 map: ``x -> M x + 2 v``."""
    H = np.eye(4)
    H[:3, :3] -= 2.0 * np.outer(v, v) / (v @ v)
    H[:3, 3] = 2.0 * v
    return H


def _affine(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = pose
    return T


def start_estimate(problem: RobotProblem, max_starts: int = 1, minima: dict | None = None) -> list[RobotEstimate]:
    """The analytical starts (``robot_start.arm_start``; the first, and restarts), joint offsets at zero,
    reconstruction points triangulated through each. ``minima``: the screen's PnP minima
    (``consensus.ImageChecks.minima``), each used where the image still has the very fiducials it had.
    With several cameras each camera's images give their own start as one camera's would; each such start
    gives the target mount and the planes, the other cameras placed in them (:func:`_joined`; a camera
    without a start of its own too: neither it nor the target on the base link, or too few arm poses), and
    the joined starts are tried best-fitting first."""
    starts: dict[str, list] = {}
    failures: dict[str, SolveError] = {}
    for role in problem.camera_roles.values():
        try:
            starts[role] = _camera_starts(problem, role, max_starts, minima)
        except SolveError as error:
            if len(problem.camera_roles) == 1:
                raise
            failures[role] = error
    if not starts:
        raise next(iter(failures.values()))
    estimates = []
    for k in range(max(len(s) for s in starts.values())):
        chosen = {role: s[min(k, len(s) - 1)] for role, s in starts.items()}
        for reference in chosen:  # one camera's start, the others placed in its planes (a consistent start)
            estimates.append(_joined(problem, reference, chosen, failures, minima))
    if len(problem.camera_roles) > 1:  # several cameras: the joined start that fits best first
        graph = problem.graph()
        estimates.sort(key=lambda e: float(graph.error(problem.values(e))))
    return estimates[:max(max_starts, 1)]


def _joined(problem: RobotProblem, reference: str, chosen: dict, failures: dict, minima: dict | None) -> RobotEstimate:
    """One start of every unknown from the camera ``reference``'s start ``(M_c, M_t, planes)``: its target
    mount and planes (placements it did not see: another camera's), each other camera placed in them
    (``robot_start.camera_from_planes``; its own start's mount where that finds none)."""
    dataset = problem.dataset
    M_c, M_t, planes = chosen[reference]
    planes = dict(planes)
    for _, _, found in chosen.values():
        for p, v in found.items():
            planes.setdefault(p, v)
    target = problem.known.get("target", M_t)
    mounts = {reference: M_c, "target": target}
    for role in problem.camera_roles.values():
        if role == reference or role in problem.known:
            continue
        placed = camera_from_planes(_single_views(problem, role, minima), target, planes)
        if placed is None and role in failures:
            name = camera_name(role)
            raise SolveError(f"{dataset.source}: camera {name!r} has no start: "
                             f"{str(failures[role]).split(': ', 1)[-1]}; nor does it see 4 or more known target "
                             "points through a placement another camera started")
        mounts[role] = placed if placed is not None else chosen[role][0]
    mounts.update(problem.known)
    missing = [p for p in problem.placements if p not in planes]
    if missing:
        raise SolveError(f"{dataset.source}: mirror {missing[0][0]} placement {missing[0][1]} has no start: each "
                         f"placement needs 3 or more arm poses seen through it alone")
    estimate = RobotEstimate(mounts, planes, {}, np.zeros(len(problem.offsets)))
    if problem.point_names:
        estimate.points = _points(problem, estimate)
    return estimate


def _single_views(problem: RobotProblem, role: str, minima: dict | None) -> list:
    """``(placement, target points (N, 3), normalized (N, 2), T_B_camlink, T_B_targetlink, PnP minima or None)``
    of each image of the camera ``role`` seen through one mirror."""
    dataset = problem.dataset
    links = (problem.links[role], problem.links["target"])
    placed = []
    for index, image in enumerate(dataset.images):
        if len(image.reflections) != 1 or problem.role_of(image) != role:
            continue
        fiducial = [k for k, n in enumerate(image.observations) if n in dataset.fiducials]
        names = [n for n in image.observations if n in dataset.fiducials]
        F = problem.recorded[index]  # at the recorded joints
        known = (minima or {}).get(image.id)
        placed.append((image.reflections[0], np.array([dataset.fiducials[n] for n in names]).reshape(-1, 3),
                       problem.normalized[index].T[fiducial].reshape(-1, 2), F[links[0]][0],
                       F[links[1]][0], known[1] if known is not None and known[0] == tuple(names) else None))
    return placed


def _camera_starts(problem: RobotProblem, role: str, max_starts: int, minima: dict | None) -> list:
    """``robot_start.arm_start`` of the images of one camera: ``[(M_c, M_t, {placement: v_B})]``."""
    dataset, base = problem.dataset, problem.kinematics.base_link
    camera_link, target_link = problem.links[role], problem.links["target"]
    if camera_link == base:
        eye_to_hand = True
    elif target_link == base:
        eye_to_hand = False
    else:
        name = camera_name(role)
        raise SolveError(f"{dataset.source}: the analytical start needs the camera or the target on the base link "
                         f"{base!r} (here on {camera_link!r} and {target_link!r})"
                         + ("" if name is None else f", or camera {name!r} placed from another camera's start"))
    source = dataset.source if camera_name(role) is None else f"{dataset.source}: camera {camera_name(role)!r}"
    return arm_start(_single_views(problem, role, minima), eye_to_hand, source, max_starts)


def _points(problem: RobotProblem, estimate: RobotEstimate) -> dict[str, np.ndarray]:
    """Reconstruction points (target frame) triangulated through the start."""
    maps: dict[str, list] = {}
    for image, factor, observed in zip(problem.dataset.images, problem.factors, problem.normalized):
        F_c, F_t = factor.fk(estimate.offsets)
        C = _affine(compose(_pose(F_c[0]), estimate.mounts[problem.role_of(image)]))
        D = _affine(compose(_pose(F_t[0]), estimate.mounts["target"]))
        T = np.linalg.inv(C)
        for p in reversed(image.reflections):
            T = T @ _reflection(estimate.mirror_vectors[p])
        T = T @ D
        for k, name in enumerate(image.observations):
            if name in problem.point_keys:
                maps.setdefault(name, []).append(((T[:3, :3], T[:3, 3]), observed[:, k]))
    return {name: triangulate(*zip(*maps[name])) for name in problem.point_names}


#: Smallest second singular value, relative to the first, of the arm's rotations (axis times angle, link axes)
#: below which they turn about one axis only (0.02: about one degree off the axis per radian turned).
ONE_AXIS_RATIO = 0.02


def check_rotation_axes(problem: RobotProblem) -> None:
    """Before any solve: a mount on a moving link whose every arm pose turns that link about one axis
    leaves its translation along the axis undetermined (``A X = Z B`` with parallel rotation axes):
    SolveError (exit 3) naming the mount, the axis in the link's axes and the motion to add."""
    import cv2

    kin = problem.kinematics
    for role in problem.mount_keys:
        link = problem.links[role]
        if link == kin.base_link:
            continue
        rotations = [kin.placements(image.joints, [link])[link][0][:3, :3] for image in problem.dataset.images
                     if not is_camera(role) or problem.role_of(image) == role]  # a camera's own images
        turns = np.array([cv2.Rodrigues(rotations[0].T @ R)[0].ravel() for R in rotations[1:]])
        if len(turns) == 0:
            continue
        s, vt = np.linalg.svd(turns, full_matrices=False)[1:]
        if s[0] > 0 and s[1] > ONE_AXIS_RATIO * s[0]:
            continue
        axis = np.round(vt[0] * np.sign(vt[0][np.argmax(np.abs(vt[0]))]), 2) + 0.0
        frame = "T_link_cam" if is_camera(role) else "T_link_target"
        raise SolveError(
            f"{problem.dataset.source}: {mount_words(role)}'s position ({frame}) along the axis "
            f"[{axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}] of link {link!r} is not determined: every arm pose turns "
            f"{link!r} about that one axis; add arm poses that rotate it about another axis (tilt the wrist or move "
            "another joint), with at least two clearly different rotation axes")


def _check_motion(problem: RobotProblem, information: np.ndarray, columns: dict, estimate: RobotEstimate) -> None:
    """A mount's translation along the one axis all arm poses rotate about is not determined (the
    hand-eye problem's known degeneracy): SolveError (exit 3) naming the direction and the motion to add."""
    scale = np.sqrt(np.maximum(np.diag(information), 1e-300))
    normalized = information / np.outer(scale, scale)
    eigenvalues, vectors = np.linalg.eigh(normalized)
    if eigenvalues[0] > UNDETERMINED_RATIO * eigenvalues[-1]:
        return
    direction = vectors[:, 0] / scale
    for role, key in problem.mount_keys.items():
        c = columns[key]
        nu = direction[c][3:]
        if np.linalg.norm(nu) < 0.5 * np.linalg.norm(direction):
            continue
        axis = estimate.mounts[role][0] @ nu  # link axes
        axis /= np.linalg.norm(axis)
        frame = "T_link_cam" if is_camera(role) else "T_link_target"
        moving = "camera" if problem.links[problem.camera] != problem.kinematics.base_link else "target"
        raise SolveError(
            f"{problem.dataset.source}: {mount_words(role)}'s position along the {problem.links[role]!r} axis "
            f"[{axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}] is not determined ({frame}): every arm pose turns the "
            f"{moving}'s link about that one axis; add arm poses that rotate the tool about another axis "
            "(tilt the wrist), at least two clearly different rotation axes")
    raise SolveError(f"{problem.dataset.source}: the data do not determine {problem.name_of(_key_at(columns, int(np.argmax(np.abs(direction)))))}: "
                     "add arm poses with rotations about different axes, or mirror placements at other tilts")


def _key_at(columns: dict, index: int) -> int:
    return next(k for k, c in columns.items() if c.start <= index < c.stop)


@dataclass
class RobotSolution:
    """One solve: the problem, its graph, the values LM ended with and their estimate, the Fisher information
    (keys in ``problem.keys`` order, ``columns`` each key's), LM's iterations and first cost."""

    problem: RobotProblem
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    estimate: RobotEstimate
    information: np.ndarray
    columns: dict
    iterations: int
    initial_error: float


def solve_robot(dataset: Dataset, initial: RobotEstimate | None = None,
                options: SolveOptions | None = None, minima: dict | None = None) -> RobotSolution:
    """The MLE (module docstring) from the analytical start with its restarts, or from ``initial``; its
    motion checked (SolveError where the data cannot determine a mount). ``minima``: the screen's PnP
    minima of these photographs (``consensus.ImageChecks.minima``), which the start takes instead of
    solving the same PnP again."""
    options = options or SolveOptions()
    problem = RobotProblem(dataset, options.robust)
    check_rotation_axes(problem)
    graph = problem.graph()
    params = lm_params(options.max_iterations, cost_scale(dataset), GENERAL_LAMBDA_UPPER_BOUND)
    expected = expected_cost(problem.size, problem.dimension())

    def optimize(begin: RobotEstimate):
        return run_optimizer(graph, problem.values(begin), params, dataset.source, lambda error: str(error),
                             options.iteration)

    optimizer, result, initial_error = optimize(initial if initial is not None else start_estimate(problem, 1, minima)[0])
    if initial is None and not plausible(graph.error(result), expected):  # restarts: one triple of placements each
        for begin in start_estimate(problem, MAX_STARTS, minima)[1:]:
            tried = optimize(begin)
            if graph.error(tried[1]) < graph.error(result):
                logger.info("%s: a restart from another triple of placements fits better", dataset.source)
                optimizer, result, initial_error = tried
            if plausible(graph.error(result), expected):
                break
    estimate = problem.read(result)
    information, columns = problem.information(graph, result)
    _check_motion(problem, information, columns, estimate)
    return RobotSolution(problem, graph, result, estimate, information, columns, int(optimizer.iterations()),
                         initial_error)


def calibrate_robot(dataset: Dataset, initial: RobotEstimate | None = None,
                    options: SolveOptions | None = None) -> Calibration:
    """The MLE of an arm's mounts, planes, points and joint offsets, and their covariances (module
    docstring), through ``calibrate()``'s pipeline (``pipeline.py``: screen -> solve -> final check ->
    finish). ``initial``: start there instead of the analytical start (e.g. the truth)."""
    return run_pipeline(RobotPipelineProblem(initial, options or SolveOptions()), dataset)


class RobotPipelineProblem:
    """The arm in ``calibrate()``'s pipeline: screen (``consensus.screen``: each image's own PnP fit, wrong
    corner orders and gross corners left out), solve (:func:`solve_robot`; after leaving some out, from the
    last estimate), the final check's measurements, finish (covariances and the :class:`Calibration`)."""

    def __init__(self, initial: RobotEstimate | None, options: SolveOptions):
        self.last, self.options = initial, options
        self.minima: dict = {}

    def screen(self, dataset: Dataset) -> tuple[Dataset, list[Exclusion]]:
        from mirror_fg.solver.screen.consensus import check_images, screen

        checked = check_images(dataset, lowest_pnp_minima(dataset))
        self.minima = checked.minima  # the start's PnP: the same photographs' (robot_start._best_map)
        screened, excluded, _ = screen(dataset, checked=checked)  # its PnP candidates (twins) unused here
        return screened, excluded

    def solve(self, solved: Dataset, left_out: list[Exclusion]) -> RobotSolution:
        solution = solve_robot(solved, self.last, self.options, self.minima)
        self.last = solution.estimate
        return solution

    def check(self, run: RobotSolution) -> Checked:
        _, whitened, labels = run.problem.residuals(run.values)
        return Checked([Label(i, p) for i, p in labels], whitened, run.problem.dimension())

    def finish(self, rechecked: Rechecked[RobotSolution]) -> Calibration:
        return _calibration(rechecked.run, self.options, rechecked.excluded)


def lowest_pnp_minima(dataset: Dataset) -> dict[str, tuple[tuple[str, ...], list]]:
    """Each image's PnP minima for the screen (``consensus.check_images``' ``known``), as the screen's own
    search finds them but without P3P starts from three fiducials on one line (``pnp.pnp_minima``'s
    ``collinear_p3p``: a board's first row, arbitrary starts). The screen judges an image by its lowest
    minimum only (the other minima are the twin candidates of the tree's analytical start, which an arm
    does not use); that search finds the same lowest minimum at about half the cost."""
    from mirror_fg.solver.screen.placement_consensus import fiducial_names
    from mirror_fg.solver.start.pnp import is_planar, pnp_minima

    out = {}
    planar: dict[tuple[str, ...], bool] = {}  # by the image's fiducials: most images see the same ones
    for image in dataset.images:
        names = tuple(fiducial_names(dataset, image))
        if len(names) < 4:
            continue
        normalized = dataset.normalized(image)
        points = np.array([dataset.fiducials[n] for n in names])
        observed = np.array([normalized[n] for n in names])
        if names not in planar:
            planar[names] = is_planar(points)
        out[image.id] = (names, pnp_minima(points, observed, len(image.reflections), collinear_p3p=False,
                                           planar=planar[names]))
    return out


def _calibration(solution: RobotSolution, options: SolveOptions, excluded: list[Exclusion]) -> Calibration:
    """The :class:`Calibration` of a solve, with its covariances where asked."""
    problem, graph, result, estimate = solution.problem, solution.graph, solution.values, solution.estimate
    information, columns, initial_error = solution.information, solution.columns, solution.initial_error
    dataset = problem.dataset
    covariances = None
    if options.compute_covariance:
        options.report(STAGES[2], 0, 1)
        covariances = problem.covariances(np.linalg.inv(information), columns, estimate)
        options.report(STAGES[2], 1, 1)
    residuals, whitened, labels = problem.residuals(result)
    dimension = problem.dimension()
    pose3_cov = None
    if covariances is not None and problem.camera in problem.mount_keys:  # the (first) camera's mount
        c = columns[problem.mount_keys[problem.camera]]
        pose3_cov = np.linalg.inv(information)[c, c]
    (R, t), P = camera_base_pose(estimate.mounts[problem.camera], pose3_cov)
    iterations = solution.iterations
    return build_calibration(
        dataset, (R, t), P, mirror_vectors=estimate.mirror_vectors,
        mirror_covariances=covariances["mirrors"] if covariances else {}, points=estimate.points,
        point_covariances=covariances["points"] if covariances else {}, residuals=residuals, whitened=whitened,
        labels=labels, unknowns=dimension, iterations=iterations, initial_error=initial_error,
        final_error=float(graph.error(result)), converged=iterations < options.max_iterations, excluded=excluded,
        robot={**robot_entries(problem, estimate, covariances),
               **({"link_error": _link_error_model(problem, estimate, information, columns)} if covariances else {})},
    )


def _link_error_model(problem: RobotProblem, estimate: RobotEstimate, information: np.ndarray, columns: dict):
    """The joint covariance of the camera mount (Pose3 tangent) and the joint offsets, for the error at a
    point on a link (``solver/result/link_point_error.py``; not written to result@1)."""
    from mirror_fg.solver.result.link_point_error import LinkErrorModel

    covariance = np.linalg.inv(information)
    index = np.full(6, -1)
    if problem.camera in problem.mount_keys:
        c = columns[problem.mount_keys[problem.camera]]
        index = np.arange(c.start, c.stop)
    if problem.offset_key is not None:
        c = columns[problem.offset_key]
        index = np.concatenate([index, np.arange(c.start, c.stop)])
    S = np.zeros((len(index), len(index)))
    known = index >= 0
    S[np.ix_(known, known)] = covariance[np.ix_(index[known], index[known])]
    return LinkErrorModel(problem.kinematics, problem.links[problem.camera], estimate.mounts[problem.camera], tuple(problem.offsets),
                          np.asarray(estimate.offsets, float).copy(), S)


def _sigma3(covariance: np.ndarray) -> dict:
    s = 3.0 * np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return {"rotation_deg": np.degrees(s[:3]).tolist(), "position_mm": (1000.0 * s[3:]).tolist()}


def robot_entries(problem: RobotProblem, estimate: RobotEstimate, covariances: dict | None) -> dict:
    """result@1's ``mounts`` (each unknown one, its covariance and 3-sigma; with several cameras each
    camera's under ``mounts.cameras`` and the first's repeated as ``mounts.camera``), ``joint_offsets`` and
    the frame of ``mirrors[].v`` (docs/formats.md, "Robot arms")."""
    mounts: dict = {}
    for role in problem.mount_keys:
        R, t = estimate.mounts[role]
        key = "T_link_cam" if is_camera(role) else "T_link_target"
        entry: dict = {"link": problem.links[role],
                       key: {"R": R.tolist(), "t": t.tolist(), "q_xyzw": rotation_to_quaternion_xyzw(R).tolist()}}
        if covariances is not None:
            C = covariances["mounts"][role]
            entry.update({"covariance": C.tolist(), "sigma3": _sigma3(C)})
        name = camera_name(role)
        if name is not None:
            mounts.setdefault("cameras", {})[name] = entry
            if role == problem.camera:
                mounts["camera"] = entry
        else:
            mounts[role] = entry
    if "cameras" in mounts:  # the cameras in the dataset's order, then the target
        mounts = {**({"camera": mounts["camera"]} if "camera" in mounts else {}), "cameras": mounts["cameras"],
                  **({"target": mounts["target"]} if "target" in mounts else {})}
    offsets = {}
    for k, name in enumerate(problem.offsets):
        prismatic = problem.kinematics.joints[name].prismatic
        value = float(estimate.offsets[k])
        sigma = math.sqrt(covariances["offsets"][k, k]) if covariances is not None else float("nan")
        offsets[name] = ({"offset_mm": 1000.0 * value, "sigma3_mm": 3000.0 * sigma} if prismatic
                         else {"offset_deg": math.degrees(value), "sigma3_deg": 3.0 * math.degrees(sigma)})
    return {"mounts": mounts, **({"joint_offsets": offsets} if offsets else {}), "mirror_frame": problem.kinematics.base_link,
            "camera_link": problem.links[problem.camera]}
