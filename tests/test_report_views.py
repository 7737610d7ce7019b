"""The report on general data: residuals of any reflection order and of several cameras
against an independent model (reflections in the base frame), their grouping by order and camera, the
scene with each placement once and every camera, the cameras / rig / placement tables, and a page without
a known target that says the base frame is the camera's instead of showing zero bounds."""
from __future__ import annotations

import re

import numpy as np
import pytest

import mirror_fg
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.geometry import so3_exp
from mirror_fg.core.transform import Transform, rotation_to_quaternion_xyzw
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.io.result import result_dict, sigma3_pose, validate_result
from mirror_fg.report.writer import write_report
from mirror_fg.report.general import view_unknown_count
from mirror_fg.report.scene import figure_views_scene
from mirror_fg.report.views import camera_stats, order_stats, placement_ties, view_residuals

CAM = {"model": "pinhole", "width": 1280, "height": 960, "fx": 1000.0, "fy": 1000.0, "cx": 640.0, "cy": 480.0,
       "dist": [0.0, 0.0, 0.0, 0.0, 0.0]}
CAM_RIGHT = dict(CAM, fx=900.0, fy=905.0, cx=650.0, cy=470.0)
BOARD = {f"F{i}_{j}": [i * 0.04, j * 0.04, 0.0] for i in range(5) for j in range(4)}
SEQUENCES = [(), ((1, 0),), ((2, 0),), ((1, 0), (2, 0)), ((2, 0), (1, 0))]


def _plane_in_base(v_owner, R_owner, t_owner):
    """The plane n . x = d in {B} of a mirror vector given in its owner camera's frame (eq. 1)."""
    n_o = v_owner / np.linalg.norm(v_owner)
    return R_owner.T @ n_o, float(np.linalg.norm(v_owner) - n_o @ t_owner)


def _seen(camera, reflections, poses, mirrors, owners, cams, base):
    """Pixels (N, 2) of base points (N, 3) seen by ``camera`` through ``reflections``: each reflection
    applied in {B} (Householder, x' = x - 2 (n.x - d) n) in the order the light meets them, then the
    camera transform and the pinhole. Independent of the solver's camera-frame model."""
    x = np.array(base, dtype=float)
    for placement in reflections:
        n, d = _plane_in_base(mirrors[placement], *poses[owners[placement]])
        x = x - 2.0 * (x @ n - d)[:, None] * n[None]
    R, t = poses[camera]
    c = x @ R.T + t
    K = cams[camera]
    return np.column_stack([K["fx"] * c[:, 0] / c[:, 2] + K["cx"], K["fy"] * c[:, 1] / c[:, 2] + K["cy"]])


def _entry(T):
    return {"R": T.R.tolist(), "t": T.t.tolist(), "q_xyzw": rotation_to_quaternion_xyzw(T.R).tolist()}


def _rig_scene():
    R_left = so3_exp(np.array([0.1, -0.05, 0.02]))
    poses = {"left": (R_left, np.array([-0.08, -0.06, 0.8]))}
    R_rl, t_rl = so3_exp(np.array([0.0, -0.08, 0.0])), np.array([-0.1, 0.0, 0.0])
    poses["right"] = (R_rl @ R_left, R_rl @ poses["left"][1] + t_rl)
    mirrors = {(1, 0): np.array([0.15, 0.0, 0.02]), (2, 0): np.array([0.0, 0.12, 0.01])}
    owners = {p: "left" for p in mirrors}
    return poses, mirrors, owners


def rig_dataset(noise=0.5, seed=0):
    """Two cameras; left sees the board directly and through both mirrors in both orders, right only
    through the mirrors; both placements are shared (one plane each, in left's frame)."""
    poses, mirrors, owners = _rig_scene()
    rng = np.random.default_rng(seed)
    cams = {"left": CAM, "right": CAM_RIGHT}
    base = np.array(list(BOARD.values()))
    images = []
    for camera in ("left", "right"):
        for seq in SEQUENCES[1:] if camera == "right" else SEQUENCES:
            px = _seen(camera, seq, poses, mirrors, owners, cams, base) + rng.normal(scale=noise, size=(len(base), 2))
            images.append({"id": f"{camera}{len(images)}", "camera": camera, "reflections": [list(p) for p in seq],
                           "observations": {n: p.tolist() for n, p in zip(BOARD, px)}})
    data = {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "cameras": cams, "pixel_sigma": 0.5,
            "fiducials": BOARD, "images": images}
    return dataset_from_dict(data, "<rig>"), (poses, mirrors, owners)


def with_cameras(result, calibration):
    """result@1 with ``cameras``, ``rig`` and ``mirrors[].camera`` (docs/formats.md "Several cameras") where
    ``result_dict`` does not write them yet; a rig entry's covariance is left out."""
    if result.get("cameras") or not calibration.cameras:
        return result
    out = dict(result)
    out["cameras"] = {}
    for name, camera in calibration.cameras.items():
        T = Transform(camera.R_cam_base, camera.t_cam_base)
        P = np.asarray(camera.covariance)
        P_bc = T.inverse_covariance(P)
        out["cameras"][name] = {"T_cam_base": _entry(T), "T_base_cam": _entry(T.inverse()),
                                "covariance_cam_base": P.tolist(), "covariance_base_cam": P_bc.tolist(),
                                "sigma3_cam_base": sigma3_pose(P), "sigma3_base_cam": sigma3_pose(P_bc)}
    names = list(calibration.cameras)
    out["rig"] = [{"from": a, "to": b, "T": _entry(calibration.cameras[b].T_cam_base @ calibration.cameras[a].T_cam_base.inverse())}
                  for a, b in zip(names, names[1:])]
    out["mirrors"] = [dict(m, camera=calibration.mirror_frames[(m["mirror"], m["config"])]) for m in result["mirrors"]]
    return validate_result(out, "<rig result>")


def truth_result(truth):
    """A result@1 at the true values of :func:`rig_dataset` (no covariances)."""
    poses, mirrors, owners = truth
    cams = {n: {"T_cam_base": _entry(Transform(*p)), "T_base_cam": _entry(Transform(*p).inverse())} for n, p in poses.items()}
    return validate_result({
        "format": "mirror-fg/result@1", "T_cam_base": cams["left"]["T_cam_base"], "cameras": cams,
        "rig": [{"from": "left", "to": "right", "T": _entry(Transform(*poses["right"]) @ Transform(*poses["left"]).inverse())}],
        "mirrors": [{"mirror": l, "config": m, "v": v.tolist(), "camera": owners[(l, m)]} for (l, m), v in mirrors.items()],
    }, "<truth>")


# --------------------------------------------------------------------------------------------------
# Residuals against the independent model


def test_residuals_of_every_view_match_reflections_in_the_base_frame():
    ds, truth = rig_dataset(noise=0.0)
    res, notes = view_residuals(truth_result(truth), ds, "<truth>")
    assert notes == [] and res.units == "px"
    assert len(res.names) == 9 * len(BOARD)
    assert np.max(np.abs(res.residual)) < 1e-7
    # A known offset on one measurement of a second-order view of the right camera comes back as -offset.
    image = next(im for im in ds.images if im.camera == "right" and len(im.reflections) == 2)
    image.observations["F2_1"] = image.observations["F2_1"] + np.array([3.0, -4.0])
    res, _ = view_residuals(truth_result(truth), ds, "<truth>")
    k = [i for i, (m, n) in enumerate(zip(res.image_ids, res.names)) if m == image.id and n == "F2_1"]
    assert np.allclose(res.residual[k[0]], [-3.0, 4.0], atol=1e-7)
    assert res.cameras[k[0]] == "right" and res.reflections[k[0]] == image.reflections
    stats = order_stats(res)
    assert list(stats) == [0, 1, 2]
    assert [s.count for s in stats.values()] == [20, 80, 80] and [s.images for s in stats.values()] == [1, 4, 4]
    assert stats[2].largest == pytest.approx(5.0, abs=1e-6)
    assert stats[2].rms == pytest.approx(5.0 / np.sqrt(80), rel=1e-6)
    assert stats[0].rms < 1e-7
    cams = camera_stats(res)
    assert list(cams) == ["left", "right"] and cams["right"].count == 80 and cams["right"].rms == pytest.approx(5 / np.sqrt(80))


def test_residuals_refuse_a_foreign_result_and_note_cameras_without_a_pose():
    ds, truth = rig_dataset(noise=0.0)
    result = truth_result(truth)
    result["mirrors"] = [m for m in result["mirrors"] if m["mirror"] != 2]
    with pytest.raises(DatasetError, match="left2.*mirror 2 configuration 0"):
        view_residuals(result, ds, "<truth>")
    single = {k: v for k, v in truth_result(truth).items() if k not in ("cameras", "rig")}
    single["mirrors"] = [{k: v for k, v in m.items() if k != "camera"} for m in single["mirrors"]]
    res, notes = view_residuals(single, ds, "<truth>")
    assert len(notes) == 1 and "'right'" in notes[0] and "4 image(s)" in notes[0]
    assert set(res.cameras) == {"left"} and np.max(np.abs(res.residual)) < 1e-7


def test_placement_ties_count_the_views_of_each_camera():
    ds, _ = rig_dataset()
    assert placement_ties(ds) == {(1, 0): {"left": 3, "right": 3}, (2, 0): {"left": 3, "right": 3}}


# --------------------------------------------------------------------------------------------------
# The report of a rig


@pytest.fixture(scope="module")
def rig_report(tmp_path_factory):
    ds, truth = rig_dataset()
    calibration = mirror_fg.calibrate(ds)
    result = with_cameras(result_dict(calibration), calibration)
    paths = write_report(result, ds, tmp_path_factory.mktemp("rig"), progress=False)
    return paths, result, ds, calibration


def test_rig_report_groups_by_order_and_camera_and_ties_the_cameras(rig_report):
    paths, result, ds, _ = rig_report
    page = paths["html"].read_text(encoding="utf-8")
    # The report's residuals of every view are the solver's: no "(on this dataset: ...)" beside the RMS.
    assert "on this dataset" not in page
    headings = re.findall(r"<h2[^>]*>([^<]*)</h2>", page)
    for heading in ("Residuals by reflection order", "Residuals per camera", "3D scene", "Reflection orders: RMS, count, largest",
                    "Cameras: RMS, count, largest", "Mirror placements and the cameras that saw them"):
        assert heading in headings, heading
    assert len(re.findall(r"data:image/png;base64,", page)) == 10  # with the error map and the validation
    orders = re.search(r"<table class='summary' id='orders'>(.*?)</table>", page).group(1)
    assert [re.search(r"(\d+) measurements", row).group(1) for row in orders.split("<tr>")[1:]] == ["20", "80", "80"]
    assert "left – right: 2 shared placement(s)" in page
    assert page.count("shared: ties left and right") == 2
    cameras = re.search(r"id='cameras'>(.*?)</table>", page).group(1)
    assert "camera right: T_base_cam 3σ" in cameras and "not estimated" not in cameras
    assert "left → right: baseline |t|, mm" in page
    baseline = 1e3 * np.linalg.norm(np.array(result["rig"][0]["T"]["t"]))
    assert f"{baseline:.4g}; " in page
    assert "the first of 2 cameras" in page
    assert paths["pdf"].read_bytes().startswith(b"%PDF")


def test_rig_unknowns_and_verdict(rig_report):
    paths, result, ds, calibration = rig_report
    # 2 camera poses (6 each) and 2 placements (3 each): the solver's own count, 2N - 2 E[cost].
    assert view_unknown_count(result, ds) == 18
    assert 2 * 180 - 2 * calibration.expected_final_error == pytest.approx(18)
    assert "342 spare of 360 measured coordinates, 99 % of the time; 18 unknowns" in paths["html"].read_text(encoding="utf-8")


def test_scene_draws_each_placement_once_at_its_foot_point_and_every_camera(rig_report):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    _, result, ds, calibration = rig_report
    fig = figure_views_scene(result, ds)
    main, close_up = fig.axes[:2]
    for ax in (main, close_up):
        quads = [c for c in ax.collections if isinstance(c, Poly3DCollection)]
        assert len(quads) == 2  # two placements, each seen by 2 cameras in 3 views: one plane each
    labels = main.get_legend_handles_labels()[1]
    assert "camera left" in labels and "camera right" in labels
    assert "mirror 1 config 0 (seen by left, right)" in labels
    # The foot points (dots) are T_base_owner v.
    T_left = calibration.cameras["left"].T_base_cam
    feet = {p: T_left.apply(v) for p, v in calibration.mirror_vectors.items()}
    dots = np.array([np.asarray(c._offsets3d).ravel() for c in main.collections
                     if type(c).__name__ == "Path3DCollection" and np.asarray(c._offsets3d).size == 3])
    for f in feet.values():
        assert np.min(np.linalg.norm(dots - f, axis=1)) < 1e-9
    # Both cameras' ellipsoids, one common magnification, named in the titles.
    assert "3σ position ellipsoids ×" in main.get_title()


# --------------------------------------------------------------------------------------------------
# Without a known target; a kaleidoscope; tree data unchanged


def notarget_dataset():
    """One camera ({B}), three fixed mirrors, one point seen directly and in first and second order."""
    poses = {"camera": (np.eye(3), np.zeros(3))}
    mirrors = {(1, 0): np.array([0.12, 0.0, 0.01]), (2, 0): np.array([0.0, 0.1, 0.02]),
               (3, 0): np.array([-0.07, -0.07, 0.01])}
    owners = {p: "camera" for p in mirrors}
    point = np.array([[0.01, 0.02, 0.6]])
    rng = np.random.default_rng(1)
    seqs = [()] + [((l, 0),) for l in (1, 2, 3)] + [((a, 0), (b, 0)) for a in (1, 2, 3) for b in (1, 2, 3) if a != b]
    images = []
    for seq in seqs:
        px = _seen("camera", seq, poses, mirrors, owners, {"camera": CAM}, point)[0]
        if 0 < px[0] < 1280 and 0 < px[1] < 960:
            images.append({"id": f"v{len(images)}", "reflections": [list(p) for p in seq],
                           "observations": {"P0": (px + rng.normal(scale=0.3, size=2)).tolist()}})
    data = {"format": "mirror-fg/dataset@1", "num_mirrors": 3, "camera": CAM, "pixel_sigma": 0.3, "fiducials": {},
            "scale": {"mirror": 1, "config": 0, "distance": float(np.linalg.norm(mirrors[(1, 0)]))}, "images": images}
    return dataset_from_dict(data, "<no target>")


def test_report_without_a_target_says_the_base_frame_is_the_camera(tmp_path):
    ds = notarget_dataset()
    result = result_dict(mirror_fg.calibrate(ds))
    assert not np.any(result["covariance_cam_base"])  # the file's bounds are zero: not an estimate
    paths = write_report(result, ds, tmp_path, progress=False)
    page = paths["html"].read_text(encoding="utf-8")
    assert "id='no-target'" in page and "the base frame {B} is the frame of the camera" in page
    summary = re.search(r"id='summary'>(.*?)</table>", page).group(1)
    bounds = [(k, v) for k, v in re.findall(r"<tr><td>([^<]*)</td><td class='v'>([^<]*)</td>", summary) if "3σ" in k]
    assert len(bounds) == 4 and all(v.startswith("not estimated (the base frame is this camera") for _, v in bounds)
    console = re.search(r"<pre>(T_base_cam.*?)</pre>", page, re.S).group(1)
    assert "±[0.000" not in console and "not estimated" in console
    headings = re.findall(r"<h2[^>]*>([^<]*)</h2>", page)
    assert "Covariance correlation" not in headings and "Residuals by reflection order" in headings
    assert "none (fiducials: {})" in page
    assert "11 unknowns" in page  # the point and 3 placements, less the scale; no pose
    assert "on this dataset" not in page


def test_report_without_a_target_and_without_a_dataset(tmp_path):
    ds = notarget_dataset()
    result = result_dict(mirror_fg.calibrate(ds))
    page = write_report(result, None, tmp_path, progress=False)["html"].read_text(encoding="utf-8")
    assert "id='no-target'" in page and "±[0.000" not in page


def test_tree_report_has_no_view_sections(tmp_path):
    from test_report import make_scene

    ds, result = make_scene()
    assert ds.is_tree
    page = write_report(result, ds, tmp_path, progress=False)["html"].read_text(encoding="utf-8")
    for absent in ("id='orders'", "id='placements'", "id='no-target'", "Residuals by reflection order"):
        assert absent not in page
    assert len(re.findall(r"data:image/png;base64,", page)) == 8  # with the error map and the validation


def test_rig_without_a_target_marks_the_first_camera_as_the_base_frame(tmp_path):
    """The board's corners as reconstruction points, {B} = left's frame: left's pose is not estimated,
    right's is (a result at the truth, with covariances written by hand)."""
    poses, mirrors, owners = _rig_scene()
    to_left = Transform(*poses["left"])
    relative = {n: Transform(*p) @ to_left.inverse() for n, p in poses.items()}
    poses = {n: (T.R, T.t) for n, T in relative.items()}
    points = {n: to_left.apply(np.array(x)) for n, x in BOARD.items()}
    cams = {"left": CAM, "right": CAM_RIGHT}
    images = []
    for camera in ("left", "right"):
        for seq in SEQUENCES[1:] if camera == "right" else SEQUENCES:
            px = _seen(camera, seq, poses, mirrors, owners, cams, np.array(list(points.values())))
            images.append({"id": f"{camera}{len(images)}", "camera": camera, "reflections": [list(p) for p in seq],
                           "observations": {n: p.tolist() for n, p in zip(points, px)}})
    ds = dataset_from_dict({"format": "mirror-fg/dataset@1", "num_mirrors": 2, "cameras": cams, "pixel_sigma": 0.5,
                            "fiducials": {}, "scale": {"mirror": 1, "config": 0, "distance": 0.15},
                            "images": images}, "<rig, no target>")
    result = dict(truth_result((poses, mirrors, owners)))
    result["points"] = {n: {"xyz": p.tolist(), "sigma3_mm": [1.0, 1.0, 3.0]} for n, p in points.items()}
    zero, P = np.zeros((6, 6)), np.diag([1e-6] * 3 + [4e-6] * 3)
    result["covariance_cam_base"] = result["covariance_base_cam"] = zero.tolist()
    result["cameras"]["left"].update(covariance_cam_base=zero.tolist(), covariance_base_cam=zero.tolist(),
                                     sigma3_base_cam=sigma3_pose(zero))
    P_bc = Transform(*poses["right"]).inverse_covariance(P)
    result["cameras"]["right"].update(covariance_cam_base=P.tolist(), covariance_base_cam=P_bc.tolist(),
                                      sigma3_base_cam=sigma3_pose(P_bc))
    page = write_report(validate_result(result, "<r>"), ds, tmp_path, progress=False)["html"].read_text(encoding="utf-8")
    assert "the base frame {B} is the frame of camera left" in page
    cameras = re.search(r"id='cameras'>(.*?)</table>", page).group(1)
    left, right = cameras.split("camera right")[0], "camera right" + cameras.split("camera right", 1)[1]
    assert "not estimated: the base frame itself" in left and "not estimated" not in right
    assert f"position {_bounds(P_bc)} mm" in right
    # 1 estimated pose, 2 placements, 20 points, less the scale.
    assert view_unknown_count(result, ds) == 6 + 6 + 60 - 1
    res, _ = view_residuals(result, ds, "<r>")
    assert np.max(np.abs(res.residual)) < 1e-7


def _bounds(P_bc):
    return "[" + ", ".join(f"{x:.3g}" for x in 3e3 * np.sqrt(np.diag(P_bc)[3:])) + "]"


def test_rig_report_without_its_dataset(rig_report, tmp_path):
    _, result, _, _ = rig_report
    page = write_report(result, None, tmp_path, progress=False)["html"].read_text(encoding="utf-8")
    for present in ("id='cameras'", "id='rig'", "3D scene"):
        assert present in page
    assert "id='orders'" not in page and "id='placements'" not in page
