"""result@1 of several cameras (``cameras``, ``rig``, ``mirrors[].camera``): written from a synthetic
multi-camera Calibration, read back through the validator, tied together; refused where inconsistent."""
from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import Transform
from mirror_fg.io.result import load_result, result_dict, validate_result, write_result
from mirror_fg.solver.model.rig import rig_jacobian
from rig_calibration import NAMES, rig_calibration


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_a_result_with_cameras_round_trips(tmp_path, suffix):
    calibration = rig_calibration(0)
    result = result_dict(calibration)
    path = tmp_path / f"calib{suffix}"
    write_result(path, result)
    loaded = load_result(path)
    assert loaded == validate_result(json.loads(json.dumps(result)), "again")
    assert list(loaded["cameras"]) == list(NAMES)  # the dataset's order
    assert [(r["from"], r["to"]) for r in loaded["rig"]] == [("left", "right"), ("right", "wrist")]
    assert [m["camera"] for m in loaded["mirrors"]] == [calibration.mirror_frames[(m["mirror"], m["config"])]
                                                        for m in loaded["mirrors"]]
    # The first camera is the top-level pose.
    assert loaded["cameras"]["left"]["T_cam_base"] == loaded["T_cam_base"]


def test_a_result_with_one_named_camera_has_an_empty_rig(tmp_path):
    from mirror_fg.io.camchain import camchain

    result = validate_result(result_dict(rig_calibration(9, names=("solo",))), "r")
    assert list(result["cameras"]) == ["solo"] and result["rig"] == []
    assert {m["camera"] for m in result["mirrors"]} == {"solo"}
    assert list(camchain(result)) == ["cam0"] and "T_cn_cnm1" not in camchain(result)["cam0"]


def test_camera_entries_hold_each_camera_with_its_own_bounds():
    calibration = rig_calibration(1)
    result = result_dict(calibration)
    for name, pose in calibration.cameras.items():
        entry = result["cameras"][name]
        T = Transform(pose.R_cam_base, pose.t_cam_base)
        assert np.allclose(entry["T_base_cam"]["R"], T.inverse().R, atol=0, rtol=0)
        assert np.allclose(entry["T_base_cam"]["t"], T.inverse().t, atol=1e-15)
        assert np.allclose(entry["covariance_cam_base"], pose.covariance, rtol=0, atol=0)
        assert np.allclose(entry["covariance_base_cam"], pose.covariance_base_cam, rtol=1e-15)
        sd3 = 3 * np.sqrt(np.diag(pose.covariance_base_cam))
        assert np.allclose(entry["sigma3_base_cam"]["rotation_deg"], np.degrees(sd3[:3]))
        assert np.allclose(entry["sigma3_base_cam"]["position_mm"], 1e3 * sd3[3:])
    assert result["cameras"]["left"]["camera"]["estimated"] == ["fx", "fy", "cx", "cy"]
    assert result["cameras"]["left"]["camera"]["sigma3"] == {"fx": 6.0, "fy": 6.0, "cx": 3.0, "cy": 3.0}
    kept = result["cameras"]["wrist"]["camera"]
    assert kept["estimated"] == [] and kept["model"] == "fisheye" and kept["dist"] == [0.02, -0.01, 0.003, -0.001]


def test_rig_entries_are_the_propagation_of_the_joint_covariance():
    calibration = rig_calibration(2)
    result = result_dict(calibration)
    poses = [(p.R_cam_base, p.t_cam_base) for p in calibration.cameras.values()]
    P = calibration.camera_pose_covariance
    for n, entry in enumerate(result["rig"], start=1):
        (R_a, t_a), (R_b, t_b) = poses[n - 1], poses[n]
        assert np.allclose(entry["T"]["R"], R_b @ R_a.T, atol=1e-15)
        assert np.allclose(entry["T"]["t"], t_b - R_b @ R_a.T @ t_a, atol=1e-15)
        J = rig_jacobian(R_a, t_a, R_b, t_b)
        block = P[6 * (n - 1): 6 * n + 6, 6 * (n - 1): 6 * n + 6]
        assert np.allclose(entry["covariance"], J @ block @ J.T, rtol=1e-12, atol=1e-22)
        sd3 = 3 * np.sqrt(np.diag(J @ block @ J.T))
        assert np.allclose(entry["sigma3"]["rotation_deg"], np.degrees(sd3[:3]))
        assert np.allclose(entry["sigma3"]["position_mm"], 1e3 * sd3[3:])


def test_without_covariances_the_cameras_and_rig_have_none():
    result = validate_result(result_dict(rig_calibration(3, covariance=False)), "r")
    assert all(e["covariance_cam_base"] is None and e["sigma3_base_cam"] is None for e in result["cameras"].values())
    assert all(r["covariance"] is None and r["sigma3"] is None for r in result["rig"])


def test_a_single_camera_result_has_no_rig_keys():
    single = dataclasses.replace(rig_calibration(4), cameras=None, camera_pose_covariance=None, rig=[], mirror_frames={})
    result = result_dict(single)
    assert "cameras" not in result and "rig" not in result
    assert all("camera" not in m for m in result["mirrors"])


def test_result_dict_refuses_a_calibration_whose_rig_or_frames_the_solver_left_out():
    calibration = rig_calibration(5)
    with pytest.raises(ValueError, match="not the chain"):
        result_dict(dataclasses.replace(calibration, rig=[]))
    frames = dict(calibration.mirror_frames)
    del frames[(1, 2)]
    with pytest.raises(ValueError, match="mirror 1 config 2 has no camera frame"):
        result_dict(dataclasses.replace(calibration, mirror_frames=frames))


def _edit(result, path, value):
    out = copy.deepcopy(result)
    node = out
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


@pytest.mark.parametrize("path, value, words", [
    (("rig", 0, "from"), "wrist", r"rig\[0\]: from 'wrist' to 'right', expected from 'left' to 'right'"),
    (("rig", 1, "T", "t"), [9.0, 9.0, 9.0], r"rig\[1\]\.T: not T_cam_base of 'wrist' times the inverse"),
    (("rig",), [], r"rig: expected 2 entries"),
    (("mirrors", 2, "camera"), "head", r"mirrors\[2\]\.camera: names camera 'head', not one of the cameras"),
    (("mirrors", 0, "camera"), KeyError, r"mirrors\[0\]\.camera: missing"),
    (("cameras", "right", "T_base_cam", "t"), [0.0, 0.0, 0.0], r"cameras\.right\.T_base_cam: not the inverse"),
    (("cameras", "left"), {"T_cam_base": {"R": np.eye(3).tolist(), "t": [1.0, 2.0, 3.0]}},
     r"cameras\.left\.T_cam_base: the first camera is not the top-level T_cam_base"),
    (("cameras",), {}, r"cameras: expected at least one camera"),
    (("rig", 0, "covariance"), [[1.0] * 5] * 6, r"rig\[0\]\.covariance\[0\]: expected 6 numbers"),
    (("cameras", "wrist", "camera", "fx"), -1.0, r"cameras\.wrist\.camera\.fx: expected a number >= "),
])
def test_inconsistent_rig_results_are_refused(path, value, words):
    result = result_dict(rig_calibration(6))
    result = json.loads(json.dumps(result))
    validate_result(result, "calib.json")
    with pytest.raises(DatasetError, match=r"^calib\.json: " + words):
        validate_result(_edit(result, path, value), "calib.json")


def test_a_covariance_base_cam_of_another_camera_is_refused():
    result = json.loads(json.dumps(result_dict(rig_calibration(7))))
    result["cameras"]["right"]["covariance_base_cam"] = result["cameras"]["wrist"]["covariance_base_cam"]
    with pytest.raises(DatasetError, match=r"cameras\.right\.covariance_base_cam: does not match"):
        validate_result(result, "calib.json")


def test_rig_or_mirror_camera_without_cameras_is_refused():
    single = dataclasses.replace(rig_calibration(8), cameras=None, camera_pose_covariance=None, rig=[], mirror_frames={})
    result = json.loads(json.dumps(result_dict(single)))
    with pytest.raises(DatasetError, match="rig: a rig without cameras"):
        validate_result({**result, "rig": result_dict(rig_calibration(8))["rig"]}, "calib.json")
    result["mirrors"][0]["camera"] = "left"
    with pytest.raises(DatasetError, match=r"mirrors\[0\]\.camera: names camera 'left' but the result has no cameras"):
        validate_result(result, "calib.json")


# --------------------------------------------------------------------------------------------------
# Kalibr camchain (io.camchain), read the way Kalibr's ConfigReader reads it
# --------------------------------------------------------------------------------------------------


class KalibrCamchain:
    """A few lines of Kalibr's ``CameraChainParameters`` / ``CameraParameters`` (kalibr_common/ConfigReader.py):
    the same keys, the same checks, the same chain composition (kalibr_camera_validator)."""

    def __init__(self, path):
        import yaml

        with open(path) as f:
            self.data = yaml.safe_load(f)

    def numCameras(self):
        return len(self.data)  # Kalibr: every top-level key is a camera

    def camera(self, nr):
        cam = self.data[f"cam{nr}"]
        assert cam["camera_model"] == "pinhole"
        fu, fv, pu, pv = cam["intrinsics"]  # checkIntrinsics: 4 floats, non-negative
        assert all(isinstance(x, float) and x >= 0.0 for x in (fu, fv, pu, pv))
        assert len(cam["distortion_coeffs"]) == {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}[cam["distortion_model"]]
        w, h = cam["resolution"]
        assert isinstance(w, int) and isinstance(h, int)
        assert isinstance(cam["rostopic"], str)
        assert all(c < self.numCameras() for c in cam["cam_overlaps"])
        return cam

    def getExtrinsicsLastCamToHere(self, nr):
        assert nr > 0, "can't get extrinsics for first camera in chain (cam0=base)"
        T = np.array(self.data[f"cam{nr}"]["T_cn_cnm1"], dtype=float)
        assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
        return T

    def T_high_low(self, low, high):
        """kalibr_camera_validator: ``T_high_low = baseline_HL * T_high_low`` over the chain."""
        T = np.eye(4)
        for cidx in range(low, high):
            T = self.getExtrinsicsLastCamToHere(cidx + 1) @ T
        return T


@pytest.mark.parametrize("seed", range(3))
def test_camchain_loads_in_kalibrs_conventions_and_holds_the_rig(tmp_path, seed):
    from mirror_fg.io.camchain import camchain_texts

    calibration = rig_calibration(seed)
    result = result_dict(calibration)
    texts = camchain_texts(result, tmp_path / "calib.json")
    assert sorted(texts) == [str(tmp_path / "calib.camchain-sigma.yaml"), str(tmp_path / "calib.camchain.yaml")]
    for path, text in texts.items():
        (tmp_path / path).write_text(text)
    chain = KalibrCamchain(tmp_path / "calib.camchain.yaml")
    assert chain.numCameras() == 3
    poses = [Transform(p.R_cam_base, p.t_cam_base).matrix() for p in calibration.cameras.values()]
    for n in range(3):
        cam = chain.camera(n)
        intrinsics = calibration.cameras[NAMES[n]].camera
        assert cam["intrinsics"] == [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy]
        assert cam["resolution"] == [intrinsics.width, intrinsics.height]
        assert cam["rostopic"] == f"/{NAMES[n]}/image_raw"
    assert chain.camera(0)["distortion_model"] == "radtan" and chain.camera(0)["distortion_coeffs"] == [-0.11, 0.08, 1e-4, -2e-4]
    assert chain.camera(2)["distortion_model"] == "equidistant"
    assert chain.camera(2)["distortion_coeffs"] == [0.02, -0.01, 0.003, -0.001]
    points = np.random.default_rng(seed).normal(size=(5, 3))
    homogeneous = np.c_[points, np.ones(5)]
    in_camera = [homogeneous @ T.T for T in poses]
    for n in (1, 2):
        T = chain.getExtrinsicsLastCamToHere(n)
        rig = result["rig"][n - 1]
        assert np.allclose(T[:3, :3], rig["T"]["R"], atol=1e-15) and np.allclose(T[:3, 3], rig["T"]["t"], atol=1e-15)
        assert np.allclose(in_camera[n - 1] @ T.T, in_camera[n], atol=1e-12)  # T_cn_cnm1: from n-1 into n
    assert np.allclose(in_camera[0] @ chain.T_high_low(0, 2).T, in_camera[2], atol=1e-12)


def test_camchain_sigma_file_holds_the_rig_and_intrinsics_standard_deviations(tmp_path):
    import yaml

    from mirror_fg.io.camchain import camchain_texts

    calibration = rig_calibration(4)
    result = result_dict(calibration)
    texts = camchain_texts(result, tmp_path / "calib.json")
    sigma = yaml.safe_load(texts[str(tmp_path / "calib.camchain-sigma.yaml")])
    assert [sigma[f"cam{n}"]["name"] for n in range(3)] == list(NAMES)
    assert sigma["cam0"]["intrinsics_sigma"] == [2.0, 2.0, 1.0, 1.0]  # sqrt of the estimated variances
    assert sigma["cam1"]["intrinsics_sigma"] == [None] * 4  # kept, not estimated
    for n in (1, 2):
        rig = calibration.rig[n - 1]
        sd = np.sqrt(np.diag(rig.covariance))
        assert sigma[f"cam{n}"]["T_cn_cnm1_from"] == NAMES[n - 1]
        assert np.allclose(sigma[f"cam{n}"]["T_cn_cnm1_sigma"]["rotation_deg"], np.degrees(sd[:3]), rtol=1e-12)
        assert np.allclose(sigma[f"cam{n}"]["T_cn_cnm1_sigma"]["position_mm"], 1e3 * sd[3:], rtol=1e-12)
        assert np.allclose(sigma[f"cam{n}"]["T_cn_cnm1_sigma3"]["position_mm"], 3e3 * sd[3:], rtol=1e-12)
        assert np.allclose(sigma[f"cam{n}"]["T_cn_cnm1_covariance"], rig.covariance, rtol=1e-12)


def test_camchain_refuses_a_result_without_cameras_and_notes_dropped_terms(tmp_path):
    from mirror_fg.core.camera import Camera
    from mirror_fg.io.camchain import camchain_texts

    single = dataclasses.replace(rig_calibration(5), cameras=None, camera_pose_covariance=None, rig=[], mirror_frames={})
    with pytest.raises(DatasetError, match=r"calib\.json: a camchain needs a result with cameras"):
        camchain_texts(result_dict(single), tmp_path / "calib.json")
    calibration = rig_calibration(5)
    right = calibration.cameras["right"]
    calibration.cameras["right"] = dataclasses.replace(right, camera=Camera(640, 480, 500.0, 500.0, 320.0, 240.0,
                                                                            (0.1, 0.01, 0.0, 0.0, 0.25)))
    text = camchain_texts(result_dict(calibration), tmp_path / "calib.json")[str(tmp_path / "calib.camchain.yaml")]
    assert "# cam1: OpenCV distortion terms beyond Kalibr's four left out: [0.25]" in text
    calibration.cameras["right"] = dataclasses.replace(right, camera=None)
    with pytest.raises(DatasetError, match="camera 'right' has no intrinsics"):
        camchain_texts(result_dict(calibration), tmp_path / "calib.json")


# --------------------------------------------------------------------------------------------------
# URDF and ROS 2 outputs of every camera (io.ros, io.ros_rig)
# --------------------------------------------------------------------------------------------------


def _publisher_matrix(args: str) -> tuple[np.ndarray, str, str]:
    """The 4x4 transform, parent and child of ``static_transform_publisher`` new-style arguments."""
    from scipy.spatial.transform import Rotation

    words = args.split()
    values = {words[i][2:]: words[i + 1] for i in range(0, len(words), 2)}
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([float(values[k]) for k in ("qx", "qy", "qz", "qw")]).as_matrix()
    T[:3, 3] = [float(values[k]) for k in ("x", "y", "z")]
    return T, values["frame-id"], values["child-frame-id"]


@pytest.mark.parametrize("seed", range(3))
def test_urdf_holds_every_camera_where_the_result_puts_it(tmp_path, seed):
    import yaml

    from mirror_fg.io.ros import write_ros_outputs

    yourdfpy = pytest.importorskip("yourdfpy")
    result = result_dict(rig_calibration(seed))
    yaml_path, urdf_path = write_ros_outputs(result, tmp_path / "calib.json")
    robot = yourdfpy.URDF.load(str(urdf_path))
    frames = {name: f"{name}_optical_frame" for name in NAMES}
    assert sorted(robot.link_map) == sorted(["base_link", *frames.values()])
    content = yaml.safe_load(yaml_path.read_text())
    assert content["frames"]["camera"] == "left_optical_frame"  # the top level is the first camera's
    for name, frame in frames.items():
        entry = result["cameras"][name]
        T_base_cam = Transform(np.array(entry["T_base_cam"]["R"]), np.array(entry["T_base_cam"]["t"])).matrix()
        assert np.max(np.abs(robot.get_transform(frame, "base_link") - T_base_cam)) < 1e-9
        camera = content["cameras"][name]
        assert np.max(np.abs(np.array(camera["T_base_cam"]["matrix"]) - T_base_cam)) < 1e-12
        assert camera["sigma3_base_cam"] == entry["sigma3_base_cam"]
        T, parent, child = _publisher_matrix(camera["static_transform_publisher"])
        assert (parent, child) == ("base_link", frame) and np.max(np.abs(T - T_base_cam)) < 1e-9
        # The camera_link variant: base -> <name>_link -> optical, the same pose (yourdfpy on its joints).
        link = camera["camera_link"]
        assert link["frames"]["link"] == f"{name}_link"
        urdf = (f'<robot name="r"><link name="base_link"/><link name="{name}_link"/><link name="{frame}"/>'
                f"{link['urdf_joints']}</robot>")
        (tmp_path / "link.urdf").write_text(urdf)
        chained = yourdfpy.URDF.load(str(tmp_path / "link.urdf"))
        assert np.max(np.abs(chained.get_transform(frame, "base_link") - T_base_cam)) < 1e-9
        commands = [c.split("static_transform_publisher ")[1] for c in link["static_transform_publisher_commands"]]
        (T1, p1, c1), (T2, p2, c2) = (_publisher_matrix(c) for c in commands)
        assert (p1, c1, p2, c2) == ("base_link", f"{name}_link", f"{name}_link", frame)
        assert np.max(np.abs(T1 @ T2 - T_base_cam)) < 1e-9
    assert content["static_transform_publisher_commands"] == [
        content["cameras"][name]["static_transform_publisher_command"] for name in NAMES]
    for k, rig in enumerate(content["rig"]):
        assert (rig["from"], rig["to"]) == (frames[NAMES[k]], frames[NAMES[k + 1]])
        assert np.allclose(np.array(rig["T_cn_cnm1"]["matrix"])[:3, :3], result["rig"][k]["T"]["R"], atol=1e-15)
        assert np.allclose(robot.get_transform(frames[NAMES[k]], frames[NAMES[k + 1]]),
                           np.array(rig["T_cn_cnm1"]["matrix"]), atol=1e-9)  # T_to_from: from's frame in to's


def test_camera_names_become_frame_names_and_clashes_are_refused(tmp_path):
    from mirror_fg.io.ros import ros_outputs

    content = ros_outputs(result_dict(rig_calibration(0, names=("front cam", "back-cam"))))
    assert [c["frames"]["camera"] for c in content["cameras"].values()] == ["front_cam_optical_frame",
                                                                           "back_cam_optical_frame"]
    with pytest.raises(DatasetError, match=r"calib\.json: cameras 'a b' and 'a_b' would both be frame 'a_b_optical_frame'"):
        ros_outputs(result_dict(rig_calibration(0, names=("a b", "a_b"))), source="calib.json")


# --------------------------------------------------------------------------------------------------
# The calibration's files (io.calibration_files): the camchain planned and written with the others
# --------------------------------------------------------------------------------------------------


def _names(tmp_path):
    return sorted(p.name for p in tmp_path.iterdir())


@pytest.mark.parametrize("expect", [True, False])
def test_camchain_is_written_with_the_result_and_the_ros_files(tmp_path, expect):
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    (tmp_path / "rig.json").write_text("{}")
    outputs = plan_calibration_outputs([tmp_path / "rig.json"], tmp_path / "calib.json")
    if expect:
        outputs.expect_cameras()
    written = outputs.write(result_dict(rig_calibration(0)))
    # left estimated its intrinsics: its camera_info too
    assert sorted(p.name for p in written) == ["calib.camchain-sigma.yaml", "calib.camchain.yaml", "calib.json",
                                               "calib.left.camera_info.yaml", "calib.ros.yaml", "calib.urdf.xml"]
    assert KalibrCamchain(tmp_path / "calib.camchain.yaml").numCameras() == 3
    # A second run replaces what mirror-fg wrote.
    again = plan_calibration_outputs([tmp_path / "rig.json"], tmp_path / "calib.json")
    again.expect_cameras()
    again.write(result_dict(rig_calibration(1)))
    assert load_result(tmp_path / "calib.json")["T_cam_base"] == validate_result(result_dict(rig_calibration(1)), "r")["T_cam_base"]


def test_a_stranger_file_where_the_camchain_goes_is_refused_before_anything_is_written(tmp_path):
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    (tmp_path / "calib.camchain.yaml").write_text("cam0: {}  # someone's own Kalibr file\n")
    outputs = plan_calibration_outputs([], tmp_path / "calib.json")
    with pytest.raises(DatasetError, match=r"calib\.camchain\.yaml: exists and was not written by mirror-fg"):
        outputs.expect_cameras()
    late = plan_calibration_outputs([], tmp_path / "calib.json")
    with pytest.raises(DatasetError, match="was not written by mirror-fg"):
        late.write(result_dict(rig_calibration(0)))
    assert _names(tmp_path) == ["calib.camchain.yaml"]  # nothing else written, the file untouched
    assert "someone's own" in (tmp_path / "calib.camchain.yaml").read_text()


def test_the_camchain_is_never_written_over_an_input(tmp_path):
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    (tmp_path / "calib.camchain-sigma.yaml").write_text("mirror-fg\n")
    outputs = plan_calibration_outputs([tmp_path / "calib.camchain-sigma.yaml"], tmp_path / "calib.json")
    with pytest.raises(DatasetError, match="refusing to write the camchain standard deviations over an input file"):
        outputs.expect_cameras()


def test_no_camchain_for_a_device_a_single_camera_or_cameras_without_intrinsics(tmp_path):
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    device = plan_calibration_outputs([], "/dev/null")
    device.expect_cameras()
    assert [p.name for p in device.write(result_dict(rig_calibration(0)))] == ["null"]
    single = dataclasses.replace(rig_calibration(0), cameras=None, camera_pose_covariance=None, rig=[], mirror_frames={})
    written = plan_calibration_outputs([], tmp_path / "one.json").write(result_dict(single))
    assert sorted(p.name for p in written) == ["one.json", "one.ros.yaml", "one.urdf.xml"]
    normalized = rig_calibration(0)
    for name, pose in normalized.cameras.items():
        normalized.cameras[name] = dataclasses.replace(pose, camera=None, estimated=None)
    written = plan_calibration_outputs([], tmp_path / "norm.json").write(result_dict(normalized))
    assert sorted(p.name for p in written) == ["norm.json", "norm.ros.yaml", "norm.urdf.xml"]


# --------------------------------------------------------------------------------------------------
# The CLI summary (report.summary): every camera and every rig transform with its own bounds
# --------------------------------------------------------------------------------------------------


def test_summary_prints_every_camera_and_rig_transform_with_its_own_bounds():
    from mirror_fg.report.summary import summary_lines, unknown_count

    calibration = rig_calibration(0)
    calibration.cameras["wrist"] = dataclasses.replace(calibration.cameras["wrist"],
                                                       estimated=dataclasses.replace(calibration.camera, camera=calibration.cameras["wrist"].camera))
    result = result_dict(calibration)
    text = "\n".join(summary_lines(result))
    fmt = lambda values, f: "[" + ", ".join(format(float(x), f) for x in values) + "]"  # noqa: E731
    for name, pose in calibration.cameras.items():
        sd3 = 3 * np.sqrt(np.diag(pose.covariance_base_cam))
        block = (f"  {name}: t {fmt(pose.T_base_cam.t, ' .5f')} m, q_xyzw {fmt(pose.T_base_cam.quaternion_xyzw(), ' .6f')}\n"
                 f"    3-sigma bounds in base axes (x, y, z): rotation ±{fmt(np.degrees(sd3[:3]), '.3f')} deg, "
                 f"camera position ±{fmt(1e3 * sd3[3:], '.2f')} mm")
        assert block in text
    for rig in calibration.rig:
        sd3 = 3 * np.sqrt(np.diag(rig.covariance))
        assert (f"  {rig.from_camera} -> {rig.to_camera}: t {fmt(rig.t, ' .5f')} m (baseline "
                f"{1e3 * np.linalg.norm(rig.t):.2f} mm)") in text
        assert (f"    3-sigma bounds in {rig.to_camera}'s axes (x, y, z): rotation ±{fmt(np.degrees(sd3[:3]), '.3f')} deg, "
                f"position ±{fmt(1e3 * sd3[3:], '.2f')} mm") in text
    # The wrist camera's intrinsics are printed under it; the first camera's once, at the top.
    assert text.count("camera intrinsics estimated through the mirrors (pinhole 1600x1200)") == 1
    assert "    camera intrinsics estimated through the mirrors (fisheye 1920x1080)" in text
    assert unknown_count(result) == 6 * 3 + 3 * 4 + 4 + 4  # three poses, four placements, 4 + 4 intrinsics


def test_summary_without_rig_covariance_says_not_computed():
    from mirror_fg.report.summary import summary_lines

    lines = summary_lines(result_dict(rig_calibration(1, covariance=False)))
    rig_start = next(i for i, line in enumerate(lines) if line.startswith("rig (Kalibr's T_cn_cnm1)"))
    assert lines[rig_start + 2] == "    3-sigma bounds: not computed (the result has no covariance)"
