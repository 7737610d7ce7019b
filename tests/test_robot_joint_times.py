"""capture@1 joints by time (docs/formats.md, "Robot arms"): a ``time`` column matched to each image's
``time`` within ``max_dt``; a video's frames at ``k / fps``; an image with no row near enough, or between
two equally near rows, is refused by name (one line, exit 2)."""
from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.core.errors import DatasetError  # noqa: E402
from mirror_fg.io.capture import capture_from_dict  # noqa: E402
from mirror_fg.io.robot_capture import add_robot_fields  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402


def _write_rows(path, header, rows) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def _capture(tmp_path, shift=None, extra_rows=()):
    """An arm's capture whose joint states come at 50 Hz-like times, each image 4-9 ms from its row; the
    CSV also holds a row between every two images (10 ms from neither) to be passed over."""
    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=4, pixel_sigma=0.5, seed=5)
    write_arm_simulation(str(tmp_path / "arm.json"), dataset, truth)
    names = list(dataset["images"][0]["joints"])
    rng = np.random.default_rng(1)
    rows, times = [], {}
    for k, image in enumerate(dataset["images"]):
        t = 100.0 + 0.5 * k
        times[image["id"]] = t + (shift or {}).get(image["id"], rng.uniform(0.004, 0.009))
        rows.append([repr(t), *[repr(image["joints"][n]) for n in names]])
        rows.append([repr(t + 0.25), *["0.3"] * len(names)])  # a state between two images: far from both
    rows += [[repr(t), *[repr(x) for x in values]] for t, values in extra_rows]
    rng.shuffle(rows)  # the rows may come in any order
    _write_rows(tmp_path / "joints.csv", ["time", *names], rows)
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": dataset["camera"], "pixel_sigma": 0.5,
        "target": {"kind": "points", "fiducials": dataset["fiducials"]},
        "robot": dataset["robot"], "mounts": dataset["mounts"], "joints": {"file": "joints.csv"},
        "images": [{"id": im["id"], "time": times[im["id"]], "mirror_configs": im["mirror_configs"],
                    "observations": im["observations"]} for im in dataset["images"]],
    }
    path = tmp_path / "capture.json"
    path.write_text(json.dumps(capture))
    return path, dataset


def test_joint_states_matched_by_time_calibrate_as_the_dataset(tmp_path) -> None:
    path, _ = _capture(tmp_path)
    assert main(["detect", str(path), "-o", str(tmp_path / "detected.json"), "-q"]) == 0
    detected = json.loads((tmp_path / "detected.json").read_text())
    original = json.loads((tmp_path / "arm.json").read_text())
    for a, b in zip(detected["images"], original["images"]):
        assert a["id"] == b["id"] and a["joints"] == b["joints"]
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.json"), "-q", "--no-ros"]) == 0
    assert main(["calibrate", str(tmp_path / "arm.json"), "-o", str(tmp_path / "d.json"), "-q", "--no-ros"]) == 0
    a = json.loads((tmp_path / "c.json").read_text())["mounts"]["camera"]
    b = json.loads((tmp_path / "d.json").read_text())["mounts"]["camera"]
    assert np.allclose(a["T_link_cam"]["t"], b["T_link_cam"]["t"], atol=1e-9)


def test_an_image_without_a_row_within_max_dt_is_refused_by_name(tmp_path, capsys) -> None:
    path, _ = _capture(tmp_path, shift={"p1_002": 0.03})
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "image 'p1_002'" in err and "no row within max_dt 0.02 s" in err, err
    assert not (tmp_path / "r.json").exists()
    # a larger max_dt admits it
    capture = json.loads(path.read_text())
    capture["joints"]["max_dt"] = 0.05
    path.write_text(json.dumps(capture))
    assert main(["detect", str(path), "-o", str(tmp_path / "d.json"), "-q"]) == 0


def test_an_image_between_two_equally_near_rows_is_refused_by_name(tmp_path, capsys) -> None:
    path, dataset = _capture(tmp_path, shift={"p2_001": 0.0})
    image = next(im for im in dataset["images"] if im["id"] == "p2_001")
    k = dataset["images"].index(image)
    t = 100.0 + 0.5 * k
    values = [v + 0.01 for v in image["joints"].values()]
    # rows 5 ms before and 5 ms after the image: which one it shows cannot be told
    path, _ = _capture(tmp_path, shift={"p2_001": 0.005}, extra_rows=[(t + 0.010, values)])
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "image 'p2_001'" in err and "two rows equally near" in err, err


def test_an_image_without_a_time_is_refused_by_name(tmp_path, capsys) -> None:
    path, _ = _capture(tmp_path)
    capture = json.loads(path.read_text())
    del capture["images"][3]["time"]
    path.write_text(json.dumps(capture))
    assert main(["detect", str(path), "-o", str(tmp_path / "d.json"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"image {capture['images'][3]['id']!r}: no time" in err, err


def test_a_videos_frames_take_their_frame_time(tmp_path) -> None:
    """Frame k of a 10 frames/s video is at k / 10 s: each takes the row nearest to it."""
    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(6):
        writer.write(np.full((48, 64, 3), 20 * k, np.uint8))
    writer.release()
    _write_rows(tmp_path / "joints.csv", ["time", "j1"], [[f"{k / 10 + 0.003:.3f}", str(k)] for k in range(6)])
    capture = capture_from_dict({
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0},
        "target": {"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.03},
        "robot": {"urdf": "arm.urdf"}, "joints": {"file": "joints.csv"},
        "video": {"file": "run.avi", "segments": [{"frames": [0, 5], "step": 2, "mirror_configs": ["each"]}]},
    }, source="c.yaml", base_dir=str(tmp_path))
    data = {"images": [{"id": f"run:{k}"} for k in (0, 2, 4)]}
    add_robot_fields(data, capture)
    assert [im["joints"] for im in data["images"]] == [{"j1": 0.0}, {"j1": 2.0}, {"j1": 4.0}]
    capture.robot["max_dt"] = 0.002  # 3 ms away: refused, naming the frame
    with pytest.raises(DatasetError, match=r"image 'run:0' \(time 0 s\)"):
        add_robot_fields({"images": [{"id": "run:0"}]}, capture)
