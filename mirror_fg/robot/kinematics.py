"""Forward kinematics of a URDF robot and its Jacobians, from Pinocchio (never hand-written).

Frames: {B} is the dataset's ``base_link``; a link's placement ``T_base_link(q)`` maps link coordinates
into {B} (``x_B = R x_link + t``), metres. Joint values are radians (revolute, continuous) or metres
(prismatic), keyed by the URDF joint name. The Jacobian of a placement is in GTSAM's Pose3 tangent
``[w, nu]`` of a right perturbation, ``T(q + dq) = T(q) Exp(J dq)`` (Pinocchio's LOCAL frame Jacobian,
its rows ``[v, w]`` swapped), one column per movable joint of the chain.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mirror_fg.core.errors import DatasetError

__all__ = ["Kinematics", "load_kinematics", "require_pinocchio"]

#: Printed where Pinocchio is missing.
INSTALL_HINT = "robot arms need Pinocchio: pip install 'mirror-fg[robot]'"


def require_pinocchio():
    """The ``pinocchio`` module, or a one-line DatasetError (exit 2) saying how to install it."""
    try:
        import pinocchio  # type: ignore[import-untyped]
    except ImportError:
        raise DatasetError(INSTALL_HINT) from None
    return pinocchio


@dataclass(frozen=True)
class JointInfo:
    """A movable joint: its first configuration index, whether it is continuous (cos, sin in Pinocchio),
    its limits (None where the URDF gives none) and whether it is prismatic."""

    index_q: int
    index_v: int
    continuous: bool
    lower: float | None
    upper: float | None
    prismatic: bool


class Kinematics:
    """Placements and Jacobians of a URDF's links in its ``base_link`` frame (module docstring)."""

    def __init__(self, urdf_path: str, base_link: str | None = None):
        pin = require_pinocchio()
        self.pin = pin
        self.urdf_path = urdf_path
        try:
            self.model = pin.buildModelFromUrdf(urdf_path)
        except (ValueError, RuntimeError, OSError) as error:
            first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise DatasetError(f"{urdf_path}: the URDF does not parse: {first}") from None
        self.data = self.model.createData()
        bodies = [f.name for f in self.model.frames if f.type == pin.FrameType.BODY]
        self.links = set(bodies)
        chosen = base_link if base_link is not None else (bodies[0] if bodies else None)
        if chosen is None or chosen not in self.links:
            raise DatasetError(f"{urdf_path}: base_link {chosen!r} is not a link of the URDF")
        self.base_link: str = chosen
        self.joints: dict[str, JointInfo] = {}
        for jid in range(1, self.model.njoints):
            joint = self.model.joints[jid]
            name = self.model.names[jid]
            shortname = joint.shortname()
            continuous = joint.nq == 2 and joint.nv == 1
            if joint.nv != 1:  # a floating or planar joint: its state is not recorded by an arm
                self.joints[name] = JointInfo(joint.idx_q, joint.idx_v, False, None, None, False)
                continue
            lo = float(self.model.lowerPositionLimit[joint.idx_q])
            hi = float(self.model.upperPositionLimit[joint.idx_q])
            bounded = not continuous and np.isfinite(lo) and np.isfinite(hi) and lo < hi
            self.joints[name] = JointInfo(joint.idx_q, joint.idx_v, continuous, lo if bounded else None,
                                          hi if bounded else None, "Prismatic" in shortname)
        self._frame = {name: self.model.getFrameId(name) for name in self.links}

    def _path_joints(self, link: str) -> list[int]:
        """Pinocchio joint ids between ``base_link`` and ``link`` (either direction)."""
        def support(name: str) -> list[int]:
            return [int(j) for j in self.model.supports[self.model.frames[self._frame[name]].parentJoint] if j > 0]
        a, b = support(self.base_link), support(link)
        return [j for j in a if j not in b] + [j for j in b if j not in a]

    def chain(self, link: str) -> list[str]:
        """The movable joints between ``base_link`` and ``link`` (names, root to tip)."""
        return [self.model.names[j] for j in sorted(self._path_joints(link))]

    def chain_links(self, link: str) -> list[str]:
        """The links from ``base_link`` to ``link``, one per joint between them (for drawing the arm)."""
        out = [self.base_link]
        for jid in sorted(self._path_joints(link)):
            child = next((f.name for f in self.model.frames
                          if f.type == self.pin.FrameType.BODY and f.parentJoint == jid), None)
            if child is not None and child not in out:
                out.append(child)
        if link not in out:
            out.append(link)
        return out

    def unrecordable(self, link: str) -> list[str]:
        """Joints between ``base_link`` and ``link`` that carry no single joint value (floating, planar):
        such a link is not connected to the base through recorded joints."""
        return [self.model.names[j] for j in self._path_joints(link) if self.model.joints[j].nv != 1]

    def _configuration(self, joints: dict[str, float]) -> np.ndarray:
        q = self.pin.neutral(self.model)
        for name, value in joints.items():
            info = self.joints[name]
            if info.continuous:
                q[info.index_q:info.index_q + 2] = np.cos(value), np.sin(value)
            else:
                q[info.index_q] = value
        return q

    def placements(self, joints: dict[str, float], links: list[str], names: list[str] | None = None):
        """``{link: (T_base_link (4, 4), J (6, len(names)))}`` at ``joints`` (module docstring); ``names``
        are the joints whose columns are wanted (default none: J has no columns)."""
        pin = self.pin
        names = names or []
        q = self._configuration(joints)
        if not names:  # no Jacobian wanted: the placements alone (the same forward pass)
            pin.framesForwardKinematics(self.model, self.data, q)
            oMb = self.data.oMf[self._frame[self.base_link]]
            none = np.zeros((6, 0))
            return {link: (np.asarray(oMb.actInv(self.data.oMf[self._frame[link]]).homogeneous, float), none.copy())
                    for link in links}
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        oMb = self.data.oMf[self._frame[self.base_link]]
        columns = [self.joints[n].index_v for n in names]
        J_base = pin.getFrameJacobian(self.model, self.data, self._frame[self.base_link], pin.LOCAL)[:, columns]
        out = {}
        for link in links:
            oMl = self.data.oMf[self._frame[link]]
            bMl = oMb.actInv(oMl)
            J = pin.getFrameJacobian(self.model, self.data, self._frame[link], pin.LOCAL)[:, columns]
            if np.any(J_base):  # the base moves too: the link's velocity relative to it, in the link's axes
                J = J - bMl.inverse().action @ J_base
            out[link] = (np.asarray(bMl.homogeneous, float), np.vstack([J[3:], J[:3]]))  # [v, w] -> [w, nu]
        return out


@lru_cache(maxsize=16)
def _cached(path: str, mtime: float, base_link: str | None) -> Kinematics:
    return Kinematics(path, base_link)


def load_kinematics(urdf_path: str, base_link: str | None = None) -> Kinematics:
    """A :class:`Kinematics` of ``urdf_path`` (read once per file version)."""
    path = os.path.abspath(urdf_path)
    if not os.path.isfile(path):
        raise DatasetError(f"{urdf_path}: no such URDF file")
    return _cached(path, os.path.getmtime(path), base_link)
