"""End to end: images -> detect -> calibrate, on the rendered two-mirror scene and the real photographs.

The rendered images are cached in tests/data/capture/rendered/ (scripts/render_scene.py, Mitsuba 3,
regenerates them with truth.json); Mitsuba is not needed here.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import TAKAHASHI, pose_difference
from mirror_fg.io.capture import load_capture
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.vision.detectors import FOUND
from mirror_fg.vision.detect import detect_capture

DATA = Path(__file__).parent / "data" / "capture"
RENDERED = DATA / "rendered"

from mirror_fg import calibrate


@pytest.fixture(scope="module")
def rendered():
    truth = json.loads((RENDERED / "truth.json").read_text())
    cap = load_capture(RENDERED / "capture.yaml")
    ds, reports = detect_capture(cap, progress=False)
    return truth, dataset_to_dict(ds), reports


def test_rendered_tags_detected_within_half_a_pixel_of_truth(rendered):
    truth, d, reports = rendered
    assert [r.status for r in reports] == [FOUND] * len(truth["images"]) == [FOUND] * 9
    errors = []
    for image, expected in zip(d["images"], truth["images"]):
        assert image["id"] == expected["id"]
        assert image["mirror_configs"] == expected["mirror_configs"]  # 'each' -> 0..8 in image order
        assert set(image["observations"]) == set(expected["corners"])  # tag 7 is on the robot, not listed
        errors += [np.linalg.norm(np.subtract(image["observations"][n], uv)) for n, uv in expected["corners"].items()]
    assert len(errors) == 9 * 12
    assert np.median(errors) < 0.3 and np.max(errors) < 0.5, (np.median(errors), np.max(errors))
    fiducials = d["fiducials"]
    assert len(fiducials) == 12 and "T7_0" not in fiducials


def test_rendered_detect_calibrate_recovers_the_camera_within_3_sigma(rendered):
    truth, d, _ = rendered
    cal = calibrate(dataset_from_dict(d, source="rendered"))
    R_true = np.array(truth["T_cam_base"]["R"])
    t_true = np.array(truth["T_cam_base"]["t"])
    error = pose_difference(cal.R_cam_base, cal.t_cam_base, R_true, t_true)  # R_true = Exp(dtheta) R_est
    bound = 3 * np.sqrt(np.diag(cal.covariance))
    assert np.all(np.abs(error) <= bound), (error, bound)
    assert np.all(bound[:3] < np.radians(10)) and np.all(bound[3:] < 0.2)  # the scene constrains it


@pytest.mark.skipif(not TAKAHASHI.is_dir(), reason="examples/takahashi2012 missing")
def test_takahashi_photographs_detect_calibrate_land_on_published_optimum():
    ds, _ = detect_capture(load_capture(DATA / "takahashi.yaml"), progress=False)
    cal = calibrate(dataset_from_dict(dataset_to_dict(ds), source="takahashi.yaml"))
    R_pub = np.array([[-0.59533, -0.02049, 0.80322], [0.02015, 0.99898, 0.04042], [-0.80323, 0.04025, -0.59431]])
    t_pub = np.array([340.55, 11.66, 354.54]) / 1000.0
    np.testing.assert_allclose(cal.t_cam_base, t_pub, atol=0.5e-3)  # published to 0.01 mm; ours within 0.02 mm
    np.testing.assert_allclose(cal.R_cam_base, R_pub, atol=2e-4)


def test_cached_truth_is_the_render_script_geometry():
    """truth.json matches scripts/render_scene.py's scene (its geometry needs no Mitsuba)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("render_scene", DATA.parent.parent.parent / "scripts" / "render_scene.py")
    scene = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scene)
    truth = json.loads((RENDERED / "truth.json").read_text())
    camera = truth["camera"]
    assert camera == scene.camera_model(camera["width"], camera["height"], 50.0)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1.0]])
    R, t, mirror1, mirror2 = scene.scene_truth()
    np.testing.assert_allclose(truth["T_cam_base"]["R"], R, atol=1e-12)
    np.testing.assert_allclose(truth["T_cam_base"]["t"], t, atol=1e-12)
    _, tags, listed = scene.robot()
    corners = {n: p for n, p in scene.tag_corners_base(tags).items() if int(n[1:].split("_")[0]) in listed}
    for image in truth["images"]:
        i, j = image["mirror_configs"][0], image["mirror_configs"][1] % 3
        expected = scene.project_two_mirror(K, R, t, mirror1[i], mirror2[i][j], corners, (camera["width"], camera["height"]))
        assert expected.keys() == image["corners"].keys()
        for name, uv in expected.items():
            np.testing.assert_allclose(image["corners"][name], uv, atol=1e-9)
