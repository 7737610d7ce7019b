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


def _result(rotation_deg: float, position_mm: float) -> dict:
    """A one-camera result 1 m from the base whose T_base_cam has these 3-sigma bounds."""
    sigma3 = {"rotation_deg": [rotation_deg] * 3, "position_mm": [position_mm] * 3}
    return {"cameras": {"a": {"T_cam_base": {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0.0, 0.0, 1.0]},
                              "sigma3_base_cam": sigma3}}}


@pytest.mark.parametrize("rotation_deg, position_mm, weak", [
    (5.0, 10.0, False), (15.0, 10.0, True),  # beyond about 10 deg a linearised covariance no longer holds
    (1.0, 400.0, False), (1.0, 700.0, True),  # half the 1000 mm scene
])
def test_weak_geometry_bounds(rotation_deg, position_mm, weak):
    from mirror_fg.report.verdict import weak_geometry

    assert (weak_geometry(_result(rotation_deg, position_mm)) is not None) == weak


def _three_placements(expected_final_error: float) -> dict:
    """A one-camera result with three mirror placements (p = 6 + 3 x 3 = 15 unknowns), tight bounds and the
    optimizer's expected final cost (GTSAM's half chi-square: (2N - p) / 2 for N measured points)."""
    import numpy as np

    return {"T_cam_base": {"R": np.eye(3).tolist(), "t": [0.0, 0.0, 1.0]},
            "covariance_cam_base": (1e-10 * np.eye(6)).tolist(),
            "mirrors": [{"mirror": 1, "config": k, "v": [0.0, 0.1 * k, 0.5]} for k in range(3)],
            "optimizer": {"expected_final_error": expected_final_error}}


@pytest.mark.parametrize("points", [9, 10, 40])
def test_too_few_spare_measurements_are_weak_geometry(points):
    """Förstner's mean redundancy (2N - p) / 2N by hand: 10 points give 20 coordinates, 5 spare (0.25, enough);
    9 give 3 spare of 18 (0.17, below 0.2). GTSAM's expected cost is half the spare count."""
    from mirror_fg.report.verdict import MIN_MEAN_REDUNDANCY, weak_geometry

    coordinates, unknowns = 2 * points, 15
    redundancy = (coordinates - unknowns) / coordinates
    found = weak_geometry(_three_placements((coordinates - unknowns) / 2.0))
    assert (found is not None) == (redundancy < MIN_MEAN_REDUNDANCY), found
    if found is not None:
        assert f"only {coordinates - unknowns} spare of {coordinates} measured coordinates" in found
