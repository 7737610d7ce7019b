"""``verify`` of an arm's mounts (mirror_fg/analysis/verify_arm.py, docs/formats.md "Has it moved?"): a
simulated arm (mirror_fg.robot.simulate), new images rendered again from the truth with a mount moved by
3x its combined sigma or where it was; the statistic against a likelihood ratio computed here with scipy's
least squares on a model written here; the CLI's exit codes and verification@1; live --verify with an
arm's session."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize, stats

pytest.importorskip("pinocchio")

from mirror_fg.analysis.verify import CANNOT_TELL, MOVED, NOT_MOVED, verify  # noqa: E402
from mirror_fg.analysis.verify_arm_study import arm_power_study, render_arm  # noqa: E402
from mirror_fg.cli import main  # noqa: E402
from mirror_fg.core.geometry import so3_exp  # noqa: E402
from mirror_fg.factors.robot import compose, inverse  # noqa: E402
from mirror_fg.robot import arm_urdf  # noqa: E402
from mirror_fg.robot.kinematics import load_kinematics  # noqa: E402
from mirror_fg.robot.simulate import CAMERA, simulate_arm  # noqa: E402
from mirror_fg.solver.calibrate import calibrate  # noqa: E402

ALPHA = 0.01
KEYS = {"camera": "T_link_cam", "target": "T_link_target"}


def test_the_renderer_is_the_simulation() -> None:
    """The study's renderer (eq. 3, pinhole) gives the simulator's pixels where nothing moved."""
    data, truth = simulate_arm("arm6", seed=3, pixel_sigma=1e-5, arm_poses=3)
    rendered = render_arm(data, truth, "camera", np.zeros(6), 0.0, None, "rendered")
    a = np.array([v for im in data["images"] for v in im["observations"].values()])
    b = np.array([v for im in rendered.images for v in im.observations.values()])
    assert np.abs(a - b).max() < 1e-3


@pytest.mark.parametrize("role,offsets", [("camera", None), ("target", {"shoulder_lift_joint": 0.4})])
def test_a_few_trials_moved_and_not(role, offsets) -> None:
    """A mount moved by 3x its combined sigma is `moved` in most trials; unmoved, never (alpha 1 %)."""
    trials = 8
    figures = arm_power_study(trials, seed=11, role=role, **({"offsets_deg": offsets} if offsets else {}))
    assert figures.detections >= trials - 1, figures
    assert figures.false_alarms == 0, figures
    assert set(figures.dof) == {6}  # three placements with four arm poses each see every direction


@pytest.mark.slow
@pytest.mark.parametrize("role,offsets", [("camera", None), ("target", {"shoulder_lift_joint": 0.4,
                                                                         "elbow_joint": -0.3})])
def test_power_and_size_over_200_trials(role, offsets) -> None:
    """The goals: a 3-sigma move `moved` in >= 95 % of 200 trials; no move, `moved` in <= alpha + 2 %; the
    unmoved d2 follows chi2(6)."""
    figures = arm_power_study(200, seed=7, role=role, **({"offsets_deg": offsets} if offsets else {}))
    assert figures.detection_rate >= 0.95, figures
    assert figures.false_alarm_rate <= ALPHA + 0.02, figures
    assert stats.kstest(figures.d2_still, "chi2", args=(6,)).pvalue > 0.001, figures


def _lr_by_least_squares(result: dict, dataset, planes: dict, sigma_px: float) -> float:
    """``d2`` of the camera mount computed here: both mounts and every plane by scipy's least squares on
    pixels predicted by this model (eq. 3, pinhole), the camera mount held by its stored covariance or
    free; the mounts perturbed in the uncertainty convention (``R = Exp(dtheta) R_s``, ``t = t_s + dt``)."""
    kin = load_kinematics(arm_urdf("arm6"))
    stored = {role: (e["link"], np.array(e[KEYS[role]]["R"]), np.array(e[KEYS[role]]["t"]))
              for role, e in result["mounts"].items()}
    S = np.array(result["mounts"]["camera"]["covariance"])
    L_inv = np.linalg.inv(np.linalg.cholesky(S))
    names = list(dataset.fiducials)
    P = np.array([dataset.fiducials[n] for n in names]).T
    images = []
    for image in dataset.images:
        F = kin.placements(image.joints, ["base_link", "tool0"])
        links = {role: (F[link][0][:3, :3], F[link][0][:3, 3]) for role, (link, _, _) in stored.items()}
        observed = np.array([image.observations[n] for n in names])
        images.append((links, image.reflections[0], observed))
    placements = sorted({p for _, p, _ in images})
    v0 = np.concatenate([planes[p] for p in placements])  # LM from the true planes

    def poses(x):
        out = {}
        for k, role in enumerate(("camera", "target")):
            _, R, t = stored[role]
            out[role] = (so3_exp(x[6 * k:6 * k + 3]) @ R, t + x[6 * k + 3:6 * k + 6])
        return out

    def residuals(x, held):
        mounts = poses(x)
        r = []
        for links, placement, observed in images:
            C = compose(links["camera"], mounts["camera"])
            D = compose(links["target"], mounts["target"])
            v = x[12 + 3 * placements.index(placement):15 + 3 * placements.index(placement)]
            X = D[0] @ P + D[1][:, None]
            X = X - 2.0 * np.outer(v, (v @ X) / (v @ v) - 1.0)
            R, t = inverse(C)
            Xc = R @ X + t[:, None]
            r.append(((CAMERA.K @ (Xc / Xc[2]))[:2].T - observed).ravel() / sigma_px)
        if held:
            r.append(L_inv @ x[:6])
        return np.concatenate(r)

    x0 = np.concatenate([np.zeros(12), v0])
    free = optimize.least_squares(residuals, x0, args=(False,), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    held = optimize.least_squares(residuals, free.x, args=(True,), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return float(np.sum(held.fun ** 2) - np.sum(free.fun ** 2))  # 2 (cost_held - cost_free), cost = 0.5 r^2


@pytest.mark.parametrize("move_mm", [0.0, 5.0])
def test_the_statistic_is_the_likelihood_ratio_computed_independently(move_mm) -> None:
    data, truth = simulate_arm("arm6", placements=3, arm_poses=6, pixel_sigma=0.5, seed=21)
    result = calibrate(render_arm(data, truth, "camera", np.zeros(6), 0.5, np.random.default_rng(1), "stored")).to_dict()
    new_data, new_truth = simulate_arm("arm6", placements=3, arm_poses=3, pixel_sigma=0.5, seed=22)
    move = np.array([0.0, 0.0, 0.0, 1e-3 * move_mm, 0.0, 0.0])
    new = render_arm(new_data, new_truth, "camera", move, 0.5, np.random.default_rng(2), "new")
    answer = verify(result, new, alpha=ALPHA).cameras["camera"]
    reference = _lr_by_least_squares(result, new, new_truth.mirror_vectors, 0.5)
    assert answer.dof == 6
    assert answer.mahalanobis2 == pytest.approx(reference, rel=1e-3, abs=1e-3)
    assert answer.p_value == pytest.approx(stats.chi2.sf(reference, 6), rel=0.05, abs=1e-6)


def test_one_placement_sees_part_of_the_base_mount_and_all_of_the_tool_mount() -> None:
    """One mirror placement, many arm poses: the plane and the mount on the base link compose into one
    virtual frame (3 of its 6 directions hidden); the mount on the tool is seen whole."""
    data, truth = simulate_arm("arm6", placements=3, arm_poses=6, pixel_sigma=0.5, seed=31)
    result = calibrate(render_arm(data, truth, "camera", np.zeros(6), 0.5, np.random.default_rng(3), "stored"))
    new_data, new_truth = simulate_arm("arm6", placements=1, arm_poses=8, pixel_sigma=0.5, seed=32)
    answer = verify(result, render_arm(new_data, new_truth, "camera", np.zeros(6), 0.5, np.random.default_rng(4), "new"))
    assert answer.cameras["camera"].dof == 3 and answer.cameras["camera"].verdict == CANNOT_TELL
    assert "3 of the mount's 6" in answer.cameras["camera"].advice
    assert answer.cameras["target"].dof == 6 and answer.cameras["target"].verdict != MOVED


def _arm_files(tmp_path, move=None):
    """stored.json (calibrated), new.json and moved.json (the camera mount moved 2 cm along x), URDF."""
    data, _ = simulate_arm("arm6", placements=3, arm_poses=6, pixel_sigma=0.5, seed=41)
    (tmp_path / "arm6.urdf").write_text(Path(arm_urdf("arm6")).read_text())
    (tmp_path / "stored.json").write_text(json.dumps(data))
    new_data, new_truth = simulate_arm("arm6", placements=3, arm_poses=4, pixel_sigma=0.5, seed=42)
    (tmp_path / "new.json").write_text(json.dumps(new_data))
    moved = render_arm(new_data, new_truth, "camera", np.array([0, 0, 0, 0.02, 0, 0.0]), 0.5,
                       np.random.default_rng(5), "moved")
    images = [{**im, "observations": {n: [float(x) for x in moved.images[k].observations[n]]
                                      for n in im["observations"]}} for k, im in enumerate(new_data["images"])]
    (tmp_path / "moved.json").write_text(json.dumps({**new_data, "images": images}))
    return data


def test_verify_an_arm_at_the_cli(tmp_path, capsys) -> None:
    _arm_files(tmp_path)
    assert main(["calibrate", str(tmp_path / "stored.json"), "-o", str(tmp_path / "result.json"), "-q"]) == 0
    code = main(["verify", str(tmp_path / "result.json"), str(tmp_path / "new.json"), "-o", str(tmp_path / "v.json"),
                 "--tolerance-mm", "20", "--tolerance-deg", "2"])
    assert code == 0, capsys.readouterr()
    document = json.loads((tmp_path / "v.json").read_text())
    assert document["format"] == "mirror-fg/verification@1" and set(document["cameras"]) == {"camera", "target"}
    assert all(e["verdict"] == NOT_MOVED and e["dof"] == 6 for e in document["cameras"].values())
    code = main(["verify", str(tmp_path / "result.json"), str(tmp_path / "moved.json"), "-o", str(tmp_path / "m.json")])
    out = capsys.readouterr().out
    assert code == 4 and "camera: MOVED" in out
    moved = json.loads((tmp_path / "m.json").read_text())["cameras"]["camera"]
    assert abs(moved["move"]["position_mm"][0] - 20.0) < moved["sigma3"]["position_mm"][0]
    # an arm's data against a fixed camera's result, and --update of an arm's result: one line, exit 2
    assert main(["verify", str(tmp_path / "result.json"), str(tmp_path / "new.json"), "--update",
                 str(tmp_path / "u.json")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1 and not (tmp_path / "u.json").exists()


def test_arm_data_against_a_fixed_camera_result_is_refused(tmp_path, capsys) -> None:
    from mirror_fg.io.dataset import load_dataset

    _arm_files(tmp_path)
    fixed = {"format": "mirror-fg/result@1"}
    with pytest.raises(Exception) as error:
        verify(fixed, load_dataset(str(tmp_path / "new.json")))
    assert "not an arm's result" in str(error.value)


def test_live_verify_with_an_arm_session(tmp_path, capsys) -> None:
    """``live --verify`` with an arm's capture: the session's frames with their joint states
    (``LiveArmSession.dataset``) tested as placements come in: the moved mount `moved` once three placements
    are in, the unmoved never; at the command, the flag is taken (a video without the board: cannot tell, 5)."""
    import cv2

    from mirror_fg.io.capture import capture_from_dict
    from mirror_fg.live.joints import LiveArmSession
    from mirror_fg.live.verify import LiveVerifier

    data = _arm_files(tmp_path)
    assert main(["calibrate", str(tmp_path / "stored.json"), "-o", str(tmp_path / "result.json"), "-q"]) == 0
    result = json.loads((tmp_path / "result.json").read_text())
    (tmp_path / "joints.csv").write_text("time," + ",".join(data["images"][0]["joints"]) + "\n")
    capture_dict = {"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": data["camera"], "pixel_sigma": 0.5,
                    "target": {"kind": "points", "fiducials": data["fiducials"]}, "robot": data["robot"],
                    "mounts": data["mounts"], "joints": {"file": "joints.csv"}}
    for name, expect in (("new.json", {NOT_MOVED, CANNOT_TELL}), ("moved.json", {MOVED})):
        new = json.loads((tmp_path / name).read_text())
        capture = capture_from_dict(capture_dict, source=str(tmp_path / "live.json"), base_dir=str(tmp_path),
                                    media=False)
        session = LiveArmSession(capture, detect=lambda gray: None)
        verifier = LiveVerifier(result, session, tolerance_mm=20.0, tolerance_deg=2.0)
        verdicts = []
        for image in new["images"]:  # as the session adds them (its frame loop is tested with the arm's session)
            session.images.append(image)
            answer = verifier.update()
            verdicts.append(None if answer is None else answer.cameras["camera"].verdict)
        assert verdicts[-1] in expect, (name, verdicts)
        assert verifier.last is not None and verifier.last.cameras["camera"].dof == 6
        if name == "new.json":
            assert MOVED not in verdicts
    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(3):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    (tmp_path / "live.json").write_text(json.dumps(capture_dict))
    capsys.readouterr()
    code = main(["live", str(tmp_path / "live.json"), "--source", str(tmp_path / "run.avi"), "--verify",
                 str(tmp_path / "result.json")])
    assert code == 5 and "verify: cannot tell" in capsys.readouterr().out
