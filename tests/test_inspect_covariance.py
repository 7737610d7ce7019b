"""scripts/inspect_covariance.py: standard deviations, correlations, 3-sigma bounds, weakest direction, PNG."""
from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def inspect():
    return load_script("inspect_covariance")


def _result(covariance: np.ndarray) -> dict:
    eye = np.eye(3).tolist()
    transform = {"R": eye, "t": [0.0, 0.0, 0.0], "q_xyzw": [0.0, 0.0, 0.0, 1.0]}
    return {
        "format": "mirror-fg/result@1",
        "T_cam_base": transform,
        "T_base_cam": transform,
        "covariance_cam_base": covariance.tolist(),
        "sigma3_cam_base": {"rotation_deg": [0.0] * 3, "position_mm": [0.0] * 3},
        "mirrors": [{"mirror": 1, "config": 0, "v": [0, 0, -0.5], "sigma3_mm": [1.0, 2.0, 3.0]},
                    {"mirror": 2, "config": 0, "v": [0, 0, 0.5], "sigma3_mm": [4.0, 5.0, 6.5]}],
        "points": {"P1": {"xyz": [0, 0, 0], "sigma3_mm": [1.0, 1.0, 9.25]},
                   "P0": {"xyz": [0, 0, 0], "sigma3_mm": [1.0, 1.0, 2.0]}},
        "optimizer": {"iterations": 4, "initial_error": 1.0, "final_error": 0.5, "converged": True},
        "residuals": {"rms_px": 1.0, "max_px": 3.0},
    }


def _covariance() -> np.ndarray:
    """Rotation about camera y weakest (1 deg), tx-tz correlated -0.8."""
    sigma = np.array([np.radians(0.1), np.radians(1.0), np.radians(0.05), 0.002, 0.001, 0.004])
    rho = np.eye(6)
    rho[3, 5] = rho[5, 3] = -0.8
    return rho * np.outer(sigma, sigma)


def test_report_names_everything(inspect):
    text, weakest = inspect.report(_result(_covariance()))
    assert "1-sigma  rotation [0.1000, 1.0000, 0.0500] deg,  position [2.000, 1.000, 4.000] mm" in text
    assert "3-sigma  rotation [0.3000, 3.0000, 0.1500] deg" in text
    assert "rotation about camera y is the weakest" in text
    assert weakest.shares[1] == pytest.approx(1.0)
    assert "strongly correlated: translation along camera x and translation along camera z (-0.80)" in text
    assert "mirror 2 placement 0: [4.00, 5.00, 6.50]" in text
    assert "least-constrained point: P1 (9.25 mm" in text
    assert text.index("  P0:") < text.index("  P1:")


def test_correlation_and_ellipse(inspect):
    covariance = _covariance()
    rho = inspect.correlation(covariance)
    np.testing.assert_allclose(np.diag(rho), 1.0)
    assert rho[3, 5] == pytest.approx(-0.8)
    block = covariance[np.ix_([3, 5], [3, 5])]
    points = inspect.ellipse(block, scale=3.0)
    # The 3-sigma ellipse's extent along each axis is 3 sigma of that axis.
    np.testing.assert_allclose(np.max(np.abs(points), axis=0), 3 * np.sqrt(np.diag(block)), rtol=1e-3)
    # Every point is at Mahalanobis distance 3.
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", points, np.linalg.inv(block), points), 9.0, rtol=1e-9)


def test_main_writes_png_and_rejects_missing_covariance(inspect, tmp_path, capsys):
    path = tmp_path / "result.json"
    path.write_text(json.dumps(_result(_covariance())))
    assert inspect.main([str(path)]) == 0
    png = tmp_path / "result_covariance.png"
    assert png.exists() and png.stat().st_size > 10_000
    assert "weakest" in capsys.readouterr().out
    no_cov = _result(_covariance())
    no_cov["covariance_cam_base"] = None
    path.write_text(json.dumps(no_cov))
    assert inspect.main([str(path), "-o", str(tmp_path / "x.png")]) == 2
    assert "no covariance_cam_base" in capsys.readouterr().err
