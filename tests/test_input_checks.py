"""Input checks at the boundary: implausible sizes (millimetres in metres fields), camchains with
several cameras, one rule for placement indices, bounded memory on a huge string, and messages in the
user's words. Each test fails on the code before the fix."""
from __future__ import annotations

import json
import re
import resource
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mirror_fg.cli import main
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import MAX_INDEX
from mirror_fg.io.capture import load_capture
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.io.result import validate_result
from mirror_fg.simulate.tree import simulate_base_case

REPO = Path(__file__).resolve().parents[1]
CAMERA = {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5}


@pytest.fixture(scope="module")
def dataset_dict() -> dict:
    dataset, _ = simulate_base_case(num_images=45, num_points=0, pixel_sigma=0.5, seed=5)
    return dataset_to_dict(dataset)


def write_capture(tmp_path: Path, **changes) -> Path:
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((48, 64), np.uint8))
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": dict(CAMERA),
               "target": {"kind": "chessboard", "cols": 4, "rows": 3, "square": 0.03},
               "images": [{"file": "a.png", "mirror_configs": [0]}]}
    capture.update(changes)
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(capture, sort_keys=False))
    return path


def capture_error(tmp_path: Path, **changes) -> str:
    path = write_capture(tmp_path, **changes)
    with pytest.raises(DatasetError) as info:
        load_capture(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    return message


def dataset_error(d: dict) -> str:
    with pytest.raises(DatasetError) as info:
        dataset_from_dict(d, source="d.json")
    message = str(info.value)
    assert "\n" not in message and message.startswith("d.json"), message
    return message


def cli_error(capsys, *argv: str) -> str:
    assert main(list(argv)) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


# --- units ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("target, words", [
    ({"kind": "chessboard", "cols": 10, "rows": 7, "square": 27.5}, ["square 27.5 m", "metres", "27.5 mm = 0.0275"]),
    ({"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 100,
      "tags": {0: {"R": np.eye(3).tolist(), "t": [0, 0, 0]}}}, ["tag_size 100 m", "metres", "= 0.1"]),
    ({"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.1,
      "grid": {"cols": 3, "rows": 2, "spacing": 150, "first_id": 0}}, ["extent", "metres"]),
    ({"kind": "points", "fiducials": {"A": [0, 0, 0], "B": [200, 0, 0], "C": [0, 200, 0]}}, ["extent", "metres"]),
])
def test_a_target_sized_in_millimetres_is_refused_naming_the_unit(tmp_path, target, words):
    """Before: `square: 27.5` loaded (and calibrated to t = 487 m)."""
    message = capture_error(tmp_path, target=target)
    for word in words:
        assert word in message, message


def test_plausible_targets_still_load(tmp_path):
    for target in ({"kind": "chessboard", "cols": 10, "rows": 7, "square": 0.0275},
                   {"kind": "apriltag", "dictionary": "tag36h11", "tag_size": 0.9,
                    "grid": {"cols": 2, "rows": 2, "spacing": 1.0, "first_id": 0}}):
        assert load_capture(write_capture(tmp_path, target=target)).target.kind == target["kind"]


def test_dataset_fiducials_in_millimetres_are_refused(dataset_dict):
    """Before: accepted; the calibration came out 1000 times too far."""
    d = dict(dataset_dict, fiducials={n: (1000 * np.asarray(p)).tolist() for n, p in dataset_dict["fiducials"].items()})
    extent = np.ptp(np.array(list(d["fiducials"].values())), axis=0)
    message = dataset_error(d)
    assert "fiducials" in message and "metres" in message, message
    assert f"{np.linalg.norm(extent):g} m" in message, message
    dataset_from_dict(dataset_dict)  # the same layout in metres is fine


# --- camchains ------------------------------------------------------------------------------------


def _kalibr(fx: float) -> dict:
    return {"camera_model": "pinhole", "intrinsics": [fx, fx, 31.5, 23.5], "distortion_model": "none",
            "resolution": [64, 48]}


def test_a_camchain_with_several_cameras_needs_the_name(tmp_path, capsys):
    """Before: cam0 was taken silently."""
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump({"cam0": _kalibr(50.0), "cam1": _kalibr(60.0)}))
    message = capture_error(tmp_path, camera="camchain.yaml")
    assert "cam0, cam1" in message and "name: cam1" in message, message
    cap = load_capture(write_capture(tmp_path, camera={"file": "camchain.yaml", "name": "cam1"}))
    assert cap.camera["fx"] == 60.0
    # the CLI says which camera it used (here detection then finds no board: exit 2)
    main(["detect", str(write_capture(tmp_path, camera={"file": "camchain.yaml", "name": "cam1"})),
          "-o", str(tmp_path / "d.json")])
    assert "camera cam1 of the camchain" in capsys.readouterr().out


def test_a_camchain_with_one_camera_needs_no_name(tmp_path):
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump({"cam0": _kalibr(55.0)}))
    assert load_capture(write_capture(tmp_path, camera="camchain.yaml")).camera["fx"] == 55.0


# --- placement indices: one rule ---------------------------------------------------------------------


def test_a_huge_placement_index_is_refused_on_input(dataset_dict, tmp_path, capsys):
    """Before: 10**12 was accepted, the calibration ran, and the result validator refused its own output."""
    d = json.loads(json.dumps(dataset_dict))
    d["images"][0]["mirror_configs"][1] = 10**12
    path = tmp_path / "d.json"
    path.write_text(json.dumps(d))
    line = cli_error(capsys, "calibrate", str(path), "-o", str(tmp_path / "r.json"))
    assert "mirror_configs[1]" in line and str(MAX_INDEX) in line, line
    assert not (tmp_path / "r.json").exists()
    message = capture_error(tmp_path, images=[{"file": "a.png", "mirror_configs": [10**12]}])
    assert "mirror_configs[0]" in message and str(MAX_INDEX) in message, message


def test_the_largest_index_accepted_on_input_is_valid_in_a_result(dataset_dict):
    """The same constant bounds both ends: a dataset at the limit gives a result the validator accepts."""
    import mirror_fg

    d = json.loads(json.dumps(dataset_dict))
    for image in d["images"]:
        image["mirror_configs"][1] = MAX_INDEX - image["mirror_configs"][1]
    ds = dataset_from_dict(d)
    cal = mirror_fg.calibrate(ds)
    result = validate_result(cal.to_dict(), "result")
    assert max(m["config"] for m in result["mirrors"]) == MAX_INDEX
    d["images"][0]["mirror_configs"][1] = MAX_INDEX + 1
    assert str(MAX_INDEX) in dataset_error(d)


# --- bounded memory on a huge string ---------------------------------------------------------------


def _run_capped(code: str, path: Path, memory_gb: float = 1.0) -> subprocess.CompletedProcess:
    """``python -c code path`` in a child whose address space is capped (a runaway is killed, not us)."""
    limit = int(memory_gb * 2**30)

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120,
                          preexec_fn=cap, cwd=REPO)


def _load_in_capped_child(path: Path) -> subprocess.CompletedProcess:
    return _run_capped("import sys, mirror_fg\n"
                       "try:\n    mirror_fg.load_dataset(sys.argv[1]); print('loaded')\n"
                       "except mirror_fg.DatasetError as e:\n    print('refused:', e)\n", path)


@pytest.mark.parametrize("kind", ["plain", "escapes", "unknown key"])
def test_a_50_mb_string_is_read_within_bounded_memory(dataset_dict, tmp_path, kind):
    """Before: the depth scan's string pattern kept one backtracking entry per character (6.5 GB for 50 MB:
    MemoryError); an unknown 50 MB key went into difflib (2.3 GB, then MemoryError)."""
    n = 50 * 2**20
    d = json.loads(json.dumps(dataset_dict))
    text = json.dumps(d)
    if kind == "plain":
        text = text.replace('"img', '"' + "x" * n + "img", 1)
    elif kind == "escapes":
        text = text.replace('"img', '"' + '\\"' * (n // 2) + "img", 1)
    else:
        text = text[:-1] + ', "' + "k" * n + '": 1}'
    path = tmp_path / "big.json"
    path.write_text(text)
    proc = _load_in_capped_child(path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout.strip()
    if kind == "unknown key":
        assert out.startswith("refused:") and "unknown key" in out and len(out) < 400, out[:400]
    else:
        assert out == "loaded", out[:400]


def test_a_json_file_of_more_values_than_the_limit_is_refused_before_parsing(tmp_path):
    """Before: MAX_NODES held for YAML only; 21 million empty objects (63 MB of "{},") became 1.7 GB of
    dicts (MemoryError under this cap). The count is exact (against the parsed data's)."""
    from mirror_fg.io.fileio import MAX_NODES, _json_shape

    path = tmp_path / "many.json"
    path.write_text("[" + "{}," * (MAX_NODES + 1_000_000) + "{}]")
    proc = _load_in_capped_child(path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("refused:") and f"more than {MAX_NODES} values" in proc.stdout, proc.stdout[:400]
    def count(value) -> int:  # the reference: values of the parsed data
        items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else []
        return 1 + sum(count(item) for item in items)

    for text in ('[1, [ ], {"a": [2, 3], "b": {}}, "x,[y"]', '{"k": [[], [[ ]], [1]]}', " 7 ", '"a,{"'):
        assert _json_shape(text)[1] == count(json.loads(text)), text


def test_a_yaml_file_of_millions_of_values_is_refused_before_they_are_kept(tmp_path):
    """Before: PyYAML composed every node first (~650 bytes each, pure Python): 2 million values in a
    4 MB capture took minutes and over a gigabyte before any check; now one line, in seconds."""
    path = tmp_path / "capture.yaml"
    path.write_text("format: mirror-fg/capture@1\nimages: [" + "0," * 2_000_000 + "0]\n")
    proc = _run_capped("import sys\nfrom mirror_fg.io.capture import load_capture\nfrom mirror_fg.core.errors import "
                       "DatasetError\ntry:\n    load_capture(sys.argv[1])\nexcept DatasetError as e:\n    print('refused:', e)\n",
                       path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "refused:" in proc.stdout and "values in a YAML file" in proc.stdout, proc.stdout[:400]


# --- messages in the user's words --------------------------------------------------------------------


def test_too_few_placements_is_said_in_placements(dataset_dict, tmp_path, capsys):
    """Before: "the root (no mirror placed) has 2 placement(s) of mirror 1 under it"."""
    d = dict(dataset_dict, images=[im for im in dataset_dict["images"] if im["mirror_configs"][0] != 2])
    path = tmp_path / "two.json"
    path.write_text(json.dumps(d))
    line = cli_error(capsys, "calibrate", str(path), "-o", str(tmp_path / "r.json"))
    assert "mirror 1 needs at least three placements, you gave two" in line, line
    assert "other order" not in line, line  # reversed, the labels fail too: no order hint


def test_swapped_mirror_order_is_hinted(dataset_dict, tmp_path, capsys):
    """Before: "placement (1, 0) has 1 placement(s) of mirror 2 under it", nothing about the order."""
    d = dict(dataset_dict, images=[dict(im, mirror_configs=im["mirror_configs"][::-1]) for im in dataset_dict["images"]])
    path = tmp_path / "swapped.json"
    path.write_text(json.dumps(d))
    line = cli_error(capsys, "calibrate", str(path), "-o", str(tmp_path / "r.json"))
    assert "under placement (1, 0) (mirror 1 at placement 0), mirror 2 needs at least three placements" in line, line
    assert "other order" in line and "mirror_configs" in line, line


def test_the_target_kind_list_names_aruco(tmp_path):
    message = capture_error(tmp_path, target={"kind": "arucoo"})
    kinds = message.split("kind must be")[1].split("got")[0]
    assert re.search(r"\baruco\b", kinds) and "apriltag" in kinds, message  # not only inside "charuco"


def test_report_of_a_dataset_says_it_is_one_and_the_order(dataset_dict, tmp_path, capsys):
    """Before: "unknown format 'mirror-fg/dataset@1'"."""
    path = tmp_path / "d.json"
    path.write_text(json.dumps(dataset_dict))
    line = cli_error(capsys, "report", str(path), "-o", str(tmp_path / "rep"))
    assert "is a dataset" in line and f"mirror-fg calibrate {path}" in line and "mirror-fg report" in line, line
    line = cli_error(capsys, "report", str(path), str(path), "-o", str(tmp_path / "rep"))
    assert "is a dataset" in line and "report RESULT DATASET" in line, line


def test_a_camera_file_in_a_dataset_says_dataset_needs_it_inline(dataset_dict):
    """Before: "camera: expected an object or null, got a string"."""
    for camera in ("cam.yaml", {"file": "cam.yaml"}):
        message = dataset_error(dict(dataset_dict, camera=camera))
        assert "dataset@1" in message and "inline" in message and "capture@1" in message, message


def test_every_missing_image_is_named(tmp_path):
    """Before: only the first missing image was named."""
    images = [{"file": "a.png", "mirror_configs": [0]}] + [
        {"file": f"missing{k}.png", "mirror_configs": [k]} for k in range(6)]
    message = capture_error(tmp_path, images=images)
    assert "6 image files not found" in message, message
    for k in range(4):
        assert f"missing{k}.png" in message, message
    assert "and 2 more" in message, message
    message = capture_error(tmp_path, images=images[:2])
    assert "missing0.png" in message and "image file not found" in message, message
