"""The building blocks of the ROS outputs (io/ros.py for one camera, io/ros_rig.py for a rig): frame names
and their checks, REP 103's frame conventions, the rotation's roll-pitch-yaw, URDF joints, tf2
static_transform_publisher arguments and the transform entries of the YAML. Frames: base <- camera
(``T_base_cam``), metres and radians."""
from __future__ import annotations

import html
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core import transform
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import Transform, _clean, rotation_to_quaternion_xyzw  # _clean: no -0.0 in YAML/URDF
from mirror_fg.io.result import base_cam_sigma3, nearest_rotation, validate_result

DEFAULT_BASE_FRAME = "base_link"
DEFAULT_CAMERA_FRAME = "camera_optical_frame"
#: ROS / tf2 frame ids: no whitespace, quotes or XML-special characters (they are pasted into XML and shells).
_FRAME_ID = re.compile(r"^[A-Za-z0-9_./:-]+$")
_CAMERA_CONVENTION = "OpenCV / ROS optical (REP 103): x right, y down, z forward"
_LINK_CONVENTION = "ROS body (REP 103): x forward, y left, z up"
#: A body frame's name: ``camera_link``, ``front_cam_link``, ``link``.
_BODY_FRAME = re.compile(r"(^|[_/.:-])link$")
#: REP 103: the optical frame's axes in the camera's body frame (optical z = body x, x = -y, y = -z);
#: the URDF joint camera_link -> camera_optical_frame with rpy (-pi/2, 0, -pi/2).
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


# --------------------------------------------------------------------------------------------------
# Rotation parameterisations
# --------------------------------------------------------------------------------------------------


def _rotation(matrix: Any, what: str) -> np.ndarray:
    """``matrix`` as a proper rotation (3, 3), re-orthonormalised; ValueError if it is not one."""
    try:
        R = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{what}: rotation must be a 3x3 matrix of numbers") from None
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{what}: rotation must be a finite 3x3 matrix, got shape {R.shape}")
    rotation = nearest_rotation(R)
    if rotation is None:
        raise ValueError(f"{what}: not a rotation matrix (R^T R != I or det R != +1)")
    return rotation


def rotation_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF ``(roll, pitch, yaw)`` (radians) of ``R`` checked as a rotation first (ValueError if it is not
    one): :func:`mirror_fg.core.transform.rotation_to_rpy` for matrices that come from users."""
    return transform.rotation_to_rpy(_rotation(R, "rotation_to_rpy"))


def _num(x: float) -> str:
    """Shortest decimal string that reads back to the same double (``repr``)."""
    return repr(_clean(x))


# --------------------------------------------------------------------------------------------------
# Result -> bounds of the camera's pose in the base frame
# --------------------------------------------------------------------------------------------------


def sigma3_base_cam(result: Mapping[str, Any], source: str = "result") -> dict[str, list[float]] | None:
    """3-sigma bounds of the camera's pose in the base frame (``T_base_cam``), None without a covariance.

    ``rotation_deg``: about the base axes (``R_base_cam_true = Exp(dphi) R_base_cam``); ``position_mm``:
    the camera centre's position in the base frame along the base axes. From the result's
    ``covariance_base_cam``, or for older results from ``covariance_cam_base`` (first order,
    :meth:`Transform.inverse_covariance`). ``result`` is validated first (DatasetError starting with
    ``source``).
    """
    return base_cam_sigma3(validate_result(result, source))


# --------------------------------------------------------------------------------------------------
# Snippets
# --------------------------------------------------------------------------------------------------


def check_frame_name(name: Any, what: str) -> str:
    if not isinstance(name, str) or not _FRAME_ID.match(name):
        raise ValueError(
            f"{what} {name!r}: a frame name must be non-empty and use only letters, digits and _ . / : -"
        )
    return name


def check_camera_frame_name(name: Any, what: str) -> str:
    """A frame name (:func:`check_frame_name`) for the *optical* frame the calibration is about.

    A body-frame name (``camera_link``, ``..._link``: x forward, y left, z up in REP 103) is refused
    with DatasetError: writing the optical pose under it would put the camera's z axis where tf users
    expect x. The outputs give that frame's pose too (:func:`ros_outputs`' ``camera_link``).
    """
    name = check_frame_name(name, what)
    if _BODY_FRAME.search(name):
        raise DatasetError(
            f"{what} {name!r} names a body frame (REP 103: x forward, y left, z up), but the calibrated pose "
            "is of the optical frame (OpenCV: x right, y down, z forward); give the optical frame's name "
            f"(e.g. camera_optical_frame): the ROS outputs also hold {link_frame_name(name)}'s pose with "
            "the REP 103 rotation applied"
        )
    return name


def link_frame_name(camera_frame: str) -> str:
    """The body frame paired with an optical frame: ``camera_optical_frame`` -> ``camera_link``."""
    if _BODY_FRAME.search(camera_frame):
        return camera_frame
    for suffix in ("_optical_frame", "_optical"):
        if camera_frame.endswith(suffix):
            return camera_frame[: -len(suffix)] + "_link"
    return camera_frame + "_link"


def quoteattr(value: str) -> str:
    """``value`` as a double-quoted XML attribute (``&``, ``<``, ``>``, quotes escaped). ``html.escape``:
    ``xml.sax.saxutils.quoteattr`` would load urllib and ssl into every ``calibrate`` (a slower start-up)."""
    return '"' + html.escape(value, quote=True) + '"'


def urdf_joint(
    R_base_cam: np.ndarray,
    t_base_cam: np.ndarray,
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
    name: str | None = None,
) -> str:
    """A fixed URDF ``<joint>`` from ``base_frame`` (parent) to ``camera_frame`` (child).

    ``<origin xyz rpy>`` is the child's pose in the parent, ``T_base_cam`` (metres, fixed-axis radians).
    """
    base_frame = check_frame_name(base_frame, "base frame")
    camera_frame = check_frame_name(camera_frame, "camera frame")
    name = name or f"{base_frame}_to_{camera_frame}".replace("/", "_")
    xyz = " ".join(_num(x) for x in np.asarray(t_base_cam, dtype=float))
    rpy = " ".join(_num(x) for x in rotation_to_rpy(R_base_cam))
    return (
        f'<joint name={quoteattr(name)} type="fixed">\n'
        f"  <parent link={quoteattr(base_frame)}/>\n"
        f"  <child link={quoteattr(camera_frame)}/>\n"
        f'  <origin xyz="{xyz}" rpy="{rpy}"/>\n'
        "</joint>\n"
    )


def urdf_robot(joint: str, base_frame: str, camera_frame: str, name: str = "mirror_fg_calibration") -> str:
    """A minimal valid URDF ``<robot>``: links ``base_frame`` and ``camera_frame`` and ``joint`` between them."""
    links = "".join(f"  <link name={quoteattr(check_frame_name(f, 'frame'))}/>\n" for f in (base_frame, camera_frame))
    return f"<robot name={quoteattr(name)}>\n{links}{joint}</robot>\n"


def static_transform_publisher_args(
    R_base_cam: np.ndarray,
    t_base_cam: np.ndarray,
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
) -> str:
    """ROS 2 ``tf2_ros static_transform_publisher`` arguments (new-style flags) for ``T_base_cam``.

    ``--x --y --z`` metres, ``--qx --qy --qz --qw`` quaternion, ``--frame-id`` the parent (base frame),
    ``--child-frame-id`` the camera frame. Use as
    ``ros2 run tf2_ros static_transform_publisher <args>``.
    """
    base_frame = check_frame_name(base_frame, "base frame")
    camera_frame = check_frame_name(camera_frame, "camera frame")
    t = np.asarray(t_base_cam, dtype=float)
    q = rotation_to_quaternion_xyzw(R_base_cam)
    parts = [f"--{k} {_num(v)}" for k, v in zip(("x", "y", "z", "qx", "qy", "qz", "qw"), [*t, *q])]
    parts += [f"--frame-id {base_frame}", f"--child-frame-id {camera_frame}"]
    return " ".join(parts)


# --------------------------------------------------------------------------------------------------
# The YAML content and files
# --------------------------------------------------------------------------------------------------


def _transform_entry(R: np.ndarray, t: np.ndarray, q_hint: Any, description: str) -> dict[str, Any]:
    """Matrix, translation, quaternion (sign of ``q_hint`` when given) and URDF rpy of one transform."""
    T = Transform(R, t).matrix()
    q = rotation_to_quaternion_xyzw(R)
    if q_hint is not None and float(np.asarray(q_hint, dtype=float) @ q) < 0.0:
        q = -q  # same rotation; keep the sign the result file uses
    return {
        "description": description,
        "matrix": [[_clean(x) for x in row] for row in T],
        "translation": [_clean(x) for x in t],
        "quaternion_xyzw": [_clean(x) for x in q],
        "rpy": list(rotation_to_rpy(R)),
    }


def _camera_link(R_bc: np.ndarray, t_bc: np.ndarray, base_frame: str, link: str, optical: str) -> dict[str, Any]:
    """``base -> link -> optical``: the calibrated pose split at the body frame (REP 103)."""
    T_base_link = Transform(R_bc, t_bc) @ Transform(R_LINK_OPTICAL, np.zeros(3)).inverse()
    commands = [
        "ros2 run tf2_ros static_transform_publisher " + static_transform_publisher_args(R, t, parent, child)
        for R, t, parent, child in (
            (T_base_link.R, T_base_link.t, base_frame, link), (R_LINK_OPTICAL, np.zeros(3), link, optical),
        )
    ]
    return {
        "frames": {"link": link, "link_convention": _LINK_CONVENTION, "optical": optical},
        "T_base_link": _transform_entry(
            T_base_link.R, T_base_link.t, None, f"pose of {link} in {base_frame}: T_base_cam with the REP 103 rotation"
        ),
        "T_link_optical": _transform_entry(R_LINK_OPTICAL, np.zeros(3), None, f"{optical} in {link} (REP 103)"),
        "urdf_joints": urdf_joint(T_base_link.R, T_base_link.t, base_frame, link)
        + urdf_joint(R_LINK_OPTICAL, np.zeros(3), link, optical),
        "static_transform_publisher_commands": commands,
    }


def _xml_comment(text: str) -> str:
    """``text`` safe inside an XML comment (no ``--``)."""
    return text.replace("--", "- -")


# --------------------------------------------------------------------------------------------------
# camera_info (intrinsics estimated through the mirrors)
# --------------------------------------------------------------------------------------------------
