"""mirror_fg.report.summary: each transform with its own bounds in its own frame, one RMS."""
from __future__ import annotations

import copy
import re

import numpy as np
import pytest

import mirror_fg
from mirror_fg.io.result import base_cam_covariance
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.report.summary import MAX_OUTLIER_LINES, summary_lines


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


def test_left_out_images_and_a_split_are_printed(result):
    extra = copy.deepcopy(result)
    extra["excluded"] = [{"image": "img3", "point": None, "reason": "PnP reprojection 14.2 px", "sigmas": None},
                         {"image": "img5", "point": "F1", "reason": "above the final check", "sigmas": 9.5}]
    extra["inconsistency"] = {"groups": [["img0"], ["img1"]], "rotation_deg": 3.1, "position_mm": 40.0,
                              "message": "images 0-4 and 5-8 disagree by 3.1° / 40 mm: did the camera or the board move?"}
    lines = summary_lines(extra)
    assert "left out: 1 image(s), 1 measurement(s):" in lines
    assert "  image 'img3': PnP reprojection 14.2 px" in lines
    assert "  image 'img5' point 'F1': above the final check (9.5 σ)" in lines
    assert "warning: images 0-4 and 5-8 disagree by 3.1° / 40 mm: did the camera or the board move?" in lines
    assert not any(line.startswith("left out") for line in summary_lines(result))


def test_estimated_intrinsics_printed_with_bounds_and_pose_correlation(result):
    extra = copy.deepcopy(result)
    P_pose = np.array(result["covariance_cam_base"])
    cross = np.zeros((2, 6))
    cross[0, 5] = -0.9 * np.sqrt(4.0 * P_pose[5, 5])  # fx strongly anti-correlated with tz
    cross[1, 0] = 0.3 * np.sqrt(1e-4 * P_pose[0, 0])
    extra["camera"] = {"model": "pinhole", "width": 800, "height": 600, "fx": 801.5, "fy": 799.0, "cx": 401.0,
                       "cy": 298.0, "dist": [-0.21, 0.0, 0.0, 0.0, 0.0], "estimated": ["fx", "k1"],
                       "sigma3": {"fx": 6.0, "k1": 0.03}, "covariance": [[4.0, 0.0], [0.0, 1e-4]],
                       "cross_covariance_cam_base": cross.tolist()}
    block = _block(summary_lines(extra), "camera intrinsics estimated")
    assert "  fx 801.5 px ± 6 px (3σ)" in block
    assert "  fy 799 px (kept)" in block
    assert "  k1 -0.21 ± 0.03 (3σ)" in block
    assert block[-1] == "  largest correlation with T_cam_base: fx~tz -0.90, k1~θx +0.30"
