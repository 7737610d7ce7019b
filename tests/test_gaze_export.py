"""``mirror-fg export RESULT --to FORMAT`` (``mirror_fg.io.gaze_export``): each file read back the way its tool
reads it (OpenCV FileStorage for OpenGaze and ETH-XGaze, ``pickle.load`` for few_shot_gaze's demo), the pose
equal to the result's, and each tool's conventions (millimetres, which way the rotation maps) checked with
a port of the tool's own code that uses the file (OpenGaze's ``readScreenConfiguration``/``mapToDisplay``,
few_shot_gaze's ``monitor.monitor_to_camera``)."""
from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import load_script
from mirror_fg import calibrate
from mirror_fg.core.camera import Camera
from mirror_fg.core.screen import Screen
from mirror_fg.core.transform import Transform
from mirror_fg.data import Dataset, Image
from mirror_fg.io.result import load_result, result_text
from mirror_fg.io.screen_result import screen_block
from mirror_fg.io.screen_target import screen_target_from_dict

SCREEN_PX = (1920, 1080)


def run_cli(*args: str, cwd: Path) -> int:
    from mirror_fg.cli import main

    here = os.getcwd()
    try:
        os.chdir(cwd)
        return main([*args, "-q"])
    except SystemExit as stop:
        return int(stop.code)
    finally:
        os.chdir(here)


@pytest.fixture(scope="module")
def screen_result(tmp_path_factory):
    """A calibrated screen (the simulated 24-inch monitor of scripts/render_screen.py, its pattern's corners
    through six mirrors with 0.3 px noise) written as result.json, and the Screen it holds."""
    render = load_script("render_screen")
    from mirror_fg.vision.pattern import design_pattern, screen_mm_from_diagonal

    mm = screen_mm_from_diagonal(*SCREEN_PX, 24.0)
    target = screen_target_from_dict(design_pattern(*SCREEN_PX, *mm).to_dict(), "test")
    R, t = render.webcam_above(mm[0] / 1000)
    fiducials = target.target_points()
    names = list(fiducials)
    rng = np.random.default_rng(4)
    images = []
    for k, mirror in enumerate(render.placements(R, t, mm[0] / 1000, mm[1] / 1000)):
        pixels = render.project(render.screen_homography(R, t, mirror), np.array([fiducials[n][:2] for n in names]))
        images.append(Image(id=f"m{k}", mirror_configs=(k,), observations=dict(zip(names, pixels + rng.normal(0, 0.3, pixels.shape)))))
    camera = Camera(*(render.WEBCAM[k] for k in ("width", "height", "fx", "fy", "cx", "cy")))
    result = calibrate(Dataset(1, camera, 0.3, fiducials, images, source="sim")).to_dict()
    result["screen"] = screen_block(target, result)
    folder = tmp_path_factory.mktemp("export")
    (folder / "result.json").write_text(result_text(result, "result.json"))
    loaded = load_result(folder / "result.json")
    return {"folder": folder, "result": loaded, "screen": Screen.from_result(loaded), "webcam": render.WEBCAM}


def _pixels() -> np.ndarray:
    return np.array([[0.0, 0.0], [960.5, 540.5], [1919.5, 1079.5], [123.25, 987.75]])


def test_opengaze_file_is_read_by_filestorage_as_opengaze_reads_it(screen_result):
    folder, screen = screen_result["folder"], screen_result["screen"]
    assert run_cli("export", "result.json", "--to", "opengaze", "-o", "monitor.yml", cwd=folder) == 0
    text = (folder / "monitor.yml").read_text()
    assert text.startswith("%YAML:1.0\n#") and "---" not in text  # the header of OpenGaze's own monitor files
    fs = cv2.FileStorage(str(folder / "monitor.yml"), cv2.FILE_STORAGE_READ)
    W, H = fs.getNode("monitor_W").real(), fs.getNode("monitor_H").real()
    R, T = fs.getNode("monitor_R").mat(), fs.getNode("monitor_T").mat()
    fs.release()
    # CV_32F, as OpenGaze multiplies them with Vec3f: the result's pose rounded to float32, exactly
    assert R.dtype == np.float32 and T.dtype == np.float32 and T.shape == (3, 1)
    np.testing.assert_array_equal(R, screen.T_cam_screen.R.astype(np.float32))
    np.testing.assert_array_equal(T.ravel(), (1000.0 * screen.T_cam_screen.t).astype(np.float32))
    assert (W, H) == (screen.width_mm, screen.height_mm)
    # readScreenConfiguration: corners (0,0), (W,0), (0,H), (W,H) mm -> R c + T: the screen's corners in mm
    ours = 1000.0 * screen.corners_cam  # top-left, top-right, bottom-right, bottom-left
    for corner, expected in zip(([0, 0, 0], [W, 0, 0], [0, H, 0], [W, H, 0]), ours[[0, 1, 3, 2]]):
        np.testing.assert_allclose((R @ np.float32(corner)[:, None] + T).ravel(), expected, atol=1e-3)  # float32
    # mapToDisplay (with its plane intersection): a gaze from an eye at a screen point lands on it, as the
    # fraction of the monitor's width and height: the pixel over the screen's pixels
    eye = screen.camera_point([960.0, 540.0]) * 1000.0 + 600.0 * screen.normal_cam
    normal = R.astype(float) @ np.array([0.0, 0.0, 1.0])
    for pixel in _pixels():
        gaze = 1000.0 * screen.camera_point(pixel) - eye
        length = normal @ (ours[0] - eye) / (normal @ gaze)
        on_monitor = np.linalg.inv(R.astype(float)) @ (eye + length * gaze - T.ravel())
        np.testing.assert_allclose(on_monitor[:2] / [W, H], pixel / SCREEN_PX, atol=1e-6)


def test_opengaze_conventions_are_those_of_its_own_example_file(screen_result):
    """OpenGaze's example ``content/calib/monitor_laptop.yml`` (as copied in zkf1997/GazeEstimator; a 310 x 174 mm
    laptop screen under its webcam): ``monitor_R``
    about diag(-1, 1, -1) and ``monitor_T`` [149.9, 29.6, -18.9] mm, the top-left corner about W / 2 to the
    camera's right and below it. The simulated webcam sits centred above its screen too: same signs, and
    ``monitor_T`` is in millimetres."""
    screen = screen_result["screen"]
    R, T_mm = screen.T_cam_screen.R, 1000.0 * screen.T_cam_screen.t
    np.testing.assert_allclose(np.sign(np.diag(R)), [-1, 1, -1])
    assert abs(T_mm[0] - screen.width_mm / 2) < 20 and 0 < T_mm[1] < 60


def test_eth_xgaze_file_gives_screen_points_in_camera_millimetres(screen_result):
    folder, screen = screen_result["folder"], screen_result["screen"]
    assert run_cli("export", "result.json", "--to", "eth-xgaze", "-o", "mirror_position.xml", cwd=folder) == 0
    fs = cv2.FileStorage(str(folder / "mirror_position.xml"), cv2.FILE_STORAGE_READ)
    R, t_mm = fs.getNode("screen_rotation").mat(), fs.getNode("screen_translation").mat()
    pix2mm = fs.getNode("pix2mm").mat().ravel()
    fs.release()
    np.testing.assert_allclose(R, screen.T_cam_screen.R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(t_mm.ravel(), 1000.0 * screen.T_cam_screen.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pix2mm, [screen.width_mm / 1920, screen.height_mm / 1080], rtol=1e-12)
    for pixel in _pixels():
        np.testing.assert_allclose(R @ np.array([pixel[0] * pix2mm[0], pixel[1] * pix2mm[1], 0.0]) + t_mm.ravel(),
                                   1000.0 * screen.camera_point(pixel), rtol=0, atol=1e-9)


def _few_shot_monitor_to_camera(calib: dict, x_pixel: float, y_pixel: float) -> np.ndarray:
    """docs/gaze_guide.md's replacement of few_shot_gaze's ``monitor.monitor_to_camera``."""
    s = np.array([x_pixel * calib["w_mm"] / calib["w_pixels"], y_pixel * calib["h_mm"] / calib["h_pixels"], 0.0])
    return calib["monitor_R"] @ s + calib["monitor_T"]


def test_few_shot_gaze_pickle_is_read_by_the_demos_loader(screen_result, tmp_path):
    folder, screen = screen_result["folder"], screen_result["screen"]
    camera_file = tmp_path / "webcam.yaml"
    webcam = screen_result["webcam"]
    camera_file.write_text(f"image_width: 640\nimage_height: 480\ncamera_matrix: {{rows: 3, cols: 3, data: "
                           f"[{webcam['fx']}, 0, {webcam['cx']}, 0, {webcam['fy']}, {webcam['cy']}, 0, 0, 1]}}\n"
                           "distortion_coefficients: {rows: 1, cols: 5, data: [0.01, -0.02, 0, 0, 0]}\n")
    assert run_cli("export", "result.json", "--to", "few-shot-gaze", "-o", "calib_cam0.pkl", "--camera",
                   str(camera_file), cwd=folder) == 0
    raw = (folder / "calib_cam0.pkl").read_bytes()
    assert b"numpy._core" not in raw and b"numpy.core" not in raw  # any NumPy, 1 or 2, reads it
    with open(folder / "calib_cam0.pkl", "rb") as handle:
        calib = pickle.load(handle)  # run_demo.py: cam_calib = pickle.load(open("calib_cam%d.pkl" % cam_idx, "rb"))
    assert isinstance(calib["mtx"], np.ndarray) and calib["mtx"].dtype == np.float64
    assert calib["mtx"].shape == (3, 3) and calib["dist"].shape == (1, 5)
    np.testing.assert_array_equal(calib["mtx"], [[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]])
    np.testing.assert_array_equal(calib["dist"], [[0.01, -0.02, 0, 0, 0]])
    np.testing.assert_allclose(calib["monitor_R"], screen.T_cam_screen.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(calib["monitor_T"], 1000.0 * screen.T_cam_screen.t, rtol=0, atol=1e-9)
    for pixel in _pixels():
        np.testing.assert_allclose(_few_shot_monitor_to_camera(calib, *pixel), 1000.0 * screen.camera_point(pixel),
                                   rtol=0, atol=1e-9)
    # its own file is replaced on a second export; a stranger's is not
    assert run_cli("export", "result.json", "--to", "few-shot-gaze", "-o", "calib_cam0.pkl", cwd=folder) == 0
    (folder / "theirs.pkl").write_bytes(pickle.dumps({"mtx": np.eye(3)}))
    assert run_cli("export", "result.json", "--to", "few-shot-gaze", "-o", "theirs.pkl", cwd=folder) == 2
    # without intrinsics (none in the result, no --camera): the monitor alone; the demo calibrates the camera
    assert run_cli("export", "result.json", "--to", "few-shot-gaze", "-o", "calib_cam1.pkl", cwd=folder) == 0
    with open(folder / "calib_cam1.pkl", "rb") as handle:
        assert "mtx" not in pickle.load(handle)


def test_few_shot_gaze_conventions_are_those_of_its_monitor_module():
    """few_shot_gaze's ``monitor.monitor_to_camera`` assumes a camera centred 10 mm above the screen, in its
    plane: ``x_cam = (w_pixels / 2 - x) / w_pixels * w_mm``, ``y_cam = 10 + y / h_pixels * h_mm``, ``z = 0``
    (mm, OpenCV camera axes). That screen as a result (R = diag(-1, 1, -1), t = (w_mm / 2, 10, 0) mm),
    exported, gives the same points through the file."""
    from mirror_fg.io.gaze_export import export_text

    w_px, h_px, w_mm, h_mm = 1920, 1080, 344.0, 194.0
    R, t = np.diag([-1.0, 1.0, -1.0]), np.array([w_mm / 2, 10.0, 0.0]) / 1000.0
    screen = Screen(w_px, h_px, w_mm, h_mm, Transform(R, t))
    result = {"T_cam_base": {"R": R.tolist(), "t": t.tolist()}, "screen": screen.to_dict()}
    calib = pickle.loads(export_text(result, "few-shot-gaze", "r.json"))
    for x, y in ((0, 0), (960, 540), (1919, 1079), (100, 1000)):
        theirs = [((int(w_px / 2) - x) / w_px) * w_mm, 10.0 + (y / h_px) * h_mm, 0.0]
        np.testing.assert_allclose(_few_shot_monitor_to_camera(calib, x, y), theirs, rtol=0, atol=1e-9)


def test_export_refuses_a_result_without_a_screen_in_one_line(screen_result, tmp_path, capsys):
    result = dict(screen_result["result"])
    del result["screen"]
    (tmp_path / "plain.json").write_text(json.dumps(result))
    for fmt in ("opengaze", "eth-xgaze", "few-shot-gaze"):
        assert run_cli("export", "plain.json", "--to", fmt, "-o", "out.file", cwd=tmp_path) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "plain.json: has no 'screen' block" in err[0], err
    assert not (tmp_path / "out.file").exists()
    assert run_cli("export", "plain.json", "--to", "opengaze", "-o", "plain.json", cwd=tmp_path) == 2  # its input
    assert json.loads((tmp_path / "plain.json").read_text()) == result
