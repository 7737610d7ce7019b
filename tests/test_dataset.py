"""Tests of mirror_fg.io.dataset: dataset@1 / result@1 files, validation messages, atomic writes."""
from __future__ import annotations

import copy
import json
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from conftest import TAKAHASHI
from mirror_fg.io.dataset import (
    DATASET_FORMAT,
    dataset_from_dict,
    dataset_to_dict,
    load_dataset,
    save_dataset,
    validate_image,
)
from mirror_fg.data import Dataset, Image
from mirror_fg.io.result import RESULT_FORMAT, load_result, write_result
from mirror_fg.core.camera import Camera
from mirror_fg.core.errors import DatasetError

SHARED = TAKAHASHI
DIST = [-0.28, 0.09, 0.0012, -0.0008, -0.015]  # a wide-angle lens, OpenCV (k1, k2, p1, p2, k3)


def good_dict() -> dict[str, Any]:
    """A small valid two-mirror dataset@1 with a distorted camera and one reconstruction point."""
    return {
        "format": DATASET_FORMAT,
        "num_mirrors": 2,
        "camera": {"model": "pinhole", "width": 1024, "height": 768,
                   "fx": 800.0, "fy": 790.0, "cx": 512.0, "cy": 384.0, "dist": list(DIST)},
        "pixel_sigma": 0.5,
        "fiducials": {"F0": [0.0, 0.0, 0.0], "F1": [0.2, 0.0, 0.0], "F2": [0.0, 0.2, 0.0],
                      "F3": [0.1, 0.1, 0.05]},
        "images": [
            {"id": "img000", "mirror_configs": [0, 0],
             "observations": {"F0": [612.3, 401.9], "F1": [655.0, 398.2], "F2": [610.1, 452.7],
                              "P0": [630.4, 420.0]}},
            {"id": "img001", "mirror_configs": [0, 1],
             "observations": {"F0": [512.5, 300.25], "F1": [555, 298], "F3": [530.0, 330.0]}},
            {"id": "img002", "mirror_configs": [1, 2],
             "observations": {"F0": [400.0, 200.0], "F2": [410.0, 260.0], "P0": [420.0, 230.0]}},
        ],
    }


def write_json(path: Path, data: Any) -> Path:
    path.write_text(json.dumps(data))
    return path


def assert_error(exc: pytest.ExceptionInfo[DatasetError], *words: str) -> None:
    """The message is one line and contains every word (case-insensitive)."""
    message = str(exc.value)
    assert "\n" not in message, message
    assert "Traceback" not in message
    for word in words:
        assert word.lower() in message.lower(), f"{word!r} not in {message!r}"


def assert_same_dataset(a: Dataset, b: Dataset) -> None:
    assert a.num_mirrors == b.num_mirrors
    assert a.camera == b.camera
    assert a.pixel_sigma == b.pixel_sigma
    assert list(a.fiducials) == list(b.fiducials)
    for name in a.fiducials:
        np.testing.assert_array_equal(a.fiducials[name], b.fiducials[name])
    assert [i.id for i in a.images] == [i.id for i in b.images]
    for ia, ib in zip(a.images, b.images):
        assert ia.mirror_configs == ib.mirror_configs
        assert list(ia.observations) == list(ib.observations)
        for name in ia.observations:
            np.testing.assert_array_equal(ia.observations[name], ib.observations[name])


# ------------------------------------------------------------------------------------------------
# Loading, types, round trips
# ------------------------------------------------------------------------------------------------


def test_loads_types_and_values() -> None:
    ds = dataset_from_dict(good_dict(), source="mem.json")
    assert ds.source == "mem.json"
    assert ds.num_mirrors == 2 and ds.pixel_sigma == 0.5
    assert ds.camera == Camera(1024, 768, 800.0, 790.0, 512.0, 384.0, tuple(DIST))
    assert all(isinstance(x, float) for x in ds.camera.dist)
    for p in ds.fiducials.values():
        assert isinstance(p, np.ndarray) and p.dtype == np.float64 and p.shape == (3,)
    for image in ds.images:
        assert isinstance(image.mirror_configs, tuple)
        assert all(type(m) is int for m in image.mirror_configs)
        for z in image.observations.values():
            assert isinstance(z, np.ndarray) and z.dtype == np.float64 and z.shape == (2,)
    np.testing.assert_array_equal(ds.images[1].observations["F1"], [555.0, 298.0])
    assert ds.images[2].mirror_configs == (1, 2)
    assert ds.reconstruction_point_names == ["P0"]
    assert ds.configurations == [(1, 0), (1, 1), (2, 0), (2, 1), (2, 2)]


def test_round_trip_file(tmp_path: Path) -> None:
    d = good_dict()
    ds = load_dataset(write_json(tmp_path / "in.json", d))
    save_dataset(tmp_path / "out.json", ds)
    again = load_dataset(tmp_path / "out.json")
    assert_same_dataset(ds, again)
    assert again.source == str(tmp_path / "out.json")
    # the file is exactly the dataset@1 shape, values as written (ints become floats)
    assert json.loads((tmp_path / "out.json").read_text()) == json.loads(json.dumps(d))
    assert dataset_to_dict(again) == dataset_to_dict(ds)


def test_round_trip_without_camera(tmp_path: Path) -> None:
    d = good_dict()
    d["camera"] = None
    d["pixel_sigma"] = 1e-3
    for image in d["images"]:
        image["observations"] = {n: [u / 1000.0, v / 1000.0] for n, (u, v) in image["observations"].items()}
    ds = dataset_from_dict(d)
    assert ds.camera is None
    np.testing.assert_allclose(ds.normalized_sigma, [1e-3, 1e-3])
    out = dataset_to_dict(ds)
    assert out["camera"] is None
    save_dataset(tmp_path / "n.json", ds)
    assert_same_dataset(ds, load_dataset(tmp_path / "n.json"))
    # absent camera means the same as null
    del d["camera"]
    assert dataset_from_dict(d).camera is None


def test_save_is_atomic_and_keeps_old_file_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "data.json"
    ds = dataset_from_dict(good_dict())
    save_dataset(path, ds)
    before = path.read_text()
    ds.images[0].observations["F0"] = np.array([np.nan, 1.0])  # cannot be written as strict JSON
    with pytest.raises(ValueError):
        save_dataset(path, ds)
    assert path.read_text() == before
    assert sorted(os.listdir(tmp_path)) == ["data.json"]


@pytest.mark.parametrize("name, fiducials", [("dataset.json", 70), ("dataset_3p.json", 3)])
def test_shared_real_datasets_load(name: str, fiducials: int) -> None:
    ds = load_dataset(SHARED / name)
    assert ds.num_mirrors == 1
    assert len(ds.fiducials) == fiducials
    assert len(ds.images) == 5
    assert ds.camera is not None and ds.camera.width == 1600 and ds.camera.height == 1200
    assert ds.configurations == [(1, m) for m in range(5)]
    assert all(len(image.observations) >= 3 for image in ds.images)
    raw = json.loads((SHARED / name).read_text())
    assert dataset_to_dict(ds) == json.loads(json.dumps(raw))  # nothing lost or reordered


# ------------------------------------------------------------------------------------------------
# normalized() against OpenCV
# ------------------------------------------------------------------------------------------------


def test_normalized_inverts_opencv_projection_with_distortion() -> None:
    d = good_dict()
    rng = np.random.default_rng(7)
    x_true = rng.uniform(-0.5, 0.5, size=(40, 2))  # normalized coordinates, out to ~30 degrees
    rays = np.hstack([x_true, np.ones((40, 1))])
    K = np.array([[800.0, 0.0, 512.0], [0.0, 790.0, 384.0], [0.0, 0.0, 1.0]])
    pixels, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.array(DIST))
    pixels = pixels.reshape(-1, 2)
    assert np.max(np.abs(pixels - (x_true * [800.0, 790.0] + [512.0, 384.0]))) > 5.0  # distortion matters
    d["images"][0]["observations"] = {f"P{i}": pixels[i].tolist() for i in range(40)}
    ds = dataset_from_dict(d)
    z = ds.normalized(ds.images[0])
    got = np.array([z[f"P{i}"] for i in range(40)])
    np.testing.assert_allclose(got, x_true, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.normalized_sigma, [0.5 / 800.0, 0.5 / 790.0])
    # Camera.distort is the inverse
    np.testing.assert_allclose(ds.camera.distort(got), pixels, rtol=0, atol=1e-6)


def test_normalized_without_camera_is_identity() -> None:
    d = good_dict()
    d["camera"] = None
    ds = dataset_from_dict(d)
    z = ds.normalized(ds.images[0])
    for name, value in ds.images[0].observations.items():
        np.testing.assert_array_equal(z[name], value)


def test_normalized_does_not_reuse_coordinates_of_another_image_with_the_same_id() -> None:
    ds = dataset_from_dict(good_dict())
    first = ds.normalized(ds.images[0])
    other = copy.deepcopy(ds.images[0])
    other.observations["F0"] = other.observations["F0"] + 10.0
    second = ds.normalized(other)
    assert not np.allclose(first["F0"], second["F0"])
    np.testing.assert_array_equal(first["F1"], second["F1"])
    np.testing.assert_allclose(ds.normalized(ds.images[0])["F0"], first["F0"], rtol=0, atol=0)


# ------------------------------------------------------------------------------------------------
# Bad input: one test per case
# ------------------------------------------------------------------------------------------------


def load_mutated(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], Any]
) -> pytest.ExceptionInfo[DatasetError]:
    """Write good_dict() changed by ``mutate`` to data.json; load_dataset must fail naming the file."""
    d = good_dict()
    mutate(d)
    path = write_json(tmp_path / "data.json", d)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    assert "data.json" in str(exc.value)
    return exc


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as exc:
        load_dataset(tmp_path / "nope.json")
    assert_error(exc, "nope.json", "cannot read")


def test_directory_is_unreadable(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as exc:
        load_dataset(tmp_path)
    assert_error(exc, str(tmp_path), "cannot read")


def test_not_json_names_line_and_column(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text('{\n  "format": "mirror-fg/dataset@1",\n  "num_mirrors": 2,,\n}\n')
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    assert_error(exc, "bad.json", "not valid JSON", "line 3", "column 20")


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "bin.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    assert_error(exc, "bin.json", "UTF-8")


def test_duplicate_json_key(tmp_path: Path) -> None:
    path = tmp_path / "dup.json"
    text = json.dumps(good_dict()).replace('"F0": [612.3, 401.9]', '"F0": [612.3, 401.9], "F0": [1.0, 2.0]')
    path.write_text(text)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    assert_error(exc, "dup.json", "'F0'", "twice")


def test_top_level_not_an_object(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as exc:
        load_dataset(write_json(tmp_path / "list.json", [1, 2]))
    assert_error(exc, "list.json", "object")


def test_missing_format(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.pop("format")), "missing 'format'", DATASET_FORMAT)


def test_unknown_format(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d.update(format="mirror-fg/dataset@2"))
    assert_error(exc, "unknown format", "dataset@2")


@pytest.mark.parametrize("value", [0, -1, 1.5, 2.0, "2", True, None])
def test_bad_num_mirrors(tmp_path: Path, value: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d.update(num_mirrors=value))
    assert_error(exc, "num_mirrors", "integer >= 1")


def test_mirror_configs_wrong_length(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][2].update(mirror_configs=[1]))
    assert_error(exc, "image 'img002'", "mirror_configs has 1 entries, expected 2 (num_mirrors)")


@pytest.mark.parametrize("entry", [-1, 1.0, 0.5, "0", True, None])
def test_mirror_configs_bad_entry(tmp_path: Path, entry: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][1].update(mirror_configs=[0, entry]))
    assert_error(exc, "image 'img001'", "mirror_configs[1]", "mirror 2", "non-negative integer")


@pytest.mark.parametrize("value", ["01", {"a": 0}, 3])
def test_mirror_configs_not_a_list(tmp_path: Path, value: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][0].update(mirror_configs=value))
    assert_error(exc, "image 'img000'", "mirror_configs")


def test_missing_mirror_configs(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][0].pop("mirror_configs"))
    assert_error(exc, "image 'img000'", "missing 'mirror_configs'")


def test_fewer_than_three_fiducials(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d.update(fiducials={"F0": [0, 0, 0], "F1": [1, 0, 0]}))
    assert_error(exc, "2 fiducials", "at least 3")


def test_missing_fiducials(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.pop("fiducials")), "missing 'fiducials'")


def test_collinear_fiducials(tmp_path: Path) -> None:
    line = {"F0": [0.0, 0.0, 0.0], "F1": [0.1, 0.2, 0.3], "F2": [0.2, 0.4, 0.6 + 1e-9],
            "F3": [-1.0, -2.0, -3.0]}
    exc = load_mutated(tmp_path, lambda d: d.update(fiducials=line))
    assert_error(exc, "collinear", "4 fiducials")


def test_coincident_fiducials_are_collinear(tmp_path: Path) -> None:
    same = {f"F{i}": [0.5, 0.5, 0.5] for i in range(3)}
    assert_error(load_mutated(tmp_path, lambda d: d.update(fiducials=same)), "collinear")


def test_nearly_collinear_but_not_within_tolerance_is_accepted() -> None:
    d = good_dict()
    d["fiducials"] = {"F0": [0.0, 0.0, 0.0], "F1": [1.0, 0.0, 0.0], "F2": [2.0, 1e-4, 0.0]}
    assert len(dataset_from_dict(d).fiducials) == 3


@pytest.mark.parametrize(
    "value, words",
    [
        ([0.0, float("nan"), 0.0], ["not finite"]),
        ([0.0, float("inf"), 0.0], ["not finite"]),
        ([0.0, 10**400, 0.0], ["not finite"]),
        ([0.0, 0.0], ["expected 3 coordinates", "got 2"]),
        ([0.0, 0.0, 0.0, 1.0], ["expected 3 coordinates", "got 4"]),
        ([0.0, "1", 0.0], ["coordinate 1", "not a number"]),
        ([0.0, True, 0.0], ["coordinate 1", "not a number"]),
        ([0.0, [1.0], 0.0], ["coordinate 1", "not a number"]),
        ("0 0 0", ["expected 3 coordinates"]),
        (None, ["missing coordinates"]),
    ],
)
def test_bad_fiducial_coordinates(tmp_path: Path, value: Any, words: list[str]) -> None:
    exc = load_mutated(tmp_path, lambda d: d["fiducials"].update(F2=value))
    assert_error(exc, "fiducial 'F2'", *words)


@pytest.mark.parametrize(
    "value, words",
    [
        ([float("nan"), 1.0], ["not finite"]),
        ([1.0, float("-inf")], ["not finite"]),
        ([1.0], ["expected 2 coordinates", "got 1"]),
        ([1.0, 2.0, 3.0], ["expected 2 coordinates", "got 3"]),
        ([1.0, "2"], ["coordinate 1", "not a number"]),
        ([False, 2.0], ["coordinate 0", "not a number"]),
        ({"u": 1, "v": 2}, ["expected 2 coordinates"]),
        (None, ["missing coordinates"]),
    ],
)
def test_bad_observation_coordinates(tmp_path: Path, value: Any, words: list[str]) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][1]["observations"].update(F1=value))
    assert_error(exc, "image 'img001'", "point 'F1'", *words)


def test_non_finite_observation_from_json_nan_literal(tmp_path: Path) -> None:
    path = tmp_path / "nan.json"
    path.write_text(json.dumps(good_dict()).replace("[612.3, 401.9]", "[NaN, 401.9]"))
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    assert_error(exc, "nan.json", "image 'img000'", "point 'F0'", "not finite")


@pytest.mark.parametrize("value", [0, -0.5, float("nan"), float("inf"), "1", True, None])
def test_bad_pixel_sigma(tmp_path: Path, value: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d.update(pixel_sigma=value))
    assert_error(exc, "pixel_sigma", "finite number > 0")


def test_missing_pixel_sigma(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.pop("pixel_sigma")), "missing 'pixel_sigma'")


def test_duplicate_image_ids(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][2].update(id="img000"))
    assert_error(exc, "image 'img000'", "duplicate image id", "images[0]", "images[2]")


def test_empty_image_list(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.update(images=[])), "no images")


def test_missing_images(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.pop("images")), "no images")


def test_images_not_a_list(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d.update(images={"img000": {}}))
    assert_error(exc, "'images' must be a list")


def test_image_not_an_object(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"].append(["img9", [0, 0]]))
    assert_error(exc, "images[3]", "expected an object")


@pytest.mark.parametrize("key", ["width", "height", "fx", "fy", "cx", "cy"])
def test_camera_missing_field(tmp_path: Path, key: str) -> None:
    exc = load_mutated(tmp_path, lambda d: d["camera"].pop(key))
    assert_error(exc, "camera", f"missing '{key}'")


@pytest.mark.parametrize("key, value", [("fx", 0.0), ("fy", -800.0), ("fx", float("nan")), ("fy", "800")])
def test_camera_bad_focal_length(tmp_path: Path, key: str, value: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["camera"].update({key: value}))
    assert_error(exc, "camera", key)


@pytest.mark.parametrize("key, value", [("width", 0), ("height", -768), ("width", 1024.5), ("height", True)])
def test_camera_bad_size(tmp_path: Path, key: str, value: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["camera"].update({key: value}))
    assert_error(exc, "camera", key, "positive integer")


@pytest.mark.parametrize(
    "dist", [[], [0.1, 0.0, 0.0], [0.0] * 6, [0.0] * 13, [0.1, "x", 0, 0], [0, 0, 0, float("nan")], 0.1]
)
def test_camera_bad_dist(tmp_path: Path, dist: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["camera"].update(dist=dist))
    assert_error(exc, "camera", "dist", "4, 5, 8, 12 or 14")


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_camera_dist_lengths_accepted(n: int) -> None:
    d = good_dict()
    d["camera"]["dist"] = [0.0] * n
    assert dataset_from_dict(d).camera.dist == (0.0,) * n


def test_camera_not_an_object_or_other_model(tmp_path: Path) -> None:
    assert_error(load_mutated(tmp_path, lambda d: d.update(camera=[800.0])), "camera", "object or null")
    exc = load_mutated(tmp_path, lambda d: d["camera"].update(model="omni"))
    assert_error(exc, "camera", "unsupported model", "omni")
    # fisheye is a model now, with exactly 4 coefficients (k1..k4): the 5 here are refused
    exc = load_mutated(tmp_path, lambda d: d["camera"].update(model="fisheye"))
    assert_error(exc, "camera", "fisheye", "4 finite numbers")


def test_image_with_no_observations(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][1].update(observations={}))
    assert_error(exc, "image 'img001'", "no observations")


def test_image_with_missing_observations(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][1].pop("observations"))
    assert_error(exc, "image 'img001'", "missing 'observations'")


@pytest.mark.parametrize("image_id", ["", 7, None, ["a"]])
def test_image_id_not_a_non_empty_string(tmp_path: Path, image_id: Any) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][1].update(id=image_id))
    assert_error(exc, "images[1]", "non-empty string")


def test_empty_point_name(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][0]["observations"].update({"": [1.0, 2.0]}))
    assert_error(exc, "image 'img000'", "point name", "non-empty string")


def test_message_names_are_quoted_on_one_line(tmp_path: Path) -> None:
    exc = load_mutated(tmp_path, lambda d: d["images"][0].update(id="a\nb", mirror_configs=[0]))
    assert_error(exc, r"image 'a\nb'", "mirror_configs has 1 entries")


# ------------------------------------------------------------------------------------------------
# validate_image (the incremental path)
# ------------------------------------------------------------------------------------------------


def test_validate_image_accepts_dict_and_image() -> None:
    ds = dataset_from_dict(good_dict())
    from_dict = validate_image({"id": "new", "mirror_configs": [3, 0], "observations": {"F0": [1, 2]}}, ds)
    assert from_dict.id == "new" and from_dict.mirror_configs == (3, 0)
    assert from_dict.observations["F0"].dtype == np.float64
    image = Image("n2", (np.int64(1), 2), {"F1": np.array([3.0, 4.0], dtype=np.float32), "Q": (5, 6)})
    checked = validate_image(image, ds)
    assert checked.mirror_configs == (1, 2) and all(type(m) is int for m in checked.mirror_configs)
    np.testing.assert_array_equal(checked.observations["Q"], [5.0, 6.0])
    assert checked is not image
    assert ds.images[0].id == "img000" and len(ds.images) == 3  # ds untouched


def test_validate_image_checks_against_num_mirrors() -> None:
    ds = dataset_from_dict(good_dict())
    with pytest.raises(DatasetError) as exc:
        validate_image(Image("x", (0, 0, 0), {"F0": np.array([1.0, 2.0])}), ds, index=12)
    assert_error(exc, "<dataset>", "image 'x'", "has 3 entries, expected 2")


def test_validate_image_rejects_non_finite_image_object() -> None:
    ds = dataset_from_dict(good_dict())
    with pytest.raises(DatasetError) as exc:
        validate_image(Image("x", (0, 0), {"F0": np.array([np.inf, 2.0])}), ds)
    assert_error(exc, "image 'x'", "point 'F0'", "not finite")
    with pytest.raises(DatasetError) as exc:
        validate_image(Image("x", (0, 0), {"F0": np.array([[1.0, 2.0]])}), ds)
    assert_error(exc, "image 'x'", "point 'F0'", "expected 2 coordinates")


def test_validate_image_index_names_an_image_without_id() -> None:
    ds = dataset_from_dict(good_dict())
    with pytest.raises(DatasetError) as exc:
        validate_image({"mirror_configs": [0, 0], "observations": {"F0": [1, 2]}}, ds, index=4)
    assert_error(exc, "images[4]", "image id", "non-empty string", "None")


def test_validate_image_known_points_is_strict() -> None:
    ds = dataset_from_dict(good_dict())
    image = {"id": "i", "mirror_configs": [0, 0], "observations": {"F0": [1, 2], "P0": [3, 4], "X": [5, 6]}}
    assert set(validate_image(image, ds).observations) == {"F0", "P0", "X"}  # lenient by default
    with pytest.raises(DatasetError) as exc:
        validate_image(image, ds, known_points={"P0"})
    assert_error(exc, "image 'i'", "unknown point 'X'")
    assert set(validate_image(image, ds, known_points={"P0", "X"}).observations) == {"F0", "P0", "X"}
    with pytest.raises(DatasetError) as exc:
        validate_image(image, ds, known_points=set())
    assert_error(exc, "unknown point 'P0'")


# ------------------------------------------------------------------------------------------------
# result@1 files
# ------------------------------------------------------------------------------------------------


def sample_result() -> dict[str, Any]:
    R = np.eye(3)
    return {
        "format": RESULT_FORMAT,
        "T_cam_base": {"R": R, "t": np.array([0.1, -0.2, 0.3]), "q_xyzw": np.array([0.0, 0.0, 0.0, 1.0])},
        "covariance_cam_base": np.eye(6) * 1e-6,
        "mirrors": [{"mirror": np.int64(1), "config": 0, "v": np.array([0.0, 0.0, 0.5]),
                     "sigma3_mm": (1.0, 2.0, 3.0)}],
        "points": {"P0": {"xyz": np.array([1.0, 2.0, 3.0]), "sigma3_mm": [0.1, 0.2, 0.3]}},
        "optimizer": {"iterations": np.int32(4), "initial_error": np.float64(12.5), "final_error": 0.25,
                      "converged": np.bool_(True)},
        "residuals": {"rms_px": np.float32(0.5), "max_px": 1.25},
    }


def expected_plain() -> dict[str, Any]:
    return {
        "format": RESULT_FORMAT,
        "T_cam_base": {"R": np.eye(3).tolist(), "t": [0.1, -0.2, 0.3], "q_xyzw": [0.0, 0.0, 0.0, 1.0]},
        "covariance_cam_base": (np.eye(6) * 1e-6).tolist(),
        "mirrors": [{"mirror": 1, "config": 0, "v": [0.0, 0.0, 0.5], "sigma3_mm": [1.0, 2.0, 3.0]}],
        "points": {"P0": {"xyz": [1.0, 2.0, 3.0], "sigma3_mm": [0.1, 0.2, 0.3]}},
        "optimizer": {"iterations": 4, "initial_error": 12.5, "final_error": 0.25, "converged": True},
        "residuals": {"rms_px": 0.5, "max_px": 1.25},
    }


def test_write_result_json_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    write_result(path, sample_result())
    assert json.loads(path.read_text()) == expected_plain()
    assert load_result(path) == expected_plain()
    loaded = load_result(path)
    assert type(loaded["optimizer"]["iterations"]) is int and loaded["optimizer"]["converged"] is True
    text = path.read_text()
    assert text.startswith('{\n  "format": "mirror-fg/result@1",\n  "T_cam_base"')  # indent 2, key order kept
    assert '"t": [0.1, -0.2, 0.3]' in text  # vectors on one line


def test_write_result_yaml(tmp_path: Path) -> None:
    for name in ("result.yaml", "RESULT.YML"):
        path = tmp_path / name
        write_result(path, sample_result())
        text = path.read_text()
        assert not text.lstrip().startswith("{")  # block style at the top
        assert text.startswith("format: mirror-fg/result@1\nT_cam_base:\n")  # keys in insertion order
        assert "t: [0.1, -0.2, 0.3]" in text  # leaf lists in flow style (default_flow_style=None)
        assert "!!" not in text  # no python/numpy tags
        assert yaml.safe_load(text) == expected_plain()
        assert load_result(path) == expected_plain()


class Unserialisable:
    pass


@pytest.mark.parametrize("name", ["result.json", "result.yaml"])
def test_failed_write_leaves_existing_file_untouched(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    write_result(path, sample_result())
    before = path.read_bytes()
    bad = sample_result()
    bad["points"]["P0"]["xyz"] = Unserialisable()
    with pytest.raises(TypeError) as exc:
        write_result(path, bad)
    assert "result['points']['P0']['xyz']" in str(exc.value) and "Unserialisable" in str(exc.value)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == [name]


def test_failure_in_the_middle_of_writing_leaves_no_trace(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "result.json"
    write_result(path, sample_result())
    before = path.read_bytes()

    def broken_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    changed = expected_plain()
    changed["residuals"]["rms_px"] = 99.0
    with pytest.raises(OSError):
        write_result(path, changed)
    monkeypatch.undo()

    def broken_replace(src: str, dst: str) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(KeyboardInterrupt):
        write_result(path, changed)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["result.json"]


def test_write_result_creates_new_file_with_normal_permissions(tmp_path: Path) -> None:
    path = tmp_path / "new.json"
    old = os.umask(0o022)
    try:
        write_result(path, expected_plain())
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644  # not mkstemp's 0600
    path.chmod(0o640)
    write_result(path, expected_plain())
    assert stat.S_IMODE(path.stat().st_mode) == 0o640  # an existing file keeps its mode


def test_write_result_through_symlink_keeps_the_link(tmp_path: Path) -> None:
    real = tmp_path / "real.json"
    link = tmp_path / "link.json"
    write_result(real, expected_plain())
    link.symlink_to(real)
    changed = expected_plain()
    changed["optimizer"]["iterations"] = 7
    write_result(link, changed)
    assert link.is_symlink()
    assert load_result(real)["optimizer"]["iterations"] == 7


def test_load_result_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as exc:
        load_result(tmp_path / "missing.json")
    assert_error(exc, "missing.json", "cannot read")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("format: mirror-fg/result@1\nT_cam_base: [1, 2\n")
    with pytest.raises(DatasetError) as exc:
        load_result(bad_yaml)
    assert_error(exc, "bad.yaml", "not valid YAML", "line")
    bad_json = tmp_path / "bad.json"
    bad_json.write_text('{"format": }')
    with pytest.raises(DatasetError) as exc:
        load_result(bad_json)
    assert_error(exc, "bad.json", "not valid JSON", "line 1", "column 12")
    wrong = write_json(tmp_path / "wrong.json", {"format": DATASET_FORMAT})
    with pytest.raises(DatasetError) as exc:
        load_result(wrong)
    assert_error(exc, "wrong.json", "unknown format", RESULT_FORMAT)
    no_format = write_json(tmp_path / "none.json", {"T_cam_base": {}})
    with pytest.raises(DatasetError) as exc:
        load_result(no_format)
    assert_error(exc, "none.json", "missing 'format'")


def test_dataset_repr_is_short_and_its_html_summary_bounded(caplog) -> None:
    """repr(ds) of 200 images is one short line (a dataclass repr printed every observation), and the
    notebook table is bounded and escaped whatever the source name."""
    import logging

    from mirror_fg.simulate.tree import simulate_base_case

    ds, _ = simulate_base_case(num_images=200, num_points=10)
    text, table = repr(ds), ds._repr_html_()
    assert len(text) < 400 and len(table) < 1000, (len(text), len(table))
    assert text.startswith("Dataset(") and "images=200" in text and "pinhole 1024x768" in text
    assert "points=10 (P0, P1, P2, P3, P4, P5, ...)" in text
    assert table.startswith("<table>") and "<tr><th>images</th><td>200</td></tr>" in table
    ds.source = "x" * 10_000 + "<script>"
    ds.camera = Camera(1024, 768, 800.0, 800.0, 512.0, 384.0, (0.1,) * 14)
    assert len(repr(ds)) < 500 and len(ds._repr_html_()) < 1000
    assert "<script>" not in ds._repr_html_()
    with caplog.at_level(logging.INFO, logger="mirror_fg"):
        path = Path(__file__).parent.parent / "examples" / "base_case.json"
        load_dataset(path)
    assert any(r.name.startswith("mirror_fg.") and "dataset loaded" in r.getMessage() for r in caplog.records)
