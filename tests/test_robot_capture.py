"""capture@1 with a robot arm (docs/formats.md, "Robot arms"): joints from a CSV matched by image name (an image without a file: its id); the
detected dataset calibrates as the dataset does; a CSV without a row for an image is refused by name."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.cli import main  # noqa: E402
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation  # noqa: E402


def _capture(tmp_path, drop=None):
    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=4, pixel_sigma=0.5, seed=5)
    write_arm_simulation(str(tmp_path / "arm.json"), dataset, truth)
    names = list(dataset["images"][0]["joints"])
    with open(tmp_path / "joints.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["image", *names])
        for image in dataset["images"]:
            if image["id"] != drop:
                writer.writerow([image["id"], *[repr(image["joints"][n]) for n in names]])
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": dataset["camera"], "pixel_sigma": 0.5,
        "target": {"kind": "points", "fiducials": dataset["fiducials"]},
        "robot": dataset["robot"], "mounts": dataset["mounts"], "joints": {"file": "joints.csv"},
        "images": [{"id": im["id"], "mirror_configs": im["mirror_configs"],
                    "observations": im["observations"]} for im in dataset["images"]],
    }
    path = tmp_path / "capture.json"
    path.write_text(json.dumps(capture))
    return path


def test_a_capture_with_joint_states_calibrates_as_its_dataset(tmp_path) -> None:
    path = _capture(tmp_path)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "from_capture.json"), "-q", "--no-ros"]) == 0
    assert main(["calibrate", str(tmp_path / "arm.json"), "-o", str(tmp_path / "from_dataset.json"), "-q", "--no-ros"]) == 0
    a = json.loads((tmp_path / "from_capture.json").read_text())["mounts"]
    b = json.loads((tmp_path / "from_dataset.json").read_text())["mounts"]
    for role, key in (("camera", "T_link_cam"), ("target", "T_link_target")):
        assert np.allclose(a[role][key]["t"], b[role][key]["t"], atol=1e-9)
        assert np.allclose(a[role]["covariance"], b[role]["covariance"], rtol=1e-6, atol=1e-15)


def test_an_image_without_joint_states_is_refused_by_name(tmp_path, capsys) -> None:
    path = _capture(tmp_path, drop="p1_002")
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "image 'p1_002'" in err and "joints.csv has no row for 'p1_002'" in err, err
