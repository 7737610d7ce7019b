"""The fit test's statistics (mirror_fg.core.fit) against a Monte Carlo of linear least squares: at the
optimum of ``rows`` unit-noise residuals in ``unknowns`` unknowns, ``0.5 chi^2`` has mean ``(rows - unknowns) / 2``."""
import numpy as np
import pytest

from mirror_fg.core.fit import expected_cost, plausible


@pytest.mark.parametrize("rows, unknowns", [(40, 6), (200, 57), (12, 11)])
def test_expected_cost_is_the_mean_optimal_cost_of_a_linear_least_squares(rows, unknowns):
    rng = np.random.default_rng(rows + unknowns)
    A = rng.normal(size=(rows, unknowns))
    x_true = rng.normal(size=unknowns)
    b = (A @ x_true)[:, None] + rng.normal(size=(rows, 20000))  # 20000 trials, one per column
    x, *_ = np.linalg.lstsq(A, b, rcond=None)  # each trial's least-squares optimum
    costs = 0.5 * np.sum((A @ x - b) ** 2, axis=0)
    dof = rows - unknowns
    # the Monte Carlo mean of 0.5 chi^2_dof has standard error sqrt(dof / 2) / sqrt(20000)
    assert abs(np.mean(costs) - expected_cost(rows, unknowns)) < 5 * np.sqrt(dof / 2) / np.sqrt(20000)


def test_no_degrees_of_freedom_left_and_the_minimum_asked_for():
    assert expected_cost(10, 12) == 0.0
    assert expected_cost(10, 10, min_dof=1) == 0.5
    assert expected_cost(30, 10, min_dof=1) == 10.0


def test_plausible_within_ten_spreads_above_the_mean():
    expected = 50.0  # dof 100: spread sqrt(50)
    assert plausible(expected + 9.9 * np.sqrt(expected), expected)
    assert not plausible(expected + 10.1 * np.sqrt(expected), expected)
    assert plausible(0.0, expected)  # a low cost is not a misfit
    assert plausible(9.9, 0.0) and not plausible(10.1, 0.0)  # the spread is at least 1
