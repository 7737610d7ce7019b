"""Simulated robot-arm scenes (docs/formats.md, "Robot arms: joint states and mounts"): a camera and a
target, one of them on the arm's tool link, the other on its base; mirror placements fixed in {B}; the
camera sees the target only through the mirrors.

Frames: {B} the URDF's base link; the scene is laid out in the camera's frame at a nominal arm pose (the
target facing the mirrors about 0.5 m ahead: eye-in-hand, beside the camera, as a person holds a board beside their
face; eye-to-hand, the board on the tool 0.3 m in front of the camera and 0.15 m to its side), then
carried into {B} through the arm's forward kinematics there. Arm poses are the nominal one
perturbed (every joint, uniform within ``spread_rad``), kept where every target point is seen through
the mirror in front of the camera. Metres, radians, pixels.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mirror_fg.core.camera import Camera, camera_to_dict
from mirror_fg.factors.robot import compose, inverse
from mirror_fg.robot import arm_urdf

__all__ = ["ArmTruth", "simulate_arm", "write_arm_simulation", "arm_outputs", "NOMINAL", "TOOL_LINK", "truth_to_dict"]

#: Nominal joint values (radians) of each test arm: the tool held in front of the base, pointing forward.
NOMINAL = {
    "arm6": [0.0, -1.2, 1.6, -0.4, 1.5708, 0.0],
    "panda": [0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785],
}
#: The tool link of each test arm.
TOOL_LINK = {"arm6": "tool0", "panda": "panda_hand"}
CAMERA = Camera(width=1024, height=768, fx=800.0, fy=800.0, cx=512.0, cy=384.0)
#: Several cameras: camera k stands ``RIG_STEP * k`` metres along the first's -x axis, turned ``RIG_TURN_DEG * k``
#: degrees about its y axis (towards the first's view of the mirror).
RIG_STEP, RIG_TURN_DEG = 0.1, 4.0


@dataclass
class ArmTruth:
    """The true unknowns: mounts ``{"camera"|"target": (link, (R, t))}``, mirror vectors in {B}
    ``{(l, m): v}``, joint offsets ``{joint: radians}`` (``q_true = q_recorded + delta``)."""

    robot: str
    mounts: dict[str, tuple[str, tuple[np.ndarray, np.ndarray]]]
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    joint_offsets: dict[str, float] = field(default_factory=dict)
    #: Several cameras: ``{name: (link, T_link_cam)}`` in order (``mounts["camera"]`` is the first's); else empty.
    cameras: dict[str, tuple[str, tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)


def _rot(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _board(rows: int = 5, cols: int = 6, square: float = 0.03) -> dict[str, np.ndarray]:
    """A chessboard's inner corners, target frame (z = 0, centred)."""
    return {f"F{r * cols + c}": np.array([(c - (cols - 1) / 2) * square, (r - (rows - 1) / 2) * square, 0.0])
            for r in range(rows) for c in range(cols)}


def _reflect(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """eq. (3): the reflection of points x (3, N) in the plane of mirror vector v (same frame)."""
    s = (v @ x) / (v @ v) - 1.0
    return x - 2.0 * np.outer(v, s)


def _seen_in_mirror(poses, x_B: np.ndarray, v_B: np.ndarray) -> bool:
    """Whether the camera sees the board's front through the plane of ``v_B`` ({B}): both on one side of it,
    the board facing it, every point ahead of the camera."""
    n_B = v_B / np.linalg.norm(v_B)
    d_B = float(np.linalg.norm(v_B))
    side_target = n_B @ x_B - d_B  # signed distances to the plane
    side_camera = float(n_B @ poses["camera"][1] - d_B)
    if abs(side_camera) < 0.1 or np.any(side_target * side_camera < 0.05 ** 2):
        return False  # the target or the camera at the mirror, or on its two sides
    toward_mirror = -np.sign(side_camera) * n_B
    if -poses["target"][0][:, 2] @ toward_mirror < 0.2:  # the board's front (-z_target) faces the mirror
        return False
    R, t = inverse(poses["camera"])
    return bool(np.all((R @ _reflect(x_B, v_B) + t[:, None])[2] >= 0.2))


def simulate_arm(robot: str = "arm6", eye_in_hand: bool = False, placements: int = 3, arm_poses: int = 8,
                 pixel_sigma: float = 0.5, joint_offsets_deg: dict[str, float] | None = None,
                 seed: int = 0, spread_rad: float = 0.25, estimate_offsets: bool = True,
                 moving: tuple[str, ...] | None = None, direct: bool = False, direct_distance: float = 0.9,
                 mirror_distance: tuple[float, float] = (0.45, 0.6), mirror_tilt_deg: tuple[float, float] = (6.0, 14.0),
                 cameras: int = 1, camera_links: tuple[str, ...] = (), board_position: tuple[float, float, float] | None = None,
                 check_occlusion: bool = False, mirror_size: tuple[float, float] | None = None):
    """A dataset@1 dictionary (its ``robot.urdf`` the arm's file name) and its :class:`ArmTruth`.

    ``arm_poses`` images per placement; ``joint_offsets_deg``: true encoder offsets, recorded joints are
    ``q_true - delta`` (and, with ``estimate_offsets``, the dataset asks for them). ``moving``: the joints
    that move between arm poses (default all; one wrist joint alone is the degenerate motion). ``direct``:
    no mirror, the camera sees the board ``direct_distance`` metres ahead (a direct-view hand-eye calibration,
    for comparison): ``arm_poses`` images in all. ``mirror_distance`` (metres from the camera) and
    ``mirror_tilt_deg`` (the plane's normal from the camera's optical axis, each placement turned a further
    third of a turn about it): the ranges each placement is drawn from. ``cameras`` > 1: a dataset with
    ``cameras`` ``cam0``, ``cam1``, ... and ``mounts.cameras``: the first camera where one camera would be,
    camera k ``RIG_STEP`` further along its x axis (turned towards the others), on ``camera_links[k - 1]``
    where given (else the first camera's link); at each arm pose every camera that sees the target through
    the mirror takes an image, ``arm_poses`` per camera and placement. ``board_position``: the board's centre
    in the camera's frame at the nominal pose (metres; default eye-to-hand 0.15 m aside and 0.3 m ahead,
    eye-in-hand 0.12 m aside), facing the mirrors. ``check_occlusion``: also leave out arm poses where the
    board's plate (3 cm beyond its corners) stands in the camera's line of sight to the mirror.
    ``mirror_size``: the glass's width and height (metres; None: a plane without edges): an arm pose is
    left out unless every point's image is seen within the glass, which stands where the camera sees the
    board's centre in it at the nominal pose, its width along the camera's x axis laid onto the plane."""
    from mirror_fg.robot.kinematics import load_kinematics

    rng = np.random.default_rng(seed)
    kin = load_kinematics(arm_urdf(robot))
    names = kin.chain(TOOL_LINK[robot])
    q0 = np.array(NOMINAL[robot], float)
    tool = TOOL_LINK[robot]
    F0 = kin.placements(dict(zip(names, q0)), [tool])[tool][0]
    F0 = (F0[:3, :3], F0[:3, 3])
    camera_mounts: dict = {}
    # in the camera's frame at the nominal pose, the board facing the mirrors (pattern normal -z_target):
    # eye-in-hand, the fixed board beside the wrist camera; eye-to-hand, the board on the tool held 0.3 m in
    # front of the camera and 0.15 m to its side (clear of its view of the mirror), as a user sets it up
    T_cam_target = (_rot([0, 1, 0], math.pi), np.array(board_position if board_position is not None
                                                       else [0.12, 0.0, 0.02] if eye_in_hand else [0.15, 0.0, 0.30], float))
    if direct:  # the board's front (-z_target) faces the camera
        T_cam_target = (np.eye(3), np.array([0.0, 0.0, direct_distance]))
    if eye_in_hand:  # camera 6 cm off the flange, looking along the tool's z
        mount_cam = (_rot([0, 0, 1], 0.3) @ _rot([1, 0, 0], 0.05), np.array([0.05, -0.03, 0.06]))
        C = compose(F0, mount_cam)
        D = compose(C, T_cam_target)
        mounts = {"camera": (tool, mount_cam), "target": (kin.base_link, D)}
    else:  # the board 4 cm off the flange, facing along the tool's z
        mount_target = (_rot([0, 0, 1], -0.4) @ _rot([0, 1, 0], math.pi), np.array([0.02, 0.01, 0.04]))
        D = compose(F0, mount_target)
        C = compose(D, inverse(T_cam_target))
        mounts = {"camera": (kin.base_link, C), "target": (tool, mount_target)}
    if cameras > 1:
        F_nominal = kin.placements(dict(zip(names, q0)), list(dict.fromkeys([tool, kin.base_link, *camera_links])))
        for k in range(cameras):
            link = camera_links[k - 1] if 0 < k <= len(camera_links) else mounts["camera"][0]
            beside = (_rot([0, 1, 0], math.radians(RIG_TURN_DEG) * k), np.array([-RIG_STEP * k, 0.01 * k, 0.0]))
            pose = compose(C, beside)
            F = F_nominal[link][0]
            mounts_k = compose(inverse((F[:3, :3], F[:3, 3])), pose)
            if k == 0:
                mounts["camera"] = (link, mounts_k)
            camera_mounts[f"cam{k}"] = (link, mounts_k)
    # mirror placements, camera frame at the nominal pose: by default 0.45-0.6 m ahead, tilted 6-14 degrees
    mirrors_cam = []
    for k in range(placements):
        angle = 2 * math.pi * k / placements + rng.uniform(-0.3, 0.3)
        tilt = math.radians(rng.uniform(*mirror_tilt_deg))
        n = np.array([math.sin(tilt) * math.cos(angle), math.sin(tilt) * math.sin(angle), -math.cos(tilt)])
        d = rng.uniform(*mirror_distance)
        mirrors_cam.append(-d * n)  # v = d n with n from the camera towards the plane
    R_C, t_C = C
    mirror_vectors = {}
    for k, v in enumerate(mirrors_cam):  # the plane n.x = d carried into {B}
        n, d = v / np.linalg.norm(v), float(np.linalg.norm(v))
        n_B = R_C @ n
        d_B = d + float(n_B @ t_C)
        mirror_vectors[(1, k)] = d_B * n_B
    delta = {n: math.radians(x) for n, x in (joint_offsets_deg or {}).items()}
    board = _board()
    points = np.array(list(board.values())).T
    board_centre = D[0] @ points.mean(axis=1) + D[1]  # {B}, at the nominal pose
    glasses = ({} if mirror_size is None or direct else
               {k: _glass(C, board_centre, v, mirror_size) for k, v in enumerate(mirror_vectors.values())})
    images, truth_joints = [], []
    roles = list(camera_mounts) if camera_mounts else ["camera"]
    links = list(dict.fromkeys([tool, kin.base_link, *(link for link, _ in camera_mounts.values())]))
    for k in range(1 if direct else placements):
        v_B = None if direct else mirror_vectors[(1, k)]
        found = dict.fromkeys(roles, 0)
        tries = 0
        while min(found.values()) < arm_poses:
            tries += 1
            if tries > max(2000, 300 * arm_poses) * len(roles):  # a scene of many poses draws longer
                raise RuntimeError(f"no visible arm pose for placement {k} after {tries - 1} tries")
            step = rng.uniform(-spread_rad, spread_rad, len(q0))
            if moving is not None:
                step *= np.array([n in moving for n in names], float)
            q = q0 + step
            info = [kin.joints[n] for n in names]
            if any(i.lower is not None and i.upper is not None and not i.lower <= x <= i.upper for i, x in zip(info, q)):
                continue
            recorded = {n: float(x - delta.get(n, 0.0)) for n, x in zip(names, q)}
            F = kin.placements(dict(zip(names, q)), links)
            F_t = F[mounts["target"][0]][0]
            target = compose((F_t[:3, :3], F_t[:3, 3]), mounts["target"][1])
            x_B = target[0] @ points + target[1][:, None]
            for role in roles:
                if found[role] >= arm_poses:
                    continue
                link, mount = camera_mounts[role] if camera_mounts else mounts["camera"]
                F_c = F[link][0]
                poses = {"camera": compose((F_c[:3, :3], F_c[:3, 3]), mount), "target": target}
                pix = _observe(poses, x_B, v_B)
                if pix is not None and check_occlusion and v_B is not None and _occluded(poses, x_B, v_B):
                    pix = None
                if pix is not None and v_B is not None and k in glasses and not _within_glass(poses, x_B, v_B, glasses[k]):
                    pix = None
                if pix is None:
                    continue
                pix = pix + rng.normal(0.0, pixel_sigma, pix.shape)
                if any(i.lower is not None and i.upper is not None and not i.lower <= recorded[n] <= i.upper
                       for n, i in zip(names, info)):
                    break  # the recorded joints out of their limits (the noise drawn as before: the same scenes)
                count = found[role]
                images.append({"id": f"p{k}_{count:03d}" if not camera_mounts else f"p{k}_{role}_{count:03d}",
                               **({"camera": role} if camera_mounts else {}),
                               **({"reflections": []} if direct else {"mirror_configs": [k]}), "joints": recorded,
                               "observations": {name: [float(u), float(w)] for name, (u, w) in zip(board, pix)}})
                truth_joints.append(q)
                found[role] += 1
    robot_entry: dict = {"urdf": f"{robot}.urdf", "base_link": kin.base_link}
    if delta and estimate_offsets:
        robot_entry["joint_offsets"] = {"estimate": list(delta), "prior_sigma_deg": 2.0}
    link_c, _ = mounts["camera"]
    link_t, _ = mounts["target"]
    camera_entries: dict[str, Any]
    camera_entries_mounts: dict[str, Any]
    if camera_mounts:  # several cameras: each its own intrinsics entry and mount
        camera_entries = {"cameras": {role: camera_to_dict(CAMERA) for role in camera_mounts}}
        camera_entries_mounts = {"cameras": {role: {"link": link} for role, (link, _) in camera_mounts.items()}}
    else:
        camera_entries = {"camera": camera_to_dict(CAMERA)}
        camera_entries_mounts = {"camera": {"link": link_c}}
    dataset = {
        "format": "mirror-fg/dataset@1", "num_mirrors": 1, **camera_entries,
        "pixel_sigma": pixel_sigma, "fiducials": {n: [float(x) for x in p] for n, p in board.items()},
        "robot": robot_entry, "mounts": {**camera_entries_mounts, "target": {"link": link_t}},
        "images": images,
    }
    return dataset, ArmTruth(robot, mounts, {} if direct else mirror_vectors, delta, camera_mounts)


def _observe(poses, x_B: np.ndarray, v_B: np.ndarray | None) -> np.ndarray | None:
    """The pixels (N, 2) of the target points ``x_B`` ({B}) seen by the camera at ``poses["camera"]`` through
    the plane of ``v_B`` (None: directly, the board facing the camera), or None where not all are seen well
    inside the image."""
    if v_B is None:
        R, t = inverse(poses["camera"])
        x_cam = R @ x_B + t[:, None]
        facing = -poses["target"][0][:, 2] @ (poses["camera"][1] - poses["target"][1])
        if np.any(x_cam[2] < 0.2) or facing <= 0.2 * np.linalg.norm(poses["camera"][1] - poses["target"][1]):
            return None
    elif not _seen_in_mirror(poses, x_B, v_B):
        return None
    else:
        R, t = inverse(poses["camera"])
        x_cam = R @ _reflect(x_B, v_B) + t[:, None]  # eq. (3)
    pix = (CAMERA.K @ (x_cam / x_cam[2]))[:2].T
    if not CAMERA.contains(pix).all() or np.any((pix < 20) | (pix > [CAMERA.width - 20, CAMERA.height - 20])):
        return None
    return pix


def _occluded(poses, x_B: np.ndarray, v_B: np.ndarray, margin: float = 0.03) -> bool:
    """Whether the board's plate (its corners' rectangle grown by ``margin``, target frame z = 0) crosses
    the camera's line of sight to the mirror point of any target point ``x_B`` ({B}) seen through the plane
    of ``v_B``."""
    R_t, t_t = poses["target"]
    c = poses["camera"][1]
    at_mirror = _mirror_points(c, x_B, v_B)  # the ray to each image point meets the mirror on the way
    corners = R_t.T @ (x_B - t_t[:, None])  # the corners in the target frame (the plate's extent)
    low, high = corners[:2].min(axis=1) - margin, corners[:2].max(axis=1) + margin
    c_t = R_t.T @ (c - t_t)  # the camera and the mirror points in the target frame
    m_t = R_t.T @ (at_mirror - t_t[:, None])
    for k in range(m_t.shape[1]):
        dz = m_t[2, k] - c_t[2]
        if abs(dz) < 1e-12:
            continue
        s = -c_t[2] / dz  # the camera-to-mirror segment crosses the board's plane at s in (0, 1)
        if 0.0 < s < 1.0:
            p = c_t[:2] + s * (m_t[:2, k] - c_t[:2])
            if np.all(p >= low) and np.all(p <= high):
                return True
    return False


def _mirror_points(camera_centre: np.ndarray, x_B: np.ndarray, v_B: np.ndarray) -> np.ndarray:
    """Where the camera's rays to the images of points ``x_B`` (3, N; {B}) in the plane of ``v_B`` meet it."""
    n_B, d_B = v_B / np.linalg.norm(v_B), float(np.linalg.norm(v_B))
    ray = _reflect(x_B, v_B) - camera_centre[:, None]  # eq. (3)
    return camera_centre[:, None] + ray * ((d_B - n_B @ camera_centre) / (n_B @ ray))


def _glass(camera, board_centre: np.ndarray, v_B: np.ndarray, size: tuple[float, float]):
    """A glass of ``size`` (width, height; metres) in the plane of ``v_B`` ({B}): its centre where the camera
    at ``camera`` sees the board's centre ``board_centre`` ({B}) in it, its width along the camera's x axis
    laid onto the plane. ``(centre, width axis, height axis, half sizes)``."""
    n_B = v_B / np.linalg.norm(v_B)
    centre = _mirror_points(camera[1], np.asarray(board_centre, float).reshape(3, 1), v_B)[:, 0]
    x = camera[0][:, 0] - (camera[0][:, 0] @ n_B) * n_B
    x /= np.linalg.norm(x)
    return centre, x, np.cross(n_B, x), 0.5 * np.asarray(size, float)


def _within_glass(poses, x_B: np.ndarray, v_B: np.ndarray, glass) -> bool:
    """Whether the camera at ``poses["camera"]`` sees every point ``x_B`` within ``glass`` (:func:`_glass`)."""
    centre, x, y, half = glass
    at = _mirror_points(poses["camera"][1], x_B, v_B) - centre[:, None]
    return bool(np.all(np.abs(x @ at) <= half[0]) and np.all(np.abs(y @ at) <= half[1]))


def _pose_dict(pose) -> dict:
    return {"R": np.asarray(pose[0], float).tolist(), "t": np.asarray(pose[1], float).tolist()}


def truth_to_dict(truth: ArmTruth) -> dict:
    """``mirror-fg/truth@1`` of an arm: mounts, planes in {B}, joint offsets (degrees)."""
    keys = {"camera": "T_link_cam", "target": "T_link_target"}
    return {
        "format": "mirror-fg/truth@1", "robot": truth.robot,
        "mounts": {**{role: {"link": link, keys[role]: _pose_dict(pose)} for role, (link, pose) in truth.mounts.items()
                      if not (truth.cameras and role == "camera")},
                   **({"cameras": {name: {"link": link, "T_link_cam": _pose_dict(pose)}
                                   for name, (link, pose) in truth.cameras.items()}} if truth.cameras else {})},
        "mirrors": [{"mirror": l, "config": m, "v": np.asarray(v, float).tolist(), "frame": "base_link"}
                    for (l, m), v in sorted(truth.mirror_vectors.items())],
        "joint_offsets": {n: {"offset_deg": math.degrees(x)} for n, x in truth.joint_offsets.items()},
    }


def arm_outputs(path: str, robot: str):
    """The checked outputs of :func:`write_arm_simulation` (DatasetError before any work where one cannot be
    written): the dataset, ``<stem>.truth.json`` and the arm's URDF beside them."""
    from mirror_fg.io.output import OutputPlan
    from mirror_fg.simulate.tree import truth_path

    plan = OutputPlan()
    plan.add(path, "dataset")
    plan.add(truth_path(path), "ground truth")
    plan.add(os.path.join(os.path.dirname(os.path.abspath(path)), f"{robot}.urdf"), "URDF")
    return plan


def write_arm_simulation(path: str, dataset: dict, truth: ArmTruth, plan=None) -> tuple[str, str]:
    """Write the dataset, ``<stem>.truth.json`` and the arm's URDF beside them, all-or-nothing; returns the
    truth's and the URDF's paths."""
    from mirror_fg.simulate.tree import truth_path

    path = os.fspath(path)
    plan = plan if plan is not None else arm_outputs(path, truth.robot)
    urdf = os.path.join(os.path.dirname(os.path.abspath(path)), dataset["robot"]["urdf"])
    with open(arm_urdf(truth.robot), encoding="utf-8") as handle:
        urdf_text = handle.read()
    truth_file = os.fspath(truth_path(path))
    plan.commit({path: json.dumps(dataset, indent=1) + "\n", truth_file: json.dumps(truth_to_dict(truth), indent=1) + "\n",
                 urdf: urdf_text})
    return truth_file, urdf
