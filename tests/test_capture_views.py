"""capture@1 reflections, kaleidoscope views and rig cameras: loading, detection per
region of interest on a rendered kaleidoscope photograph, and the dataset@1 dictionary detection builds.

The dataset parser for ``reflections`` / ``cameras`` is not this module's: the dictionary that
``detect_capture`` hands to ``dataset_from_dict`` is captured (``dataset_from_dict`` monkeypatched) and
checked as it is.
"""
from __future__ import annotations

import copy
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import load_script, pose_difference
import mirror_fg.vision.detect as detect_module
from mirror_fg.core.camera import camera_from_dict
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.capture import capture_from_dict
from mirror_fg.vision.detect import detect_capture
from mirror_fg.vision.detect_views import Output, expand_each, view_camera
from mirror_fg.vision.detectors import FOUND, NOT_FOUND, REFUSED, detect_charuco, detect_chessboard

render_kaleidoscope = load_script("render_kaleidoscope")

POINTS = {"kind": "points", "fiducials": {"F0": [0, 0, 0], "F1": [0.2, 0, 0], "F2": [0, 0.2, 0], "F3": [0.2, 0.2, 0.05]}}
CAMERA = {"model": "pinhole", "width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}
OBS = {"F0": [100.0, 100.0], "F1": [200.0, 110.0], "F2": [110.0, 200.0], "F3": [210.0, 205.0]}


def detected_dict(capture, monkeypatch) -> tuple[dict, list]:
    """The dataset@1 dictionary ``detect_capture`` builds (handed to a stand-in ``dataset_from_dict``)."""
    seen: dict = {}

    def keep(data, source=""):
        seen["data"] = copy.deepcopy(data)
        return "dataset"

    monkeypatch.setattr(detect_module, "dataset_from_dict", keep)
    dataset, reports = detect_capture(capture, progress=False)
    assert dataset == "dataset"
    return seen["data"], reports


# --------------------------------------------------------------------------------------------------
# The rendered kaleidoscope: one photograph, five views, each detected in its region
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["chessboard", "charuco"])
def kaleidoscope(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(f"kaleidoscope_{request.param}")
    path, truth = render_kaleidoscope.write(out, request.param)
    from mirror_fg.io.capture import load_capture

    capture = load_capture(path)
    with pytest.MonkeyPatch.context() as mp:
        data, reports = detected_dict(capture, mp)
    return request.param, path, truth, data, reports


def test_each_view_detected_in_its_region_sub_pixel(kaleidoscope):
    kind, _, truth, data, reports = kaleidoscope
    views = truth["views"]
    assert [r.status for r in reports] == [FOUND] * len(views) == [FOUND] * 5
    assert [im["id"] for im in data["images"]] == [f"kaleidoscope#{k}" for k in range(5)]
    all_errors = []
    for image, view in zip(data["images"], views):
        errors = np.array([np.linalg.norm(np.subtract(image["observations"][n], view["pixels"][n]))
                           for n in image["observations"]])
        x, y, w, h = view["roi"]
        assert all(x <= u < x + w and y <= v < y + h for u, v in image["observations"].values())  # full-image pixels
        print(f"{kind} {image['id']} reflections {image['reflections']}: {len(errors)} corners, "
              f"median {np.median(errors):.3f} px, max {errors.max():.3f} px")
        if kind == "chessboard":  # every corner, in capture@1 order (handedness per view)
            assert len(errors) == 20 and errors.max() < 0.25, errors.max()
        else:  # corners by id; OpenCV's ChArUco interpolation is looser on the small foreshortened views
            # (the same detector on full images: tests/test_charuco.py); a wrong shift or parity is pixels off
            assert len(errors) >= 8 and np.median(errors) < 0.3, np.median(errors)
        all_errors += list(errors)
    all_errors = np.array(all_errors)
    assert np.median(all_errors) < 0.1
    if kind == "charuco":
        assert np.mean(all_errors < 0.5) > 0.9 and all_errors.max() < 3.0, np.sort(all_errors)[-5:]


def test_views_keep_their_reflections_in_the_dataset(kaleidoscope):
    _, _, truth, data, _ = kaleidoscope
    assert [im["reflections"] for im in data["images"]] == [v["reflections"] for v in truth["views"]]
    assert all("mirror_configs" not in im and "camera" not in im for im in data["images"])
    assert data["camera"]["width"] == 1600 and "cameras" not in data and data["num_mirrors"] == 2
    assert set(data["fiducials"]) >= set(data["images"][0]["observations"])


def test_kaleidoscope_photograph_calibrates_to_the_truth(kaleidoscope):
    """End to end: the views' dataset (the real parser) calibrated; pose and both fixed mirrors within 3 sigma."""
    from mirror_fg import calibrate
    from mirror_fg.io.capture import load_capture

    kind, path, truth, _, _ = kaleidoscope
    ds, _ = detect_capture(load_capture(path), progress=False)
    assert [im.reflections for im in ds.images] == [tuple(map(tuple, v["reflections"])) for v in truth["views"]]
    cal = calibrate(ds)
    error = pose_difference(truth["R_cam_base"], truth["t_cam_base"], cal.R_cam_base, cal.t_cam_base)
    sigma = np.sqrt(np.diag(cal.covariance))
    print(f"{kind}: pose error / sigma {np.round(error / sigma, 2)}")
    assert np.all(np.abs(error) < 3 * sigma), error / sigma
    for mirror in cal.to_dict()["mirrors"]:
        v_true = np.array(truth["mirror_vectors"][str(mirror["mirror"])])
        assert np.all(np.abs(np.array(mirror["v"]) - v_true) < np.array(mirror["sigma3_mm"]) / 1000), mirror


def test_mirrored_views_need_their_own_parity(kaleidoscope):
    """A view through one mirror is mirror-imaged, through two it is not: detecting a crop with the
    other parity fails (ChArUco markers do not decode) or reads the board in the wrong handedness."""
    kind, path, truth, _, _ = kaleidoscope
    gray = cv2.imread(str(path.parent / "kaleidoscope.png"), cv2.IMREAD_GRAYSCALE)
    target = render_kaleidoscope.scene(kind).target
    for view in truth["views"]:
        x, y, w, h = view["roi"]
        crop = np.ascontiguousarray(gray[y:y + h, x:x + w])
        wrong = len(view["reflections"]) % 2 == 0
        if kind == "charuco":
            assert detect_charuco(crop, target, mirrored=wrong).status == NOT_FOUND, view["reflections"]
        else:
            det = detect_chessboard(crop, target, mirrored=wrong)
            if det.status == FOUND:
                error = max(np.linalg.norm(det.points[n] + [x, y] - view["pixels"][n]) for n in det.points)
                assert error > 10.0, view["reflections"]  # corners mislabelled: a square (>= 20 px) off
            else:
                assert det.status in (NOT_FOUND, REFUSED)


def test_view_camera_moves_the_principal_point_with_the_crop():
    camera = {**CAMERA, "dist": [-0.2, 0.05, 0.001, -0.002, 0.01]}
    roi = (150, 90, 200, 170)
    full = camera_from_dict(camera, "full")
    crop = camera_from_dict(view_camera(camera, roi), "crop")
    pixels = np.array([[170.0, 100.0], [340.5, 250.25], [260.0, 180.0]])
    np.testing.assert_allclose(crop.normalize(pixels - [roi[0], roi[1]]), full.normalize(pixels), atol=1e-12)


# --------------------------------------------------------------------------------------------------
# Loading: one-line errors naming the capture file and the image
# --------------------------------------------------------------------------------------------------


@pytest.fixture
def photo(tmp_path) -> Path:
    cv2.imwrite(str(tmp_path / "k.png"), np.full((480, 640), 128, np.uint8))
    return tmp_path


def board_capture(images, **top) -> dict:
    """A chessboard capture of ``images`` (with ``cameras`` in ``top``: a rig, without ``camera``)."""
    one = {} if "cameras" in top else {"camera": CAMERA}
    return {"format": "mirror-fg/capture@1", "num_mirrors": 2, **one,
            "target": {"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.03}, "images": images, **top}


@pytest.mark.parametrize("image, words", [
    ({"file": "k.png", "views": [{"roi": [10, 10, 0, 50], "reflections": []}]}, "views[0]: roi must be [x, y, w, h]"),
    ({"file": "k.png", "views": [{"roi": [-1, 10, 50, 50], "reflections": []}]}, "views[0]: roi must be"),
    ({"file": "k.png", "views": [{"roi": [10.5, 10, 50, 50], "reflections": []}]}, "integer pixels"),
    ({"file": "k.png", "views": [{"roi": [10, 10, 50], "reflections": []}]}, "roi must be"),
    ({"file": "k.png", "views": [{"reflections": []}]}, "views[0]: missing 'roi'"),
    ({"file": "k.png", "views": [{"roi": [600, 10, 50, 50], "reflections": []}]}, "reaches outside the 640 x 480 image"),
    ({"file": "k.png", "views": [{"roi": [0, 0, 10, 10], "reflections": []}, {"roi": [0, 400, 50, 81], "reflections": []}]},
     "views[1]: roi [0, 400, 50, 81] reaches outside"),
    ({"file": "k.png", "mirror_configs": [0, 0], "reflections": [[1, 0]]}, "give mirror_configs or reflections, not both"),
    ({"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "mirror_configs": [0, 0], "reflections": []}]}, "not both"),
    ({"file": "k.png", "reflections": [[3, 0]]}, "reflections[0]: mirror 3 is not one of 1..2"),
    ({"file": "k.png", "reflections": [[0, 0]]}, "mirror 0 is not one of 1..2"),
    ({"file": "k.png", "reflections": [[1, 0], [2, 1], [2, 0]]}, "reflections[2]: mirror 2 twice in a row"),
    ({"file": "k.png", "reflections": [[1, -1]]}, "reflections[0]: config must be a non-negative integer"),
    ({"file": "k.png", "reflections": [1, 0]}, "reflections[0] must be a [mirror, config] pair"),
    ({"file": "k.png", "reflections": {"1": 0}}, "reflections must be a list of [mirror, config] pairs"),
    ({"file": "k.png"}, "missing 'mirror_configs' (or 'reflections'"),
    ({"file": "k.png", "reflections": [], "views": [{"roi": [0, 0, 9, 9], "reflections": []}]}, "views: give each view its reflections"),
    ({"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "reflections": [], "id": "a"},
                                 {"roi": [0, 0, 9, 9], "reflections": [], "id": "a"}]}, "view id 'a' is given twice"),
    ({"file": "k.png", "views": []}, "views must be a non-empty list"),
    ({"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "reflection": []}]}, "reflection"),
    ({"file": "k.png", "camera": "left", "reflections": []}, "an image names its camera only when the capture declares 'cameras"),
])
def test_bad_reflections_and_views_are_one_line_naming_the_image(photo, image, words):
    with pytest.raises(DatasetError) as info:
        capture_from_dict(board_capture([image]), source="cap.yaml", base_dir=str(photo))
    message = str(info.value)
    assert "\n" not in message and message.startswith("cap.yaml: images[0] (k.png)") and words in message, message


def test_overlapping_rois_and_mixed_forms_load(photo):
    cap = capture_from_dict(board_capture([
        {"file": "k.png", "views": [{"roi": [0, 0, 300, 300], "reflections": []},
                                    {"roi": [200, 200, 300, 280], "reflections": [[1, 0], [2, "each"]], "id": "double"}]},
        {"file": "k.png", "id": "tree", "mirror_configs": [1, "each"]},
        {"file": "k.png", "id": "direct", "reflections": []},
    ]), source="cap.yaml", base_dir=str(photo))
    kal, tree, direct = cap.images
    assert [v.id for v in kal.views] == ["k#0", "double"] and kal.views[1].roi == (200, 200, 300, 280)
    assert kal.views[1].reflections == ((1, 0), (2, "each")) and kal.mirror_configs == ()
    assert tree.mirror_configs == (1, "each") and tree.reflections == ((1, 1), (2, "each")) and tree.mirrored is False
    assert direct.reflections == () and direct.mirror_configs == () and direct.mirrored is False


def test_view_ids_do_not_collide_with_image_ids(photo):
    with pytest.raises(DatasetError, match=r"images\[1\] \(k.png\): views\[0\]: image id 'k#0' is also that of images\[0\]"):
        capture_from_dict(board_capture([
            {"file": "k.png", "id": "k#0", "reflections": []},
            {"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "reflections": []}]},
        ]), source="cap.yaml", base_dir=str(photo))


def test_track_with_views_is_refused(photo):
    capture = board_capture([{"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "reflections": []}]}],
                            track={"P0": {"frame": 0, "pixel": [5.0, 5.0]}})
    with pytest.raises(DatasetError, match="track: tracking through photographs with 'views' is not supported"):
        capture_from_dict(capture, source="cap.yaml", base_dir=str(photo))


# --------------------------------------------------------------------------------------------------
# each, and the dataset dictionary's forms
# --------------------------------------------------------------------------------------------------


def points_capture(images, **top) -> dict:
    return {**board_capture(images, **top), "target": POINTS}


def test_each_is_fresh_per_photograph_in_both_forms(monkeypatch):
    cap = capture_from_dict(points_capture([
        {"id": "a", "mirror_configs": [0, "each"], "observations": OBS},
        {"id": "b", "mirror_configs": [0, "each"], "observations": OBS},
        {"id": "c", "reflections": [[2, "each"], [1, "each"]], "observations": OBS},
        {"id": "d", "reflections": [], "observations": OBS},
        {"id": "e", "reflections": [[1, 4], [2, 3]], "observations": OBS},
    ]), source="cap.yaml")
    data, reports = detected_dict(cap, monkeypatch)
    assert [r.status for r in reports] == [FOUND] * 5
    images = {im["id"]: im for im in data["images"]}
    # fresh integers above every integer the capture uses for that mirror (mirror 1: 4, mirror 2: 3)
    assert images["a"]["mirror_configs"] == [0, 4] and images["b"]["mirror_configs"] == [0, 5]
    assert images["c"]["reflections"] == [[2, 6], [1, 5]] and "mirror_configs" not in images["c"]
    assert images["d"]["reflections"] == [] and images["e"]["reflections"] == [[1, 4], [2, 3]]
    assert all("reflections" not in images[i] for i in "ab")
    assert images["a"]["observations"] == OBS and data["camera"]["fx"] == 500.0


def test_each_is_shared_by_the_views_of_one_photograph(photo):
    cap = capture_from_dict(board_capture([
        {"file": "k.png", "views": [{"roi": [0, 0, 9, 9], "reflections": [[1, "each"]]},
                                    {"roi": [0, 0, 9, 9], "reflections": [[1, "each"], [2, 0]]}]},
        {"file": "k.png", "id": "other", "views": [{"roi": [0, 0, 9, 9], "reflections": [[1, "each"]]}]},
    ]), source="cap.yaml", base_dir=str(photo))
    first, other = cap.images
    outputs = [Output(v.id, (), {}, v.reflections, group=e.id) for e in cap.images for v in e.views]
    assert expand_each(cap, outputs) == [{"reflections": [[1, 0]]}, {"reflections": [[1, 0], [2, 0]]},
                                         {"reflections": [[1, 1]]}]


# --------------------------------------------------------------------------------------------------
# Rigs
# --------------------------------------------------------------------------------------------------


RIG = {"left": CAMERA, "right": {**CAMERA, "width": 320, "height": 240, "fx": 260.0, "fy": 260.0, "cx": 159.5, "cy": 119.5}}


def test_rig_dataset_has_cameras_and_each_image_its_camera(monkeypatch):
    cap = capture_from_dict(points_capture([
        {"id": "l0", "camera": "left", "mirror_configs": [0, 0], "observations": OBS},
        {"id": "r0", "camera": "right", "mirror_configs": [0, 0], "observations": OBS},  # triggered together
        {"id": "r1", "camera": "right", "reflections": [[1, 1]], "observations": OBS},
    ], cameras=RIG), source="cap.yaml")
    assert list(cap.cameras) == ["left", "right"] and cap.camera == cap.cameras["left"]
    data, _ = detected_dict(cap, monkeypatch)
    assert "camera" not in data and list(data["cameras"]) == ["left", "right"]
    assert data["cameras"]["right"]["width"] == 320 and data["cameras"]["right"]["fx"] == 260.0
    assert [(im["id"], im["camera"]) for im in data["images"]] == [("l0", "left"), ("r0", "right"), ("r1", "right")]
    assert data["images"][0]["mirror_configs"] == data["images"][1]["mirror_configs"] == [0, 0]
    assert data["images"][2]["reflections"] == [[1, 1]]


@pytest.mark.parametrize("change, words", [
    (lambda c: c["images"][0].update(camera="centre"), "images[0]: camera 'centre' is not declared under 'cameras' (left, right)"),
    (lambda c: c["images"][0].pop("camera"), "images[0]: missing 'camera' (which camera took it: one of left, right)"),
    (lambda c: c.update(camera=CAMERA), "give 'camera' (one camera) or 'cameras'"),
    (lambda c: c.update(cameras={}), "cameras: expected {name: camera} with at least one camera"),
    (lambda c: c.update(cameras={1: CAMERA}), "camera names must be non-empty strings"),
    (lambda c: c["cameras"].update(right={**CAMERA, "fx": -1.0}), "cameras: right"),
    (lambda c: (c.pop("images"), c.update(target={"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.03},
                                          video={"file": "v.mp4", "segments": []})), "video: a rig ('cameras') needs 'images'"),
])
def test_bad_rig_is_one_line(change, words):
    capture = points_capture([{"id": "l0", "camera": "left", "mirror_configs": [0, 0], "observations": OBS}],
                             cameras=copy.deepcopy(RIG))
    change(capture)
    with pytest.raises(DatasetError) as info:
        capture_from_dict(capture, source="cap.yaml")
    assert "\n" not in str(info.value) and str(info.value).startswith("cap.yaml: ") and words in str(info.value), str(info.value)


def test_rig_images_are_checked_against_their_own_camera(tmp_path, monkeypatch):
    cv2.imwrite(str(tmp_path / "l.png"), np.full((480, 640), 128, np.uint8))
    cv2.imwrite(str(tmp_path / "r.png"), np.full((240, 320), 128, np.uint8))
    capture = board_capture([
        {"file": "l.png", "camera": "left", "mirror_configs": [0, 0]},
        {"file": "r.png", "camera": "right", "mirror_configs": [0, 0]},
        {"file": "l.png", "id": "wrong", "camera": "right", "mirror_configs": [0, 1]},
    ], cameras=RIG)
    cap = capture_from_dict(capture, source="cap.yaml", base_dir=str(tmp_path))
    with pytest.raises(DatasetError) as info:
        detected_dict(cap, monkeypatch)  # blank images: nothing found, but only the wrong one is refused
    message = str(info.value)
    assert "l: not found" in message and "r: not found" in message
    assert "wrong: refused: image is 640 x 480 pixels, the camera 320 x 240" in message


def test_rendered_rig_kaleidoscope_detected_per_camera_and_calibrated(tmp_path, monkeypatch):
    """Two cameras photograph the kaleidoscope at once: each photograph's views are detected with its own
    camera, share the two fixed placements, and the rig calibrates to both cameras' true poses."""
    from mirror_fg import calibrate
    from mirror_fg.io.capture import load_capture

    path, truth = render_kaleidoscope.write(tmp_path, "chessboard", rig=True)
    capture = load_capture(path)
    data, reports = detected_dict(capture, monkeypatch)
    assert [r.status for r in reports] == [FOUND] * 10
    assert list(data["cameras"]) == ["left", "right"] and "camera" not in data
    for image in data["images"]:
        name, k = image["id"].removeprefix("kaleidoscope_").split("#")
        view = truth[name]["views"][int(k)]
        assert image["camera"] == name and image["reflections"] == view["reflections"]
        errors = [np.linalg.norm(np.subtract(image["observations"][n], view["pixels"][n])) for n in view["pixels"]]
        assert max(errors) < 0.25, (image["id"], max(errors))
    monkeypatch.undo()
    ds, _ = detect_capture(capture, progress=False)
    cal = calibrate(ds)
    assert list(cal.cameras) == ["left", "right"]
    for name, pose in cal.cameras.items():
        error = pose_difference(truth[name]["R_cam_base"], truth[name]["t_cam_base"], pose.R_cam_base, pose.t_cam_base)
        sigma = np.sqrt(np.diag(pose.covariance))
        print(f"rig {name}: pose error / sigma {np.round(error / sigma, 2)}")
        assert np.all(np.abs(error) < 3 * sigma), (name, error / sigma)


def test_rig_cameras_from_one_camchain_and_input_files(tmp_path):
    import yaml

    chain = {f"cam{k}": {"camera_model": "pinhole", "intrinsics": [500.0 + k, 500.0, 319.5, 239.5],
                         "distortion_model": "radtan", "distortion_coeffs": [0.0, 0.0, 0.0, 0.0],
                         "resolution": [640, 480]} for k in range(2)}
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(chain))
    cameras = {"left": {"file": "camchain.yaml", "name": "cam0"}, "right": {"file": "camchain.yaml", "name": "cam1"}}
    cap = capture_from_dict(points_capture([
        {"id": "l0", "camera": "left", "reflections": [[1, 0]], "observations": OBS},
        {"id": "r0", "camera": "right", "reflections": [[1, 0]], "observations": OBS},
    ], cameras=cameras), source="cap.yaml", base_dir=str(tmp_path))
    assert (cap.cameras["left"]["fx"], cap.cameras["right"]["fx"]) == (500.0, 501.0)
    assert cap.input_files() == [str(tmp_path / "camchain.yaml")]  # once; no capture file (built from a dict)


def test_video_segments_take_reflections(tmp_path):
    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48), isColor=False)
    for _ in range(6):
        writer.write(np.full((48, 64), 128, np.uint8))
    writer.release()
    capture = board_capture(None, video={"file": "run.avi", "segments": [
        {"frames": [0, 2], "reflections": [[1, "each"]]}, {"frames": [3, 5], "mirror_configs": [0, 1]}]})
    del capture["images"]
    cap = capture_from_dict(capture, source="cap.yaml", base_dir=str(tmp_path))
    first, second = cap.video.segments
    assert first.reflections == ((1, "each"),) and first.mirror_configs == ()
    assert second.reflections == ((1, 0), (2, 1)) and second.mirror_configs == (0, 1)
    outputs = [Output(f"run:{f}", s.mirror_configs, {}, s.reflections) for s in (first, second) for f in s.output_frames()]
    assert expand_each(cap, outputs) == [{"reflections": [[1, 1]]}, {"reflections": [[1, 2]]}, {"reflections": [[1, 3]]}] \
        + [{"mirror_configs": [0, 1]}] * 3
    capture["video"]["segments"][0]["mirror_configs"] = [0, 0]
    with pytest.raises(DatasetError, match=r"cap.yaml: video \(run.avi\): segments\[0\]: give mirror_configs or reflections"):
        capture_from_dict(capture, source="cap.yaml", base_dir=str(tmp_path))


def test_symmetric_chessboard_with_views_is_refused_in_one_line(photo):
    capture = board_capture([{"file": "k.png", "views": [{"roi": [0, 0, 99, 99], "reflections": []}]}])
    capture["target"] = {"kind": "chessboard", "cols": 5, "rows": 3, "square": 0.03}
    with pytest.raises(DatasetError, match=r"^cap.yaml: target: a symmetric chessboard .* use a board with cols \+ rows odd"):
        detect_capture(capture_from_dict(capture, source="cap.yaml", base_dir=str(photo)), progress=False)
