"""``mirror-fg calibrate CAPTURE``: images that detection left out are named in result@1's ``excluded``."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from mirror_fg.cli import main

RENDERED = Path(__file__).parent / "data" / "capture" / "rendered"


def test_images_detection_left_out_are_in_the_result(tmp_path):
    for path in RENDERED.iterdir():
        shutil.copy(path, tmp_path / path.name)
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((600, 800), 128, np.uint8))
    capture = tmp_path / "capture.yaml"
    capture.write_text(capture.read_text() + "  - {file: blank.png, mirror_configs: [2, 9]}\n")
    assert main(["calibrate", str(capture), "-o", str(tmp_path / "r.json"), "--no-ros"]) == 0
    result = json.loads((tmp_path / "r.json").read_text())
    left_out = [e for e in result["excluded"] if e["image"].startswith("blank")]
    assert len(left_out) == 1 and left_out[0]["point"] is None
    assert left_out[0]["reason"].startswith("detection: not found")
    assert all(not e["image"].startswith("img_") for e in result["excluded"])
