"""A solved rig end to end at the command line: the camchain in Kalibr's reader conventions and the URDF in
yourdfpy put every camera where the result does, and the rig where the truth is (within 3 sigma)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import views_scenes as scenes
from mirror_fg.core.transform import Transform
from test_rig_outputs import KalibrCamchain


def test_solved_rig_camchain_and_urdf(tmp_path) -> None:
    yourdfpy = pytest.importorskip("yourdfpy")
    data, truth = scenes.rig_three_cameras(2)
    (tmp_path / "rig.json").write_text(json.dumps(data))
    done = subprocess.run([sys.executable, "-c", "import sys; from mirror_fg.cli import main; sys.exit(main())",
                           "calibrate", "rig.json", "-o", "rig.result.json"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "rig.result.json").read_text())
    names = list(data["cameras"])
    assert list(result["cameras"]) == names
    chain = KalibrCamchain(tmp_path / "rig.result.camchain.yaml")
    assert chain.numCameras() == len(names)
    true_poses = [Transform(*truth.T_cam_base[n]).matrix() for n in names]
    for n in range(1, len(names)):
        T = chain.getExtrinsicsLastCamToHere(n)
        rig = result["rig"][n - 1]
        assert (rig["from"], rig["to"]) == (names[n - 1], names[n])
        np.testing.assert_allclose(T[:3, :3], rig["T"]["R"], atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], rig["T"]["t"], atol=1e-12)
        true_T = true_poses[n] @ np.linalg.inv(true_poses[n - 1])  # from camera n-1 into camera n
        sigma = np.sqrt(np.diag(np.array(rig["covariance"])))
        assert np.all(np.abs(T[:3, 3] - true_T[:3, 3]) < 3 * sigma[3:] + 1e-12)
    robot = yourdfpy.URDF.load(str(tmp_path / "rig.result.urdf.xml"))
    for name in names:
        entry = result["cameras"][name]["T_base_cam"]
        T_base_cam = Transform(np.array(entry["R"]), np.array(entry["t"])).matrix()
        assert np.max(np.abs(robot.get_transform(f"{name}_optical_frame", robot.base_link) - T_base_cam)) < 1e-9
