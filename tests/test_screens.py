"""Several screens in one graph (``mirror_fg.solver.batch.screens``; docs/formats.md, "The answer in the user's
units"): two monitors side by side seen by one webcam through a hand-held mirror.

Fast tests: the screens' corners projected through the mirrors by scripts/render_screen.py's own geometry
(its homography of a screen through the reflected camera) with Gaussian pixel noise; the second monitor
stands right of the first, turned 35 degrees towards the viewer. The goal test renders the photographs
(``render_screen.py --screens 2``) and runs ``mirror-fg calibrate`` on its capture.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from conftest import load_script, pose_difference
from mirror_fg.core.camera import Camera
from mirror_fg.core.transform import Transform
from mirror_fg.data import Dataset, Image
from mirror_fg.io.screen_target import screen_target_from_dict
from mirror_fg.solver.batch.screens import calibrate_screens, relative_pose

SCREEN_PX = (1920, 1080)
PIXEL_SIGMA = 0.3


@pytest.fixture(scope="module")
def scene():
    render = load_script("render_screen")
    from mirror_fg.vision.pattern import design_pattern, screen_mm_from_diagonal

    mm = screen_mm_from_diagonal(*SCREEN_PX, 24.0)
    target = screen_target_from_dict(design_pattern(*SCREEN_PX, *mm).to_dict(), "test")
    poses = render.two_screens(mm[0] / 1000)
    camera = Camera(*(render.WEBCAM[k] for k in ("width", "height", "fx", "fy", "cx", "cy")))
    mirrors = {name: (render.placements if name == "left" else render.side_placements)(R, t, mm[0] / 1000, mm[1] / 1000)
               for name, (R, t) in poses.items()}
    return {"render": render, "mm": mm, "target": target, "poses": poses, "camera": camera, "mirrors": mirrors}


def observe(scene, name: str, mirror, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Screen ``name``'s pattern corners through ``mirror``, with noise; only those inside the image."""
    render, fiducials = scene["render"], scene["target"].target_points()
    R, t = scene["poses"][name]
    names = list(fiducials)
    pixels = render.project(render.screen_homography(R, t, mirror), np.array([fiducials[n][:2] for n in names]))
    pixels = pixels + rng.normal(0.0, PIXEL_SIGMA, pixels.shape)
    inside = (pixels[:, 0] > 0) & (pixels[:, 0] < 639) & (pixels[:, 1] > 0) & (pixels[:, 1] < 479)
    return {n: p for n, p, keep in zip(names, pixels, inside) if keep}


def datasets_of(scene, rng: np.random.Generator, shared: bool = False) -> dict[str, Dataset]:
    """One dataset per screen: six placements each (labels 0-5 and 6-11), and with ``shared`` two more
    photographs of one placement (12) aimed between the screens, each seeing both."""
    render = scene["render"]
    images: dict[str, list[Image]] = {"left": [], "right": []}
    label = 0
    for name in ("left", "right"):
        for mirror in scene["mirrors"][name]:
            images[name].append(Image(id=f"{name}{label}", mirror_configs=(label,), observations=observe(scene, name, mirror, rng)))
            label += 1
    if shared:
        R, t = scene["poses"]["left"]
        junction = R @ np.array([scene["mm"][0] / 1000 + 0.01, scene["mm"][1] / 2000, 0.0]) + t
        mirror = render.aim_mirror(0.30, (320, 240), junction)
        for name in ("left", "right"):
            images[name].append(Image(id=f"{name}-both", mirror_configs=(label,), observations=observe(scene, name, mirror, rng)))
    fiducials = scene["target"].target_points()
    return {name: Dataset(1, scene["camera"], PIXEL_SIGMA, fiducials, imgs, source=f"sim {name}")
            for name, imgs in images.items()}


def test_two_screens_in_one_graph_hold_their_truths_and_relative_pose(scene):
    cal = calibrate_screens(datasets_of(scene, np.random.default_rng(1)))
    assert cal.names == ["left", "right"]
    for name in cal.names:
        R, t = scene["poses"][name]
        error = pose_difference(R, t, cal.poses[name].R, cal.poses[name].t)
        bound = 3 * np.sqrt(np.diag(cal.covariance(name)))
        assert np.all(np.abs(error) <= bound), (name, error, bound)
        # the joint solve equals each screen's own where they share nothing (independent placements)
        alone = cal.alone[name]
        np.testing.assert_allclose(cal.poses[name].t, alone.t_cam_base, atol=1e-6)
        np.testing.assert_allclose(cal.covariance(name), alone.covariance, rtol=1e-3, atol=1e-14)
    (R_l, t_l), (R_r, t_r) = scene["poses"]["left"], scene["poses"]["right"]
    T, C = cal.relative("left", "right")
    true = Transform(R_l, t_l).inverse() @ Transform(R_r, t_r)
    e = pose_difference(true.R, true.t, T.R, T.t)
    assert e @ np.linalg.solve(C, e) < chi2.ppf(0.9973, 6)  # within "3 sigma" in 6 dof
    # no placement in common: the joint covariance has no cross terms, the relative pose's is the two propagated
    np.testing.assert_allclose(cal.joint_covariance[:6, 6:], 0.0, atol=1e-3 * np.abs(cal.joint_covariance).max())


def test_relative_pose_covariance_is_the_first_order_propagation(scene):
    """Against central differences of ``T_to_from`` under the uncertainty convention's perturbations."""
    import cv2

    (Ra, ta), (Rb, tb) = scene["poses"]["left"], scene["poses"]["right"]
    A = np.random.default_rng(2).normal(size=(12, 12))
    joint = A @ A.T * 1e-6
    T, C = relative_pose(Transform(Ra, ta), Transform(Rb, tb), joint)

    def rel(xi):
        Ra2, ta2 = cv2.Rodrigues(xi[:3])[0] @ Ra, ta + xi[3:6]
        Rb2, tb2 = cv2.Rodrigues(xi[6:9])[0] @ Rb, tb + xi[9:]
        T2 = Transform(Ra2, ta2).inverse() @ Transform(Rb2, tb2)
        return pose_difference(T.R, T.t, T2.R, T2.t)

    h = 1e-6
    J = np.column_stack([(rel(h * e) - rel(-h * e)) / (2 * h) for e in np.eye(12)])
    np.testing.assert_allclose(C, J @ joint @ J.T, rtol=1e-5, atol=1e-15)


def test_a_placement_seen_with_both_screens_ties_them(scene):
    """Two photographs of one mirror placement, one per screen, tie the screens together beyond each
    alone: its relative pose is tighter than theirs combined, and the truth is within its bounds."""
    rng = np.random.default_rng(3)
    cal = calibrate_screens(datasets_of(scene, rng, shared=True))
    assert (1, 12) in cal.mirror_vectors
    T, C = cal.relative("left", "right")
    independent = np.zeros((12, 12))
    independent[:6, :6], independent[6:, 6:] = cal.alone["left"].covariance, cal.alone["right"].covariance
    _, C_alone = relative_pose(Transform(cal.alone["left"].R_cam_base, cal.alone["left"].t_cam_base),
                               Transform(cal.alone["right"].R_cam_base, cal.alone["right"].t_cam_base), independent)
    assert np.trace(C) < np.trace(C_alone)
    (R_l, t_l), (R_r, t_r) = scene["poses"]["left"], scene["poses"]["right"]
    true = Transform(R_l, t_l).inverse() @ Transform(R_r, t_r)
    e = pose_difference(true.R, true.t, T.R, T.t)
    assert e @ np.linalg.solve(C, e) < chi2.ppf(0.9973, 6)


def test_relative_pose_nees_over_runs(scene):
    """The relative pose's covariance holds the truth: mean NEES over 12 runs within chi-square's band."""
    (R_l, t_l), (R_r, t_r) = scene["poses"]["left"], scene["poses"]["right"]
    true = Transform(R_l, t_l).inverse() @ Transform(R_r, t_r)
    rng = np.random.default_rng(11)
    nees = []
    for _ in range(12):
        cal = calibrate_screens(datasets_of(scene, rng, shared=True))
        T, C = cal.relative("left", "right")
        e = pose_difference(true.R, true.t, T.R, T.t)
        nees.append(e @ np.linalg.solve(C, e))
    band = chi2.ppf([0.0005, 0.9995], 6 * 12) / 12
    assert band[0] < np.mean(nees) < band[1], (np.mean(nees), band)


# --- the goal: two rendered monitors side by side, through mirror-fg calibrate -------------------------------


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


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """``scripts/render_screen.py --screens 2``: twelve photographs (six per monitor), its capture and truth."""
    import subprocess
    import sys

    from conftest import REPO

    folder = tmp_path_factory.mktemp("two_screens")
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "render_screen.py"), "--out", str(folder),
                           "--screens", "2"], env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return folder


def test_two_rendered_monitors_are_each_within_3_mm_and_0_3_deg_and_their_relative_pose_within_3_sigma(rendered, capsys):
    from mirror_fg.io.result import load_result

    assert run_cli("calibrate", "capture.yaml", "-o", "result.json", cwd=rendered) == 0
    printed = capsys.readouterr().out
    assert "screen left: T_cam_screen" in printed and "screen left in screen right's frame" in printed
    result = load_result(rendered / "result.json")  # a valid result@1
    truth = json.loads((rendered / "truth.json").read_text())["screens"]
    assert list(result["screens"]) == ["left", "right"]
    for name, block in result["screens"].items():
        R, t = np.array(block["T_cam_screen"]["R"]), np.array(block["T_cam_screen"]["t"])
        error = pose_difference(np.array(truth[name]["R"]), np.array(truth[name]["t"]), R, t)
        print(f"{name}: error {np.degrees(error[:3]).round(3)} deg, {(1000 * error[3:]).round(2)} mm; 3-sigma "
              f"{np.round(block['sigma3']['rotation_deg'], 3)} deg, {np.round(block['sigma3']['position_mm'], 2)} mm")
        assert np.all(np.abs(np.degrees(error[:3])) < 0.3) and np.all(np.abs(error[3:]) < 0.003), (name, error)
        assert np.all(np.abs(error) <= 3 * np.sqrt(np.diag(block["covariance"]))), name
        # each screen block is that screen's: its corners are those of its own T_cam_screen
        w, h = block["width_mm"] / 1000, block["height_mm"] / 1000
        np.testing.assert_allclose(block["corners_cam"], [R @ c + t for c in ([0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0])],
                                   atol=1e-12)
        assert "sigma3_on_screen_mm" in block
    # the first screen is the top level (single-screen readers)
    np.testing.assert_allclose(result["T_cam_base"]["t"], result["screens"]["left"]["T_cam_screen"]["t"], atol=1e-12)
    assert result["screen"]["corners_cam"] == result["screens"]["left"]["corners_cam"]
    (pair,) = result["screen_pairs"]
    assert (pair["from"], pair["to"]) == ("left", "right")
    T = Transform(np.array(truth["right"]["R"]), np.array(truth["right"]["t"])).inverse() @ \
        Transform(np.array(truth["left"]["R"]), np.array(truth["left"]["t"]))  # left's points into right's frame
    e = pose_difference(T.R, T.t, np.array(pair["T"]["R"]), np.array(pair["T"]["t"]))
    nees = e @ np.linalg.solve(np.array(pair["covariance"]), e)
    print(f"relative pose: error {np.degrees(e[:3]).round(3)} deg, {(1000 * e[3:]).round(2)} mm, NEES {nees:.2f}")
    assert nees < chi2.ppf(0.9973, 6)
    joint = np.array(result["screens_joint_covariance"])
    np.testing.assert_allclose(joint[6:, 6:], result["screens"]["right"]["covariance"], rtol=1e-12)


@pytest.mark.parametrize("change, words", [
    (lambda c: c["images"][3].pop("screen"), "images[3]: screen must name one of the screens (left, right), got None"),
    (lambda c: c["images"][0].update(screen="middle"), "images[0]: screen must name one of the screens"),
    (lambda c: c.update(target=c["screens"]["left"]), "target: not with screens (give either target or screens)"),
    (lambda c: c["screens"].pop("right"), "screens: expected a mapping of two or more"),
    (lambda c: c["screens"]["right"].update(width_mm=0), "screens: right: width_mm must be a number > 0"),
])
def test_a_capture_with_screens_refuses_what_it_cannot_use_in_one_line(rendered, tmp_path, capsys, change, words):
    import yaml

    capture = yaml.safe_load((rendered / "capture.yaml").read_text())
    for entry in capture["images"]:
        entry["file"] = str(rendered / entry["file"])
    change(capture)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(capture))
    assert run_cli("calibrate", "bad.yaml", "-o", "r.json", cwd=tmp_path) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "r.json").exists()


def test_several_screens_refuse_incremental(rendered, capsys):
    assert run_cli("calibrate", "capture.yaml", "-o", "inc.json", "--incremental", cwd=rendered) == 2
    assert "screens: several screens are calibrated in one batch; drop --incremental" in capsys.readouterr().err
    assert not (rendered / "inc.json").exists()


def test_export_writes_the_screen_it_is_asked_for(rendered, capsys):
    import cv2

    from mirror_fg.io.result import load_result

    if not (rendered / "result.json").exists():
        assert run_cli("calibrate", "capture.yaml", "-o", "result.json", "-q", cwd=rendered) == 0
    right = load_result(rendered / "result.json")["screens"]["right"]
    assert run_cli("export", "result.json", "--to", "eth-xgaze", "--screen", "right", "-o", "right.xml", "-q",
                   cwd=rendered) == 0
    fs = cv2.FileStorage(str(rendered / "right.xml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("screen_rotation").mat(), right["T_cam_screen"]["R"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fs.getNode("screen_translation").mat().ravel(), 1000 * np.array(right["T_cam_screen"]["t"]),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(fs.getNode("screen_sigma3_translation_mm").mat().ravel(), right["sigma3"]["position_mm"])
    fs.release()
    capsys.readouterr()
    assert run_cli("export", "result.json", "--to", "opengaze", "--screen", "middle", "-o", "m.yml", cwd=rendered) == 2
    assert "--screen middle: no such screen in the result (its screens: left, right)" in capsys.readouterr().err


def test_report_draws_each_screens_gaze_error(rendered):
    from mirror_fg.io.result import load_result
    from mirror_fg.report.screen import figure_gaze, gaze_screens

    if not (rendered / "result.json").exists():
        assert run_cli("calibrate", "capture.yaml", "-o", "result.json", "-q", cwd=rendered) == 0
    result = load_result(rendered / "result.json")
    assert gaze_screens(result) == ["left", "right"]
    figure = figure_gaze(result, "right")
    assert "screen right" in figure.axes[0].get_title()
    centre = result["screens"]["right"]["sigma3_on_screen_mm"]["centre"]
    assert f"±{centre[0]:.1f}, {centre[1]:.1f} mm" in figure.axes[0].texts[0].get_text()
    assert run_cli("report", "result.json", "-o", "report", "-q", cwd=rendered) == 0
    page = (rendered / "report" / "report.html").read_text()
    assert "Gaze point error over the screen left" in page and "Gaze point error over the screen right" in page


def test_other_commands_say_how_a_capture_of_several_screens_is_used(rendered, capsys):
    for args in (["detect", "capture.yaml", "-o", "d.json"], ["report", "capture.yaml", "-o", "rep"]):
        if args[0] == "report":
            if not (rendered / "result.json").exists():
                assert run_cli("calibrate", "capture.yaml", "-o", "result.json", "-q", cwd=rendered) == 0
            args = ["report", "result.json", "capture.yaml", "-o", "rep"]
        capsys.readouterr()
        assert run_cli(*args, cwd=rendered) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "screens: a capture of several screens is calibrated by mirror-fg calibrate" in err[0]
