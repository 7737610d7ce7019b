"""The gaze point's error a screen calibration costs (``mirror_fg.core.gaze_error``; docs/formats.md, "The
answer in the user's units"): against a Monte Carlo of the result's own covariance, and against the
simulator's truth (NEES) over many simulated captures; the CLI's ``--viewing-distance``, console and report.

The simulated captures: the 24-inch monitor and webcam of ``scripts/render_screen.py`` (its own geometry:
the screen's homography through the reflected camera), a ChArUco pattern's corners seen through the six
hand-held mirror placements, Gaussian pixel noise of the stated sigma (no rendering: fast).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.stats import chi2

from conftest import load_script
from mirror_fg import calibrate
from mirror_fg.core.camera import Camera
from mirror_fg.core.gaze_error import gaze_error
from mirror_fg.core.screen import Screen
from mirror_fg.core.transform import Transform
from mirror_fg.data import Dataset, Image
from mirror_fg.io.screen_target import screen_target_from_dict

SCREEN_PX = (1920, 1080)
PIXEL_SIGMA = 0.3


def _exp(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, dtype=float).reshape(3, 1))[0]


@pytest.fixture(scope="module")
def setup():
    render = load_script("render_screen")
    from mirror_fg.vision.pattern import design_pattern, screen_mm_from_diagonal

    mm = screen_mm_from_diagonal(*SCREEN_PX, 24.0)
    target = screen_target_from_dict(design_pattern(*SCREEN_PX, *mm).to_dict(), "test")
    R, t = render.webcam_above(mm[0] / 1000)
    mirrors = render.placements(R, t, mm[0] / 1000, mm[1] / 1000)
    return {"render": render, "mm": mm, "target": target, "R": R, "t": t, "mirrors": mirrors}


def simulated(setup, rng: np.random.Generator, sigma: float = PIXEL_SIGMA) -> Dataset:
    """The pattern's corners through the six mirrors, with Gaussian pixel noise ``sigma``."""
    render, fiducials = setup["render"], setup["target"].target_points()
    names = list(fiducials)
    images = []
    for k, mirror in enumerate(setup["mirrors"]):
        H = render.screen_homography(setup["R"], setup["t"], mirror)
        pixels = render.project(H, np.array([fiducials[n][:2] for n in names])) + rng.normal(0.0, sigma, (len(names), 2))
        images.append(Image(id=f"mirror{k}", mirror_configs=(k,), observations=dict(zip(names, pixels))))
    camera = Camera(*(render.WEBCAM[k] for k in ("width", "height", "fx", "fy", "cx", "cy")))
    return Dataset(num_mirrors=1, camera=camera, pixel_sigma=sigma, fiducials=fiducials, images=images, source="sim")


def screen_of_calibration(setup, cal) -> Screen:
    return Screen(*SCREEN_PX, *setup["mm"], Transform(cal.R_cam_base, cal.t_cam_base), cal.covariance)


def hit_mm(R: np.ndarray, t: np.ndarray, eye: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Where the ray meets the screen (R, t): its screen-frame x, y in mm (independent of Screen)."""
    normal = R[:, 2]
    lam = normal @ (t - eye) / (normal @ direction)
    return 1000.0 * (R.T @ (eye + lam * direction - t))[:2]


def test_gaze_error_is_the_monte_carlo_of_the_results_own_covariance(setup):
    """3 sigma in mm and degrees within 3 % of 20,000 draws of the pose from its covariance."""
    screen = screen_of_calibration(setup, calibrate(simulated(setup, np.random.default_rng(1))))
    error = gaze_error(screen, 0.6)
    R, t = screen.T_cam_screen.R, screen.T_cam_screen.t
    draws = np.random.default_rng(2).multivariate_normal(np.zeros(6), screen.covariance, 20000)
    perturbed = [(_exp(xi[:3]) @ R, t + xi[3:]) for xi in draws]
    mm_per_px = np.array(setup["mm"]) / np.array(SCREEN_PX)
    for k, pixel in enumerate(error.points_px):
        target = screen.camera_point(pixel)
        direction = target - error.eye_cam
        nominal = pixel * mm_per_px
        offsets = np.array([hit_mm(Rp, tp, error.eye_cam, direction) for Rp, tp in perturbed]) - nominal
        np.testing.assert_allclose(error.sigma3_mm[k], 3.0 * offsets.std(axis=0), rtol=0.03)
        # the angle at the eye between the point looked at and the screen point at the reported coordinates
        for axis in range(2):
            step = np.zeros((len(offsets), 3))
            step[:, axis] = offsets[:, axis] / 1000.0
            seen = target + step @ R.T - error.eye_cam
            cos = seen @ direction / (np.linalg.norm(seen, axis=1) * np.linalg.norm(direction))
            angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) * np.sign(offsets[:, axis])
            np.testing.assert_allclose(error.sigma3_deg[k, axis], 3.0 * angle.std(), rtol=0.03)
    # the centre is seen head-on from 0.6 m: degrees are mm / 600 mm, in radians
    np.testing.assert_allclose(np.radians(error.sigma3_deg[0]), error.sigma3_mm[0] / 600.0, rtol=1e-9)
    np.testing.assert_allclose(error.eye_cam, screen.camera_point(np.array(SCREEN_PX) / 2) + 0.6 * screen.normal_cam)


def nees_of_runs(setup, runs: int, seed: int) -> np.ndarray:
    """(runs, 5): each run's NEES of the gaze point's error against the truth, centre then corners."""
    rng = np.random.default_rng(seed)
    nees = np.zeros((runs, 5))
    for run in range(runs):
        screen = screen_of_calibration(setup, calibrate(simulated(setup, rng)))
        error = gaze_error(screen, 0.6)
        mm_per_px = np.array(setup["mm"]) / np.array(SCREEN_PX)
        for k, pixel in enumerate(error.points_px):
            looked_at = hit_mm(setup["R"], setup["t"], error.eye_cam, screen.camera_point(pixel) - error.eye_cam)
            e = looked_at - pixel * mm_per_px  # the true screen point minus the one the calibration gives
            nees[run, k] = e @ np.linalg.solve(error.covariance_mm[k], e)
    return nees


def _nees_in_band(nees: np.ndarray) -> None:
    runs = len(nees)
    band = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs  # the mean of `runs` chi-square(2) values, 99.9 %
    means = nees.mean(axis=0)
    print(f"mean NEES over {runs} runs (centre, corners): {np.round(means, 2)}, band {np.round(band, 2)}")
    assert np.all((band[0] < means) & (means < band[1])), (means, band)


def test_gaze_error_holds_the_truth_nees_fast(setup):
    _nees_in_band(nees_of_runs(setup, 20, seed=30))


@pytest.mark.slow
def test_gaze_error_holds_the_truth_nees_over_100_runs(setup):
    _nees_in_band(nees_of_runs(setup, 100, seed=31))


def test_gaze_error_refuses_what_it_cannot_give(setup):
    screen = Screen(*SCREEN_PX, *setup["mm"], Transform(setup["R"], setup["t"]))
    with pytest.raises(ValueError, match="no covariance"):
        gaze_error(screen)
    with pytest.raises(ValueError, match="must be > 0"):
        gaze_error(Screen(*SCREEN_PX, *setup["mm"], Transform(setup["R"], setup["t"]), np.eye(6) * 1e-8), 0.0)


# --- the command line: --viewing-distance, the result's screen block, the console, the report ------------------


def write_observed_capture(setup, folder: Path, rng: np.random.Generator) -> Path:
    """A capture@1 with the screen target whose images give their corners as observations (blank
    photographs: nothing is detected, the given pixels are used)."""
    dataset = simulated(setup, rng)
    blank = np.full((480, 640), 128, np.uint8)
    images = []
    for image in dataset.images:
        cv2.imwrite(str(folder / f"{image.id}.png"), blank)
        images.append({"file": f"{image.id}.png", "mirror_configs": list(image.mirror_configs),
                       "observations": {n: [float(p[0]), float(p[1])] for n, p in image.observations.items()}})
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": setup["render"].WEBCAM,
               "pixel_sigma": PIXEL_SIGMA, "target": setup["target"].to_dict(), "images": images}
    path = folder / "capture.yaml"
    path.write_text(yaml.safe_dump(capture, sort_keys=False))
    return path


def run_cli(*args: str, cwd: Path) -> int:
    from mirror_fg.cli import main

    here = os.getcwd()
    try:
        os.chdir(cwd)
        return main(list(args))
    except SystemExit as stop:
        return int(stop.code)
    finally:
        os.chdir(here)


def test_calibrate_writes_and_prints_the_gaze_error_at_the_viewing_distance(setup, tmp_path, capsys):
    write_observed_capture(setup, tmp_path, np.random.default_rng(8))
    assert run_cli("calibrate", "capture.yaml", "-o", "result.json", "--viewing-distance", "0.5", cwd=tmp_path) == 0
    printed = capsys.readouterr().out
    result = json.loads((tmp_path / "result.json").read_text())
    block = result["screen"]
    assert block["viewing_distance_m"] == 0.5
    error = gaze_error(Screen.from_result(result), 0.5)
    np.testing.assert_allclose(block["sigma3_on_screen_mm"]["centre"], error.sigma3_mm[0], rtol=1e-12)
    np.testing.assert_allclose(block["sigma3_on_screen_mm"]["corners"], error.sigma3_mm[1:], rtol=1e-12)
    np.testing.assert_allclose(block["sigma3_on_screen_deg"]["corners"], error.sigma3_deg[1:], rtol=1e-12)
    centre = block["sigma3_on_screen_mm"]["centre"]
    assert "gaze point 3-sigma on the screen (eye 50 cm in front of its centre" in printed
    assert f"centre  ±[{centre[0]:.2f}, {centre[1]:.2f}] mm" in printed
    # nearer eye, same screen: the same on-screen millimetres at the centre subtend more degrees
    assert run_cli("calibrate", "capture.yaml", "-o", "far.json", "-q", cwd=tmp_path) == 0
    far = json.loads((tmp_path / "far.json").read_text())["screen"]
    assert far["viewing_distance_m"] == 0.6
    np.testing.assert_allclose(far["sigma3_on_screen_mm"]["centre"], centre, rtol=1e-9)
    assert far["sigma3_on_screen_deg"]["centre"][0] < block["sigma3_on_screen_deg"]["centre"][0]
    assert run_cli("calibrate", "capture.yaml", "-o", "bad.json", "--viewing-distance", "0", cwd=tmp_path) == 2
    assert not (tmp_path / "bad.json").exists()


def test_report_draws_the_gaze_error_over_the_screen(setup, tmp_path):
    from mirror_fg.report.screen import figure_gaze

    write_observed_capture(setup, tmp_path, np.random.default_rng(9))
    assert run_cli("calibrate", "capture.yaml", "-o", "result.json", "-q", cwd=tmp_path) == 0
    result = json.loads((tmp_path / "result.json").read_text())
    figure = figure_gaze(result)
    assert figure is not None and "Gaze point 3σ" in figure.axes[0].get_title()
    labels = [text.get_text() for text in figure.axes[0].texts]
    centre = result["screen"]["sigma3_on_screen_mm"]["centre"]
    assert f"±{centre[0]:.1f}, {centre[1]:.1f} mm" in labels[0] and len(labels) == 5
    assert run_cli("report", "result.json", "-o", "report", "-q", cwd=tmp_path) == 0
    assert "Gaze point error over the screen" in (tmp_path / "report" / "report.html").read_text()
    assert figure_gaze({k: v for k, v in result.items() if k != "screen"}) is None
