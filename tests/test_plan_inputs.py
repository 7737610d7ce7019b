"""``mirror-fg plan --camera FILE`` and ``--capture FILE``: the plan of a setup described by
the files the calibration will use equals the plan with the same numbers given by hand."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from mirror_fg.cli import main

SMALL = ["--mirrors", "1", "--placements", "3", "--images", "12", "--draws", "1"]


def _plan(tmp_path, capsys, *args: str) -> dict:
    out = tmp_path / f"plan{len(list(tmp_path.glob('plan*.json')))}.json"
    assert main(["plan", *args, "--json", str(out)]) == 0, capsys.readouterr().err
    capsys.readouterr()
    return json.loads(out.read_text())


def test_camera_file_gives_the_focal_length(tmp_path, capsys):
    camera = tmp_path / "camera.yaml"
    fs = cv2.FileStorage(str(camera), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("camera_matrix", np.array([[1500.0, 0, 640], [0, 1400.0, 480], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    from_file = _plan(tmp_path, capsys, *SMALL, "--camera", str(camera))
    by_hand = _plan(tmp_path, capsys, *SMALL, "--focal", "1450")
    assert from_file["setup"]["focal_px"] == 1450.0
    assert from_file["sigma3_cam_base"] == by_hand["sigma3_cam_base"]


def test_capture_gives_target_sigma_mirrors_and_estimate_before_the_photographs_exist(tmp_path, capsys):
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": 1600, "height": 1200, "fx": 2400.0, "fy": 2400.0, "cx": 800.0,
                   "cy": 600.0, "estimate": ["fx", "fy"]},
        "pixel_sigma": 0.4,
        "target": {"kind": "chessboard", "cols": 5, "rows": 4, "square": 0.03},
        "T_base_target": {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0.1, 0.0, 0.0]},
        "images": [{"file": "not_taken_yet.jpg", "mirror_configs": [0]}],
    }
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(capture))
    layout = {f"C{r * 5 + c:02d}": [0.1 + 0.03 * c, 0.03 * r, 0.0] for r in range(4) for c in range(5)}
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    from_capture = _plan(tmp_path, capsys, "--placements", "3", "--images", "12", "--draws", "1",
                         "--capture", str(tmp_path / "capture.yaml"))
    by_hand = _plan(tmp_path, capsys, *SMALL, "--fiducials-file", str(tmp_path / "layout.json"), "--sigma", "0.4",
                    "--focal", "2400", "--estimate", "fx,fy")
    assert from_capture["setup"]["num_mirrors"] == 1 and from_capture["setup"]["pixel_sigma"] == 0.4
    assert from_capture["setup"]["estimate"] == ["fx", "fy"]
    assert np.allclose(from_capture["sigma3_cam_base"]["position_mm"], by_hand["sigma3_cam_base"]["position_mm"])
    assert np.allclose(from_capture["sigma3_intrinsics"]["fx"], by_hand["sigma3_intrinsics"]["fx"])
    # an option given on the command line wins over the capture's value
    louder = _plan(tmp_path, capsys, "--placements", "3", "--images", "12", "--draws", "1", "--sigma", "0.8",
                   "--capture", str(tmp_path / "capture.yaml"))
    assert np.allclose(louder["sigma3_cam_base"]["position_mm"], 2 * np.array(from_capture["sigma3_cam_base"]["position_mm"]))


def test_camera_and_capture_together_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["plan", "--camera", "a.yaml", "--capture", "b.yaml"])
    assert stop.value.code == 2 and "not allowed with" in capsys.readouterr().err
