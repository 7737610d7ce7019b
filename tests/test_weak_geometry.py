"""Weak geometry is called by its name where the user meets it (console, result file, report), and the
noise-model check widens with few spare measurements (mirror_fg.report.verdict).

The real photographs (examples/takahashi2012) cut down to three placements of the mirror and three
neighbouring chessboard corners: 18 measurements, 15 unknowns (the pose, three mirror vectors), 3 spare.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mirror_fg.cli import main
from mirror_fg.report.verdict import NOISE_CONFIDENCE, WEAK_GEOMETRY, noise_band

CORNERS = ("C00", "C01", "C10")  # 27.5 mm apart
IMAGES = (2, 3, 4)


def _weak_dataset(takahashi_dir, path, pixel_sigma):
    data = json.loads((takahashi_dir / "dataset.json").read_text())
    data["fiducials"] = {name: data["fiducials"][name] for name in CORNERS}
    data["images"] = [dict(data["images"][i], observations={n: data["images"][i]["observations"][n] for n in CORNERS})
                      for i in IMAGES]
    data["pixel_sigma"] = pixel_sigma
    path.write_text(json.dumps(data))
    return path


def _calibrate(path, out, capsys):
    assert main(["calibrate", str(path), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    (line,) = [line for line in printed.splitlines() if line.startswith("verdict:")]
    return printed, line, json.loads(out.read_text())


@pytest.fixture
def weak(takahashi_dir, tmp_path):
    return _weak_dataset(takahashi_dir, tmp_path / "weak.json", 0.5)


@pytest.mark.parametrize("pixel_sigma", [0.5, 0.2])
def test_three_placements_of_three_corners_are_weak_geometry_on_the_console_and_in_the_result(
        takahashi_dir, tmp_path, capsys, pixel_sigma):
    path = _weak_dataset(takahashi_dir, tmp_path / "weak.json", pixel_sigma)
    printed, line, result = _calibrate(path, tmp_path / "r.json", capsys)
    rotation = max(result["sigma3_base_cam"]["rotation_deg"])
    assert rotation > 10.0, printed  # ±27 deg at 0.5 px, ±11 deg at 0.2 px: far beyond a linearised covariance
    assert line.startswith("verdict: CHECK:") and WEAK_GEOMETRY in line, line
    assert f"±{rotation:.1f} deg" in line and "only 3 spare of 18 measured coordinates" in line
    verdict = result["verdict"]
    assert verdict["level"] == "check" and verdict["console"] == line
    (problem,) = [p for p in verdict["problems"] if p["check"] == "weak_geometry"]
    assert problem["text"].startswith(WEAK_GEOMETRY)


def test_the_report_headline_says_weak_geometry(weak, tmp_path, capsys):
    _, line, result = _calibrate(weak, tmp_path / "r.json", capsys)
    assert main(["report", str(tmp_path / "r.json"), str(weak), "-o", str(tmp_path / "rep")]) == 0
    page = (tmp_path / "rep" / "report.html").read_text(encoding="utf-8")
    headline = re.search(r"<div class='verdict (\w+)'><strong>(.*?)</strong>", page, re.S)
    assert headline.group(1) == "bad" and "weak geometry" in headline.group(2)
    assert headline.group(2) == result["verdict"]["headline"]
    assert "barely determine the answer" in page and "plan --next" in page


def test_the_full_photographs_are_not_weak(takahashi_dir, tmp_path, capsys):
    """The control: all five placements and 70 corners (679 spare measurements, bounds of a few mm)."""
    _, line, result = _calibrate(takahashi_dir / "dataset.json", tmp_path / "r.json", capsys)
    assert "weak geometry" not in line
    assert not any(p["check"] == "weak_geometry" for p in result["verdict"]["problems"])


def test_a_correct_sigma_with_few_spare_measurements_is_not_called_too_large(weak, tmp_path, capsys):
    """With 3 spare measurements the residuals came out at 0.24 × their predicted size: inside the 99 %
    chi-square band for 3 degrees of freedom (0.15-2.07), where the fixed 0.5-2 band called pixel_sigma
    too large."""
    _, line, result = _calibrate(weak, tmp_path / "r.json", capsys)
    ratio = float(re.search(r"residuals ([0-9.]+) × their predicted size", line).group(1))
    assert ratio < 0.5
    assert "too large" not in line and not any(p["check"] == "noise" for p in result["verdict"]["problems"])
    assert "0.15-2.07 × with 3 spare of 18 measured coordinates, 99 % of the time; 15 unknowns" in line


@pytest.mark.parametrize("dof", [1, 3, 5, 10, 30, 100, 1000])
def test_the_noise_band_holds_a_correct_sigma_at_its_stated_rate(dof):
    """Monte Carlo of the statistic: at the optimum chi2 = 2 final cost ~ chi2(dof), and the verdict's ratio is
    sqrt(chi2 / dof). A correct pixel_sigma must fall outside the band at most 1 - NOISE_CONFIDENCE of the
    time (binomial 4-sigma margin on 200,000 draws)."""
    draws = 200_000
    ratio = np.sqrt(np.random.default_rng(dof).chisquare(dof, draws) / dof)
    low, high = noise_band(dof)
    outside = float(np.mean((ratio < low) | (ratio > high)))
    allowed = 1.0 - NOISE_CONFIDENCE
    assert outside <= allowed + 4 * np.sqrt(allowed * (1 - allowed) / draws), (dof, outside, low, high)
    if dof <= 5:  # the fixed band it replaces: a correct sigma outside it 14 % of the time with 3 dof
        assert float(np.mean((ratio < 0.5) | (ratio > 2.0))) > 0.05


def test_the_band_is_the_chi_square_interval_where_that_is_wider():
    from scipy.stats import chi2

    low, high = noise_band(3)
    assert low == pytest.approx(np.sqrt(chi2.ppf(0.005, 3) / 3), rel=1e-9)
    assert high == pytest.approx(np.sqrt(chi2.ppf(0.995, 3) / 3), rel=1e-9)
    assert noise_band(10_000) == (0.5, 2.0)  # never narrower than a factor 2 either way


def test_bounds_that_are_not_numbers_are_never_called_right(takahashi_dir, tmp_path, capsys):
    """A result whose 3-sigma bounds are nan (a degenerate scale) is a CHECK, whatever else it holds."""
    from mirror_fg.report.verdict import judge

    _, _, result = _calibrate(takahashi_dir / "dataset_3p.json", tmp_path / "r.json", capsys)
    result["points"] = {"P0": {"xyz": [0.1, 0.0, 0.5], "sigma3_mm": [float("nan"), 1.0, 1.0]}}
    verdict = judge(result)
    assert verdict.level == "check" and any(p.check == "bounds" for p in verdict.problems), verdict.line
