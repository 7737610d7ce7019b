"""The general view model with a robot arm (docs/formats.md, "Robot arms: joint states and mounts"): which
key holds which unknown, the graph of every image (``factors/robot.py``: the view model of
``factors/views.py`` with each image's camera and target poses from forward kinematics), the estimate read
back and the covariances.

Frames: {B} the robot's base link. Unknowns: the unknown mounts ``M(0)`` (camera, ``T_link_cam``) and
``M(1)`` (target, ``T_link_target``) as Pose3, with several cameras ``M(0)`` the first's and ``M(k + 1)``
the k-th's after it (each image's camera pose from its own camera's mount, the role ``camera:NAME``); one ``OrientedPlane3`` ``V(i)`` per placement, fixed in {B}
while the arm moves; ``L(j)`` reconstruction points (target frame, metres); ``O(0)`` the estimated joint
offsets (radians, metres for prismatic joints; ``q_true = q_recorded + delta``) with their zero-mean
Gaussian prior. Covariances leave in the uncertainty convention (docs/formats.md), each mount's about and
along its link's axes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, M, O, V

from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.robot import RobotViewFactor, adjoint, inverse
from mirror_fg.factors.robot_stack import robot_stacks
from mirror_fg.factors.views import plane_of, vector_of_plane
from mirror_fg.data import Dataset
from mirror_fg.solver.model.views import points_of

__all__ = ["RobotProblem", "RobotEstimate", "ROLES", "camera_base_pose", "camera_role", "is_camera", "camera_name",
           "mount_words"]

ROLES = ("camera", "target")
Pose = tuple[np.ndarray, np.ndarray]


def camera_role(name: str | None) -> str:
    """The mount role of a camera: ``camera`` (the one camera), ``camera:NAME`` (one of several)."""
    return "camera" if name is None else f"camera:{name}"


def is_camera(role: str) -> bool:
    """Whether a mount role is a camera's (``camera``, ``camera:NAME``) rather than the target's."""
    return role != "target"


def mount_words(role: str) -> str:
    """A mount in a user's words: "the camera mount", "the 'left' camera mount", "the target mount"."""
    name = camera_name(role)
    return f"the {role} mount" if name is None else f"the {name!r} camera mount"


def camera_name(role: str) -> str | None:
    """The camera's name in a ``camera:NAME`` role (None for ``camera``)."""
    return role.split(":", 1)[1] if ":" in role else None


@dataclass
class RobotEstimate:
    """Values of every unknown: ``mounts`` (both, known ones as given), mirror vectors in {B}, points
    (target frame), joint offsets (in ``RobotSetup.offsets`` order)."""

    mounts: dict[str, Pose]
    mirror_vectors: dict[tuple[int, int], np.ndarray]
    points: dict[str, np.ndarray] = field(default_factory=dict)
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))


class RobotProblem:
    """Keys, graph, estimate and covariances of an arm's dataset (module docstring)."""

    def __init__(self, dataset: Dataset, robust: str | None = None):
        assert dataset.robot is not None
        self.dataset = dataset
        setup = self.setup = dataset.robot
        self.kinematics = setup.kinematics
        #: Each camera's mount role (``camera_role``), in the ``cameras`` order; the first's is :attr:`camera`.
        self.camera_roles = {name: camera_role(name) for name in setup.camera_mounts()}
        self.camera = next(iter(self.camera_roles.values()))
        mounts = {camera_role(name): mount for name, mount in setup.camera_mounts().items()}
        mounts["target"] = setup.mounts["target"]
        self.roles = list(mounts)
        self.links = {role: mount.link for role, mount in mounts.items()}
        self.known: dict[str, Pose] = {role: mount.known for role, mount in mounts.items() if mount.known is not None}
        numbers = {role: (0 if k == 0 else k + 1) for k, role in enumerate(self.camera_roles.values())}
        numbers["target"] = 1
        self.mount_keys = {role: M(numbers[role]) for role in self.roles if role not in self.known}
        self.placements = sorted({p for im in dataset.images for p in im.reflections})
        self.mirror_keys = {p: V(i) for i, p in enumerate(self.placements)}
        self.point_names = dataset.reconstruction_point_names
        self.point_keys = {name: L(j) for j, name in enumerate(self.point_names)}
        self.offsets = tuple(setup.offsets)
        self.offset_key = O(0) if self.offsets else None
        self.factors: list[RobotViewFactor] = []
        self.normalized: list[np.ndarray] = []
        #: Each image's placements ``{link: (T_base_link, J)}`` of its camera's and the target's links at its
        #: recorded joints (no Jacobian columns): the start and the motion check read them here.
        self.recorded: list[dict] = []
        # an image's sigmas, target points and landmarks depend on its camera and point names only: built once
        # for the images that share them (a board's images mostly see the same corners)
        shared: dict[tuple, tuple[np.ndarray, np.ndarray, list[int]]] = {}
        for image in dataset.images:
            names = list(image.observations)
            normalized = dataset.normalized(image)
            observed = np.array([normalized[n] for n in names], float).reshape(-1, 2).T
            self.normalized.append(observed)
            camera = dataset.camera_of(image)
            if (id(camera), *names) not in shared:
                shared[(id(camera), *names)] = points_of(dataset, camera, names, self.point_keys)
            sigmas, points, landmarks = shared[(id(camera), *names)]
            sigmas, points, landmarks = sigmas.copy(), points.copy(), list(landmarks)
            assert image.joints is not None
            role = self.role_of(image)
            placed = self.kinematics.placements(image.joints, list(dict.fromkeys((self.links[role], self.links["target"]))))
            self.recorded.append(placed)
            keys = {r: self.mount_keys[w] for r, w in (("camera", role), ("target", "target")) if w in self.mount_keys}
            known = {r: self.known[w] for r, w in (("camera", role), ("target", "target")) if w in self.known}
            self.factors.append(RobotViewFactor(
                image.reflections, keys, known, self.mirror_keys, self.forward(image.joints, role, placed),
                self.offset_key, len(self.offsets), points, landmarks, observed, sigmas, robust))
        self._stacks: tuple | None = None
        # what :meth:`residuals` reads every time: each image's measured pixels (N, 2), and all images'
        # normalized observations and sigmas side by side (2, total)
        self._raw = [np.array([im.observations[n] for n in im.observations], float).reshape(-1, 2)
                     for im in dataset.images]
        self._observed = np.hstack(self.normalized) if self.normalized else np.zeros((2, 0))
        self._labels = [(image.id, n) for image in dataset.images for n in image.observations]
        self._sigmas = np.hstack([f.sigmas for f in self.factors]) if self.factors else np.zeros((2, 0))
        #: Number of residual rows (2 per measurement).
        self.size = sum(2 * len(im.observations) for im in dataset.images)
        self.constraints = 0

    @property
    def stacks(self):
        """``factors/robot_stack.robot_stacks`` of the images' factors (built once)."""
        if self._stacks is None:
            self._stacks = robot_stacks(self.factors)
        return self._stacks

    def predictions(self, values: gtsam.Values) -> list[np.ndarray]:
        """Each image's predicted normalized coordinates (2, N) at ``values`` (file order), the stacked
        images' in one pass per stack."""
        stacks, alone = self.stacks
        out: list = [None] * len(self.factors)
        for i in alone:
            out[i] = self.factors[i].predict(values)
        for members, stack in stacks:
            for i, z in zip(members, stack.predict(values)):
                out[i] = z
        return out

    def role_of(self, image) -> str:
        """The mount role of the camera that took ``image``."""
        return self.camera_roles[image.camera] if self.setup.cameras is not None else self.camera

    def forward(self, joints: dict[str, float], role: str | None = None, placed: dict | None = None):
        """The image's forward kinematics for ``factors/robot.py``: at ``joints + delta``, the placements
        of the camera's (``role``, default the first camera) and the target's links in {B} and their
        Jacobians in the offsets (``placed``: those links' placements at ``joints``, when known)."""
        kin, offsets = self.kinematics, self.offsets
        camera_link, target_link = self.links[role or self.camera], self.links["target"]
        unique = list(dict.fromkeys((camera_link, target_link)))
        if not offsets:  # nothing moves the joints: the placements once
            out = placed if placed is not None else kin.placements(joints, unique)
            fixed = (out[camera_link], out[target_link])
            return lambda delta: fixed

        def fk(delta: np.ndarray):
            q = dict(joints)
            for name, d in zip(offsets, delta):
                q[name] += float(d)
            out = kin.placements(q, unique, list(offsets))
            return out[camera_link], out[target_link]
        return fk

    # ------------------------------------------------------------------ values
    def values(self, estimate: RobotEstimate) -> gtsam.Values:
        values = gtsam.Values()
        for role, key in self.mount_keys.items():
            R, t = estimate.mounts[role]
            values.insert(key, gtsam.Pose3(gtsam.Rot3(R), np.asarray(t, float)))
        for p, key in self.mirror_keys.items():
            values.insert(key, plane_of(estimate.mirror_vectors[p]))
        for name, key in self.point_keys.items():
            values.insert(key, np.asarray(estimate.points[name], float))
        if self.offset_key is not None:
            values.insert(self.offset_key, np.asarray(estimate.offsets, float).reshape(len(self.offsets)))
        return values

    def read(self, values: gtsam.Values) -> RobotEstimate:
        mounts = dict(self.known)
        for role, key in self.mount_keys.items():
            pose = values.atPose3(key)
            mounts[role] = (pose.rotation().matrix(), np.asarray(pose.translation(), float))
        return RobotEstimate(
            mounts, {p: vector_of_plane(values.atOrientedPlane3(k))[0] for p, k in self.mirror_keys.items()},
            {n: np.asarray(values.atPoint3(k), float) for n, k in self.point_keys.items()},
            np.asarray(values.atVector(self.offset_key), float) if self.offset_key is not None else np.zeros(0))

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """Every image's factor, those of one shape stacked (``factors/robot_stack.py``: one call per
        placement per LM step instead of one per image), and the joint offsets' prior."""
        graph = gtsam.NonlinearFactorGraph()
        stacks, alone = self.stacks
        for i in alone:
            graph.add(self.factors[i].factor())
        for _, stack in stacks:
            graph.add(stack.factor())
        if self.offset_key is not None:  # the encoders' zero: a zero-mean prior of the given sigma
            sigmas = np.array([self.setup.offset_sigma[n] for n in self.offsets])
            graph.add(gtsam.PriorFactorVector(self.offset_key, np.zeros(len(sigmas)),
                                              gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
        return graph

    @property
    def keys(self) -> list[int]:
        return [*self.mount_keys.values(), *self.mirror_keys.values(), *self.point_keys.values(),
                *([self.offset_key] if self.offset_key is not None else [])]

    def name_of(self, key: int) -> str:
        for role, k in self.mount_keys.items():
            if k == key:
                return f"{mount_words(role)} T_link_{'cam' if is_camera(role) else 'target'}"
        for p, k in self.mirror_keys.items():
            if k == key:
                return f"mirror {p[0]} placement {p[1]}"
        for name, k in self.point_keys.items():
            if k == key:
                return f"point {name!r}"
        return "the joint offsets"

    def dimension(self) -> int:
        return 6 * len(self.mount_keys) + 3 * len(self.mirror_keys) + 3 * len(self.point_keys) + len(self.offsets)

    # ------------------------------------------------------------------ residuals
    def residuals(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, list[tuple[str, str]]]:
        """Per measurement (file order): residuals (N, 2) in pixels with a camera (else normalized), whitened
        norms and ``(image, point)`` labels."""
        residuals: list[np.ndarray] = []
        by_camera: dict[int, list[int]] = {}  # images distorted together, one call per camera
        predictions = self.predictions(values)
        if not predictions:
            return np.zeros((0, 2)), np.zeros(0), []
        # every image's whitened norms at once (each column on its own: the same numbers as image by image)
        whitened = np.linalg.norm((np.hstack(predictions) - self._observed) / self._sigmas, axis=0)
        for i, (image, observed, z) in enumerate(zip(self.dataset.images, self.normalized, predictions)):
            camera = self.dataset.camera_of(image)
            if camera is not None:
                by_camera.setdefault(id(camera), []).append(i)
                residuals.append(self._raw[i])  # the measured pixels, replaced below
            else:
                residuals.append((z - observed).T)
        labels = list(self._labels)
        for members in by_camera.values():
            camera = self.dataset.camera_of(self.dataset.images[members[0]])
            assert camera is not None
            pixels = camera.distort(np.vstack([predictions[i].T for i in members]))  # each point on its own
            start = 0
            for i in members:
                count = len(residuals[i])
                residuals[i] = pixels[start:start + count] - residuals[i]
                start += count
        return np.vstack(residuals), whitened, labels

    # ------------------------------------------------------------------ covariances
    def information(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> tuple[np.ndarray, dict]:
        """The Fisher information (dense, the keys in :attr:`keys` order) and each key's columns."""
        ordering = gtsam.Ordering()
        columns, start = {}, 0
        for key in self.keys:
            ordering.push_back(key)
            dim = 6 if key in self.mount_keys.values() else (len(self.offsets) if key == self.offset_key else 3)
            columns[key] = slice(start, start + dim)
            start += dim
        A, _ = graph.linearize(values).jacobian(ordering)
        return A.T @ A, columns

    def covariances(self, covariance: np.ndarray, columns: dict, estimate: RobotEstimate) -> dict:
        """``{"mounts": {role: 6x6}, "mirrors": {p: 3x3 of v}, "points": {...}, "offsets": KxK}`` from the
        joint covariance in the keys' tangents (mounts: uncertainty convention, link axes)."""
        out: dict = {"mounts": {}, "mirrors": {}, "points": {}, "offsets": None}
        for role, key in self.mount_keys.items():
            c = columns[key]
            out["mounts"][role] = covariance_from_pose3(estimate.mounts[role][0], covariance[c, c])
        for p, key in self.mirror_keys.items():
            J = vector_of_plane(plane_of(estimate.mirror_vectors[p]))[1]
            c = columns[key]
            out["mirrors"][p] = J @ covariance[c, c] @ J.T
        for name, key in self.point_keys.items():
            c = columns[key]
            out["points"][name] = covariance[c, c].copy()
        if self.offset_key is not None:
            c = columns[self.offset_key]
            out["offsets"] = covariance[c, c].copy()
        return out


def camera_base_pose(mount: Pose, pose3_covariance: np.ndarray | None) -> tuple[Pose, np.ndarray | None]:
    """``T_cam_link`` (the inverse of the camera mount) and its covariance in the uncertainty convention,
    from the mount's Pose3 tangent covariance: ``T Exp(xi)`` inverts to ``T^-1 Exp(-Ad(T) xi)``."""
    inv = inverse(mount)
    if pose3_covariance is None:
        return inv, None
    Ad = adjoint(mount)
    return inv, covariance_from_pose3(inv[0], Ad @ pose3_covariance @ Ad.T)

