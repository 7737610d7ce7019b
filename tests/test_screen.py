"""Screens: ``mirror-fg pattern``, target kind ``screen``, the result's ``screen`` block, gaze rays.

The end-to-end test draws the pattern with ``mirror-fg pattern``, shows it on a simulated 24-inch monitor
and photographs it with the 640 x 480 webcam above the monitor through a hand-held mirror in six
placements (scripts/render_screen.py: its own homography renderer of the screen's pixels through the
reflected camera, display gamma, a finite mirror, blur, sRGB, noise); ``mirror-fg calibrate`` then
detects and calibrates, and the true camera-to-screen transform must lie within the reported 3 sigma.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import load_script, pose_difference
from mirror_fg.core.screen import Screen
from mirror_fg.core.transform import Transform
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.result import load_result, validate_result
from mirror_fg.io.target import target_from_dict
from mirror_fg.vision.detectors import FOUND, NOT_FOUND, detect_charuco

SCREEN_PX = (1920, 1080)
DIAGONAL_IN = 24.0
#: Pixel noise given to the solver: about twice the corners' measured error on these renders
#: (test_screen_corners_are_detected_sub_pixel_through_the_mirror measures it).
PIXEL_SIGMA = 0.12


def run_cli(*args: str, cwd: Path) -> int:
    """``mirror-fg ARGS`` run in ``cwd`` (in this process: the command's own parser, runner and exit status)."""
    from mirror_fg.cli import main

    here = os.getcwd()
    try:
        os.chdir(cwd)
        return main([*args, "-q"])
    except SystemExit as stop:  # argparse's usage errors
        return int(stop.code)
    finally:
        os.chdir(here)


def diagonal_mm(diagonal_in: float, w: int, h: int) -> tuple[float, float]:
    """Independent of vision.pattern: a w:h rectangle whose diagonal is diagonal_in inches."""
    d = diagonal_in * 25.4
    height = d / math.sqrt(1 + (w / h) ** 2)
    return height * w / h, height


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The pattern (drawn by the CLI), six photographs through the mirror, the capture file and the truth."""
    render = load_script("render_screen")
    folder = tmp_path_factory.mktemp("screen")
    assert run_cli("pattern", "--screen", f"{SCREEN_PX[0]}x{SCREEN_PX[1]}", "--diagonal", str(DIAGONAL_IN),
                   "-o", "pattern.png", cwd=folder) == 0
    target_block = yaml.safe_load((folder / "pattern.target.yaml").read_text())
    png = cv2.imread(str(folder / "pattern.png"), cv2.IMREAD_UNCHANGED)
    mm = (target_block["width_mm"], target_block["height_mm"])
    R, t = render.webcam_above(mm[0] / 1000)
    mirrors = render.placements(R, t, mm[0] / 1000, mm[1] / 1000)
    rng = np.random.default_rng(26)
    target = target_from_dict(target_block, "test")
    fiducials = target.target_points()
    images, truth_pixels = [], []
    for k, mirror in enumerate(mirrors):
        cv2.imwrite(str(folder / f"mirror{k}.png"), render.render(png, mm, R, t, mirror, rng))
        images.append({"file": f"mirror{k}.png", "mirror_configs": [k]})
        H = render.screen_homography(R, t, mirror)
        names = list(fiducials)
        truth_pixels.append(dict(zip(names, render.project(H, np.array([fiducials[n][:2] for n in names])))))
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": render.WEBCAM,
               "pixel_sigma": PIXEL_SIGMA, "target": target_block, "images": images}
    (folder / "capture.yaml").write_text(yaml.safe_dump(capture, sort_keys=False))
    return {"folder": folder, "R": R, "t": t, "png": png, "target": target, "truth_pixels": truth_pixels,
            "block": target_block}


@pytest.fixture(scope="module")
def calibrated(scene):
    assert run_cli("calibrate", "capture.yaml", "-o", "result.json", cwd=scene["folder"]) == 0
    return load_result(scene["folder"] / "result.json")


# --- mirror-fg pattern ------------------------------------------------------------------------------


def test_pattern_has_exactly_the_screens_pixels_and_its_target_describes_them(scene):
    png, target, block = scene["png"], scene["target"], scene["block"]
    assert png.shape == (SCREEN_PX[1], SCREEN_PX[0]) and png.dtype == np.uint8
    assert block["kind"] == "screen" and (block["width_px"], block["height_px"]) == SCREEN_PX
    np.testing.assert_allclose([block["width_mm"], block["height_mm"]], diagonal_mm(DIAGONAL_IN, *SCREEN_PX), rtol=1e-12)
    assert block["pattern"]["kind"] == "charuco"
    # OpenCV finds every ChArUco corner of the PNG itself (a direct view: not mirrored), and each lies at
    # the pixel-edge coordinates the target gives (OpenCV's pixel centres are at edge + 0.5).
    det = detect_charuco(png, target.pattern_target, mirrored=False)
    assert det.status == FOUND
    edges = target.fiducial_pixels()
    assert set(det.points) == set(edges)
    for name, p in det.points.items():
        assert np.linalg.norm(p + 0.5 - edges[name]) < 0.05, (name, p, edges[name])
    # ... which is a corner of four squares: two black, two white across it
    for name, (u, v) in edges.items():
        u, v = int(u), int(v)
        assert png[v - 1, u - 1] == png[v, u] != png[v - 1, u] == png[v, u - 1], name
    # the screen frame: metres from pixel-edge coordinates, x right, y down
    mx, my = block["width_mm"] / 1000 / SCREEN_PX[0], block["height_mm"] / 1000 / SCREEN_PX[1]
    for name, p in target.target_points().items():
        np.testing.assert_allclose(p, [edges[name][0] * mx, edges[name][1] * my, 0.0], atol=1e-15)
    # a quiet white border: no dark pixel within half a square of the screen's edge
    border = int(block["pattern"]["square_px"] // 2)
    assert png[:border].min() == png[-border:].min() == png[:, :border].min() == png[:, -border:].min() == 255


def test_pattern_page_shows_it_at_device_pixels(scene):
    page = (scene["folder"] / "pattern.html").read_text()
    assert 'src="pattern.png"' in page and "devicePixelRatio" in page and "1920" in page and "1080" in page


@pytest.mark.parametrize("kind", ["chessboard", "apriltag"])
def test_other_pattern_kinds_are_found_where_their_target_says(tmp_path, kind):
    assert run_cli("pattern", "--screen", "1366x768", "--screen-mm", "293.4x164.9", "--kind", kind, "-o", "p.png",
                   cwd=tmp_path) == 0
    target = target_from_dict(yaml.safe_load((tmp_path / "p.target.yaml").read_text()), "test")
    png = cv2.imread(str(tmp_path / "p.png"), cv2.IMREAD_GRAYSCALE)
    assert png.shape == (768, 1366)
    from mirror_fg.vision.detectors import detect_chessboard, detect_tags

    pattern = target.pattern_target
    det = detect_chessboard(png, pattern, False) if kind == "chessboard" else detect_tags(png, pattern, False)
    assert det.status == FOUND
    edges = target.fiducial_pixels()
    assert set(det.points) == set(edges)
    off = max(np.linalg.norm(p + 0.5 - edges[n]) for n, p in det.points.items())
    assert off < 0.6, off  # chessboard saddles are exact; tag corners within the refinement's reach


@pytest.mark.parametrize(
    "args, words",
    [
        (["--screen", "1920x1080", "--screen-mm", "0x296.5"], "more than 0 mm"),
        (["--screen", "1920x1080", "--screen-mm", "527x0"], "more than 0 mm"),
        (["--screen", "0x1080", "--diagonal", "24"], "at least 1 x 1 pixels"),
        (["--screen", "48x32", "--screen-mm", "10x7"], "does not fit on the 48 x 32 screen"),
        (["--screen", "1920x1080", "--screen-mm", "527x296.5", "--square-mm", "200"], "does not fit"),
        (["--screen", "1920x1080", "--diagonal", "0"], "--diagonal"),
        (["--screen", "3840x2160", "--diagonal", "32", "--square-mm", "3"], "more than DICT_4X4_1000 has (1000)"),
        (["--screen", "1920x1080", "--screen-mm", "527x296.5", "-o", "p.jpg"], "ending in .png"),
    ],
)
def test_pattern_refuses_impossible_sizes_in_one_line(tmp_path, capsys, args, words):
    if "-o" not in args:
        args = args + ["-o", "p.png"]
    assert run_cli("pattern", *args, cwd=tmp_path) == 2
    stderr = capsys.readouterr().err
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in stderr, stderr
    assert not list(tmp_path.iterdir())  # nothing written


def test_screen_target_refuses_a_pattern_off_the_screen(scene):
    block = json.loads(json.dumps(scene["block"]))
    block["pattern"]["origin_px"] = [900.0, 102.0]
    with pytest.raises(DatasetError, match="do not fit on the 1920 x 1080 screen"):
        target_from_dict(block, "cap.yaml")
    block = json.loads(json.dumps(scene["block"]))
    block["width_mm"] = 0
    with pytest.raises(DatasetError, match="cap.yaml: target: width_mm must be a number > 0"):
        target_from_dict(block, "cap.yaml")


# --- detection and calibration through the mirror ---------------------------------------------------


def test_screen_corners_are_detected_sub_pixel_through_the_mirror(scene):
    from mirror_fg.io.capture import load_capture
    from mirror_fg.vision.detect import detect_capture

    ds, reports = detect_capture(load_capture(scene["folder"] / "capture.yaml"), progress=False)
    assert [r.status for r in reports] == [FOUND] * 6
    errors = np.array([np.linalg.norm(image.observations[n] - truth[n])
                       for image, truth in zip(ds.images, scene["truth_pixels"]) for n in image.observations])
    rms = float(np.sqrt(np.mean(errors**2) / 2))
    print(f"{len(errors)} corners: median {np.median(errors):.3f} px, max {errors.max():.3f} px, RMS per axis {rms:.3f} px")
    assert rms < PIXEL_SIGMA and errors.max() < 5 * PIXEL_SIGMA * math.sqrt(2)
    # fiducials are the screen frame's: the dataset's are the target's
    for name, p in scene["target"].target_points().items():
        if name in ds.fiducials:
            np.testing.assert_allclose(ds.fiducials[name], p)


def test_mirror_imaged_photographs_need_the_flip(scene):
    gray = cv2.imread(str(scene["folder"] / "mirror0.png"), cv2.IMREAD_GRAYSCALE)
    pattern = scene["target"].pattern_target
    assert detect_charuco(gray, pattern, mirrored=False).status == NOT_FOUND
    assert detect_charuco(gray, pattern, mirrored=True).status == FOUND


def test_calibration_has_the_true_camera_to_screen_transform_within_3_sigma(scene, calibrated):
    R, t = np.array(calibrated["T_cam_base"]["R"]), np.array(calibrated["T_cam_base"]["t"])
    error = pose_difference(scene["R"], scene["t"], R, t)
    bound = 3 * np.sqrt(np.diag(np.array(calibrated["covariance_cam_base"])))
    print(f"error / sigma {np.round(3 * error / bound, 2)}; 3-sigma {np.degrees(bound[:3]).round(3)} deg, "
          f"{(1000 * bound[3:]).round(2)} mm")
    assert np.all(np.abs(error) <= bound), (error, bound)
    assert np.all(bound[3:] < 0.02) and np.all(bound[:3] < np.radians(1.5))  # the scene constrains it


def test_screen_block_corners_are_those_of_T_cam_base(scene, calibrated):
    block = calibrated["screen"]
    assert (block["width_px"], block["height_px"]) == SCREEN_PX
    R, t = np.array(calibrated["T_cam_base"]["R"]), np.array(calibrated["T_cam_base"]["t"])
    w, h = block["width_mm"] / 1000, block["height_mm"] / 1000
    expected = np.array([R @ c + t for c in ([0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0])])
    np.testing.assert_allclose(block["corners_cam"], expected, atol=1e-12)
    normal = np.array(block["normal_cam"])
    assert normal @ (-t) > 0  # towards the viewer: the camera (in front of the screen) is on that side
    np.testing.assert_allclose(normal, -R[:, 2], atol=1e-12)
    # the true corners lie within each corner's 3-sigma bounds
    true = np.array([scene["R"] @ c + scene["t"] for c in ([0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0])])
    assert np.all(np.abs(true - expected) * 1000 <= np.array(block["corners_sigma3_mm"]))
    # a block that does not match T_cam_base is refused by the reader
    bad = json.loads(json.dumps(calibrated))
    bad["screen"]["corners_cam"][2][0] += 0.001
    with pytest.raises(DatasetError, match=r"screen.corners_cam: not the corners"):
        validate_result(bad, "result.json")
    bad["screen"]["corners_cam"] = bad["screen"]["corners_cam"][:3]
    with pytest.raises(DatasetError, match=r"screen.corners_cam: expected 4 corners"):
        validate_result(bad, "result.json")


def test_gaze_file_beside_the_result_gives_screen_pixels_in_camera_millimetres(scene, calibrated):
    fs = cv2.FileStorage(str(scene["folder"] / "result.screen.xml"), cv2.FILE_STORAGE_READ)
    R, t_mm = fs.getNode("screen_rotation").mat(), fs.getNode("screen_translation").mat().ravel()
    pix2mm = fs.getNode("pix2mm").mat().ravel()
    size_px = fs.getNode("screen_size_px").mat().ravel()
    np.testing.assert_allclose(cv2.Rodrigues(fs.getNode("screen_rotation_vector").mat())[0], R, atol=1e-12)
    fs.release()
    assert tuple(size_px) == SCREEN_PX
    screen = Screen.from_result(calibrated)
    for pixel in ([0.0, 0.0], [960.5, 540.5], [1919.5, 1079.5]):
        mm = R @ np.array([pixel[0] * pix2mm[0], pixel[1] * pix2mm[1], 0.0]) + t_mm
        np.testing.assert_allclose(mm, 1000 * screen.camera_point(pixel), atol=1e-9)


def test_screen_from_result_takes_the_result_file_too(scene, calibrated):
    """A path (str or Path) is read as the result@1 file; anything but a path or a dict is refused in words."""
    for path in (scene["folder"] / "result.json", str(scene["folder"] / "result.json")):
        screen = Screen.from_result(path)
        np.testing.assert_allclose(screen.T_cam_screen.t, Screen.from_result(calibrated).T_cam_screen.t, atol=0)
        assert (screen.width_px, screen.height_px) == SCREEN_PX
    with pytest.raises(TypeError, match="a result@1 dictionary or the path of its file, got int"):
        Screen.from_result(3)


# --- gaze rays -----------------------------------------------------------------------------------------


def test_gaze_ray_hits_the_pixel_it_was_aimed_at(scene, calibrated):
    screen = Screen.from_result(calibrated)
    R, t = screen.T_cam_screen.R, screen.T_cam_screen.t
    m = np.array([screen.width_mm / screen.width_px, screen.height_mm / screen.height_px]) / 1000
    rng = np.random.default_rng(3)
    for _ in range(50):
        pixel = rng.uniform([0, 0], SCREEN_PX)
        eye = rng.uniform([-0.2, -0.1, 0.4], [0.2, 0.2, 0.8])  # a viewer in front of the screen, camera frame
        target = R @ np.array([pixel[0] * m[0], pixel[1] * m[1], 0.0]) + t  # independent of Screen
        hit = screen.pixel_of_ray(eye, (target - eye) * rng.uniform(0.5, 3.0))
        assert hit is not None
        assert np.linalg.norm(hit.pixel - pixel) <= 0.01, (hit.pixel, pixel)
        np.testing.assert_allclose(hit.point_cam, target, atol=1e-9)
        np.testing.assert_allclose(screen.pixel_of_point(target), pixel, atol=1e-6)
        np.testing.assert_allclose(screen.camera_point(pixel), target, atol=1e-12)
    eye = np.array([0.0, 0.1, 0.6])
    assert screen.pixel_of_ray(eye, [0.0, 0.0, 1.0]) is None  # looking away from the screen
    off = R @ np.array([-0.05, 0.1, 0.0]) + t  # left of the active area
    assert screen.pixel_of_ray(eye, off - eye) is None
    assert screen.pixel_of_ray(eye, off - eye, inside=False) is not None
    assert screen.pixel_of_ray(eye, np.cross(R[:, 2], [1.0, 0.0, 0.0])) is None  # parallel to the screen


def _exp(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, dtype=float).reshape(3, 1))[0]


def test_uncertainties_are_the_first_order_propagation_of_the_pose_covariance(calibrated):
    """Each Jacobian against central differences of the pose in the docs/formats.md's convention
    (``R' = Exp(dtheta) R``, ``t' = t + dt``), and the ray's pixel covariance against Monte Carlo."""
    screen = Screen.from_result(calibrated)
    P = screen.covariance
    eye, pixel = np.array([0.03, 0.12, 0.55]), np.array([700.3, 333.7])
    direction = screen.camera_point(pixel) - eye

    def perturbed(xi: np.ndarray) -> Screen:
        T = screen.T_cam_screen
        return Screen(screen.width_px, screen.height_px, screen.width_mm, screen.height_mm,
                      Transform(_exp(xi[:3]) @ T.R, T.t + xi[3:]))

    h = 1e-7
    J_point = np.column_stack([(perturbed(h * e).camera_point(pixel) - perturbed(-h * e).camera_point(pixel)) / (2 * h)
                               for e in np.eye(6)])
    J_ray = np.column_stack([(perturbed(h * e).pixel_of_ray(eye, direction).pixel
                              - perturbed(-h * e).pixel_of_ray(eye, direction).pixel) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(screen.camera_point_covariance(pixel), J_point @ P @ J_point.T, rtol=1e-5, atol=1e-14)
    hit = screen.pixel_of_ray(eye, direction)
    np.testing.assert_allclose(hit.covariance_px, J_ray @ P @ J_ray.T, rtol=1e-5)
    samples = np.random.default_rng(5).multivariate_normal(np.zeros(6), P, 4000)
    pixels = np.array([perturbed(xi).pixel_of_ray(eye, direction, inside=False).pixel for xi in samples])
    np.testing.assert_allclose(np.cov(pixels.T), hit.covariance_px, rtol=0.1)
    assert hit.sigma3_px is not None and np.all(hit.sigma3_px > 0)


def test_a_screen_capture_refuses_T_base_target(scene):
    from mirror_fg.io.capture import capture_from_dict

    capture = yaml.safe_load((scene["folder"] / "capture.yaml").read_text())
    capture["T_base_target"] = {"R": np.eye(3).tolist(), "t": [0.1, 0.0, 0.0]}
    with pytest.raises(DatasetError, match="T_base_target: with a screen target the base frame is the screen's"):
        capture_from_dict(capture, "cap.yaml", base_dir=str(scene["folder"]))


def test_pattern_replaces_its_own_side_files_but_not_a_strangers(tmp_path, capsys):
    args = ("pattern", "--screen", "1280x800", "--screen-mm", "261x163", "-o", "p.png")
    assert run_cli(*args, cwd=tmp_path) == 0
    assert run_cli(*args, cwd=tmp_path) == 0  # again: its own files
    (tmp_path / "p.html").write_text("<html>my page</html>")
    capsys.readouterr()
    assert run_cli(*args, cwd=tmp_path) == 2
    assert "p.html: exists and was not written by mirror-fg" in capsys.readouterr().err
    assert (tmp_path / "p.html").read_text() == "<html>my page</html>"


def test_the_api_gives_the_same_screen_block_as_the_command(scene, calibrated):
    from mirror_fg import calibrate
    from mirror_fg.io.capture import load_capture
    from mirror_fg.io.screen_result import screen_block
    from mirror_fg.vision.detect import detect_capture

    capture = load_capture(scene["folder"] / "capture.yaml")
    dataset, _ = detect_capture(capture, progress=False)
    result = calibrate(dataset).to_dict()
    block = screen_block(capture.target, result)
    np.testing.assert_allclose(block["corners_cam"], calibrated["screen"]["corners_cam"], atol=1e-9)
    np.testing.assert_allclose(block["normal_cam"], calibrated["screen"]["normal_cam"], atol=1e-12)


def test_a_screen_capture_on_standard_input_is_read_once_and_keeps_its_screen(scene, tmp_path):
    """The screen target comes from the one reading of the capture (a pipe cannot be read twice)."""
    import subprocess
    import sys

    from conftest import REPO

    with open(scene["folder"] / "capture.yaml") as handle:
        done = subprocess.run([sys.executable, "-m", "mirror_fg", "calibrate", "/dev/stdin", "-o",
                               str(tmp_path / "piped.json"), "-q"], stdin=handle, cwd=scene["folder"],
                              env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert load_result(tmp_path / "piped.json")["screen"]["width_px"] == SCREEN_PX[0]
    assert (tmp_path / "piped.screen.xml").exists()


def test_calibrate_many_writes_the_screen_too(scene, tmp_path):
    from mirror_fg.analysis.many import calibrate_one

    row = calibrate_one(str(scene["folder"] / "capture.yaml"), str(tmp_path), ros=False)
    assert row["status"] == "ok", row["reason"]
    assert "screen" in load_result(row["result"]) and (tmp_path / "capture.result.screen.xml").exists()


@pytest.mark.parametrize("scale", [1.5, 2.0])
def test_pattern_page_shows_every_pattern_pixel_on_one_device_pixel_under_display_scaling(tmp_path, scale):
    """Headless Chromium at an OS display scaling of 150 % / 200 % (``--force-device-scale-factor``): the
    screenshot, in device pixels, is the PNG pixel for pixel (outside the page's centred note, shown
    because the headless screen is not 600 x 360)."""
    import shutil
    import subprocess

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no Chromium to render the page")
    assert run_cli("pattern", "--screen", "600x360", "--screen-mm", "160x96", "-o", "p.png", cwd=tmp_path) == 0
    shot = tmp_path / "shot.png"
    size = f"{round(600 / scale)},{round(360 / scale)}"  # CSS pixels of a 600 x 360 device-pixel window
    subprocess.run([browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--force-device-scale-factor={scale}", f"--window-size={size}", f"--screenshot={shot}",
                    (tmp_path / "p.html").as_uri()], capture_output=True, timeout=120)
    if not shot.exists():
        pytest.skip("Chromium could not take a screenshot here")
    pattern = cv2.imread(str(tmp_path / "p.png"), cv2.IMREAD_GRAYSCALE)
    seen = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert seen.shape == pattern.shape
    outside_note = np.ones(pattern.shape, bool)
    outside_note[:, 140:460] = False
    assert np.array_equal(seen[outside_note], pattern[outside_note])


#: Pixel noise per kind: ChArUco and chessboard saddles as above; AprilTag corners (cornerSubPix on the
#: linearized image) sit ~0.2 px off per axis on rendered tags (STYLE.md, OpenCV pitfalls), so 0.3 px.
KIND_PIXEL_SIGMA = {"chessboard": PIXEL_SIGMA, "apriltag": 0.3}


@pytest.mark.parametrize("kind", ["chessboard", "apriltag"])
def test_other_pattern_kinds_calibrate_through_the_mirror_too(tmp_path, kind):
    """The chessboard must be seen whole: a photograph in which the mirror cuts it is left out, named."""
    from mirror_fg import calibrate
    from mirror_fg.io.capture import capture_from_dict
    from mirror_fg.vision.pattern import design_pattern, draw_pattern, screen_mm_from_diagonal
    from mirror_fg.vision.detect import detect_capture

    render = load_script("render_screen")
    mm = screen_mm_from_diagonal(*SCREEN_PX, DIAGONAL_IN)
    screen = design_pattern(*SCREEN_PX, *mm, kind)
    png = draw_pattern(screen)
    R, t = render.webcam_above(mm[0] / 1000)
    rng = np.random.default_rng(7)
    images = []
    for k, mirror in enumerate(render.placements(R, t, mm[0] / 1000, mm[1] / 1000)):
        cv2.imwrite(str(tmp_path / f"m{k}.png"), render.render(png, mm, R, t, mirror, rng))
        images.append({"file": f"m{k}.png", "mirror_configs": [k]})
    capture = capture_from_dict({"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": render.WEBCAM,
                                 "pixel_sigma": KIND_PIXEL_SIGMA[kind], "target": screen.to_dict(), "images": images},
                                base_dir=str(tmp_path))
    dataset, reports = detect_capture(capture, progress=False)
    assert sum(r.status == FOUND for r in reports) >= 5, [r.line() for r in reports]
    assert all(r.reason for r in reports if r.status != FOUND)
    cal = calibrate(dataset)
    error = pose_difference(R, t, cal.R_cam_base, cal.t_cam_base)
    bound = 3 * np.sqrt(np.diag(cal.covariance))
    assert np.all(np.abs(error) <= bound), (error, bound)
