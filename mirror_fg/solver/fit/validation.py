"""Held-out validation: does each image fit where the others and the bounds say it should?

docs/formats.md, "The answer in the user's units". Each image (up to :data:`MAX_IMAGES`, sampled evenly)
is held out in turn: every unknown is re-estimated without it by one Gauss-Newton step from the full
solution, then the image is fitted with only the unknowns that no other image sees left free (its own
mirror placements); its whitened residual cost ``c`` (all of its measurements, also those the solve left
out) is compared with what it should be given the re-estimated unknowns' covariance, ``E[c] = k + tr(A
P A^T)`` (``k`` the image's rows less its own unknowns, ``A`` its Jacobian on the shared unknowns with its
own unknowns projected out, ``P`` their held-out covariance). The image's ratio is ``sqrt(c / E[c])``
(as ``Calibration.fit_ratio``: an RMS whitened residual over what the model allows), about 1 when the
noise model and the bounds hold; the summary is the RMS of the ratios.

How (linear algebra on the linearised graph, no re-solve): every image's factor of the general view model
(``factors/views.py``; the paper's tree is one of its cases) is linearised at the solution and whitened,
rows ``r + J dx``. The unknowns seen by one image only are projected out of its rows (``V^T``, ``V`` an
orthonormal basis of the complement of their columns), leaving rows ``(A, b)`` on the shared unknowns.
Their information is ``S = sum A^T A`` (+ priors), ``Sigma = S^-1`` the full solution's covariance. Holding
image ``i`` out is the rank-downdate ``S - A_a^T A_a`` (``a``: its rows the solve used); with ``M_xy = A_x
Sigma A_y^T`` (Woodbury), the held-out image's predicted rows are ``e = b_f + M_fa (I - M_aa)^-1 b_a`` and
``E[c] = k_f + tr(M_ff) + tr(M_fa (I - M_aa)^-1 M_af)`` (``f``: all its rows), where ``b`` are taken after
one Gauss-Newton step of the full system (zero where the solution is the optimum). An image whose
removal leaves an unknown undetermined (``I - M_aa`` singular) cannot be held out and is listed.
Measurements in normalized coordinates (pixels where intrinsics are estimated), whitened by their sigma.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from mirror_fg.data import Dataset, Image
from mirror_fg.solver.model.views import SINGLE_CAMERA, ViewEstimate, ViewProblem, camera_names, tangent_dimension

__all__ = ["MAX_IMAGES", "Validation", "validate", "validate_calibration", "validate_result_file", "image_ratios",
           "estimate_of_calibration", "estimate_of_result"]

#: Images held out at most (sampled evenly in file order beyond it).
MAX_IMAGES = 200
#: ``I - M_aa`` with an eigenvalue below this: the others alone leave an unknown undetermined.
_SINGULAR = 1e-9


@dataclass(frozen=True)
class Validation:
    """Per held-out image (file order): ``images`` ids, ``ratios`` ``sqrt(cost / expected)``, ``costs``
    (whitened residual cost, chi^2) and ``expected`` (its expected value); ``not_held_out``: images whose
    removal leaves an unknown undetermined."""

    images: tuple[str, ...]
    ratios: np.ndarray
    costs: np.ndarray
    expected: np.ndarray
    not_held_out: tuple[str, ...] = ()

    @property
    def ratio(self) -> float:
        """The RMS of the images' ratios (1 when the noise model and the bounds hold); NaN without images."""
        return float(np.sqrt(np.mean(self.ratios ** 2))) if len(self.ratios) else float("nan")

    @property
    def worst(self) -> tuple[str, float] | None:
        """``(image id, ratio)`` of the image farthest above what the model predicts."""
        if not len(self.ratios):
            return None
        k = int(np.argmax(self.ratios))
        return self.images[k], float(self.ratios[k])

    def to_dict(self) -> dict[str, Any]:
        """result@1's ``validation`` (docs/formats.md)."""
        worst = self.worst
        out: dict[str, Any] = {"images": len(self.images), "ratio": self.ratio,
                               "worst": None if worst is None else {"image": worst[0], "ratio": worst[1]}}
        if self.not_held_out:
            out["not_held_out"] = list(self.not_held_out)
        return out


def sampled(count: int, limit: int = MAX_IMAGES) -> list[int]:
    """Indices of ``count`` images to hold out: all, or ``limit`` evenly spread."""
    if count <= limit:
        return list(range(count))
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, limit)})


def estimate_of_calibration(calibration: Any) -> tuple[ViewEstimate, dict[str, Any]]:
    """The estimate of a :class:`~mirror_fg.solver.result.calibration.Calibration` as the view model's values, and
    ``{camera: Camera}`` of the cameras whose intrinsics it estimated (as estimated)."""
    estimated: dict[str, Any] = {}
    if calibration.cameras:
        poses = {n: (np.asarray(c.R_cam_base, float), np.asarray(c.t_cam_base, float))
                 for n, c in calibration.cameras.items()}
        estimated = {n: c.estimated.camera for n, c in calibration.cameras.items() if c.estimated is not None}
    else:
        poses = {SINGLE_CAMERA: (np.asarray(calibration.R_cam_base, float), np.asarray(calibration.t_cam_base, float))}
        if calibration.camera is not None:
            estimated = {SINGLE_CAMERA: calibration.camera.camera}
    estimate = ViewEstimate(poses, {p: np.asarray(v, float) for p, v in calibration.mirror_vectors.items()},
                            {n: np.asarray(x, float) for n, x in calibration.points.items()})
    return estimate, estimated


def estimate_of_result(result: Mapping[str, Any], dataset: Dataset) -> tuple[ViewEstimate, dict[str, Any]]:
    """The same from a validated result@1 dictionary (and the dataset it came from, for camera models)."""
    from mirror_fg.io.result import estimated_camera, mirror_vectors, points, pose

    estimated: dict[str, Any] = {}
    if result.get("cameras"):
        poses = {n: pose(c["T_cam_base"]) for n, c in result["cameras"].items()}
        for name, entry in result["cameras"].items():
            block = entry.get("camera") or {}
            if block.get("estimated") and dataset.cameras is not None and name in dataset.cameras:
                estimated[name] = estimated_camera(entry, f"cameras.{name}", dataset.cameras[name])
    else:
        poses = {SINGLE_CAMERA: pose(result["T_cam_base"])}
        camera = estimated_camera(result, "result", dataset.camera)
        if camera is not None:
            estimated = {SINGLE_CAMERA: camera}
    return ViewEstimate(poses, mirror_vectors(result), {n: xyz for n, (xyz, _) in points(result).items()}), estimated


def validate_calibration(dataset: Dataset, calibration: Any, limit: int = MAX_IMAGES) -> Validation:
    """:func:`validate` of a calibration of ``dataset`` (``calibrate --validate``)."""
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded]
    return validate(dataset, estimate, excluded, estimated, limit)


def validate_result_file(dataset: Dataset, result: Mapping[str, Any], limit: int = MAX_IMAGES) -> Validation:
    """:func:`validate` of a validated result@1 dictionary of ``dataset`` (the report)."""
    estimate, estimated = estimate_of_result(result, dataset)
    excluded = [(e["image"], e.get("point")) for e in result.get("excluded") or []]
    return validate(dataset, estimate, excluded, estimated, limit)


def validate(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
             estimated_cameras: Mapping[str, Any] | None = None, limit: int = MAX_IMAGES) -> Validation:
    """Hold each image out in turn (module docstring). ``estimate``: the full solution (mirror vectors in
    their owner cameras' frames, points in {B}); ``excluded``: ``(image, point or None)`` the solve left
    out (a whole image is not held out: it was not used; a point is, in its image's cost);
    ``estimated_cameras``: ``{camera: Camera as estimated}`` where intrinsics were estimated."""
    ids, cost_list, expected_list, skipped = image_ratios(dataset, estimate, excluded, estimated_cameras, limit)
    costs, expected = np.asarray(cost_list, float), np.asarray(expected_list, float)
    ratios = np.sqrt(costs / expected) if len(costs) else np.zeros(0)
    return Validation(tuple(ids), ratios, costs, expected, tuple(skipped))


def used_images(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]]) -> Dataset:
    """``dataset`` with the images the solve used: not left out whole, every placement estimated, each with
    its measurements of known points (fiducials and estimated points) that it has (any)."""
    images_out = {image_id for image_id, point in excluded if point is None}
    known = set(dataset.fiducials) | set(estimate.points)
    images: list[Image] = []
    for image in dataset.images:
        if image.id in images_out or not all(p in estimate.mirror_vectors for p in image.reflections):
            continue
        observations = {n: z for n, z in image.observations.items() if n in known}
        if observations:
            images.append(replace(image, observations=observations) if len(observations) < len(image.observations)
                          else image)
    return replace(dataset, images=images)


def _problem(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
             estimated_cameras: Mapping[str, Any] | None):
    """The view model of the images the solve used, with every measurement of theses images; its values at
    ``estimate``, and each image's mask of the rows the solve used."""
    from mirror_fg.factors.intrinsics import IntrinsicsModel
    from mirror_fg.solver.batch.intrinsics import camera_intrinsics

    used = used_images(dataset, estimate, excluded)
    points_out: dict[str, set[str]] = {}
    for image_id, point in excluded:
        if point is not None:
            points_out.setdefault(image_id, set()).add(point)
    models: dict[str, IntrinsicsModel] = {}
    theta: dict[str, np.ndarray] = {}
    given = dataset.cameras if dataset.cameras is not None else {SINGLE_CAMERA: dataset.camera}
    for name, camera in (estimated_cameras or {}).items():
        start = given.get(name)
        if start is not None and start.estimate:
            models[name] = IntrinsicsModel(camera_intrinsics(start), start.estimate)
            theta[name] = camera_intrinsics(camera)
    problem = ViewProblem(used, None, models)
    names = camera_names(used)
    poses = {n: estimate.poses[n] for n in names if n in estimate.poses}
    values = problem.values(ViewEstimate(poses, estimate.mirror_vectors, estimate.points, theta or None))
    masks = []
    for used_image, view in zip(used.images, problem.views):
        out = points_out.get(used_image.id, set())
        masks.append(np.repeat([n not in out for n in view.names], 2))
    return used, problem, values, masks


def _complement(J_local: np.ndarray, rows: int) -> np.ndarray:
    """An orthonormal basis (rows, k) of the complement of ``J_local``'s column space (all rows if none)."""
    if J_local.shape[1] == 0 or rows == 0:
        return np.eye(rows)
    U, s, _ = np.linalg.svd(J_local, full_matrices=True)
    rank = int(np.sum(s > max(s[0], 1e-300) * 1e-10)) if len(s) else 0
    return U[:, rank:]


def image_ratios(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
                 estimated_cameras: Mapping[str, Any] | None = None, limit: int = MAX_IMAGES
                 ) -> tuple[list[str], list[float], list[float], list[str]]:
    """``(image ids, costs, expected costs, images not held out)`` of the held-out images (module docstring)."""
    used, problem, values, masks = _problem(dataset, estimate, excluded, estimated_cameras)
    linear = []  # per image: keys, column blocks, whitened J (rows, cols), whitened error r
    touches: dict[int, int] = {}
    for factor in problem.factors:
        gaussian = factor.factor().linearize(values)
        A, b = gaussian.jacobian()
        keys = list(gaussian.keys())
        linear.append((keys, A, -b))
        for key in keys:
            touches[key] = touches.get(key, 0) + 1
    graph = problem.graph(stacked=False)  # one factor per image, then the priors
    priors = [graph.at(k) for k in range(len(problem.factors), graph.size())]
    for prior in priors:  # a prior's keys are shared whatever sees them
        for key in prior.keys():
            touches[key] = touches.get(key, 0) + 2
    dims = {key: tangent_dimension(key, values) for key in touches}
    shared = [key for key in touches if touches[key] > 1]
    offset: dict[int, int] = {}
    size = 0
    for key in shared:
        offset[key] = size
        size += dims[key]
    information = np.zeros((size, size))
    gradient = np.zeros(size)
    reduced = []  # per image: shared columns (global indices), (A_f, b_f), (A_a, b_a)
    for (keys, J, r), mask in zip(linear, masks):
        local_cols, shared_cols, index = [], [], []
        column = 0
        for key in keys:
            cols = list(range(column, column + dims[key]))
            if key in offset:
                shared_cols += cols
                index += list(range(offset[key], offset[key] + dims[key]))
            else:
                local_cols += cols
            column += dims[key]
        V_f = _complement(J[:, local_cols], J.shape[0])
        J_a, r_a = J[mask], r[mask]
        V_a = _complement(J_a[:, local_cols], J_a.shape[0])
        A_f, b_f = V_f.T @ J[:, shared_cols], V_f.T @ r
        A_a, b_a = V_a.T @ J_a[:, shared_cols], V_a.T @ r_a
        information[np.ix_(index, index)] += A_a.T @ A_a
        gradient[index] += A_a.T @ b_a
        reduced.append((np.array(index, dtype=int), A_f, b_f, A_a, b_a))  # index: global columns
    for prior in priors:
        gaussian = prior.linearize(values)
        A, b = gaussian.jacobian()
        columns = [i for key in gaussian.keys() for i in range(offset[key], offset[key] + dims[key])]
        information[np.ix_(columns, columns)] += A.T @ A
        gradient[columns] += A.T @ (-b)
    covariance = np.linalg.pinv(information, hermitian=True) if size else np.zeros((0, 0))
    step = -covariance @ gradient  # one Gauss-Newton step of the full system: its optimum
    ids, costs, expected, skipped = [], [], [], []
    for k in sampled(len(used.images), limit):
        at, A_f, b_f, A_a, b_a = reduced[k]
        image_id = used.images[k].id
        Sigma = covariance[np.ix_(at, at)]
        b_f = b_f + A_f @ step[at]
        b_a = b_a + A_a @ step[at]
        M_aa, M_fa, M_ff = A_a @ Sigma @ A_a.T, A_f @ Sigma @ A_a.T, A_f @ Sigma @ A_f.T
        W = np.eye(len(b_a)) - M_aa
        if len(b_a) and np.min(np.linalg.eigvalsh(0.5 * (W + W.T))) < _SINGULAR:
            skipped.append(image_id)
            continue
        e = b_f + M_fa @ np.linalg.solve(W, b_a) if len(b_a) else b_f
        trace = float(np.trace(M_ff)) + (float(np.trace(M_fa @ np.linalg.solve(W, M_fa.T))) if len(b_a) else 0.0)
        if len(b_f) == 0:  # its own unknowns absorb every row: nothing to compare
            skipped.append(image_id)
            continue
        ids.append(image_id)
        costs.append(float(e @ e))
        expected.append(len(b_f) + trace)
    return ids, costs, expected, skipped
