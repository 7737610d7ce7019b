"""The one verdict of an arm's calibration judges the residuals the arm's model predicts (through the
kinematics), not the camera-to-base model's: a simulated arm with the right noise model looks right."""
from __future__ import annotations

import json

import pytest

from mirror_fg.cli import main

pytest.importorskip("pinocchio", reason="robot arms need Pinocchio: pip install 'mirror-fg[robot]'")


def test_a_simulated_arm_looks_right(tmp_path, capsys):
    data, result = tmp_path / "panda.json", tmp_path / "panda.result.json"
    assert main(["simulate", "--robot", "panda", "--eye-in-hand", "--arm-poses", "8", "-o", str(data), "-q"]) == 0
    assert main(["calibrate", str(data), "-o", str(result), "--no-ros"]) == 0
    verdict = [line for line in capsys.readouterr().out.splitlines() if line.startswith("verdict:")]
    assert verdict and verdict[0].startswith("verdict: looks right"), verdict
    stored = json.loads(result.read_text())["verdict"]
    assert stored["level"] == "good", stored
