"""The exact factors of factors/view_points.py: ``_rows_of`` (LAPACK's pivoted Cholesky) keeps
``[R | r]^T [R | r]`` equal to a singular positive semidefinite matrix (no shift, no eigendecomposition);
``_own_rows`` with the rest's Schur complement gives back the whole matrix; and the split factors (each
stack's own placements' rows, one shared factor of the rest) solve the same Gauss-Newton and damped steps
as one ``ViewFactor`` per image (the reference linearisation), with the same covariances."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.factors.view_points import ViewPointStack, _diagonal_own_rows, _own_rows, SMALL_EIGEN, _rows_of
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.batch.views_solve import _start
from mirror_fg.solver.model.views import ViewProblem, tangent_dimension
from mirror_fg.solver.options import SolveOptions


def _singular(rows: int, width: int, seed: int = 0) -> np.ndarray:
    """``[J | e]^T [J | e]`` of a random ``J`` (rows, width) whose columns 1 and 4 repeat columns 0 and 2
    (two unknowns the rows leave free), entries spread over six orders of magnitude."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(rows, width)) * np.logspace(0, 3, width)
    J[:, 1] = J[:, 0]
    J[:, 4] = -2.0 * J[:, 2]
    M = np.column_stack([J, rng.normal(size=rows)])
    return M.T @ M


@pytest.mark.parametrize("rows", [40, 9])  # 9 rows for 12 columns: rank 9
def test_rows_of_singular_is_exact(rows):
    normal = _singular(rows, 11)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(normal)  # (the case the factor is for)
    R = _rows_of(normal)
    assert R.shape == normal.shape and R.flags.f_contiguous
    assert np.abs(R.T @ R - normal).max() <= 1e-13 * np.abs(normal).max()
    assert np.linalg.matrix_rank(R) == np.linalg.matrix_rank(normal)


def test_rows_of_reads_the_upper_triangle_and_rejects_non_finite():
    normal = _singular(30, 8)
    upper = np.triu(normal)  # the buffer's layout: the lower triangle not filled
    R = _rows_of(upper)
    assert np.abs(R.T @ R - normal).max() <= 1e-13 * np.abs(normal).max()
    normal[0, 0] = np.nan
    assert np.isnan(_rows_of(normal)).all()


def test_own_rows_and_schur_complement_give_the_whole_matrix():
    """Own columns 0..5 (one of them left free by the rows), the rest 6..12 and e."""
    normal = _singular(14, 12, seed=3)
    own, rest = np.arange(6), np.arange(6, 13)
    rows = _own_rows(normal[np.ix_(own, own)], normal[np.ix_(own, rest)])
    schur = normal[np.ix_(rest, rest)] - rows[:, 6:].T @ rows[:, 6:]
    whole = np.zeros((len(rows) + len(rest), 13))
    whole[:6] = rows
    whole[6:, 6:] = _rows_of(schur)
    assert np.abs(whole.T @ whole - normal).max() <= 1e-12 * np.abs(normal).max()


def _tree(num_images: int, num_points: int, seed: int = 0):
    return simulate_base_case(num_images=num_images, num_points=num_points, mirror1_placements=3, pixel_sigma=1.0,
                              mirror_distance=0.5, tilt_deg=30.0, seed=seed, num_mirrors=2, num_fiducials=3)[0]


def _damped(linear: gtsam.GaussianFactorGraph, values: gtsam.Values, damping: float) -> gtsam.GaussianFactorGraph:
    out = gtsam.GaussianFactorGraph()
    for i in range(linear.size()):
        if linear.at(i) is not None:
            out.push_back(linear.at(i))
    for key in values.keys():
        d = tangent_dimension(key, values)
        out.push_back(gtsam.JacobianFactor(key, np.sqrt(damping) * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    return out


@pytest.mark.parametrize("placements_per_factor", [32, 4])
def test_split_factors_solve_as_the_reference(placements_per_factor):
    """Own placements in factors of their own, the rest shared: Gauss-Newton and LM steps, cost and marginal
    covariances of the views' own linearisation (one ViewFactor per image)."""
    problem = ViewProblem(_tree(24, 6, seed=2))
    values = problem.values(_start(problem, None, SolveOptions()))
    stack = ViewPointStack(problem.factors, placements_per_factor)
    graph, reference = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    for factor in stack.factors:
        graph.add(factor)
    for factor in problem.factors:
        reference.add(factor.factor())
    shared = len(stack.factors) - stack._first_shared
    assert stack._first_shared >= 1 and shared <= len(stack._stack_keys)  # own rows split off, shared merged
    assert graph.error(values) == pytest.approx(reference.error(values), rel=1e-12)
    linear, linear_ref = graph.linearize(values), reference.linearize(values)
    for damping in (0.0, 1e3):
        step = (_damped(linear, values, damping) if damping else linear).optimize()
        step_ref = (_damped(linear_ref, values, damping) if damping else linear_ref).optimize()
        for key in problem.keys:
            assert np.abs(step.at(key) - step_ref.at(key)).max() <= 1e-8 * np.abs(step_ref.at(key)).max() + 1e-15
    marginals, marginals_ref = gtsam.Marginals(graph, values), gtsam.Marginals(reference, values)
    for key in problem.keys:
        a, b = marginals.marginalCovariance(key), marginals_ref.marginalCovariance(key)
        assert np.abs(a - b).max() <= 1e-8 * np.abs(b).max()


def test_diagonal_own_rows_as_the_general_ones():
    """Own placements that share no view (3 x 3 blocks on the diagonal): the same products as _own_rows;
    a block that is not positive definite leaves it to _own_rows."""
    rng = np.random.default_rng(5)
    E, rest = 4, 7
    J = np.zeros((6 * E, 3 * E + rest))  # each placement's 6 rows: its own 3 columns and the rest
    for e in range(E):
        J[6 * e:6 * e + 6, 3 * e:3 * e + 3] = rng.normal(size=(6, 3))
        J[6 * e:6 * e + 6, 3 * E:] = rng.normal(size=(6, rest))
    normal = J.T @ J
    own, others = np.arange(3 * E), np.arange(3 * E, 3 * E + rest)
    N_own, N_cross = normal[np.ix_(own, own)], normal[np.ix_(own, others)]
    rows = _diagonal_own_rows(N_own, N_cross)
    assert rows is not None and rows.flags.f_contiguous
    assert np.abs(rows[:, :3 * E].T @ rows[:, :3 * E] - N_own).max() <= 1e-13 * np.abs(N_own).max()
    assert np.abs(rows[:, :3 * E].T @ rows[:, 3 * E:] - N_cross).max() <= 1e-13 * np.abs(N_cross).max()
    general = _own_rows(N_own, N_cross)
    schur, schur_general = (r[:, 3 * E:].T @ r[:, 3 * E:] for r in (rows, general))
    assert np.abs(schur - schur_general).max() <= 1e-12 * np.abs(schur_general).max()
    N_own[3:6, 3:6] = 0.0  # the second placement left free
    assert _diagonal_own_rows(N_own, N_cross) is None


@pytest.mark.parametrize("size", [SMALL_EIGEN - 1, SMALL_EIGEN + 40])
def test_rows_of_both_routes_are_exact_and_keep_the_rank(size):
    """Small factors by numpy's eigendecomposition, larger ones by LAPACK's pivoted Cholesky: both exact on
    a singular matrix given by its upper triangle, both of its rank."""
    normal = _singular(size - 7, size, seed=5)
    R = _rows_of(np.triu(normal))
    assert np.abs(R.T @ R - normal).max() <= 1e-13 * np.abs(normal).max()
    assert np.linalg.matrix_rank(R) == np.linalg.matrix_rank(normal) == size - 7
