"""capture@1 loading and validation (mirror_fg.io.capture)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import TAKAHASHI
from mirror_fg.io.capture import EACH, load_capture
from mirror_fg.io.target import ChessboardTarget, PointsTarget, TagTarget
from mirror_fg.core.errors import DatasetError

DATA = Path(__file__).parent / "data" / "capture"
CAMERA = {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5}

needs_takahashi = pytest.mark.skipif(not TAKAHASHI.is_dir(), reason="examples/takahashi2012 missing")


def write(tmp_path: Path, capture: dict, name: str = "capture.yaml") -> Path:
    path = tmp_path / name
    if name.endswith(".json"):
        path.write_text(json.dumps(capture))
    else:
        path.write_text(yaml.safe_dump(capture, sort_keys=False))
    return path


def image(tmp_path: Path, name: str = "a.png") -> str:
    cv2.imwrite(str(tmp_path / name), np.zeros((48, 64), np.uint8))
    return name


def chessboard_capture(tmp_path: Path, **changes) -> dict:
    capture = {
        "format": "mirror-fg/capture@1",
        "num_mirrors": 1,
        "camera": dict(CAMERA),
        "target": {"kind": "chessboard", "cols": 4, "rows": 3, "square": 0.03},
        "images": [{"file": image(tmp_path), "mirror_configs": [0]}],
    }
    capture.update(changes)
    return capture


def error_of(tmp_path: Path, capture: dict, name: str = "capture.yaml") -> str:
    path = write(tmp_path, capture, name)
    with pytest.raises(DatasetError) as info:
        load_capture(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    return message


@needs_takahashi
def test_takahashi_capture_loads():
    cap = load_capture(DATA / "takahashi.yaml")
    assert cap.num_mirrors == 1 and cap.mirrored
    assert isinstance(cap.target, ChessboardTarget) and (cap.target.cols, cap.target.rows) == (10, 7)
    assert [e.id for e in cap.images] == [f"input{n}" for n in range(1, 6)]
    assert all(Path(e.file).is_file() for e in cap.images)
    fid = cap.fiducials()
    assert len(fid) == 70
    np.testing.assert_allclose(fid["C00"], [0, 0, 0])
    np.testing.assert_allclose(fid["C69"], [9 * 0.0275, 6 * 0.0275, 0])
    np.testing.assert_allclose(fid["C12"], [2 * 0.0275, 1 * 0.0275, 0])  # C{row*cols+col}
    model = np.loadtxt(TAKAHASHI / "model.txt") / 1000.0
    np.testing.assert_allclose(np.array(list(fid.values())), model, atol=1e-12)


def test_minimal_chessboard_capture_and_defaults(tmp_path):
    cap = load_capture(write(tmp_path, chessboard_capture(tmp_path)))
    assert cap.pixel_sigma == 0.5
    assert cap.camera["dist"] == [0.0] * 5
    assert cap.images[0].id == "a" and cap.images[0].mirror_configs == (0,)
    np.testing.assert_allclose(cap.R_base_target, np.eye(3))


def test_json_capture_and_each(tmp_path):
    capture = chessboard_capture(tmp_path, num_mirrors=2)
    capture["images"] = [{"file": image(tmp_path), "mirror_configs": [0, "each"]}]
    cap = load_capture(write(tmp_path, capture, "capture.json"))
    assert cap.images[0].mirror_configs == (0, EACH)


def test_T_base_target_applied(tmp_path):
    R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    capture = chessboard_capture(tmp_path, T_base_target={"R": R, "t": [1.0, 2.0, 3.0]})
    fid = load_capture(write(tmp_path, capture)).fiducials()
    np.testing.assert_allclose(fid["C00"], [1, 2, 3])
    np.testing.assert_allclose(fid["C01"], [1, 2.03, 3])  # (0.03, 0, 0) turned to (0, 0.03, 0)
    q = {"q_xyzw": [0, 0, float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))], "t": [1.0, 2.0, 3.0]}
    fid_q = load_capture(write(tmp_path, chessboard_capture(tmp_path, T_base_target=q))).fiducials()
    np.testing.assert_allclose(fid_q["C01"], fid["C01"], atol=1e-12)


def test_apriltag_tags_and_grid(tmp_path):
    capture = chessboard_capture(tmp_path, target={
        "kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.1,
        "tags": {3: {"R": np.eye(3).tolist(), "t": [0.5, 0.0, 0.0]}, "4": {"R": np.eye(3).tolist(), "t": [0, 0, 1.0]}}})
    cap = load_capture(write(tmp_path, capture))
    assert isinstance(cap.target, TagTarget) and sorted(cap.target.tags) == [3, 4]
    fid = cap.fiducials()
    np.testing.assert_allclose(fid["T3_0"], [0.45, 0.05, 0])  # (-s/2, s/2, 0) in the tag frame
    np.testing.assert_allclose(fid["T3_2"], [0.55, -0.05, 0])
    grid = chessboard_capture(tmp_path, target={
        "kind": "aruco", "dictionary": "DICT_4X4_50", "tag_size": 0.04,
        "grid": {"cols": 2, "rows": 2, "spacing": 0.05, "first_id": 10}},
        T_base_target={"R": np.eye(3).tolist(), "t": [0, 0, 1.0]})
    fid = load_capture(write(tmp_path, grid)).fiducials()
    assert sorted({n.split("_")[0] for n in fid}) == ["T10", "T11", "T12", "T13"]
    np.testing.assert_allclose(fid["T13_3"], [0.05 - 0.02, -0.05 - 0.02, 1.0])


def test_points_capture_with_text_files_matches_published_dataset(tmp_path):
    if not TAKAHASHI.is_dir():
        pytest.skip("examples/takahashi2012 missing")
    model = np.loadtxt(TAKAHASHI / "model.txt") / 1000.0
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": 1600, "height": 1200, "fx": 2445.724853515625,
                   "fy": 2442.3916015625, "cx": 819.2930297851562, "cy": 660.1307373046875},
        "target": {"kind": "points", "fiducials": {f"C{i:02d}": p.tolist() for i, p in enumerate(model)}},
        "images": [{"observations": str(TAKAHASHI / f"input{n}.txt"), "mirror_configs": [n - 1]} for n in range(1, 6)],
    }
    cap = load_capture(write(tmp_path, capture))
    assert isinstance(cap.target, PointsTarget)
    assert [e.id for e in cap.images] == [f"input{n}" for n in range(1, 6)]
    published = json.loads((TAKAHASHI / "dataset.json").read_text())
    for entry, pub in zip(cap.images, published["images"]):
        for name, uv in pub["observations"].items():
            np.testing.assert_allclose(entry.observations[name], uv, atol=1e-6)


def test_named_observation_lines(tmp_path):
    (tmp_path / "obs.txt").write_text("# name u v\nA 1 2\nB 3 4\nP0 5 6\n")
    capture = chessboard_capture(tmp_path, target={"kind": "points", "fiducials": {
        "A": [0, 0, 0], "B": [1, 0, 0], "C": [0, 1, 0]}})
    capture["images"] = [{"observations": "obs.txt", "mirror_configs": [0]}]
    cap = load_capture(write(tmp_path, capture))
    assert set(cap.images[0].observations) == {"A", "B", "P0"}


def test_camera_from_opencv_filestorage(tmp_path):
    fs = cv2.FileStorage(str(tmp_path / "cam.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.2, 0.001, 0.002, 0.05]]))
    fs.release()
    cap = load_capture(write(tmp_path, chessboard_capture(tmp_path, camera="cam.yaml")))
    assert cap.camera["width"] == 640 and cap.camera["fy"] == 501.0
    np.testing.assert_allclose(cap.camera["dist"], [0.1, -0.2, 0.001, 0.002, 0.05])


def test_camera_from_kalibr_and_ros(tmp_path):
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0],
        "distortion_model": "radtan", "distortion_coeffs": [0.01, 0.02, 0.003, 0.004], "resolution": [640, 480]}}))
    cap = load_capture(write(tmp_path, chessboard_capture(tmp_path, camera="camchain.yaml")))
    assert (cap.camera["fx"], cap.camera["cy"], cap.camera["width"]) == (400.0, 240.0, 640)
    assert cap.camera["dist"] == [0.01, 0.02, 0.003, 0.004]
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump({
        "image_width": 64, "image_height": 48,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [50.0, 0, 31.5, 0, 50.0, 23.5, 0, 0, 1]},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0, 0, 0, 0, 0]}}))
    cap = load_capture(write(tmp_path, chessboard_capture(tmp_path, camera={"file": "ros.yaml"})))
    assert cap.camera["cx"] == 31.5 and cap.camera["height"] == 48
    (tmp_path / "fish.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [1, 1, 0, 0], "distortion_model": "equidistant",
        "distortion_coeffs": [0, 0, 0, 0], "resolution": [64, 48]}}))
    cap = load_capture(write(tmp_path, chessboard_capture(tmp_path, camera="fish.yaml")))  # a fisheye
    assert (cap.camera["model"], cap.camera["dist"], cap.camera["width"]) == ("fisheye", [0, 0, 0, 0], 64)
    (tmp_path / "fov.yaml").write_text(yaml.safe_dump({"cam0": {
        "camera_model": "pinhole", "intrinsics": [1, 1, 0, 0], "distortion_model": "fov",
        "distortion_coeffs": [0.9], "resolution": [64, 48]}}))
    assert "fov" in error_of(tmp_path, chessboard_capture(tmp_path, camera="fov.yaml"))


@pytest.mark.parametrize(
    "change, words",
    [
        ({"format": "mirror-fg/capture@2"}, "unknown format"),
        ({"num_mirrors": 0}, "num_mirrors"),
        ({"pixel_sigma": -1}, "pixel_sigma"),
        ({"camera": {"fx": 1}}, "missing"),
        ({"camera": "nowhere.yaml"}, "not found"),
        ({"target": {"kind": "chessboard", "cols": 2, "rows": 4, "square": 0.03}}, "cols must be an integer >= 3"),
        ({"target": {"kind": "chessboard", "cols": 4, "rows": 3, "square": 0}}, "square"),
        ({"target": {"kind": "circles"}}, "kind"),
        ({"target": {"kind": "apriltag", "dictionary": "tag99h1", "tag_size": 0.1, "tags": {0: {"R": np.eye(3).tolist(), "t": [0, 0, 0]}}}}, "unknown dictionary"),
        ({"target": {"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.1, "tags": {600: {"R": np.eye(3).tolist(), "t": [0, 0, 0]}}}}, "tag id 600 is not in dictionary"),
        ({"target": {"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.1, "tags": {1: {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "t": [0, 0, 0]}}}}, "not a rotation"),
        ({"target": {"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.1, "tags": {1: {"R": np.eye(3).tolist(), "t": [0, 0, 0]}}},
          "T_base_target": {"R": np.eye(3).tolist(), "t": [0, 0, 0]}}, "already in the base frame"),
        ({"images": [{"file": "missing.png", "mirror_configs": [0]}]}, "images[0] (missing.png): image file not found"),
        ({"images": [{"file": "a.png", "mirror_configs": [0, 1]}]}, "expected 1"),
        ({"images": [{"file": "a.png", "mirror_configs": ["sometimes"]}]}, "'each'"),
        ({"images": [{"file": "a.png", "mirror_configs": [0]}, {"file": "a.png", "mirror_configs": [1]}]}, "image id 'a'"),
        ({"track": {"P0": {"frame": 5, "pixel": [1, 2]}}}, "past the last image"),
        ({"track": {"P0": {"frame": 0, "pixel": [1, 2], "feature": "edge"}}}, "feature must be one of"),
        ({"track": {"P0": {"frame": 0, "pixel": [1, 2], "sigma": 0}}}, "sigma must be"),
        ({"extra": 1}, "unknown key 'extra'"),
        ({"video": {"file": "a.png", "segments": []}}, "exactly one of 'images' and 'video'"),
    ],
)
def test_bad_captures_give_one_line(tmp_path, change, words):
    message = error_of(tmp_path, chessboard_capture(tmp_path, **change))
    assert words in message, message


def test_unreadable_and_short_video(tmp_path):
    (tmp_path / "broken.avi").write_bytes(b"not a video at all" * 100)
    capture = chessboard_capture(tmp_path)
    del capture["images"]
    capture["video"] = {"file": "broken.avi", "segments": [{"frames": [0, 3], "mirror_configs": [EACH]}]}
    assert "cannot open the video" in error_of(tmp_path, capture) or "cannot read" in error_of(tmp_path, capture)
    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 10, (64, 48), isColor=False)
    for _ in range(5):
        writer.write(np.zeros((48, 64), np.uint8))
    writer.release()
    capture["video"] = {"file": "v.avi", "segments": [{"frames": [0, 9], "mirror_configs": [EACH]}]}
    assert "past the end of the video (5 frames" in error_of(tmp_path, capture)
    capture["video"] = {"file": "v.avi", "segments": [{"frames": [0, 2], "mirror_configs": [0]},
                                                      {"frames": [2, 4], "mirror_configs": [1]}]}
    assert "overlap" in error_of(tmp_path, capture)
    capture["video"] = {"file": "v.avi", "segments": [{"frames": [0, 4], "mirror_configs": [EACH]}]}
    capture["track"] = {"C00": {"frame": 0, "pixel": [1, 1]}}
    assert "is a fiducial name" in error_of(tmp_path, capture)
    capture["track"] = {"P0": {"frame": 7, "pixel": [1, 1]}}
    assert "in no video segment" in error_of(tmp_path, capture)
    capture["track"] = {"P0": {"frame": 1, "pixel": [1, 1], "feature": "blob", "sigma": 0.7}}
    cap = load_capture(write(tmp_path, capture))
    assert cap.video.frame_count == 5 and cap.track["P0"].frame == 1
    assert cap.track["P0"].feature == "blob" and cap.track["P0"].sigma == 0.7


def test_yaml_syntax_and_duplicate_keys(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("format: mirror-fg/capture@1\nnum_mirrors: [1\n")
    with pytest.raises(DatasetError, match="not valid YAML"):
        load_capture(path)
    path.write_text("format: mirror-fg/capture@1\nnum_mirrors: 1\nnum_mirrors: 2\n")
    with pytest.raises(DatasetError, match="appears twice"):
        load_capture(path)
    with pytest.raises(DatasetError, match="cannot read file"):
        load_capture(tmp_path / "absent.yaml")
