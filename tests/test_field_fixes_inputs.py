"""Inputs a user types wrong, refused where they meet the tool: lengths in the wrong unit, non-physical
values, sizes that would exhaust memory, side files of an earlier run, a rig camera no image names,
mislabelled rig images, and messages in the user's words. Each test runs the command line and fails on
the code before its fix."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mirror_fg.cli import main


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    """The command line's status, stdout and stderr."""
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def one_error_line(err: str) -> str:
    """The one ``mirror-fg: ...`` line a refusal prints (and nothing else on stderr)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def target_free(tmp_path_factory) -> tuple[dict, dict]:
    """A simulated kaleidoscope without a known target: its dataset and truth as plain dicts."""
    folder = tmp_path_factory.mktemp("kaleidoscope")
    assert main(["simulate", "--kind", "kaleidoscope", "--no-target", "--points", "6", "-o",
                 str(folder / "k.json")]) == 0
    return (json.loads((folder / "k.json").read_text()), json.loads((folder / "k.truth.json").read_text()))


def with_point_scale(target_free, distance: float, tmp_path: Path) -> Path:
    dataset = json.loads(json.dumps(target_free[0]))
    dataset["scale"] = {"points": ["P0", "P1"], "distance": distance}
    path = tmp_path / "data.json"
    path.write_text(json.dumps(dataset))
    return path


def true_point_distance(target_free) -> float:
    points = target_free[1]["points"]
    return float(np.linalg.norm(np.subtract(points["P0"], points["P1"])))


# -- lengths in the wrong unit, non-physical lengths --------------------------------------------------


@pytest.mark.parametrize("factor", [1000.0, 100.0], ids=["millimetres", "centimetres"])
def test_target_free_scale_in_the_wrong_unit_is_refused(target_free, factor, tmp_path, capsys):
    path = with_point_scale(target_free, true_point_distance(target_free) * factor, tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "data.json" in line and "metres" in line
    assert not (tmp_path / "r.json").exists()


def test_target_free_scale_in_metres_still_solves(target_free, tmp_path, capsys):
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 0, out + err
    result = json.loads((tmp_path / "r.json").read_text())
    assert all(np.isfinite(p["sigma3_mm"]).all() for p in result["points"].values())


@pytest.mark.parametrize("distance", [1e-100, 1e-300, 0.0, -0.02], ids=["1e-100", "1e-300", "zero", "negative"])
def test_non_physical_scale_distance_is_refused_at_load(target_free, distance, tmp_path, capsys):
    path = with_point_scale(target_free, distance, tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "scale: distance" in line and "metres" in line
    assert "warning" not in err and not (tmp_path / "r.json").exists()


def test_nan_bounds_are_never_written_as_a_success(target_free, tmp_path, capsys, monkeypatch):
    """Whatever made them (a degenerate solve), NaN bounds exit 3 with one line and write nothing."""
    import mirror_fg.solver.calibrate as calibrate_module

    solve = calibrate_module.calibrate

    def degenerate(dataset, **options):
        calibration = solve(dataset, **options)
        key = next(iter(calibration.point_covariances))
        calibration.point_covariances[key] = np.full((3, 3), np.nan)
        return calibration

    monkeypatch.setattr(calibrate_module, "calibrate", degenerate)
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 3, out + err
    line = one_error_line(err)
    assert "point P" in line and "NaN" in line and "not written" in line
    assert not (tmp_path / "r.json").exists()


def test_mirror_absurdly_far_is_refused(target_free, tmp_path, capsys, monkeypatch):
    """After solving: a mirror hundreds of metres away is no success, whichever length caused it."""
    import mirror_fg.solver.calibrate as calibrate_module

    solve = calibrate_module.calibrate

    def far(dataset, **options):
        calibration = solve(dataset, **options)
        key = next(iter(calibration.mirror_vectors))
        calibration.mirror_vectors[key] = calibration.mirror_vectors[key] * 1000.0
        return calibration

    monkeypatch.setattr(calibrate_module, "calibrate", far)
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "mirror 1 placement 0" in line and "m from the camera" in line and "metres" in line
    assert not (tmp_path / "r.json").exists()


# -- sizes bounded before anything is allocated -------------------------------------------------------


@pytest.mark.parametrize("argv, words", [
    (["--screen", "100000x100000", "--diagonal", "15"], "--screen 100000x100000 is not a plausible screen"),
    (["--screen", "1920x1080", "--diagonal", "1e-9"], "--diagonal 1e-09 in"),
    (["--screen", "1920x1080", "--screen-mm", "0.527x0.296"], "0.527 m = 527 mm"),
    (["--screen", "1920x1080", "--screen-mm", "527000x296000"], "at most 10000 mm"),
    (["--screen", "1920x1080", "--screen-mm", "527x296", "--square-mm", "1e300"], "--square-mm 1e+300 is larger than"),
], ids=["8-GB-screen", "nanometre-diagonal", "metres-as-mm", "micrometres-as-mm", "square-larger-than-screen"])
def test_pattern_refuses_implausible_sizes_before_drawing(argv, words, tmp_path, capsys):
    status, out, err = run(["pattern", *argv, "-o", tmp_path / "p.png"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert words in line, line
    assert list(tmp_path.iterdir()) == []


def test_screen_target_in_metres_is_refused(tmp_path, capsys):
    """A capture's screen target whose width_mm / height_mm were typed in metres."""
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((48, 64), np.uint8))
    screen = {"kind": "screen", "width_px": 1920, "height_px": 1080, "width_mm": 0.527, "height_mm": 0.296,
              "pattern": {"kind": "chessboard", "cols": 5, "rows": 4, "square_px": 100, "origin_px": [0, 0]}}
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1,
               "camera": {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5},
               "target": screen, "images": [{"file": "a.png", "mirror_configs": [0]}]}
    (tmp_path / "c.json").write_text(json.dumps(capture))
    status, out, err = run(["calibrate", tmp_path / "c.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "c.json" in line and "width_mm" in line and "millimetres" in line


def test_target_square_of_no_size_is_refused(tmp_path, capsys):
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((48, 64), np.uint8))
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1,
               "camera": {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5},
               "target": {"kind": "chessboard", "cols": 4, "rows": 3, "square": 1e-9},
               "images": [{"file": "a.png", "mirror_configs": [0]}]}
    (tmp_path / "c.json").write_text(json.dumps(capture))
    status, out, err = run(["calibrate", tmp_path / "c.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "square" in line and "not a plausible" in line


# -- a rig camera no image names -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> tuple[Path, dict]:
    """A simulated two-camera rig: its file and its dataset as a dict."""
    folder = tmp_path_factory.mktemp("rig")
    assert main(["simulate", "--cameras", "2", "-o", str(folder / "rig.json")]) == 0
    return folder / "rig.json", json.loads((folder / "rig.json").read_text())


def test_rig_camera_without_images_is_refused_by_name(rig, tmp_path, capsys):
    dataset = json.loads(json.dumps(rig[1]))
    dataset["cameras"]["spare"] = dict(next(iter(dataset["cameras"].values())))
    (tmp_path / "rig.json").write_text(json.dumps(dataset))
    status, out, err = run(["calibrate", tmp_path / "rig.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "rig.json" in line and "'spare'" in line and "no image names it" in line


def test_capture_rig_camera_without_images_is_refused_by_name(tmp_path, capsys):
    camera = {"model": "pinhole", "width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}
    observations = {"F0": [100.0, 100.0], "F1": [200.0, 110.0], "F2": [110.0, 200.0], "F3": [210.0, 205.0]}
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "cameras": {"left": camera, "right": camera},
               "target": {"kind": "points", "fiducials": {"F0": [0, 0, 0], "F1": [0.1, 0, 0], "F2": [0, 0.1, 0],
                                                        "F3": [0.1, 0.1, 0]}},
               "images": [{"id": "l0", "camera": "left", "mirror_configs": [0], "observations": observations}]}
    (tmp_path / "cap.json").write_text(json.dumps(capture))
    status, out, err = run(["calibrate", tmp_path / "cap.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "cap.json" in line and "'right'" in line and "no image names it" in line


# -- messages in the user's words ----------------------------------------------------------------------


def test_calibrate_of_a_result_says_it_is_a_result(target_free, tmp_path, capsys):
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 0
    capsys.readouterr()
    status, out, err = run(["calibrate", tmp_path / "r.json", "-o", tmp_path / "again.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "r.json: this is a result" in line and "calibrate takes a dataset or capture" in line, line
    assert "unknown format" not in line


@pytest.mark.parametrize("name, header, kind", [
    ("photo.jpg", b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\xff", "a JPEG image"),
    ("photo.png", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff", "a PNG image"),
])
def test_calibrate_of_a_photo_says_it_wants_a_capture(name, header, kind, tmp_path, capsys):
    (tmp_path / name).write_bytes(header + bytes(range(256)))
    status, out, err = run(["calibrate", tmp_path / name, "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert f"{name}: is {kind}" in line and "capture file" in line and "docs/capture_guide.md" in line, line
    assert "UTF-8" not in line


def test_missing_image_says_where_it_looked(tmp_path, capsys):
    import shutil
    import tempfile

    # a short folder: the command line elides a path longer than 80 characters in the middle
    folder = Path(tempfile.mkdtemp(prefix="mfg"))
    try:
        _check_missing_image_message(folder, tmp_path, capsys)
    finally:
        shutil.rmtree(folder)


def _check_missing_image_message(folder: Path, tmp_path: Path, capsys) -> None:
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1,
               "camera": {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5},
               "target": {"kind": "chessboard", "cols": 4, "rows": 3, "square": 0.03},
               "images": [{"file": "shots/a.png", "mirror_configs": [0]}]}
    (folder / "c.json").write_text(json.dumps(capture))
    status, out, err = run(["calibrate", folder / "c.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert "image file not found" in line and str(folder / "shots" / "a.png") in line and "capture's folder" in line
    capture["images"].append({"file": "shots/b.png", "mirror_configs": [1]})
    (folder / "c.json").write_text(json.dumps(capture))
    status, out, err = run(["calibrate", folder / "c.json", "-o", tmp_path / "r.json"], capsys)
    line = one_error_line(err)
    assert status == 2 and "2 image files not found" in line and f"looked in {folder}" in line, line


# -- side files of an earlier run under the same name, target-free outputs ----------------------------


def test_earlier_rig_side_files_are_removed_and_a_strangers_file_is_named(target_free, tmp_path, capsys):
    """A one-camera result written over a rig's name: the rig's camchain, its standard deviations and its
    cameras' camera_info files (mirror-fg's) go; a file mirror-fg did not write is left, with a warning."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "r.json").write_text(json.dumps({"format": "mirror-fg/result@1", "cameras": {"left": {}, "right": {}}}))
    ours = {"r.camchain.yaml": "# Kalibr camchain written by mirror-fg from r.json\ncam0: {}\n",
            "r.camchain-sigma.yaml": "# Standard deviations of the mirror-fg camchain of r.json\n",
            "r.left.camera_info.yaml": "# camera_info of the camera estimated through the mirrors by mirror-fg\n",
            "r.camera_info.yaml": "# camera_info of the camera estimated through the mirrors by mirror-fg\n"}
    for name, text in ours.items():
        (out / name).write_text(text)
    (out / "r.right.camera_info.yaml").write_text("image_width: 640\n")  # the user's own
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, stdout, err = run(["calibrate", path, "-o", out / "r.json"], capsys)
    assert status == 0, stdout + err
    assert sorted(p.name for p in out.iterdir()) == ["r.json", "r.right.camera_info.yaml"]
    for name in ours:
        assert f"removed {out / name}" in stdout
    assert f"warning: {out / 'r.right.camera_info.yaml'} is not from this run" in stdout
    assert (out / "r.right.camera_info.yaml").read_text() == "image_width: 640\n"


def test_earlier_side_file_that_is_an_input_is_kept(target_free, tmp_path, capsys):
    """A side file of the earlier run that this run reads (a camera file, say) is never removed."""
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "a.json")]) == 0
    result = json.loads((tmp_path / "a.json").read_text())
    side = tmp_path / "r.camera_info.yaml"
    side.write_text("# camera_info of the camera estimated through the mirrors by mirror-fg\n")
    outputs = plan_calibration_outputs([path, side], tmp_path / "r.json")
    outputs.write(result)
    assert side.exists() and (tmp_path / "r.json").exists()
    assert not any(str(side) in note for note in outputs.notes)


def test_target_free_run_writes_no_identity_ros_files(target_free, tmp_path, capsys):
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, out, err = run(["calibrate", path, "-o", tmp_path / "r.json"], capsys)
    assert status == 0, out + err
    assert not (tmp_path / "r.ros.yaml").exists() and not (tmp_path / "r.urdf.xml").exists()
    assert "note: no ROS/URDF files: without a known target" in out


def test_calibrate_many_says_the_base_is_the_camera_without_a_target(target_free, tmp_path, capsys):
    path = with_point_scale(target_free, true_point_distance(target_free), tmp_path)
    status, out, err = run(["calibrate-many", path, "-o", tmp_path / "fleet"], capsys)
    assert status == 0, out + err
    row = next(line for line in out.splitlines() if "data.json" in line)
    assert "base = camera (no target)" in row and "[0.0, 0.0, 0.0]" not in row, row
    assert sorted(p.name for p in (tmp_path / "fleet").iterdir()) == ["data.result.json"]


# -- the analytical start of the general model --------------------------------------------------------


def _rotation_deg(Ra, Rb) -> float:
    cos = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@pytest.mark.parametrize("cameras", [None, "2"], ids=["one-camera", "rig"])
def test_general_result_carries_the_propagation_start(cameras, tmp_path, capsys):
    """docs/formats.md promises the analytical solution's T_cam_base in every result: for the general model
    it is the propagation's start (per camera for a rig), near the truth but not the MLE itself."""
    argv = ["simulate", "--kind", "mixed", "-o", tmp_path / "d.json"] + (["--cameras", cameras] if cameras else [])
    assert run(argv, capsys)[0] == 0
    status, out, err = run(["calibrate", tmp_path / "d.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 0, out + err
    result = json.loads((tmp_path / "r.json").read_text())
    truth = json.loads((tmp_path / "d.truth.json").read_text())
    analytic = result["analytic"]
    assert analytic is not None
    starts = analytic["cameras"] if cameras else {None: analytic}
    truths = truth["cameras"] if cameras else {None: truth}
    if cameras:
        assert list(starts) == list(result["cameras"]) == list(truths)
        assert starts[next(iter(starts))]["T_cam_base"] == analytic["T_cam_base"]
    for name, start in starts.items():
        R, t = np.array(start["T_cam_base"]["R"]), np.array(start["T_cam_base"]["t"])
        true = truths[name]["T_cam_base"]
        # a start (noisy PnP and propagation), far closer to the truth than to the identity (~25 deg away)
        assert _rotation_deg(R, true["R"]) < 10.0 and np.linalg.norm(t - np.array(true["t"])) < 0.1, name
    final = np.array(result["T_cam_base"]["t"])
    assert not np.allclose(np.array(analytic["T_cam_base"]["t"]), final, atol=1e-9)  # the start, not the MLE


# -- a rig with four fiducials, and rig images naming the wrong camera --------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_simulated_rig_with_four_fiducials_solves(seed, tmp_path, capsys):
    """With 4 fiducials a rig camera's pose comes from PnP through the shared placements (rule 1); its own
    mirror's placements, two unknown in every view, still need the camera's own tree (rule 2)."""
    assert run(["simulate", "--cameras", "2", "--fiducials", "4", "--seed", seed, "-o", tmp_path / "d.json"],
               capsys)[0] == 0
    status, out, err = run(["calibrate", tmp_path / "d.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 0, out + err
    result = json.loads((tmp_path / "r.json").read_text())
    truth = json.loads((tmp_path / "d.truth.json").read_text())
    for name, entry in result["cameras"].items():  # each camera within 5 of its 3-sigma bounds of the truth
        true = truth["cameras"][name]["T_cam_base"]
        error_mm = 1000 * np.abs(np.array(entry["T_cam_base"]["t"]) - np.array(true["t"]))
        bound_mm = np.array(entry["sigma3_cam_base"]["position_mm"])
        assert np.all(error_mm <= 5 * bound_mm), (name, error_mm, bound_mm)


def test_rig_images_relabelled_as_another_camera_are_named(rig, tmp_path, capsys):
    dataset = json.loads(json.dumps(rig[1]))
    moved = [im for im in dataset["images"] if im["camera"] == "cam1"][:2]
    for image in moved:
        image["camera"] = "cam0"
    (tmp_path / "rig.json").write_text(json.dumps(dataset))
    status, out, err = run(["calibrate", tmp_path / "rig.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 2, out + err
    line = one_error_line(err)
    assert f"'{moved[0]['id']}'" in line and "mislabelled" in line and "camera 'cam1' has no image there" in line, line
    assert "plane" not in line


def test_target_free_rig_says_the_first_cameras_entries_are_no_calibration(target_free, tmp_path, capsys):
    """Two cameras without a known target (here coincident, seeing the same views): the ROS files are
    written for the second camera's pose relative to the first, with a note that the first's is the identity."""
    dataset = json.loads(json.dumps(target_free[0]))
    dataset["scale"] = {"points": ["P0", "P1"], "distance": true_point_distance(target_free)}
    camera = dataset.pop("camera")
    dataset["cameras"] = {"a": camera, "b": camera}
    dataset["images"] = [dict(image, camera=name, id=f"{image['id']}_{name}")
                         for image in dataset["images"] for name in ("a", "b")]
    (tmp_path / "rig.json").write_text(json.dumps(dataset))
    status, out, err = run(["calibrate", tmp_path / "rig.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 0, out + err
    assert (tmp_path / "r.ros.yaml").exists()
    assert "base frame is camera a's own frame" in out and "identity by definition" in out


def test_rig_images_of_own_placements_relabelled_are_named(rig, tmp_path, capsys):
    """Relabelled images of placements only their true camera sees: the start fails, and says which images
    look mislabelled before the plane it could not start."""
    dataset = json.loads(json.dumps(rig[1]))
    own = [im for im in dataset["images"] if im["camera"] == "cam1" and (im.get("mirror_configs") or [0])[0] >= 3][:2]
    assert len(own) == 2
    for image in own:
        image["camera"] = "cam0"
    (tmp_path / "rig.json").write_text(json.dumps(dataset))
    status, out, err = run(["calibrate", tmp_path / "rig.json", "-o", tmp_path / "r.json"], capsys)
    assert status == 3, out + err
    line = one_error_line(err)
    assert all(f"image '{im['id']}' is the only image of camera 'cam0'" in line for im in own), line
    assert "name the wrong camera?" in line and line.index("wrong camera") < line.index("plane")
