"""The general view model at the command line and with intrinsics: refusals (exit 2 / 3, one line naming
the camera or file), intrinsics estimated per camera in a kaleidoscope and in a rig."""
from __future__ import annotations

import copy
import json
import subprocess
import sys

import numpy as np
import pytest

import mirror_fg
import views_scenes as scenes


def _cli(tmp_path, *args):
    return subprocess.run([sys.executable, "-c", "import sys; from mirror_fg.cli import main; sys.exit(main())", *args],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)


def test_a_camera_that_cannot_be_started_exits_3_naming_it(tmp_path) -> None:
    data, _ = scenes.rig_two_cameras(0)
    # right keeps only its own placements 5 and 6: two placements, none shared, no direct view
    data["images"] = [im for im in data["images"] if im["camera"] == "left" or im["reflections"][0][1] in (5, 6)]
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    done = _cli(tmp_path, "calibrate", "rig.json", "-o", "r.json")
    assert done.returncode == 3, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "rig.json" in done.stderr and "camera 'right'" in done.stderr
    assert not (tmp_path / "r.json").exists()


def test_plan_next_refuses_data_off_the_tree(tmp_path) -> None:
    data, _ = scenes.kaleidoscope_two_mirrors(0)
    (tmp_path / "k.json").write_text(json.dumps(data))
    done = _cli(tmp_path, "plan", "--next", "k.json")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1 and "plan --kind" in done.stderr


def _pose_sigmas(cal_R, cal_t, R, t, covariance):
    from scipy.spatial.transform import Rotation

    error = np.concatenate([Rotation.from_matrix(R @ cal_R.T).as_rotvec(), t - cal_t])
    return error / np.sqrt(np.diag(covariance))


@pytest.mark.parametrize("case", ["kaleidoscope", "rig"])
def test_intrinsics_estimated_per_camera(case) -> None:
    """fx, fy, cx, cy started 2 % / 8 px off the truth and estimated: each within 4 sigma of the truth,
    the pose too, and its covariance larger than with the intrinsics known."""
    if case == "kaleidoscope":
        data, truth = scenes.kaleidoscope_two_mirrors(1)
        camera, name = data["camera"], None
    else:
        data, truth = scenes.rig_two_cameras(1)
        camera, name = data["cameras"]["right"], "right"
    true = {k: camera[k] for k in ("fx", "fy", "cx", "cy")}
    known = mirror_fg.calibrate(copy.deepcopy(data))
    camera.update(fx=true["fx"] * 1.02, fy=true["fy"] * 0.98, cx=true["cx"] + 8.0, cy=true["cy"] - 8.0,
                  estimate=["fx", "fy", "cx", "cy"])
    cal = mirror_fg.calibrate(data)
    estimated = cal.camera if name is None else cal.cameras[name].estimated
    assert estimated is not None and estimated.estimated == ("fx", "fy", "cx", "cy")
    sigma = np.sqrt(np.diag(estimated.covariance))
    values = np.array([getattr(estimated.camera, k) for k in ("fx", "fy", "cx", "cy")])
    assert np.all(np.abs(values - np.array(list(true.values()))) < 4 * sigma), (values, true, sigma)
    pose = (cal.R_cam_base, cal.t_cam_base, cal.covariance) if name is None else (
        cal.cameras[name].R_cam_base, cal.cameras[name].t_cam_base, cal.cameras[name].covariance)
    key = "camera" if name is None else name
    assert np.all(np.abs(_pose_sigmas(pose[0], pose[1], *truth.T_cam_base[key], pose[2])) < 4)
    before = known.covariance if name is None else known.cameras[name].covariance
    assert np.all(np.diag(pose[2]) > np.diag(before) * 0.999)
    assert cal.fit_ratio < 1.5 and cal.converged


def test_rig_camera_that_estimates_intrinsics_gets_its_camera_info_and_refuses_incremental(tmp_path) -> None:
    import yaml

    data, _ = scenes.rig_two_cameras(1)
    camera = data["cameras"]["right"]
    camera.update(fx=camera["fx"] * 1.01, estimate=["fx", "fy", "cx", "cy"])
    (tmp_path / "rig.json").write_text(json.dumps(data))
    refused = _cli(tmp_path, "calibrate", "rig.json", "-o", "r.json", "--incremental")
    assert refused.returncode == 2 and "batch" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    with pytest.raises(mirror_fg.DatasetError, match="batch"):
        mirror_fg.IncrementalCalibrator(mirror_fg.dataset_from_dict(data))
    done = _cli(tmp_path, "calibrate", "rig.json", "-o", "r.json")
    assert done.returncode == 0, done.stderr
    info = yaml.safe_load((tmp_path / "r.right.camera_info.yaml").read_text())
    result = json.loads((tmp_path / "r.json").read_text())
    block = result["cameras"]["right"]["camera"]
    assert info["camera_matrix"]["data"][0] == pytest.approx(block["fx"]) and block["estimated"] == ["fx", "fy", "cx", "cy"]
    assert not (tmp_path / "r.left.camera_info.yaml").exists()  # left estimated nothing
