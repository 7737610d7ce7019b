"""dataset@1's robot fields (docs/formats.md, "Robot arms: joint states and mounts"): ``robot``,
``mounts`` and each image's ``joints``, read and checked once. With several cameras (``cameras``), each
camera's mount is in ``mounts.cameras`` (``{name: {link, T_link_cam}}``, every camera and no other).

Frames: {B} is ``robot.base_link``; ``T_link_cam`` / ``T_link_target`` map mount coordinates into the
link's (``x_link = R x_mount + t``), metres. Joint values: radians (metres for a prismatic joint).
Kinematics (Pinocchio) is loaded lazily, only for data that name a robot.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_keys, short, type_name

__all__ = ["Mount", "RobotSetup", "robot_from_dict", "image_joints", "robot_to_dict", "joints_to_dict", "pose_from_dict"]

_ROBOT_KEYS = ("urdf", "base_link", "joint_offsets")
_OFFSET_KEYS = ("estimate", "prior_sigma_deg", "prior_sigma_mm")
_MOUNT_KEYS = {"camera": ("link", "T_link_cam"), "target": ("link", "T_link_target")}
#: Default prior sigma of an estimated joint offset (docs/formats.md: ``prior_sigma_deg``).
DEFAULT_PRIOR_DEG = 2.0
DEFAULT_PRIOR_MM = 2.0
#: Slack on a URDF limit (radians or metres): a recorded value at the limit rounds either way.
LIMIT_SLACK = 1e-6


@dataclass(frozen=True)
class Mount:
    """What a camera or target rides: ``link``, and ``T_link_mount`` (R, t) where known, else None."""

    link: str
    known: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class RobotSetup:
    """A dataset's robot: its URDF (absolute path; ``urdf_name`` as the file gave it), base link, the
    mounts ``{"camera": Mount, "target": Mount}``, whether the file gave ``mounts.target`` (else the
    fiducials are in {B}), the joints whose offsets are estimated and their prior sigmas (radians or
    metres, per joint)."""

    urdf: str
    urdf_name: str
    base_link: str
    mounts: dict[str, Mount]
    target_given: bool
    offsets: tuple[str, ...] = ()
    offset_sigma: dict[str, float] = field(default_factory=dict)
    prior_sigma_deg: float | None = None
    prior_sigma_mm: float | None = None
    camera_given: bool = True
    #: A dataset with several cameras: each camera's mount ``mounts.cameras`` ``{name: Mount}`` in the
    #: ``cameras`` order (``mounts["camera"]`` is then the first's); None with one camera.
    cameras: dict[str, Mount] | None = None

    def camera_mounts(self) -> dict[str | None, Mount]:
        """``{camera name: Mount}`` of every camera: ``{None: mounts["camera"]}`` with one camera."""
        if self.cameras is None:
            return {None: self.mounts["camera"]}
        return {name: mount for name, mount in self.cameras.items()}

    @property
    def kinematics(self):
        from mirror_fg.robot.kinematics import load_kinematics
        return load_kinematics(self.urdf, self.base_link)

    @property
    def joints(self) -> list[str]:
        """The movable joints between the base and each mount's link (every image gives these)."""
        kin = self.kinematics
        names: list[str] = []
        for mount in [*self.mounts.values(), *(self.cameras or {}).values()]:
            names += [n for n in kin.chain(mount.link) if n not in names]
        return names


def pose_from_dict(value: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``{"R": 3x3, "t": 3}`` as (R, t), R a rotation (orthonormal, det +1 within 1e-6)."""
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected {{\"R\": [[3 x 3]], \"t\": [3]}}, got {type_name(value)}")
    check_keys(value, ("R", "t", "q_xyzw"), where)
    try:
        R = np.array(value.get("R"), dtype=float)
        t = np.array(value.get("t"), dtype=float)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: R must be 3 x 3 numbers and t 3 numbers") from None
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise DatasetError(f"{where}: R must be 3 x 3 finite numbers and t 3 finite numbers")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: R is not a rotation (orthonormal with determinant +1)")
    return R, t


def robot_from_dict(d: Mapping[str, Any], source: str) -> RobotSetup | None:
    """The dataset's ``robot`` and ``mounts`` (None without ``robot``); DatasetError (exit 2) on a URDF that
    does not parse, an unknown link or joint, a mount on a link not connected to the base."""
    robot, mounts = d.get("robot"), d.get("mounts")
    if robot is None:
        if mounts is not None:
            raise DatasetError(f"{source}: mounts needs a robot (robot: {{urdf, base_link}})")
        return None
    where = f"{source}: robot"
    if not isinstance(robot, Mapping):
        raise DatasetError(f"{where}: expected an object {{urdf, base_link, joint_offsets}}, got {type_name(robot)}")
    check_keys(robot, _ROBOT_KEYS, where)
    name = robot.get("urdf")
    if not isinstance(name, str) or not name:
        raise DatasetError(f"{where}: urdf must be the URDF file's name (relative to the dataset), got {short(name)}")
    folder = os.path.dirname(os.path.abspath(source)) if os.path.exists(source) else os.getcwd()
    path = name if os.path.isabs(name) else os.path.join(folder, name)
    from mirror_fg.robot.kinematics import load_kinematics

    base_link = robot.get("base_link")
    if base_link is not None and (not isinstance(base_link, str) or not base_link):
        raise DatasetError(f"{where}: base_link must be a link's name, got {short(base_link)}")
    try:
        kin = load_kinematics(path, base_link)
    except DatasetError as error:
        raise DatasetError(f"{where}: urdf {name!r}: {str(error).split(': ', 1)[-1]}") from None
    if mounts is not None and not isinstance(mounts, Mapping):
        raise DatasetError(f"{source}: mounts: expected an object {{camera, target}}, got {type_name(mounts)}")
    mounts = dict(mounts or {})
    check_keys(mounts, (*_MOUNT_KEYS, "cameras"), f"{source}: mounts")
    names = _camera_names(d, mounts, source)
    parsed: dict[str, Mount] = {}
    for role, (_, pose_key) in _MOUNT_KEYS.items():
        entry = mounts.get(role)
        if entry is None:  # the camera: on the base, unknown; the target: the fiducials are in {B}
            parsed[role] = Mount(kin.base_link, None if role == "camera" else (np.eye(3), np.zeros(3)))
            continue
        parsed[role] = _mount(entry, role, f"{source}: mounts.{role}", kin, name)
    cameras = None
    if names is not None:  # several cameras (docs/formats.md "Robot arms", several cameras): one mount each
        cameras = {camera: _mount(mounts["cameras"][camera], "camera", f"{source}: mounts.cameras.{camera}", kin, name)
                   for camera in names}
        parsed["camera"] = cameras[names[0]]
    setup = RobotSetup(path, name, kin.base_link, parsed, "target" in mounts, camera_given="camera" in mounts,
                       cameras=cameras)
    if (all(m.known is not None for m in setup.camera_mounts().values()) and parsed["target"].known is not None
            and not _has_offsets(robot)):
        raise DatasetError(f"{source}: mounts: both T_link_cam and T_link_target are known: nothing to calibrate "
                           "(leave the one to estimate out)")
    _offsets(robot.get("joint_offsets"), setup, f"{where}: joint_offsets")
    return setup


def _mount(entry: Any, role: str, at: str, kin, urdf_name: str) -> Mount:
    """One ``{link, T_link_cam | T_link_target}`` entry (``at`` names it in messages)."""
    pose_key = _MOUNT_KEYS[role][1]
    if not isinstance(entry, Mapping):
        raise DatasetError(f"{at}: expected an object {{link, {pose_key}}}, got {type_name(entry)}")
    check_keys(entry, _MOUNT_KEYS[role], at)
    link = entry.get("link", kin.base_link)
    if not isinstance(link, str) or link not in kin.links:
        raise DatasetError(f"{at}: link {short(link)} is not a link of {urdf_name}")
    cut = kin.unrecordable(link)
    if cut:
        raise DatasetError(f"{at}: link {link!r} is not connected to the base link {kin.base_link!r} through "
                           f"recorded joints (joint {cut[0]!r} is floating or planar)")
    known = pose_from_dict(entry[pose_key], f"{at}: {pose_key}") if pose_key in entry else None
    return Mount(link, known)


def _camera_names(d: Mapping[str, Any], mounts: dict[str, Any], source: str) -> list[str] | None:
    """The names of a dataset's ``cameras`` (None with one ``camera``), each with its entry in
    ``mounts.cameras`` and no other: ``mounts.camera`` beside ``cameras``, ``mounts.cameras`` without them, a
    camera without a mount and a mount of an undeclared camera are refused (one line, exit 2)."""
    declared = d.get("cameras")
    given = mounts.get("cameras")
    if not isinstance(declared, Mapping):
        if given is not None:
            raise DatasetError(f"{source}: mounts.cameras: the data have one camera (camera); give its mount as "
                               "mounts.camera, or the cameras as cameras: {name: camera}")
        return None
    names = [str(n) for n in declared]
    if "camera" in mounts:
        raise DatasetError(f"{source}: mounts.camera: the data have several cameras ({', '.join(names)}); give each "
                           "its mount in mounts.cameras: {name: {link, T_link_cam}}")
    if given is None:
        given = {}
    if not isinstance(given, Mapping):
        raise DatasetError(f"{source}: mounts.cameras: expected an object {{camera name: {{link, T_link_cam}}}}, got "
                           f"{type_name(given)}")
    for camera in given:
        if camera not in declared:
            raise DatasetError(f"{source}: mounts.cameras: {short(camera)} is not one of the cameras "
                               f"({', '.join(names)})")
    for camera in names:
        if camera not in given:
            raise DatasetError(f"{source}: mounts.cameras: camera {camera!r} has no mount: give mounts.cameras."
                               f"{camera}: {{link, T_link_cam}} (the link it is fixed to; T_link_cam where known)")
    return names


def _has_offsets(robot: Mapping[str, Any]) -> bool:
    offsets = robot.get("joint_offsets")
    return isinstance(offsets, Mapping) and bool(offsets.get("estimate"))


def _offsets(value: Any, setup: RobotSetup, where: str) -> None:
    if value is None:
        return
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected {{estimate: [joint names], prior_sigma_deg}}, got {type_name(value)}")
    check_keys(value, _OFFSET_KEYS, where)
    names = value.get("estimate", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise DatasetError(f"{where}: estimate must be a list of joint names, got {short(names)}")
    kin = setup.kinematics
    chain = setup.joints
    sigmas = {}
    for key, default in (("prior_sigma_deg", DEFAULT_PRIOR_DEG), ("prior_sigma_mm", DEFAULT_PRIOR_MM)):
        s = value.get(key, default)
        if not isinstance(s, (int, float)) or isinstance(s, bool) or not math.isfinite(s) or s <= 0:
            raise DatasetError(f"{where}: {key} must be a positive number, got {short(s)}")
        sigmas[key] = float(s)
    for n in names:
        if n not in kin.joints:
            raise DatasetError(f"{where}: unknown joint {n!r} (not a movable joint of {setup.urdf_name})")
        if n not in chain:
            raise DatasetError(f"{where}: joint {n!r} is not between the base and a mount: its offset changes nothing")
        prismatic = kin.joints[n].prismatic
        setup.offset_sigma[n] = sigmas["prior_sigma_mm"] / 1000.0 if prismatic else math.radians(sigmas["prior_sigma_deg"])
    if len(set(names)) != len(names):
        raise DatasetError(f"{where}: estimate names a joint twice")
    setup.offsets = tuple(names)
    setup.prior_sigma_deg = sigmas["prior_sigma_deg"]
    setup.prior_sigma_mm = sigmas["prior_sigma_mm"]


def image_joints(setup: RobotSetup | None, value: Any, prefix: str) -> dict[str, float] | None:
    """An image's ``joints`` checked against the robot: every joint of the chains, no other, finite and
    within the URDF's limits (``prefix`` names the image)."""
    if setup is None:
        if value is not None:
            raise DatasetError(f"{prefix}: joints needs a robot (robot: {{urdf, base_link}})")
        return None
    if value is None:
        raise DatasetError(f"{prefix}: missing 'joints' (the arm's joint values in this image)")
    if not isinstance(value, Mapping):
        raise DatasetError(f"{prefix}: joints must be an object {{joint: value}}, got {type_name(value)}")
    kin = setup.kinematics
    needed = setup.joints
    joints: dict[str, float] = {}
    for name, x in value.items():
        if name not in kin.joints:
            raise DatasetError(f"{prefix}: joint {short(name)} is not a movable joint of {setup.urdf_name}")
        if name not in needed:
            raise DatasetError(f"{prefix}: joint {name!r} is not between the base link and a mount (extra joint)")
        if not isinstance(x, (int, float)) or isinstance(x, bool):
            raise DatasetError(f"{prefix}: joint {name!r}: expected a number, got {short(x)}")
        if not math.isfinite(x):
            raise DatasetError(f"{prefix}: joint {name!r} is {x} (not a finite number)")
        info = kin.joints[name]
        if info.lower is not None and not info.lower - LIMIT_SLACK <= x <= info.upper + LIMIT_SLACK:  # type: ignore[operator]
            unit = "m" if info.prismatic else "rad"
            raise DatasetError(f"{prefix}: joint {name!r} at {x:.6g} {unit} is outside its URDF limits "
                               f"[{info.lower:.6g}, {info.upper:.6g}]")
        joints[name] = float(x)
    missing = [n for n in needed if n not in joints]
    if missing:
        raise DatasetError(f"{prefix}: joint {missing[0]!r} is missing (every image gives {', '.join(needed)})")
    return {n: joints[n] for n in needed}


def _pose_dict(pose: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    return {"R": [[float(x) for x in row] for row in pose[0]], "t": [float(x) for x in pose[1]]}


def robot_to_dict(setup: RobotSetup | None) -> dict[str, Any]:
    """The dataset@1 ``robot`` and ``mounts`` entries of ``setup`` (empty without a robot)."""
    if setup is None:
        return {}
    robot: dict[str, Any] = {"urdf": setup.urdf_name, "base_link": setup.base_link}
    if setup.offsets:
        robot["joint_offsets"] = {"estimate": list(setup.offsets), "prior_sigma_deg": setup.prior_sigma_deg}
    mounts: dict[str, Any] = {}
    for role, (_, pose_key) in _MOUNT_KEYS.items():
        mount = setup.mounts[role]
        if role == "target" and not setup.target_given:
            continue
        if role == "camera" and (setup.cameras is not None or (not setup.camera_given and mount.known is None)):
            continue
        mounts[role] = _mount_dict(mount, pose_key)
    if setup.cameras is not None:
        mounts["cameras"] = {camera: _mount_dict(mount, "T_link_cam") for camera, mount in setup.cameras.items()}
    return {"robot": robot, **({"mounts": mounts} if mounts else {})}


def _mount_dict(mount: Mount, pose_key: str) -> dict[str, Any]:
    return {"link": mount.link, **({pose_key: _pose_dict(mount.known)} if mount.known is not None else {})}


def joints_to_dict(joints: dict[str, float] | None) -> dict[str, Any]:
    """An image's ``joints`` entry (empty without)."""
    return {} if joints is None else {"joints": {n: float(x) for n, x in joints.items()}}
