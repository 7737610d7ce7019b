"""`mirror-fg plan` says its bounds as calibrate does: T_base_cam (the camera's pose on the robot) about and
along the base axes, for the paper's tree and for `--kind`/`--cameras` alike; and it refuses, as calibrate
does, intrinsics that photographs of three fiducials cannot determine."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mirror_fg.cli import main
from mirror_fg.core.geometry import so3_exp
from mirror_fg.core.transform import Transform
from mirror_fg.analysis.plan import plan
from mirror_fg.simulate.tree import simulate_base_case


def _plan(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["plan", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_tree_and_kind_plans_both_print_t_base_cam_in_base_axes(capsys, tmp_path):
    code, tree, _ = _plan(capsys, "--images", "30", "--draws", "1", "--json", str(tmp_path / "p.json"))
    assert code == 0
    assert "T_base_cam  the camera's pose on the robot; bounds about and along the base axes" in tree
    code, kind, _ = _plan(capsys, "--kind", "kaleidoscope", "--draws", "1")
    assert code == 0
    assert "T_base_cam is each camera's pose on the robot, its bounds about and along the base axes" in kind
    assert "camera: T_base_cam rotation" in kind
    written = json.loads((tmp_path / "p.json").read_text())
    assert set(written["sigma3_base_cam"]) == {"rotation_deg", "position_mm"}


def test_the_tree_plans_t_base_cam_bounds_are_its_inverse_at_the_truth():
    """The printed T_base_cam bounds are the T_cam_base covariance carried to the base axes at the simulated
    truth (Transform.inverse_covariance), checked against a first-order propagation by finite differences."""
    result = plan(draws=1, num_images=30, seed=4)
    _, truth = simulate_base_case(num_images=30, pixel_sigma=0.0, mirror_distance=0.5, tilt_deg=30.0,
                                  mirror1_placements=3, seed=4, num_mirrors=2, num_fiducials=3)
    T = Transform(truth.R_cam_base, truth.t_cam_base)

    def inverse_error(delta):  # T_cam_base perturbed by delta = [dtheta, dt] (camera axes) -> T_base_cam error
        R = so3_exp(delta[:3]) @ T.R
        t = T.t + delta[3:]
        R_bc, t_bc = R.T, -R.T @ t
        inv = T.inverse()
        return np.concatenate([_log(R_bc @ inv.R.T), t_bc - inv.t])  # R_true = Exp(dtheta) R, base axes

    J = np.column_stack([(inverse_error(e * 1e-7) - inverse_error(-e * 1e-7)) / 2e-7 for e in np.eye(6)])
    expected = 3.0 * np.sqrt(np.diag(J @ result.pose_covariance @ J.T))
    assert np.allclose(result.sigma3_base_cam_rotation_deg, np.degrees(expected[:3]), rtol=1e-4)
    assert np.allclose(result.sigma3_base_cam_position_mm, 1000.0 * expected[3:], rtol=1e-4)


def _log(R: np.ndarray) -> np.ndarray:
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return w if angle < 1e-12 else w * angle / np.sin(angle)


@pytest.mark.parametrize("fiducials, code", [("3", 3), ("4", 0)])
def test_plan_refuses_intrinsics_that_calibrate_refuses(capsys, fiducials, code):
    status, out, err = _plan(capsys, "--images", "30", "--draws", "1", "--fiducials", fiducials,
                             "--estimate", "fx,fy,cx,cy")
    assert status == code, err
    if code:
        assert "would not determine fx, fy, cx, cy" in err and "calibrate refuses it" in err and not out
    else:
        assert "intrinsics (3-sigma): fx" in out
