"""The general view model's problem (docs/formats.md, "Views of any reflection order, and several
cameras"): which key holds which unknown, the graph of every view, the estimate read back and the
covariances, for data that the paper's tree does not describe (direct views, fixed mirrors, any order of
reflections, no known target, several cameras). ``calibrate()`` drives it (``solver/calibrate.py``).

Unknowns: one ``Pose3`` ``X(k)`` per camera (``T_cam_base``; not a variable for the first camera without
a known target, whose frame is then the base frame), one ``OrientedPlane3`` ``V(i)`` per placement (its
mirror plane in its owner camera's frame, ``v = d n``: the first camera, in ``cameras`` order, with an
image that sees it; ``factors/views.py`` says why a plane and not ``v``) and one
``Point3`` ``L(j)`` per reconstruction point (base frame). Measurements: ``factors/views.py``, one factor
per image. Without a known target the scale is held by a prior of relative sigma :data:`SCALE_SIGMA` on
the named distance (the measurements do not change along the gauge, so the optimum meets it exactly),
and the covariances are those with the gauge held exactly: with the prior's information ``H`` (well
conditioned), ``C = H^-1 - H^-1 a a^T H^-1 / (a^T H^-1 a)``, ``a`` the constraint's gradient (the limit
of a vanishing prior sigma; dense, the data without a target are small).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import K, L, V, X

from mirror_fg.core.camera import Camera
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.intrinsics import IntrinsicsModel, intrinsics_prior_factor, predict_pixels
from mirror_fg.factors.view_eliminated import EliminatedViewStack
from mirror_fg.factors.view_points_eliminated import EliminatedViewPointStack
from mirror_fg.factors.view_stack import stacked_view_factors
from mirror_fg.factors.view_table import ViewBlock, ViewTable, placement_indices, unique_rows
from mirror_fg.factors.view_table import view_factor_like  # noqa: F401 (its home was here: importers keep working)
from mirror_fg.factors.views import ViewFactor, plane_of, vector_of_plane
from mirror_fg.data import Dataset, Image
from mirror_fg.data.dataset import observation_array
from mirror_fg.io.point_sigma import normalized_sigmas
from mirror_fg.solver.model.graph import unknown_name
from mirror_fg.solver.model.schur_marginals import marginals_of
from mirror_fg.solver.start.propagation import Propagation, ViewObs, mirror_vector_in

__all__ = ["SINGLE_CAMERA", "ViewProblem", "views_of", "camera_names", "scale_prior", "mirror_vector_at", "plane_of"]

#: The camera's name where a dataset gives one ``camera``.
SINGLE_CAMERA = "camera"
#: Relative standard deviation of the scale prior without a known target.
SCALE_SIGMA = 1e-3

Placement = tuple[int, int]


def camera_names(dataset: Dataset) -> list[str]:
    """The dataset's camera names in order (one ``camera`` is :data:`SINGLE_CAMERA`)."""
    return list(dataset.cameras) if dataset.cameras is not None else [SINGLE_CAMERA]


def _camera_name(image: Image) -> str:
    return image.camera if image.camera is not None else SINGLE_CAMERA


def views_of(dataset: Dataset) -> list[ViewObs]:
    """Every image as a view, observations normalized with its own camera."""
    return [_view_of(image, dataset.normalized(image)) for image in dataset.images]


def _view_of(image: Image, normalized: dict[str, np.ndarray]) -> ViewObs:
    """An image as a view, given its normalized observations (``Dataset.normalized``: in file order)."""
    names = list(normalized)
    return ViewObs(image.id, _camera_name(image), tuple(image.reflections), names, observation_array(normalized, names))


@dataclass
class ViewEstimate:
    """Values of every unknown: poses ``{camera: (R, t)}``, mirror vectors (owner frames), points, and
    the nine intrinsics of every camera that estimates them (``theta``)."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]]
    mirror_vectors: dict[Placement, np.ndarray]
    points: dict[str, np.ndarray]
    theta: dict[str, np.ndarray] | None = None


class ViewProblem:
    """Keys, graph, estimate and covariances of a dataset in the general view model.

    ``intrinsics``: ``{camera: IntrinsicsModel}`` of the cameras whose intrinsics are estimated (their
    factors then predict pixels, with one ``Vector`` key ``K(k)`` per camera)."""

    def __init__(self, dataset: Dataset, robust: str | None = None,
                 intrinsics: dict[str, IntrinsicsModel] | None = None):
        self.dataset = dataset
        self.cameras = camera_names(dataset)
        images = dataset.images
        # every image's normalized observations ({name: (2,)} in file order, dataset.normalized), camera and
        # reflections: what views_of reads, the views themselves made when first asked (:attr:`views`)
        self._normalized = [dataset.normalized(image) for image in images]
        cameras = [_camera_name(image) for image in images]
        self.fixed: dict[str, tuple[np.ndarray, np.ndarray]] = (
            {} if dataset.fiducials else {self.cameras[0]: (np.eye(3), np.zeros(3))})
        seen = set(cameras)
        self.pose_keys = {name: X(k) for k, name in enumerate(self.cameras) if name not in self.fixed and name in seen}
        self.placements = sorted({p for image in images for p in image.reflections})
        # each placement's owner: the first camera (in ``cameras`` order) with a view through it; one pass
        # over the views (a pass per placement was quadratic: 1.7 s of 3,000 tree images)
        if len(seen) == 1:
            self.owners: dict[Placement, str] = dict.fromkeys(self.placements, cameras[0])
        else:
            order = {name: k for k, name in enumerate(self.cameras)}
            owners: dict[Placement, str] = {}
            for image, camera in zip(images, cameras):
                for p in image.reflections:
                    if p not in owners or order[camera] < order[owners[p]]:
                        owners[p] = camera
            self.owners = {p: owners[p] for p in self.placements}
        self.mirror_keys = {p: V(i) for i, p in enumerate(self.placements)}
        self.point_names = dataset.reconstruction_point_names
        self.point_keys = {name: L(j) for j, name in enumerate(self.point_names)}
        self.robust = robust
        self.intrinsics = dict(intrinsics or {})
        self.intrinsics_keys = {name: K(k) for k, name in enumerate(self.cameras) if name in self.intrinsics}
        self.table = ViewTable(self._blocks(cameras), self.placements, self.mirror_keys, self.owners, len(images))
        self._factors: list[ViewFactor] | None = None
        self._views: list[ViewObs] | None = None
        self.constraints = 1 if dataset.scale is not None else 0
        #: Number of residual rows (2 per measurement).
        self.size = sum(2 * len(image.observations) for image in images)

    def _blocks(self, cameras: list[str]) -> list[ViewBlock]:
        """The views as blocks of one shape (factors/view_table.py: one camera, the same points seen, owner at
        each reflection and pattern of repeated placements), grouped with array operations: the first view of
        each block gets its ViewFactor (the sigmas, base points and point keys of each (camera, points seen)
        read once), the others only their placements and observations (a ViewFactor, or a key of Python
        objects, per image was most of building a problem of thousands of images)."""
        images, dataset = self.dataset.images, self.dataset
        camera_index = {name: k for k, name in enumerate(self.cameras)}
        seen: dict[tuple, int] = {}
        shape = np.array([[camera_index[c] for c in cameras],
                          [seen.setdefault(tuple(image.observations), len(seen)) for image in images]],
                         dtype=np.intp).reshape(2, -1).T  # (camera, points seen) of each view
        lengths = np.array([len(image.reflections) for image in images], dtype=np.intp)
        owner_index = np.array([camera_index[self.owners[p]] for p in self.placements], dtype=np.intp)
        known: dict[tuple, tuple[np.ndarray, np.ndarray, list[int]]] = {}
        blocks = []
        for k in np.unique(lengths).tolist():
            rows = np.flatnonzero(lengths == k)
            ids = placement_indices(self.placements, [images[i].reflections for i in rows])  # (m, k)
            # each reflection's first reflection through its placement, whether it is that first one, and
            # its placement's place among the view's placements (in order of first reflection)
            first = (ids[:, :, None] == ids[:, None, :]).argmax(axis=2) if k else ids
            new = first == np.arange(k)
            local = np.take_along_axis(np.cumsum(new, axis=1) - 1, first, axis=1)
            key = np.concatenate([shape[rows], owner_index[ids], local], axis=1)
            which = unique_rows(key)[1]
            order = np.argsort(which, kind="stable")  # each block's views in file order
            for part in np.split(order, np.cumsum(np.bincount(which))[:-1]):
                members = rows[part]
                i, camera = int(members[0]), cameras[int(members[0])]
                pixel = camera in self.intrinsics
                names = list(images[i].observations)
                if (camera, *names) not in known:
                    camera_model = None if pixel else dataset.camera_of(images[i])
                    known[(camera, *names)] = self._points_of(dataset, camera_model, names)
                sigmas, base, landmarks = known[(camera, *names)]
                views = members.tolist()
                if pixel:  # pixels, as given (factors/intrinsics.py)
                    observed = np.array([list(images[j].observations.values()) for j in views], dtype=float)
                else:  # (in file order: dataset.normalized; each a (2,) array)
                    observed = np.concatenate([z for j in views for z in self._normalized[j].values()])
                observed_array = observed.astype(float, copy=False).reshape(len(views), -1, 2).transpose(0, 2, 1)
                model = (self.intrinsics[camera], self.intrinsics_keys[camera]) if pixel else None
                template = ViewFactor(camera, tuple(images[i].reflections), self.pose_keys, self.fixed,
                                      self.mirror_keys, self.owners, base, landmarks, observed_array[0], sigmas,
                                      self.robust, intrinsics=model)
                blocks.append(ViewBlock(template, members, ids[part][:, new[part[0]]], observed_array))
        return blocks

    @property
    def views(self) -> list[ViewObs]:
        """Every image as a view (:func:`views_of`), made when first asked."""
        if self._views is None:
            self._views = [_view_of(image, normalized)
                           for image, normalized in zip(self.dataset.images, self._normalized)]
        return self._views

    @property
    def factors(self) -> list[ViewFactor]:
        """Every image's ``ViewFactor``, in file order (made when first asked: ``ViewTable.factors``)."""
        if self._factors is None:
            self._factors = self.table.factors()
        return self._factors

    def _points_of(self, dataset: Dataset, camera: Camera | None, names: list[str]):
        return points_of(dataset, camera, names, self.point_keys)

    # ------------------------------------------------------------------ estimates
    def estimate_from(self, known: Propagation) -> ViewEstimate:
        """The propagation's base-frame planes as mirror vectors in their owners' frames."""
        poses = {name: known.poses[name] for name in self.cameras if name in known.poses}
        mirrors = {p: mirror_vector_in(known.planes[p], poses[self.owners[p]]) for p in self.placements}
        points = {name: np.asarray(known.points[name], float) for name in self.point_names}
        return self._scaled(ViewEstimate(poses, mirrors, points))

    def _scaled(self, estimate: ViewEstimate) -> ViewEstimate:
        """``estimate`` with the scale constraint met exactly (no known target), so LM starts on it."""
        scale = self.dataset.scale
        if scale is None:
            return estimate
        if scale.placement is not None:
            length = float(np.linalg.norm(estimate.mirror_vectors[scale.placement]))
        else:
            a, b = scale.points  # type: ignore[misc]
            length = float(np.linalg.norm(estimate.points[a] - estimate.points[b]))
        f = scale.distance / length
        return ViewEstimate({n: (R, t * f) for n, (R, t) in estimate.poses.items()},
                            {p: v * f for p, v in estimate.mirror_vectors.items()},
                            {n: x * f for n, x in estimate.points.items()})

    def values(self, estimate: ViewEstimate, skip: frozenset | set = frozenset()) -> gtsam.Values:
        """Every unknown's value at ``estimate`` (``skip``: placements eliminated inside their factors)."""
        values = gtsam.Values()
        for name, key in self.pose_keys.items():
            R, t = estimate.poses[name]
            values.insert(key, gtsam.Pose3(gtsam.Rot3(R), np.asarray(t, float)))
        for p, key in self.mirror_keys.items():
            if p not in skip:
                values.insert(key, plane_of(estimate.mirror_vectors[p]))
        for name, key in self.point_keys.items():
            values.insert(key, np.asarray(estimate.points[name], float))
        for name, key in self.intrinsics_keys.items():
            theta = (estimate.theta or {}).get(name, self.intrinsics[name].fixed)
            values.insert(key, np.asarray(theta, float)[self.intrinsics[name].index])
        return values

    def read(self, values: gtsam.Values, eliminated: EliminatedViewStack | None = None) -> ViewEstimate:
        """The estimate at ``values`` (and the placements ``eliminated`` solves inside its factors)."""
        inside = eliminated.vectors_at(values) if eliminated is not None else {}
        poses = dict(self.fixed)
        for name, key in self.pose_keys.items():
            pose = values.atPose3(key)
            poses[name] = (pose.rotation().matrix(), np.asarray(pose.translation(), float))
        theta = {name: self.intrinsics[name].theta(np.asarray(values.atVector(key), float))
                 for name, key in self.intrinsics_keys.items()}
        return ViewEstimate(poses, {p: inside[p] if p in inside else vector_of_plane(values.atOrientedPlane3(k))[0]
                                    for p, k in self.mirror_keys.items()},
                            {n: np.asarray(values.atPoint3(k), float) for n, k in self.point_keys.items()}, theta or None)

    # ------------------------------------------------------------------ graph
    def graph(self, stacked: bool = True) -> gtsam.NonlinearFactorGraph:
        """Every view's factor (``stacked``: evaluated together, one factor per set of placements,
        ``factors/view_stack.py``; else one ``ViewFactor`` per image), the intrinsics priors and the
        scale prior."""
        graph = gtsam.NonlinearFactorGraph()
        for factor in (stacked_view_factors(self.table) if stacked else [f.factor() for f in self.factors]):
            graph.add(factor)
        self._priors(graph)
        return graph

    def solve_graph(self, estimate: ViewEstimate, eliminate: bool = True):
        """``(graph, values, eliminated)`` to solve from ``estimate``: where the data allow it (a known target,
        intrinsics known, no robust kernel) the placements that one stacked factor alone sees eliminated
        inside it (``factors/view_eliminated.py``; ``eliminated`` that evaluator, its placements not in
        ``values``), else :meth:`graph` and :meth:`values` (``eliminated`` None)."""
        if eliminate and self.dataset.scale is None and not self.intrinsics and self.robust is None:
            if self.table.blocks and all(block.template.unique_landmarks for block in self.table.blocks):
                return self._points_solve_graph(estimate)
            views = self.table.subset(lambda block: block.eliminable)
            others = [block for block in self.table.blocks if not block.eliminable]
            keep = {self.placements[u] for block in others for u in np.unique(block.placements).tolist()}
            evaluator = EliminatedViewStack(views, estimate.mirror_vectors, keep) if views.count else None
            if evaluator is not None and evaluator.eliminated:
                rest = stacked_view_factors(self.table.subset(lambda block: not block.eliminable)) if others else []
                return self.eliminated_graph(evaluator, estimate, rest)
        return self.graph(), self.values(estimate), None

    def eliminated_graph(self, evaluator: EliminatedViewStack | EliminatedViewPointStack, estimate: ViewEstimate,
                         others: Sequence[gtsam.NonlinearFactor] = ()):
        """``(graph, values, evaluator)`` of a stack with its placements eliminated (:meth:`solve_graph`): its
        factors, ``others`` (the views it does not hold), the priors, and the values of the rest at
        ``estimate``."""
        graph = gtsam.NonlinearFactorGraph()
        for factor in [*evaluator.factors, *others]:
            graph.add(factor)
        evaluator.factors = []  # the factors hold the evaluator: no cycle through C++ (freed with the graph)
        self._priors(graph)
        return graph, self.values(estimate, skip=set(evaluator.eliminated)), evaluator

    def _points_solve_graph(self, estimate: ViewEstimate):
        """:meth:`solve_graph` where every view sees reconstruction points: each photograph's own placement
        eliminated inside the points' stacked factors (``factors/view_points_eliminated.py``), else (none to
        eliminate) :meth:`graph` and :meth:`values`."""
        evaluator = EliminatedViewPointStack(self.factors, estimate.mirror_vectors)
        if not evaluator.eliminated:
            return self.graph(), self.values(estimate), None
        return self.eliminated_graph(evaluator, estimate)

    def _priors(self, graph: gtsam.NonlinearFactorGraph) -> None:
        """The intrinsics priors and the scale prior, added to ``graph``."""
        for name, key in self.intrinsics_keys.items():
            camera = self.dataset.cameras[name] if self.dataset.cameras is not None else self.dataset.camera
            assert camera is not None  # it estimates intrinsics
            prior = intrinsics_prior_factor(self.intrinsics[name], dict(camera.prior_sigma), key)
            if prior is not None:
                graph.add(prior)
        graph.push_back(scale_prior(self.dataset, self.mirror_keys, self.point_keys))

    @property
    def keys(self) -> list[int]:
        """Every unknown's key: the camera poses, the placements, the points, the intrinsics vectors."""
        return [*self.pose_keys.values(), *self.mirror_keys.values(), *self.point_keys.values(),
                *self.intrinsics_keys.values()]

    def name_of(self, key: int) -> str:
        for name, k in self.intrinsics_keys.items():
            if k == key:
                return f"the intrinsics of {'camera ' + repr(name) if self.dataset.cameras is not None else 'the camera'}"
        poses = {k: (f"camera {name!r}" if self.dataset.cameras is not None else "T_cam_base")
                 for name, k in self.pose_keys.items()}
        return unknown_name(key, poses, self.mirror_keys, self.point_keys)

    # ------------------------------------------------------------------ residuals
    def residuals(self, estimate: ViewEstimate) -> tuple[np.ndarray, np.ndarray, list[tuple[str, str]]]:
        """Per measurement (file order): residuals (N, 2) in pixels with a camera (else normalized), their
        whitened norms (sigmas) and ``(image, point)`` labels. The views of one block (one camera, the same
        points seen) at once."""
        images = self.dataset.images
        predicted = self._predictions(estimate)
        residuals: list[np.ndarray] = [np.zeros((0, 2))] * self.table.count
        whitened: list[np.ndarray] = [np.zeros(0)] * self.table.count
        for block in self.table.blocks:
            members = block.members.tolist()
            factor = block.template
            z = np.array([predicted[i] for i in members], dtype=float).reshape(len(members), -1, 2)  # (b, N, 2)
            observed = block.observed.transpose(0, 2, 1)  # normalized; pixels where the intrinsics are estimated
            sigmas = factor.sigmas.T  # (N, 2), in the observations' units
            if factor.intrinsics is not None:  # pixels through the estimated intrinsics
                assert estimate.theta is not None
                residual = predict_pixels(estimate.theta[factor.camera], z.reshape(-1, 2)).reshape(z.shape) - observed
                norms = np.linalg.norm(residual / sigmas, axis=2)
            else:
                norms = np.linalg.norm((z - observed) / sigmas, axis=2)
                camera: Camera | None = self.dataset.camera_of(images[members[0]])
                if camera is not None:
                    pixels = np.array([list(images[i].observations.values()) for i in members], dtype=float)
                    residual = camera.distort(z.reshape(-1, 2)).reshape(z.shape) - pixels.reshape(z.shape)
                else:
                    residual = z - observed
            for row, i in enumerate(members):
                residuals[i], whitened[i] = residual[row], norms[row]
        labels = [(image.id, name) for image in images for name in image.observations]
        return np.vstack(residuals), np.concatenate(whitened), labels

    def _predictions(self, estimate: ViewEstimate) -> list[np.ndarray]:
        """Every view's predicted normalized coordinates (N, 2) at ``estimate`` (``views.view_model``, eqs. 2, 3,
        9), the views of one shape at once (``view_stack._Group``)."""
        values = {self.point_keys[n]: np.asarray(x, float) for n, x in estimate.points.items() if n in self.point_keys}
        predicted: list[np.ndarray] = [np.zeros((0, 2))] * self.table.count
        for first, members, parts in self.table.groups():
            group = self.table.group_of(first, parts)
            z = group.model(estimate.poses, estimate.mirror_vectors, {}, False, base=group.points(values))[0]
            for row, i in enumerate(members.tolist()):
                predicted[i] = z[row].T
        return predicted

    # ------------------------------------------------------------------ covariances
    def covariances(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, estimate: ViewEstimate,
                    eliminated: EliminatedViewStack | None = None):
        """``(pose covariances {camera: 6x6}, joint (6C, 6C), mirrors {p: 3x3}, points {name: 3x3})`` in
        docs/formats.md's conventions; a fixed camera's blocks are zero. ``eliminated``: the evaluator of
        the placements solved inside the factors (:meth:`solve_graph`)."""
        marginals = marginals_of(graph, values) if self.dataset.scale is None else _GaugeHeld(self, graph, values)
        inside = eliminated.covariances(values, marginals) if eliminated is not None else {}
        keys = list(self.pose_keys.values())
        joint = np.zeros((6 * len(self.cameras), 6 * len(self.cameras)))
        if keys:
            kv = gtsam.KeyVector()
            for key in keys:
                kv.append(key)
            block = marginals.jointMarginalCovariance(kv).fullMatrix()
            index = {name: k for k, name in enumerate(self.pose_keys)}
            for i, a in enumerate(self.cameras):
                for j, b in enumerate(self.cameras):
                    if a in index and b in index:
                        Ja = np.kron(np.eye(2), estimate.poses[a][0])
                        Jb = np.kron(np.eye(2), estimate.poses[b][0])
                        C = block[6 * index[a]:6 * index[a] + 6, 6 * index[b]:6 * index[b] + 6]
                        joint[6 * i:6 * i + 6, 6 * j:6 * j + 6] = Ja @ C @ Jb.T
        poses = {name: joint[6 * i:6 * i + 6, 6 * i:6 * i + 6].copy() for i, name in enumerate(self.cameras)}
        for name in self.pose_keys:  # the diagonal blocks exactly as the single-camera path converts them
            R = estimate.poses[name][0]
            poses[name] = covariance_from_pose3(R, marginals.marginalCovariance(self.pose_keys[name]))
        mirrors = {}
        for p, k in self.mirror_keys.items():  # of v = d n, from the plane's local coordinates
            if p in inside:
                mirrors[p] = inside[p]
                continue
            J = vector_of_plane(plane_of(estimate.mirror_vectors[p]))[1]
            mirrors[p] = J @ marginals.marginalCovariance(k) @ J.T
        points = {n: marginals.marginalCovariance(k) for n, k in self.point_keys.items()}
        intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        for name, key in self.intrinsics_keys.items():  # (k, k) and its cross-covariance (k, 6) with the pose
            k = len(self.intrinsics[name].index)
            if name in self.pose_keys:
                kv = gtsam.KeyVector()
                kv.append(key)
                kv.append(self.pose_keys[name])
                both = marginals.jointMarginalCovariance(kv).fullMatrix()
                J = np.kron(np.eye(2), estimate.poses[name][0])
                intrinsics[name] = (both[:k, :k], both[:k, k:] @ J.T)
            else:
                intrinsics[name] = (marginals.marginalCovariance(key), None)
        return poses, joint, mirrors, points, intrinsics


def scale_prior(dataset: Dataset, mirror_keys: dict, point_keys: dict) -> gtsam.NonlinearFactorGraph:
    """The prior that holds the scale without a known target (module docstring); empty with a target."""
    graph = gtsam.NonlinearFactorGraph()
    scale = dataset.scale
    if scale is not None:
        noise = gtsam.noiseModel.Isotropic.Sigma(1, SCALE_SIGMA * scale.distance)
        if scale.placement is not None:
            graph.add(gtsam.CustomFactor(noise, [mirror_keys[scale.placement]], _distance_error(scale.distance)))
        else:
            a, b = scale.points  # type: ignore[misc]
            graph.add(gtsam.CustomFactor(noise, [point_keys[a], point_keys[b]], _length_error(scale.distance)))
    return graph


def mirror_vector_at(values: gtsam.Values, key: int) -> np.ndarray:
    """The mirror vector ``d n`` of a placement's plane variable in ``values``."""
    return vector_of_plane(values.atOrientedPlane3(key))[0]


def _distance_error(distance: float):
    """A scale factor's error on a plane variable: ``|d| - distance``."""
    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        d = float(values.atOrientedPlane3(this.keys()[0]).distance())
        if jacobians is not None:
            jacobians[0] = np.array([[0.0, 0.0, np.sign(d)]])
        return np.array([abs(d) - distance])
    return error


def _length_error(distance: float):
    """A scale factor's error on two points: ``|a - b| - distance``."""
    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        keys = this.keys()
        diff = np.asarray(values.atPoint3(keys[0]), float) - np.asarray(values.atPoint3(keys[1]), float)
        length = float(np.linalg.norm(diff))
        if jacobians is not None:
            jacobians[0] = (diff / length).reshape(1, 3)
            jacobians[1] = (-diff / length).reshape(1, 3)
        return np.array([length - distance])
    return error


class _GaugeHeld:
    """Covariances with the scale held exactly (module docstring), read like ``gtsam.Marginals``."""

    def __init__(self, problem: ViewProblem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        ordering = gtsam.Ordering()
        self.columns: dict[int, slice] = {}
        start = 0
        for key in [*problem.pose_keys.values(), *problem.mirror_keys.values(), *problem.point_keys.values(),
                    *problem.intrinsics_keys.values()]:
            ordering.push_back(key)
            dim = tangent_dimension(key, values)
            self.columns[key] = slice(start, start + dim)
            start += dim
        A, _ = graph.linearize(values).jacobian(ordering)
        information = A.T @ A
        gradient = np.zeros(start)
        scale = problem.dataset.scale
        assert scale is not None and (scale.placement is not None or scale.points is not None)
        if scale.placement is not None:
            d = float(values.atOrientedPlane3(problem.mirror_keys[scale.placement]).distance())
            gradient[self.columns[problem.mirror_keys[scale.placement]]] = [0.0, 0.0, np.sign(d)]
        else:
            assert scale.points is not None
            a, b = (problem.point_keys[n] for n in scale.points)
            diff = np.asarray(values.atPoint3(a), float) - np.asarray(values.atPoint3(b), float)
            gradient[self.columns[a]] = diff / np.linalg.norm(diff)
            gradient[self.columns[b]] = -diff / np.linalg.norm(diff)
        try:
            covariance = np.linalg.inv(information)
        except np.linalg.LinAlgError as error:
            raise RuntimeError(f"indeterminant system: {error}") from None
        along = covariance @ gradient
        self.covariance = covariance - np.outer(along, along) / float(gradient @ along)

    def marginalCovariance(self, key: int) -> np.ndarray:
        c = self.columns[key]
        return self.covariance[c, c].copy()

    def jointMarginalCovariance(self, keys) -> "_Block":
        rows = np.concatenate([np.arange(self.columns[k].start, self.columns[k].stop) for k in keys])
        return _Block(self.covariance[np.ix_(rows, rows)])


class _Block:
    def __init__(self, matrix: np.ndarray):
        self.matrix = matrix

    def fullMatrix(self) -> np.ndarray:
        return self.matrix


def tangent_dimension(key: int, values: gtsam.Values | None = None) -> int:
    """The tangent dimension of an unknown by its key: a camera pose ``X`` 6, a plane ``V`` or a point ``L``
    3, an intrinsics vector ``K`` its length in ``values``."""
    symbol = chr(gtsam.Symbol(key).chr())
    if symbol == "x":
        return 6
    if symbol == "k":
        assert values is not None, "an intrinsics vector's dimension is its value's length"
        return len(values.atVector(key))
    return 3

def points_of(dataset: Dataset, camera: Camera | None, names: list[str], point_keys: dict[str, int]):
    """A view's sigmas (2, N) (normalized with ``camera``, else pixels), base points (3, N) (NaN where a
    reconstruction point) and point keys (-1 for a fiducial; ``point_keys`` the others') of the points
    ``names``."""
    sigmas = normalized_sigmas(camera, dataset.pixel_sigma, dataset.point_sigma, names).T
    base = np.full((3, len(names)), np.nan)
    landmarks = []
    for k, name in enumerate(names):
        if name in dataset.fiducials:
            base[:, k] = dataset.fiducials[name]
            landmarks.append(-1)
        else:
            landmarks.append(point_keys[name])
    return sigmas, base, landmarks
