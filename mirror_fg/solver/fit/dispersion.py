"""Image-level dispersion: do the images agree with each other as closely as their noise model says?

docs/formats.md, "Has it moved? `mirror-fg verify`". Each image's measurements determine its virtual
camera (the camera seen through its mirrors: a 6-dof rigid, or with one mirror improper, transform of
the target; Sect. 3 of the paper). A per-image systematic error (a corner detector's bias, distortion the
model lacks) moves that virtual camera without showing in the image's own residuals: its mirror
placement absorbs it, the residuals look right, the pose is biased. What shows it is how far each image
would go on its own: with the image's camera pose and mirror placements free for it alone, its cost falls
by ``c_i = |P_i r_i|^2`` (whitened rows ``r_i`` at the solution, ``P_i`` the projection onto the column
space of its Jacobian on the camera pose and its mirror placements, rank 6 where the image determines its
virtual camera). Under the noise model (linearised) ``B = sum_i c_i`` has expectation
``nu = sum_i rank_i - sum_i tr(Sigma G_i)`` (``G_i = (U_i^T J_i)^T (U_i^T J_i)``, ``U_i`` an orthonormal
basis of that column space, ``J_i`` the image's whole Jacobian, ``Sigma`` the solution's covariance):
``r = (I - H) e`` so ``E[B] = tr(P (I - H))``. For one camera and one mirror, ``nu = 3 n - 6`` (each
image adds 6 conditions, its placement takes 3, the pose 6).

``factor = B / nu`` is the variance factor of the images' virtual cameras: about 1 where the noise model
holds (``nu factor ~ chi2_nu``), larger where the images disagree beyond it. ``mirror-fg verify`` divides
its statistic by it (an F-test: the noise level estimated from the image-level redundancy, the standard
remedy when sigma is not known). ``nu = 0`` (every image needed to determine the solution): no estimate.
Whitened units (each row by its measurement sigma); measurements the solve left out are not counted.

Cost: ``Sigma`` on each image's columns comes from eliminating the columns one image touches and
inverting the rest densely, cubic in the shared unknowns. With more than :data:`MAX_IMAGES` images, or
more than :data:`MAX_DENSE_COLUMNS` shared columns, ``B`` and ``nu`` are summed over
:data:`MAX_IMAGES` images evenly spread through the capture instead, ``Sigma``'s blocks from GTSAM's
marginals (its Bayes tree): the factor is then estimated from those images' redundancy, and ``dof``
and ``images`` say so (an F-test takes that ``dof``). Where every view is a plain Gaussian factor
(intrinsics known, no robust kernel, no scale prior, no single measurement left out), every view is
linearised in one vectorised pass of the view model and the shared columns inverted densely or cluster by
cluster (``view_dispersion.py``), over the same images: the same ``B`` and ``nu`` to rounding.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from mirror_fg.factors.schur import one_blas_thread
from mirror_fg.data import Dataset
from mirror_fg.solver.fit.validation import _problem, estimate_of_calibration, used_images
from mirror_fg.solver.fit.view_dispersion import view_dispersion, view_dispersion_applies
from mirror_fg.solver.model.views import ViewEstimate, ViewProblem, scale_prior, tangent_dimension

__all__ = ["Dispersion", "image_dispersion", "dispersion_of_calibration", "dispersion_of_solve", "MAX_IMAGES", "MAX_DENSE_COLUMNS"]

#: Above this many images the dispersion is summed over this many, evenly spread (module docstring).
MAX_IMAGES = 400
#: Above this many columns shared by several images, likewise (a dense inverse of them is cubic).
MAX_DENSE_COLUMNS = 1500
#: Whether the views are linearised in one vectorised pass where they can be (``view_dispersion.py``); the
#: tests turn it off to compare with GTSAM's factors linearised one by one.
VECTORISED = True


@dataclass(frozen=True)
class Dispersion:
    """``cost``: ``B`` (chi^2 units); ``dof``: ``nu``, its expectation under the noise model; ``images``: how
    many images counted."""

    cost: float
    dof: float
    images: int

    @property
    def factor(self) -> float:
        """``B / nu`` (1 where the noise model holds); NaN where ``nu`` is not positive."""
        return self.cost / self.dof if self.dof > 0.5 else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """result@1's ``dispersion`` (docs/formats.md)."""
        return {"factor": self.factor if self.dof > 0.5 else None, "dof": self.dof, "cost": self.cost,
                "images": self.images}


def dispersion_of_calibration(dataset: Dataset, calibration: Any) -> Dispersion:
    """:func:`image_dispersion` of a calibration of ``dataset`` (stored in its result by ``calibrate``)."""
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded]
    return image_dispersion(dataset, estimate, excluded, estimated)


def image_dispersion(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
                     estimated_cameras: Mapping[str, Any] | None = None) -> Dispersion:
    """``B`` and ``nu`` (module docstring) of ``dataset``'s images at ``estimate``; arguments as
    :func:`~mirror_fg.solver.fit.validation.validate`. Where it can, in one vectorised pass of the view
    model (``view_dispersion.py``: the same ``B`` and ``nu`` to rounding). BLAS on one thread: the
    matrices are small and many (``factors/schur.one_blas_thread``)."""
    with one_blas_thread():
        return _image_dispersion(dataset, estimate, excluded, estimated_cameras)


def _image_dispersion(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
                      estimated_cameras: Mapping[str, Any] | None) -> Dispersion:
    if not estimated_cameras and all(point is None for _, point in excluded):  # every measurement of a view used
        fast = _vectorised(ViewProblem(used_images(dataset, estimate, excluded)), estimate)
        if fast is not None:
            return fast
    used, problem, values, masks = _problem(dataset, estimate, excluded, estimated_cameras)
    if len(problem.factors) > MAX_IMAGES or _shared_columns(problem, values) > MAX_DENSE_COLUMNS:
        if all(mask.all() for mask in masks):  # no measurement left out: this very problem
            return _sampled_from(problem, values)
        return _sampled_dispersion(dataset, estimate, excluded, estimated_cameras)
    return _dense(problem, values, masks)


def dispersion_of_solve(problem: Any, estimate: ViewEstimate) -> Dispersion | None:
    """:func:`image_dispersion` from the general view model's own solve (``views_solve.py``): ``problem`` the
    view problem it solved (the images it kept, every measurement of them used), ``estimate`` its solution,
    without building the problem again; None where that problem is not the dispersion's (a robust kernel
    weighs its factors: :func:`image_dispersion` then builds the Gaussian one)."""
    if problem.robust is not None:
        return None
    with one_blas_thread():
        fast = _vectorised(problem, estimate)
        if fast is not None:
            return fast
        values = problem.values(estimate)
        if len(problem.factors) > MAX_IMAGES or _shared_columns(problem, values) > MAX_DENSE_COLUMNS:
            return _sampled_from(problem, values)
        return _dense(problem, values, [np.ones(2 * len(view.names), dtype=bool) for view in problem.views])


def _vectorised(problem: ViewProblem, estimate: ViewEstimate) -> Dispersion | None:
    """The dispersion in one vectorised pass of the view model (``view_dispersion.py``), where it applies:
    None elsewhere (GTSAM's factors linearised one by one then)."""
    if not VECTORISED or not view_dispersion_applies(problem):
        return None
    fast = view_dispersion(problem, estimate, MAX_IMAGES, MAX_DENSE_COLUMNS)
    return Dispersion(*fast) if fast is not None else None


def _dense(problem: Any, values: gtsam.Values, masks: Sequence[np.ndarray]) -> Dispersion:
    """``B`` and ``nu`` over every image of ``problem`` at ``values`` (``masks``: each image's rows the solve
    used), ``Sigma``'s blocks from :func:`_explained`."""
    graph = problem.graph(stacked=False)  # one factor per view, in order, then the priors
    offset: dict[int, int] = {}
    size = 0
    for key in problem.keys:
        offset[key] = size
        size += tangent_dimension(key, values)
    own_keys = set(problem.pose_keys.values()) | set(problem.mirror_keys.values())
    blocks: list[tuple[np.ndarray, np.ndarray]] = []  # (global columns, information block): H, sparse
    parts = []  # per image: its block's index, U_i^T J_i
    cost = 0.0
    rank_sum = 0
    for factor, mask in zip(problem.factors, masks):
        gaussian = factor.factor().linearize(values)
        A, b = gaussian.jacobian()
        A, r = A[mask], -b[mask]
        columns, own, at = [], [], 0
        for key in gaussian.keys():
            dim = tangent_dimension(key, values)
            columns += list(range(offset[key], offset[key] + dim))
            if key in own_keys:
                own += list(range(at, at + dim))
            at += dim
        blocks.append((np.array(columns, dtype=int), A.T @ A))
        if not own or not len(r):
            continue
        U = _range(A[:, own])
        rank_sum += U.shape[1]
        cost += float(np.sum((U.T @ r) ** 2))
        parts.append((len(blocks) - 1, U.T @ A))
    for k in range(len(problem.factors), graph.size()):  # priors (intrinsics, scale): in Sigma only
        gaussian = graph.at(k).linearize(values)
        A, _ = gaussian.jacobian()
        columns = [i for key in gaussian.keys() for i in range(offset[key], offset[key] + tangent_dimension(key, values))]
        blocks.append((np.array(columns, dtype=int), A.T @ A))
    return Dispersion(cost, max(rank_sum - _explained(blocks, parts, size), 0.0), len(parts))


def _explained(blocks: list[tuple[np.ndarray, np.ndarray]], parts: list[tuple[int, np.ndarray]], size: int) -> float:
    """``sum_i tr(Sigma_cc G_i)`` over each image's columns ``c``, without inverting the whole information:
    the columns only one block touches (a placement one image sees) are eliminated block by block (Schur
    complement), the rest (pose, intrinsics, points, shared placements) inverted densely; ``blocks``: each
    factor's columns and information, ``parts``: an image's block and ``U_i^T J_i``."""
    touches = np.zeros(size, dtype=int)
    for columns, _ in blocks:
        touches[columns] += 1
    shared = np.flatnonzero(touches > 1)
    where = np.full(size, -1)
    where[shared] = np.arange(len(shared))
    H_ss = np.zeros((len(shared), len(shared)))
    eliminated = []  # per block: its shared columns (positions in H_ss), local positions in the block, K, H_ll^-1
    for columns, H in blocks:
        local = touches[columns] == 1
        s_at = where[columns[~local]]
        H_ss[np.ix_(s_at, s_at)] += H[np.ix_(~local, ~local)]
        if not np.any(local):
            eliminated.append((s_at, local, np.zeros((0, len(s_at))), np.zeros((0, 0))))
            continue
        H_ll_inv = np.linalg.pinv(H[np.ix_(local, local)], hermitian=True)
        K = H_ll_inv @ H[np.ix_(local, ~local)]  # H_ll^-1 H_ls
        H_ss[np.ix_(s_at, s_at)] -= H[np.ix_(~local, local)] @ K
        eliminated.append((s_at, local, K, H_ll_inv))
    Sigma_ss = np.linalg.pinv(0.5 * (H_ss + H_ss.T), hermitian=True) if len(shared) else np.zeros((0, 0))
    total = 0.0
    for index, UJ in parts:
        columns = blocks[index][0]
        s_at, local, K, H_ll_inv = eliminated[index]
        S = Sigma_ss[np.ix_(s_at, s_at)]
        Sigma = np.zeros((len(columns), len(columns)))
        Sigma[np.ix_(~local, ~local)] = S
        if np.any(local):
            Sigma[np.ix_(~local, local)] = -S @ K.T
            Sigma[np.ix_(local, ~local)] = -K @ S
            Sigma[np.ix_(local, local)] = H_ll_inv + K @ S @ K.T
        total += float(np.sum((UJ @ Sigma) * UJ))
    return total


def _range(J: np.ndarray) -> np.ndarray:
    """An orthonormal basis of ``J``'s column space."""
    U, s, _ = np.linalg.svd(J, full_matrices=False)
    rank = int(np.sum(s > max(s[0], 1e-300) * 1e-10)) if len(s) else 0  # as validation's complement
    return U[:, :rank]


def _shared_columns(problem, values) -> int:
    """How many tangent columns more than one image's factor touches."""
    touched: dict[int, int] = {}
    for factor in problem.factors:
        for key in factor.keys:  # the view's keys (not its gtsam factor, built again by each route)
            touched[key] = touched.get(key, 0) + 1
    return sum(tangent_dimension(key, values) for key, count in touched.items() if count > 1)


def _sampled_dispersion(dataset: Dataset, estimate: ViewEstimate, excluded: Sequence[tuple[str, str | None]],
                        estimated_cameras: Mapping[str, Any] | None) -> Dispersion:
    """``B`` and ``nu`` over :data:`MAX_IMAGES` images evenly spread, ``Sigma``'s blocks of each from GTSAM's
    marginals of the whole solve (module docstring). The measurements the solve left out are dropped from
    the graph (they carry no information in the solve)."""
    from dataclasses import replace

    points_out: dict[str, set[str]] = {}
    for image_id, point in excluded:
        if point is not None:
            points_out.setdefault(image_id, set()).add(point)
    kept = replace(dataset, images=[replace(image, observations={n: z for n, z in image.observations.items()
                                                                  if n not in points_out.get(image.id, ())})
                                    for image in dataset.images])
    _, problem, values, _ = _problem(kept, estimate, [(i, p) for i, p in excluded if p is None], estimated_cameras)
    return _sampled_from(problem, values)


#: Above this many columns shared by the counted images, their joint marginal is asked image by image
#: (one joint over every shared column would cost more than the small ones).
MAX_JOINT_COLUMNS = 600


def _sampled_from(problem, values) -> Dispersion:
    """:func:`_sampled_dispersion` of a view problem with every measurement used, at ``values``.

    ``Sigma`` on an image's columns: the columns no other factor touches (a placement only this image sees)
    carry only this image's information, so they are eliminated from its own block (Schur complement, as
    :func:`_explained`); the shared ones come from GTSAM's marginals, in one joint over every shared column
    of the counted images (at most :data:`MAX_JOINT_COLUMNS`; else a joint per image)."""
    graph = problem.graph()
    marginals = gtsam.Marginals(graph, values)
    touches: dict[int, int] = {}
    for factor in problem.factors:
        for key in factor.keys:
            touches[key] = touches.get(key, 0) + 1
    priors = scale_prior(problem.dataset, problem.mirror_keys, problem.point_keys)
    for key in [*problem.intrinsics_keys.values(), *(k for i in range(priors.size()) for k in priors.at(i).keys())]:
        touches[key] = touches.get(key, 0) + 1  # a prior's information is not the image's alone
    own_keys = set(problem.pose_keys.values()) | set(problem.mirror_keys.values())
    count = len(problem.factors)
    chosen = sorted(set(np.linspace(0, count - 1, min(MAX_IMAGES, count)).round().astype(int).tolist()))
    linearised = []
    for index in chosen:
        gaussian = problem.factors[index].factor().linearize(values)
        A, b = gaussian.jacobian()
        keys = list(gaussian.keys())
        dims = [tangent_dimension(key, values) for key in keys]
        linearised.append((keys, dims, A, b))
    shared_keys = list(dict.fromkeys(k for keys, _, _, _ in linearised for k in keys if touches.get(k, 0) > 1))
    joint = None
    if sum(tangent_dimension(k, values) for k in shared_keys) <= MAX_JOINT_COLUMNS and shared_keys:
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector(shared_keys))
    cost, rank_sum, explained, images = 0.0, 0, 0.0, 0
    for keys, dims, A, b in linearised:
        starts = np.concatenate([[0], np.cumsum(dims)]).astype(int)
        columns = {key: np.arange(a, z) for key, a, z in zip(keys, starts[:-1], starts[1:])}
        own = [i for key in keys if key in own_keys for i in columns[key]]
        if not own or not len(b):
            continue
        U = _range(A[:, own])
        UJ = U.T @ A
        if joint is None:
            block = marginals.jointMarginalCovariance(gtsam.KeyVector(keys))
            Sigma = np.block([[block.at(k, m) for m in keys] for k in keys])
        else:
            Sigma = _image_covariance(A, keys, columns, joint, [touches.get(k, 0) > 1 for k in keys])
        rank_sum += U.shape[1]
        cost += float(np.sum((U.T @ -b) ** 2))
        explained += float(np.sum((UJ @ Sigma) * UJ))
        images += 1
    return Dispersion(cost, max(rank_sum - explained, 0.0), images)


def _image_covariance(A: np.ndarray, keys: list[int], columns: dict[int, np.ndarray], joint,
                      shared: list[bool]) -> np.ndarray:
    """The marginal covariance on one image's columns: its shared keys' block from ``joint`` (GTSAM's
    joint marginal of every shared key), its own-only columns eliminated from its information ``A^T A``
    (``Sigma_ll = H_ll^-1 + K S K^T``, ``Sigma_ls = -K S``, ``K = H_ll^-1 H_ls``)."""
    s = np.concatenate([columns[k] for k, is_shared in zip(keys, shared) if is_shared] or [np.zeros(0, int)])
    loc = np.concatenate([columns[k] for k, is_shared in zip(keys, shared) if not is_shared] or [np.zeros(0, int)])
    shared_keys = [k for k, is_shared in zip(keys, shared) if is_shared]
    S = np.block([[joint.at(k, m) for m in shared_keys] for k in shared_keys]) if shared_keys else np.zeros((0, 0))
    Sigma = np.zeros((A.shape[1], A.shape[1]))
    Sigma[np.ix_(s, s)] = S
    if len(loc):
        H = A.T @ A
        H_ll_inv = np.linalg.pinv(H[np.ix_(loc, loc)], hermitian=True)
        K = H_ll_inv @ H[np.ix_(loc, s)]
        Sigma[np.ix_(s, loc)] = -S @ K.T
        Sigma[np.ix_(loc, s)] = -K @ S
        Sigma[np.ix_(loc, loc)] = H_ll_inv + K @ S @ K.T
    return Sigma
