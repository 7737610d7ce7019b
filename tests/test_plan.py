"""Experiment planner (mirror_fg.analysis.plan): Cramér-Rao bounds before data, checked against a Monte Carlo."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mirror_fg.solver.information.crb import chi2_quantile, nees, nees_band, pose_error
from mirror_fg.core.errors import DatasetError
from mirror_fg import calibrate
from mirror_fg.analysis.plan import PlanSetup, format_plan, load_fiducials, plan
from mirror_fg.simulate.tree import simulate_base_case


def test_planner_predicts_the_monte_carlo_spread():
    """The MLE's spread over noisy runs of the same setup matches the planner's bounds.

    The planner's draws use the simulator's seeds 0..N-1, the same mirror placements as the Monte
    Carlo runs below, so only the noise differs. The MLE is started from the truth (the global optimum
    of each run) to test the bound alone. Tolerances are chi-square sampling bands for N runs.
    """
    N, images, sigma_px = 40, 30, 0.5
    predicted = plan(draws=N, seed=0, num_images=images, pixel_sigma=sigma_px)
    errors = []
    for seed in range(N):
        dataset, truth = simulate_base_case(num_images=images, pixel_sigma=sigma_px, seed=seed)
        cal = calibrate(dataset, initial=truth, compute_covariance=False)
        errors.append(pose_error(truth.R_cam_base, truth.t_cam_base, cal.R_cam_base, cal.t_cam_base))
    errors = np.array(errors)
    # Pooled over the six axes: mean NEES against each draw's bound, inside the 95 % band.
    lo, hi = nees_band(N)
    mean_nees = float(np.mean(nees(errors, np.array([b.pose_covariance for b in predicted.bounds]))))
    assert lo < mean_nees < hi, (mean_nees, lo, hi)
    # Per axis: the Monte Carlo RMS over the predicted 1-sigma, inside a 99 % band (Bonferroni over 6 axes).
    rms = np.sqrt(np.mean(errors**2, axis=0))
    ratio = rms / np.sqrt(np.diag(predicted.pose_covariance))
    alpha = 0.01 / 6
    band = np.sqrt([chi2_quantile(alpha / 2, N) / N, chi2_quantile(1 - alpha / 2, N) / N])
    assert np.all((band[0] < ratio) & (ratio < band[1])), (ratio, band)
    # 3-sigma bounds as printed are three times the 1-sigma of the same covariance.
    np.testing.assert_allclose(predicted.sigma3_position_mm, 3000 * np.sqrt(np.diag(predicted.pose_covariance))[3:])


def test_bounds_scale_with_pixel_noise_focal_length_and_images():
    base = plan(draws=2, num_images=30)
    doubled = plan(draws=2, num_images=30, pixel_sigma=2.0)
    np.testing.assert_allclose(doubled.sigma3_rotation_deg, 2 * base.sigma3_rotation_deg, rtol=1e-9)
    np.testing.assert_allclose(doubled.sigma3_position_mm, 2 * base.sigma3_position_mm, rtol=1e-9)
    longer_lens = plan(draws=2, num_images=30, focal_px=1600.0)
    np.testing.assert_allclose(longer_lens.sigma3_position_mm, base.sigma3_position_mm / 2, rtol=1e-9)
    more = plan(draws=2, num_images=120)
    assert np.all(more.sigma3_position_mm < base.sigma3_position_mm)
    assert np.all(more.sigma3_rotation_deg < base.sigma3_rotation_deg)
    lo, hi = base.sigma3_position_mm_range
    assert np.all(lo <= hi)


def test_reconstruction_points_and_a_fourth_fiducial_tighten_the_bounds():
    base = plan(draws=2, num_images=30)
    with_points = plan(draws=2, num_images=30, num_points=10)
    assert with_points.point_sigma3_mm_worst is not None and with_points.point_sigma3_mm_worst > 0
    assert base.point_sigma3_mm_worst is None
    assert np.linalg.det(with_points.pose_covariance) < np.linalg.det(base.pose_covariance)
    four = plan(draws=2, num_images=30, num_fiducials=4)
    assert np.linalg.det(four.pose_covariance) < np.linalg.det(base.pose_covariance)


def test_custom_fiducial_layout_and_printout():
    tag = {"C0": [0.0, 0.0, 0.0], "C1": [0.2, 0.0, 0.0], "C2": [0.2, 0.2, 0.0], "C3": [0.0, 0.2, 0.0]}
    result = plan(PlanSetup(num_images=30, fiducials=tag), draws=2)
    assert result.visible_fraction == pytest.approx(1.0)
    text = format_plan(result)
    assert "T_base_cam  the camera's pose on the robot" in text and "4 given fiducials" in text
    assert "weakest" in text and " deg" in text and " mm" in text
    assert json.loads(json.dumps(result.to_dict()))["setup"]["fiducials"]["C2"] == [0.2, 0.2, 0.0]
    far = {name: np.add(p, [3.0, 0.0, 0.0]) for name, p in tag.items()}  # off to the side of the robot
    assert plan(PlanSetup(num_images=30, fiducials=far), draws=1).visible_fraction < 1.0


def test_bad_setups_raise():
    with pytest.raises(ValueError, match="placements"):
        plan(draws=1, placements=2)
    with pytest.raises(ValueError, match="pixel_sigma"):
        plan(draws=1, pixel_sigma=0.0)
    with pytest.raises(ValueError, match="draws"):
        plan(draws=0)
    with pytest.raises(TypeError):
        plan(PlanSetup(), draws=1, num_images=30)


def test_load_fiducials(tmp_path):
    good = tmp_path / "layout.json"
    good.write_text(json.dumps({"fiducials": {"A": [0, 0, 0], "B": [0.1, 0, 0], "C": [0, 0.1, 0]}}))
    assert set(load_fiducials(good)) == {"A", "B", "C"}
    yaml_file = tmp_path / "layout.yaml"
    yaml_file.write_text("A: [0, 0, 0]\nB: [0.1, 0, 0]\nC: [0, 0.1, 0.05]\n")
    np.testing.assert_allclose(load_fiducials(yaml_file)["C"], [0, 0.1, 0.05])
    line = tmp_path / "line.json"
    line.write_text(json.dumps({"A": [0, 0, 0], "B": [0.1, 0, 0], "C": [0.2, 0, 0]}))
    with pytest.raises(DatasetError, match="collinear"):
        load_fiducials(line)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"A": [0, 0], "B": [0.1, 0, 0], "C": [0, 0.1, 0]}))
    with pytest.raises(DatasetError, match=r"bad.json: fiducial 'A'"):
        load_fiducials(bad)
    with pytest.raises(DatasetError, match="cannot read"):
        load_fiducials(tmp_path / "missing.json")
