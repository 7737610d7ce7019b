"""OpenCV's fisheye (equidistant) camera model: normalisation, forward projection, files, calibration.

The reference is ``cv2.fisheye.projectPoints`` (3D points -> pixels), independent of the
``cv2.fisheye.undistortPoints`` / ``distortPoints`` pair that :class:`mirror_fg.core.camera.Camera` uses.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from mirror_fg import calibrate
from mirror_fg.core.camera import Camera, camera_from_dict, camera_to_dict, check_camera
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.camera_files import camera_from_file
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.data import Dataset
from mirror_fg.simulate.tree import simulate_base_case

DIST = (0.08, -0.03, 0.01, -0.002)  # k1..k4: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)
FISHEYE = {"model": "fisheye", "width": 1024, "height": 768, "fx": 800.0, "fy": 801.5, "cx": 511.2, "cy": 383.9,
           "dist": list(DIST)}


def rays(n: int, max_angle_deg: float, seed: int = 0) -> np.ndarray:
    """``n`` 3D points (camera frame) at angles up to ``max_angle_deg`` from the optical axis, 0.2-5 m away."""
    rng = np.random.default_rng(seed)
    theta = np.radians(max_angle_deg) * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    direction = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    return direction * rng.uniform(0.2, 5.0, (n, 1))


def reference_pixels(camera: Camera, points: np.ndarray) -> np.ndarray:
    pixels, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K,
                                          np.array(camera.dist))
    return pixels.reshape(-1, 2)


def test_normalize_inverts_cv2_fisheye_projectPoints():
    camera = camera_from_dict(FISHEYE, "camera")
    assert camera.model == "fisheye" and camera.dist == DIST
    points = rays(2000, 80.0)
    pixels = reference_pixels(camera, points)
    normalized = camera.normalize(pixels)
    expected = points[:, :2] / points[:, 2:]
    # relative: at 80 degrees a normalized coordinate is ~5.7 and the ray's angle is what the pixel fixes
    np.testing.assert_allclose(normalized, expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(camera.distort(expected), pixels, rtol=0, atol=1e-9)
    np.testing.assert_allclose(camera.distort(normalized), pixels, rtol=0, atol=1e-9)


def test_fisheye_differs_from_pinhole_and_is_not_silently_pinhole():
    fisheye = camera_from_dict(FISHEYE, "camera")
    pinhole = camera_from_dict({**FISHEYE, "model": "pinhole", "dist": [0.0] * 5}, "camera")
    z = np.array([[0.5, -0.3]])
    assert np.linalg.norm(fisheye.distort(z) - pinhole.distort(z)) > 10.0
    centre = np.array([[FISHEYE["cx"], FISHEYE["cy"]]])
    np.testing.assert_allclose(fisheye.normalize(centre), [[0.0, 0.0]], atol=1e-15)


def test_a_pixel_beyond_the_fisheye_field_of_view_is_refused_by_name():
    # k1 < 0 strongly: theta_d peaks below the image corner, whose pixels then have no ray
    d = {"format": "mirror-fg/dataset@1", "num_mirrors": 1, "pixel_sigma": 1.0,
         "camera": {**FISHEYE, "fx": 200.0, "fy": 200.0, "dist": [-0.5, 0.0, 0.0, 0.0]},
         "fiducials": {"F0": [0, 0, 0], "F1": [0.1, 0, 0], "F2": [0, 0.1, 0]},
         "images": [{"id": "a", "mirror_configs": [0], "observations": {"F0": [510, 380], "F1": [1020, 760]}}]}
    assert np.isnan(camera_from_dict(d["camera"], "c").normalize(np.array([[1020.0, 760.0]]))).all()
    with pytest.raises(DatasetError, match=r"image 'a': point 'F1' .* cannot be undistorted with the fisheye"):
        dataset_from_dict(d)


def test_camera_object_checks_the_fisheye_model():
    assert check_camera({k: v for k, v in FISHEYE.items() if k != "dist"}, "c")["dist"] == [0.0] * 4
    assert camera_to_dict(camera_from_dict(FISHEYE, "c")) == {**FISHEYE, "dist": list(DIST)}
    for dist in ([0.0] * 5, [0.0] * 3, [0.1, 0.2, float("nan"), 0.0]):
        with pytest.raises(DatasetError, match="fisheye camera must be 4 finite numbers"):
            check_camera({**FISHEYE, "dist": dist}, "c")
    with pytest.raises(DatasetError, match="p1 and p2 are not terms of the fisheye model"):
        check_camera({**FISHEYE, "estimate": ["fx", "p1"]}, "c")
    with pytest.raises(DatasetError, match="unsupported model 'omni'"):
        check_camera({**FISHEYE, "model": "omni"}, "c")
    # the default stays the pinhole model, and a pinhole Camera built by position is unchanged
    assert Camera(1024, 768, 800.0, 800.0, 512.0, 384.0).model == "pinhole"
    assert camera_from_dict({k: v for k, v in FISHEYE.items() if k not in ("model", "dist")}, "c").dist == (0.0,) * 5


def test_kalibr_equidistant_and_ros_equidistant_files_read_as_fisheye(tmp_path):
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0], "distortion_model": "equidistant",
        "distortion_coeffs": list(DIST), "resolution": [640, 480]}}))
    c = camera_from_file(str(tmp_path / "camchain.yaml"), None, "cam")
    assert (c["model"], c["dist"], c["fx"], c["width"]) == ("fisheye", list(DIST), 400.0, 640)
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump({
        "image_width": 640, "image_height": 480, "distortion_model": "equidistant",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [400.0, 0, 320.0, 0, 401.0, 240.0, 0, 0, 1]},
        "distortion_coefficients": {"rows": 1, "cols": 4, "data": list(DIST)}}))
    assert camera_from_file(str(tmp_path / "ros.yaml"), None, "cam")["model"] == "fisheye"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0], "distortion_model": "equidistant",
        "distortion_coeffs": [0.1, 0.0, 0.0, 0.0, 0.0], "resolution": [640, 480]}}))
    with pytest.raises(DatasetError, match=r"equidistant distortion_coeffs must be \[k1, k2, k3, k4\]"):
        camera_from_file(str(tmp_path / "bad.yaml"), None, "cam")
    (tmp_path / "fov.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0], "distortion_model": "fov",
        "distortion_coeffs": [0.9], "resolution": [640, 480]}}))
    with pytest.raises(DatasetError, match="distortion_model 'fov' is not supported"):
        camera_from_file(str(tmp_path / "fov.yaml"), None, "cam")
    (tmp_path / "ros_fov.yaml").write_text((tmp_path / "ros.yaml").read_text().replace("equidistant", "fov"))
    with pytest.raises(DatasetError, match="distortion_model 'fov' is not supported"):
        camera_from_file(str(tmp_path / "ros_fov.yaml"), None, "cam")


def fisheye_twin(ds: Dataset, camera: Camera) -> tuple[Dataset, Dataset]:
    """The same measurements as pixels of ``camera`` (fisheye) and as normalized coordinates."""
    pixels, normalized = [], []
    for image in ds.images:
        z = ds.normalized(image)
        names = list(z)
        uv = camera.distort(np.array([z[n] for n in names]))
        pixels.append({"id": image.id, "mirror_configs": list(image.mirror_configs),
                       "observations": {n: uv[i].tolist() for i, n in enumerate(names)}})
        normalized.append({"id": image.id, "mirror_configs": list(image.mirror_configs),
                           "observations": {n: z[n].tolist() for n in names}})
    common = {"format": "mirror-fg/dataset@1", "num_mirrors": ds.num_mirrors,
              "fiducials": {n: p.tolist() for n, p in ds.fiducials.items()}}
    assert camera.fx == camera.fy
    fish = dataset_from_dict({**common, "camera": camera_to_dict(camera), "pixel_sigma": ds.pixel_sigma,
                              "images": pixels}, source="fisheye")
    norm = dataset_from_dict({**common, "camera": None, "pixel_sigma": ds.pixel_sigma / camera.fx,
                              "images": normalized}, source="normalized")
    return fish, norm


def test_simulated_fisheye_dataset_calibrates_like_its_normalized_twin():
    ds, truth = simulate_base_case(num_images=60, num_points=3, pixel_sigma=1.0, seed=3)
    camera = camera_from_dict({**FISHEYE, "fy": 800.0}, "camera")
    fish, norm = fisheye_twin(ds, camera)
    # the pixels really are fisheye pixels: cv2.fisheye.projectPoints of the reflected points agrees
    image = fish.images[0]
    z = norm.images[0].observations
    np.testing.assert_allclose(
        np.array(list(image.observations.values())),
        reference_pixels(camera, np.array([[*z[n], 1.0] for n in image.observations])), atol=1e-9)
    fish = dataset_from_dict(dataset_to_dict(fish), source="fisheye")  # through the file format
    assert fish.camera is not None and fish.camera.model == "fisheye"
    cal_fish, cal_norm = calibrate(fish), calibrate(norm)
    np.testing.assert_allclose(cal_fish.t_cam_base, cal_norm.t_cam_base, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cal_fish.R_cam_base, cal_norm.R_cam_base, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cal_fish.covariance, cal_norm.covariance, rtol=1e-6, atol=0)
    for name in cal_norm.points:
        np.testing.assert_allclose(cal_fish.points[name], cal_norm.points[name], rtol=0, atol=1e-9)
    assert "fisheye 1024x768" in repr(fish)
    # and near the truth (1 px noise)
    assert np.linalg.norm(cal_fish.t_cam_base - truth.t_cam_base) < 0.05

