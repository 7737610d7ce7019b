"""The noise band against scipy.stats' chi-square quantiles: with few spare measurements it is the two-sided
99 % interval of ``sqrt(chi2_dof / dof)`` (wider than the fixed band), with many the fixed band."""
from __future__ import annotations

import math

import pytest
from scipy import stats

from mirror_fg.report.verdict import NOISE_BAND, noise_band


@pytest.mark.parametrize("dof", [1, 2, 3])
def test_few_spare_measurements_give_the_chi_square_interval(dof):
    low, high = noise_band(dof)
    assert low == pytest.approx(math.sqrt(stats.chi2.ppf(0.005, dof) / dof), rel=1e-9)
    assert high == pytest.approx(math.sqrt(stats.chi2.ppf(0.995, dof) / dof), rel=1e-9)
    assert low < NOISE_BAND[0] and high > NOISE_BAND[1]


def test_many_spare_measurements_give_the_fixed_band():
    assert noise_band(5000) == NOISE_BAND
