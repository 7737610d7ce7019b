"""The simulated eye-to-hand scene (``simulate --robot arm6``): the board on the tool 0.3 m in front of the
camera and 0.15 m to its side at the nominal pose, facing the mirrors; the shipped example is what
``mirror-fg simulate --robot arm6 --arm-poses 6`` writes."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from mirror_fg.factors.robot import compose, inverse  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402
from mirror_fg.robot.simulate import NOMINAL, TOOL_LINK, simulate_arm  # noqa: E402


def test_the_eye_to_hand_board_is_held_in_front_of_the_camera() -> None:
    _, truth = simulate_arm("arm6", False, placements=3, arm_poses=3, seed=1)
    kin = load_kinematics(arm_urdf("arm6"))
    T = kin.placements(dict(zip(kin.chain(TOOL_LINK["arm6"]), NOMINAL["arm6"])), ["tool0"])["tool0"][0]
    board = compose((T[:3, :3], T[:3, 3]), truth.mounts["target"][1])
    R, t = compose(inverse(truth.mounts["camera"][1]), board)  # the board in the camera frame
    assert np.allclose(t, [0.15, 0.0, 0.30], atol=1e-9)
    assert R[2, 2] < -0.99  # its printed face (-z) looks along the camera's axis, at the mirrors


def test_the_example_is_the_simulators_output() -> None:
    from conftest import REPO

    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=6, pixel_sigma=0.5, seed=0)
    assert json.loads((REPO / "examples" / "arm6" / "arm6_mirror.json").read_text()) == json.loads(json.dumps(dataset))
