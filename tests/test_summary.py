"""mirror_fg.tools.summary: each transform with its own bounds in its own frame, one RMS (issue 17)."""
from __future__ import annotations

import copy
import re

import numpy as np
import pytest

import mirror_fg
from mirror_fg.io.result import base_cam_covariance
from mirror_fg.tools.simulate import simulate_base_case
from mirror_fg.tools.summary import MAX_OUTLIER_LINES, summary_lines


@pytest.fixture(scope="module")
def result() -> dict:
    ds, _ = simulate_base_case(num_images=30, num_points=1, seed=5)
    return mirror_fg.calibrate(ds).to_dict()


def _numbers(line: str, after: str) -> list[float]:
    """The bracketed numbers after ``after`` in ``line``."""
    match = re.search(re.escape(after) + r"\s*±?\[([^\]]*)\]", line)
    assert match, (after, line)
    return [float(x) for x in match.group(1).split(",")]


def _block(lines: list[str], title: str) -> list[str]:
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].startswith("  ")), len(lines))
    return lines[start:end]


def test_each_transform_has_its_own_bounds_in_its_own_frame(result):
    lines = summary_lines(result)
    base = _block(lines, "T_base_cam")
    cam = _block(lines, "T_cam_base")
    P = np.array(result["covariance_cam_base"])
    R, t = np.array(result["T_cam_base"]["R"]), np.array(result["T_cam_base"]["t"])
    sd3_bc = 3.0 * np.sqrt(np.diag(base_cam_covariance(R, t, P)))  # checked against GTSAM in test_base_cam_covariance
    sd3_cb = 3.0 * np.sqrt(np.diag(P))
    (b,) = [line for line in base if "3-sigma bounds" in line]
    (c,) = [line for line in cam if "3-sigma bounds" in line]
    assert "base axes" in b and "camera axes" in c
    assert np.allclose(_numbers(b, "camera position"), 1e3 * sd3_bc[3:], atol=0.006)
    assert np.allclose(_numbers(b, "rotation"), np.rad2deg(sd3_bc[:3]), atol=6e-4)
    assert np.allclose(_numbers(c, "base origin"), 1e3 * sd3_cb[3:], atol=0.006)
    assert np.allclose(_numbers(c, "rotation"), np.rad2deg(sd3_cb[:3]), atol=6e-4)
    assert np.allclose(_numbers(_block(lines, "T_base_cam")[4], "t"), result["T_base_cam"]["t"], atol=6e-6)
    assert any("x right, y down, z forward" in line for line in lines)


def test_one_rms_definition(result):
    lines = summary_lines(result, verbose=True)
    text = "\n".join(lines)
    assert len(re.findall(r"\bRMS\b", text)) == 1
    (line,) = [line for line in lines if line.startswith("residuals:")]
    assert f"RMS {result['residuals']['rms_px']:.3f} px" in line and "√2·σ" in line
    assert f"mean length {result['residuals']['mean_px']:.3f} px" in line
    assert f"largest {result['residuals']['max_px']:.3f} px" in line
    assert re.search(r"optimizer: \d+ LM iterations, converged", text)
    assert "warning" not in text
    assert "iSAM2 updates" in "\n".join(summary_lines(result, incremental=True))


def test_implausible_cost_warns(result):
    bad = copy.deepcopy(result)
    bad["optimizer"]["final_error"] = 10.0 * bad["optimizer"]["expected_final_error"]
    assert any(line.startswith("warning: final cost") for line in summary_lines(bad))


def test_outliers_listed_and_bounded(result):
    bad = copy.deepcopy(result)
    bad["residuals"]["outliers"] = [{"image": f"img{k}", "point": "F0", "sigmas": 6.0 + k} for k in range(30)]
    lines = summary_lines(bad)
    assert "30 measurement(s) above 5 σ after the solve:" in lines
    assert sum(1 for line in lines if line.startswith("  image ")) == MAX_OUTLIER_LINES
    assert any("10 more" in line for line in lines)
    assert sum(1 for line in summary_lines(bad, verbose=True) if line.startswith("  image ")) == 30


def test_without_covariance_and_older_results(result):
    bare = copy.deepcopy(result)
    for key in ("covariance_cam_base", "sigma3_cam_base", "covariance_base_cam", "sigma3_base_cam",
                "covariance_base_cam_ros"):
        bare[key] = None
    assert sum("not computed" in line for line in summary_lines(bare)) == 2
    older = copy.deepcopy(result)  # written before sigma3_base_cam: computed from covariance_cam_base
    for key in ("covariance_base_cam", "sigma3_base_cam", "covariance_base_cam_ros"):
        del older[key]
    assert summary_lines(older) == summary_lines(result)
    normalized = copy.deepcopy(result)
    normalized["residuals"]["units"] = "normalized"
    assert "(normalized)" in "\n".join(summary_lines(normalized))
