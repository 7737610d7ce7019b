"""The console's one-line verdict (mirror_fg.tools.summary.verdict_line, issue 27): a pixel_sigma far
from the measurements' real noise is named, with the sigma the residuals fit."""
from __future__ import annotations

import dataclasses
import re

import pytest

import mirror_fg
from mirror_fg.tools.simulate import simulate_base_case
from mirror_fg.tools.summary import summary_lines

NOISE_PX = 0.5  # the simulated measurements' noise


@pytest.fixture(scope="module")
def simulated():
    ds, _ = simulate_base_case(num_images=60, pixel_sigma=NOISE_PX, seed=11)
    return ds


def _verdict(ds, pixel_sigma: float) -> str:
    result = mirror_fg.calibrate(dataclasses.replace(ds, pixel_sigma=pixel_sigma)).to_dict()
    lines = summary_lines(result)
    verdicts = [line for line in lines if line.startswith("verdict:")]
    assert len(verdicts) == 1 and lines[-1] == verdicts[0]
    return verdicts[0]


def _fitted_sigma(line: str) -> float:
    return float(re.search(r"fit σ ≈ ([0-9.]+) px", line).group(1))


def test_the_right_sigma_looks_right(simulated):
    line = _verdict(simulated, NOISE_PX)
    assert line.startswith("verdict: looks right") and "CHECK" not in line


def test_too_large_a_sigma_is_named_with_the_sigma_the_residuals_fit(simulated):
    line = _verdict(simulated, 4 * NOISE_PX)  # RMS about 0.71 px where sqrt(2) * 2 = 2.8 px is expected
    assert line.startswith("verdict: CHECK") and "pixel_sigma 2 px is too large" in line, line
    assert _fitted_sigma(line) == pytest.approx(NOISE_PX, rel=0.1)
    too_wide = float(re.search(r"about ([0-9.]+) × too wide", line).group(1))
    assert too_wide == pytest.approx(4 * NOISE_PX / _fitted_sigma(line), abs=0.1)


def test_too_small_a_sigma_is_named(simulated):
    line = _verdict(simulated, NOISE_PX / 3)
    assert line.startswith("verdict: CHECK") and "what pixel_sigma 0.167 px predicts" in line, line
    assert _fitted_sigma(line) == pytest.approx(NOISE_PX, rel=0.1)


def test_a_robust_solve_is_judged_by_the_datasets_sigma(takahashi_dir, tmp_path, capsys):
    """A robust kernel's cost is below the plain one: the CLI's verdict judges the plain RMS against the
    dataset's pixel_sigma (0.5 px), not a sigma read from that cost."""
    import json
    import math

    from mirror_fg.cli import main

    assert main(["calibrate", str(takahashi_dir / "dataset.json"), "--robust", "cauchy", "-o", str(tmp_path / "r.json")]) == 0
    (line,) = [l for l in capsys.readouterr().out.splitlines() if l.startswith("verdict:")]
    assert "under pixel_sigma 0.5 px" in line, line
    result = json.loads((tmp_path / "r.json").read_text())
    expected, rms = result["optimizer"]["expected_final_error"], result["residuals"]["rms_px"]
    measurements = sum(len(im["observations"]) for im in json.loads((takahashi_dir / "dataset.json").read_text())["images"])
    predicted = 0.5 * math.sqrt(2 * expected / measurements)  # sqrt(2) sigma, one degree of freedom less per unknown
    assert f"residuals {rms / predicted:.2f} ×" in line
