"""The one verdict (mirror_fg.report.verdict): a pixel_sigma far from the measurements' real noise is named,
with the sigma the residuals fit; the console, the result and the report say the same."""
from __future__ import annotations

import dataclasses
import re

import pytest

import mirror_fg
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.report.summary import summary_lines

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


def test_the_report_and_its_console_block_say_the_one_verdict(takahashi_dir, tmp_path):
    """A result from the Python API carries no verdict: the report judges it once, and its headline and the
    console summary it shows agree (the headline said "Check before use: ... distortion" while the console
    block said "looks right")."""
    from mirror_fg.report.writer import write_report
    from mirror_fg.report.verdict import judge

    ds = mirror_fg.load_dataset(takahashi_dir / "dataset.json")
    result = mirror_fg.calibrate(ds).to_dict()
    assert "verdict" not in result
    verdict = judge(result, ds)
    paths = write_report(result, ds, tmp_path, progress=False)
    page = paths["html"].read_text(encoding="utf-8")
    headline = re.search(r"<div class='verdict (\w+)'><strong>(.*?)</strong>", page, re.S).group(2)
    assert headline == verdict.headline == "Check before use: residuals grow towards the image edge (distortion)"
    import html

    console = [line.removesuffix("</pre>") for line in html.unescape(page).splitlines() if line.startswith("verdict:")]
    assert console == [verdict.line] and console[0].startswith("verdict: CHECK:") and "distortion" in console[0]


def test_the_noise_band_without_scipy_is_the_chi_square_interval():
    """Where the chi-square's Laurent-Massart bounds lie inside NOISE_BAND, noise_band returns it without
    SciPy's quantiles: the same band as the exact interval at every dof and confidence tried."""
    import math

    import numpy as np
    from scipy.special import chdtri

    from mirror_fg.report.verdict import NOISE_BAND, noise_band

    def exact(dof, confidence):
        tail = (1.0 - confidence) / 2.0
        low = math.sqrt(float(chdtri(dof, 1.0 - tail)) / dof)
        high = math.sqrt(float(chdtri(dof, tail)) / dof)
        return min(low, NOISE_BAND[0]), max(high, NOISE_BAND[1])

    for confidence in (0.9, 0.99, 0.999):
        for dof in [*np.arange(0.25, 60.0, 0.25), *range(60, 20000, 97)]:
            assert noise_band(float(dof), confidence) == exact(float(dof), confidence), (dof, confidence)
