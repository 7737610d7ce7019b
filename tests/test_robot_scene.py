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


@pytest.mark.parametrize("eye_in_hand, robot", [(True, "panda"), (False, "arm6")])
def test_with_a_glass_every_corner_is_seen_within_it(eye_in_hand, robot) -> None:
    """``mirror_size``: in every image the camera's ray to each corner's image meets the plane within the
    glass (its centre where the nominal pose sees the board's centre, its width along the camera's x axis),
    checked here by intersecting the rays again; a glass too small for any arm pose is said."""
    size = (0.3, 0.2)
    scene = dict(placements=3, arm_poses=4, seed=2, check_occlusion=True, mirror_distance=(0.3, 0.35),
                 mirror_tilt_deg=(20.0, 30.0), **({} if eye_in_hand else {"board_position": (0.15, 0.0, 0.05)}))
    data, truth = simulate_arm(robot, eye_in_hand, mirror_size=size, **scene)
    kin = load_kinematics(arm_urdf(robot))
    (link_c, mount_c), (link_t, mount_t) = truth.mounts["camera"], truth.mounts["target"]
    nominal = kin.placements(dict(zip(kin.chain(TOOL_LINK[robot]), NOMINAL[robot])), list({link_c, link_t}))
    pose = {link: (F[0][:3, :3], F[0][:3, 3]) for link, F in nominal.items()}
    C0, D0 = compose(pose[link_c], mount_c), compose(pose[link_t], mount_t)
    points = np.array(list(data["fiducials"].values())).T
    centre_B = D0[0] @ points.mean(axis=1) + D0[1]

    def hit(camera_centre, x, v):  # where the ray to x's image in the plane of v meets it
        n, d = v / np.linalg.norm(v), np.linalg.norm(v)
        image = x - 2.0 * v * ((v @ x) / (v @ v) - 1.0)  # eq. (3)
        ray = image - camera_centre
        return camera_centre + ray * (d - n @ camera_centre) / (n @ ray)

    for image in data["images"]:
        v = truth.mirror_vectors[(1, image["mirror_configs"][0])]
        n = v / np.linalg.norm(v)
        width = C0[0][:, 0] - (C0[0][:, 0] @ n) * n
        width /= np.linalg.norm(width)
        height = np.cross(n, width)
        middle = hit(C0[1], centre_B, v)
        F = kin.placements(image["joints"], list({link_c, link_t}))
        C = compose((F[link_c][0][:3, :3], F[link_c][0][:3, 3]), mount_c)
        D = compose((F[link_t][0][:3, :3], F[link_t][0][:3, 3]), mount_t)
        for x in (D[0] @ points + D[1][:, None]).T:
            at = hit(C[1], x, v) - middle
            assert abs(at @ width) <= size[0] / 2 + 1e-9 and abs(at @ height) <= size[1] / 2 + 1e-9
    with pytest.raises(RuntimeError, match="no visible arm pose"):
        simulate_arm(robot, eye_in_hand, mirror_size=(0.02, 0.02), **scene)
