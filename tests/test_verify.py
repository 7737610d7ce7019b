"""mirror_fg.analysis.verify and `mirror-fg verify` (docs/formats.md, "Has it moved?"): the test's degrees of
freedom, its false-alarm rate and power on simulated data, the detectable move against an independent
Monte Carlo, the update's bounds, verification@1, the exit statuses and the refusals; the real photographs."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from mirror_fg import calibrate, load_dataset
from mirror_fg.cli import main
from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.io.dataset import save_dataset
from mirror_fg.io.result import load_result, write_result
from mirror_fg.analysis.verify import CANNOT_TELL, MOVED, NOT_MOVED, detectable_noncentrality, verify
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.analysis.verify_study import moved_data, power_study


def _scene(seed: int = 3, new_images: int = 3, stored_images: int = 20):
    stored_data, _ = simulate_base_case(num_images=stored_images, num_mirrors=1, num_fiducials=4, seed=seed)
    new, truth = simulate_base_case(num_images=new_images, num_mirrors=1, num_fiducials=4, mirror1_placements=1,
                                    seed=seed + 1)
    return calibrate(stored_data), new, truth


@pytest.mark.parametrize("placements, dof", [(1, 3), (2, 5), (3, 6)])
def test_degrees_of_freedom_seen(placements, dof):
    """One placement hides any rotation about a line in its plane (3 of 6 seen), two the rotation about
    their common line (5), three none: the test says what it could see, and only then gives the move."""
    stored, new, _ = _scene(new_images=placements)
    answer = verify(stored, new).cameras["camera"]
    assert answer.dof == dof
    assert (answer.move is not None) == (dof == 6)
    if dof < 6:
        assert answer.verdict in (MOVED, CANNOT_TELL) and answer.detectable_m == np.inf


def test_detectable_noncentrality_against_monte_carlo():
    """lambda* gives power 0.9 at alpha: k unit normals shifted by sqrt(lambda*), counted above the critical value."""
    rng = np.random.default_rng(0)
    for k in (3, 5, 6):
        ncp = detectable_noncentrality(k, 0.01)
        draws = rng.normal(size=(200_000, k))
        draws[:, 0] += np.sqrt(ncp)
        power = np.mean(np.sum(draws**2, axis=1) > stats.chi2.isf(0.01, k))
        assert abs(power - 0.9) < 0.005


def test_verdicts_follow_the_tolerance():
    """Same data: `not moved` with a tolerance above the detectable move, `cannot tell` below it."""
    stored, new, _ = _scene()
    loose = verify(stored, new, tolerance_mm=1000.0, tolerance_deg=50.0).cameras["camera"]
    assert loose.p_value >= 0.01 and loose.dof == 6
    assert loose.verdict == NOT_MOVED
    tight_mm = 0.5 * 1e3 * loose.detectable_m
    tight = verify(stored, new, tolerance_mm=tight_mm, tolerance_deg=50.0).cameras["camera"]
    assert tight.verdict == CANNOT_TELL and "add" in tight.advice or "calibrate again" in tight.advice


def test_power_fast():
    """CI version of the 200-trial study (scripts/verify_power.py): 20 trials, binomial bounds at about 1 %."""
    figures = power_study(trials=20, seed=1, stored_images=12)
    assert figures.false_alarms <= 2  # P(X >= 3 | n=20, p=0.03) = 2 %
    assert figures.detections >= 17  # P(X <= 16 | n=20, p=0.95) = 1.6 %
    assert 3.0 < figures.mean_d2_still < 9.5  # chi2_6 mean 6; the mean of 20 has sd 0.8


@pytest.mark.slow
def test_power_200_trials():
    """A move of 3x the combined sigma of each pose component is `moved` in >= 95 % of 200 trials; no move
    is `moved` in <= alpha + 2 %."""
    figures = power_study(trials=200, seed=0)
    assert figures.detection_rate >= 0.95
    assert figures.false_alarm_rate <= 0.01 + 0.02


def test_estimated_intrinsics_fast():
    """A stored result that estimated fx, fy, cx, cy: its intrinsics are held under their stored covariance,
    jointly with the pose's (analysis/verify_priors.py); the test stays calibrated (fast version)."""
    figures = power_study(trials=6, seed=4, stored_images=12, estimate=("fx", "fy", "cx", "cy"))
    assert figures.false_alarms <= 1 and figures.detections >= 5
    assert 2.0 < figures.mean_d2_still < 11.0


@pytest.mark.slow
def test_estimated_intrinsics_calibrated():
    """Mean d2 without a move is the degrees of freedom (6; 40 trials: sd 0.55). Holding the intrinsics at
    their estimate instead (no joint prior) gave 3.2 on 20 trials: the pose's stored covariance includes
    the intrinsics' error, which the new images share."""
    figures = power_study(trials=40, seed=4, stored_images=12, estimate=("fx", "fy", "cx", "cy"))
    assert 4.6 < figures.mean_d2_still < 7.4
    assert figures.false_alarm_rate <= 0.01 + 0.05 and figures.detection_rate >= 0.9


def test_cannot_tell_whenever_the_detectable_move_exceeds_the_tolerance():
    stored, new, truth = _scene(seed=11)
    rng = np.random.default_rng(5)
    for tolerance_mm in (0.5, 5.0, 50.0, 500.0):
        data = moved_data(new, truth, np.zeros(6), 1.0, rng)
        for answer in verify(stored, data, tolerance_mm=tolerance_mm, tolerance_deg=90.0).cameras.values():
            if answer.p_value >= 0.01:
                assert (answer.verdict == CANNOT_TELL) == (1e3 * answer.detectable_m > tolerance_mm)


def test_update_narrows_every_bound():
    stored, new, _ = _scene()
    answer = verify(stored, new)
    (R, t, P), = answer.fused.values()
    before = np.diag(stored.covariance)
    assert np.all(np.diag(P) <= before * (1 + 1e-12))
    assert np.any(np.diag(P) < 0.99 * before)


def _files(tmp_path, new_images=3, seed=3):
    stored, new, _ = _scene(seed=seed, new_images=new_images)
    result = tmp_path / "stored.result.json"
    write_result(result, stored.to_dict())
    data = tmp_path / "new.json"
    save_dataset(data, new)
    return result, data


def test_cli_not_moved_writes_verification_and_update(tmp_path, capsys):
    result, data = _files(tmp_path)
    out, updated = tmp_path / "verification.json", tmp_path / "updated.json"
    status = main(["verify", str(result), str(data), "--tolerance-mm", "1000", "--tolerance-deg", "50",
                   "-o", str(out), "--update", str(updated)])
    assert status == 0
    printed = capsys.readouterr().out
    assert "NOT MOVED" in printed and "deg" in printed and "mm" in printed
    document = json.loads(out.read_text())
    assert document["format"] == "mirror-fg/verification@1" and document["alpha"] == 0.01
    entry = document["cameras"]["camera"]
    assert set(entry) >= {"verdict", "p_value", "mahalanobis2", "move", "sigma3", "detectable"}
    assert entry["verdict"] == "not moved" and len(entry["move"]["position_mm"]) == 3
    before, after = load_result(result), load_result(updated)
    for key in ("sigma3_cam_base", "sigma3_base_cam"):
        for part in ("rotation_deg", "position_mm"):
            assert all(a <= b * (1 + 1e-9) for a, b in zip(after[key][part], before[key][part]))


def test_cli_moved_and_cannot_tell_exit_codes(tmp_path, capsys):
    result, data = _files(tmp_path)
    assert main(["verify", str(result), str(data)]) == 5  # 2 mm / 0.2 deg: too tight for these data
    assert "CANNOT TELL" in capsys.readouterr().out
    new = load_dataset(data)
    shifted = replace(new, fiducials={n: p + np.array([0.05, 0.0, 0.0]) for n, p in new.fiducials.items()})
    moved = tmp_path / "moved.json"
    save_dataset(moved, shifted)
    updated = tmp_path / "updated.json"
    assert main(["verify", str(result), str(moved), "--update", str(updated)]) == 4
    assert "MOVED" in capsys.readouterr().out and not updated.exists()


def test_cli_bad_input_is_one_line(tmp_path, capsys):
    result, data = _files(tmp_path)
    assert main(["verify", str(data), str(data)]) == 2  # a dataset given as the result
    assert main(["verify", str(result), str(result)]) == 2  # a result given as the data
    new = load_dataset(data)
    rig = replace(new, camera=None, cameras={"left": new.camera}, images=[replace(im, camera="left") for im in new.images])
    save_dataset(tmp_path / "rig.json", rig)
    assert main(["verify", str(result), str(tmp_path / "rig.json")]) == 2  # an unknown camera name
    normalized = replace(new, camera=None, pixel_sigma=1.0 / 800,
                         images=[replace(im, observations={n: (z - [512, 384]) / 800 for n, z in im.observations.items()})
                                 for im in new.images])
    save_dataset(tmp_path / "normalized.json", normalized)
    assert main(["verify", str(result), str(tmp_path / "normalized.json")]) == 2  # pixels against normalized
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 4 and all(line.startswith("mirror-fg: ") for line in errors)
    assert "left" in errors[2] and "different set-ups" in errors[2]


#: The three-image calibrations of the five Takahashi photographs whose other two images verify (of the ten:
#: input1,2,5 leaves mirror 1's normals undetermined; input2,3,4 and input3,4,5 leave input1 among the new
#: two, which fits no camera at its noise model: refused, exit 2; test_takahashi_unsolvable_splits_refused).
SOLVABLE = [(0, 1, 2), (0, 1, 3), (0, 2, 3), (0, 2, 4), (0, 3, 4), (1, 2, 4), (1, 3, 4)]


def _takahashi(takahashi_dir, stored=(0, 1, 2)):
    ds = load_dataset(takahashi_dir / "dataset.json")
    calibration = calibrate(replace(ds, images=[ds.images[i] for i in stored]))
    return calibration, replace(ds, images=[im for i, im in enumerate(ds.images) if i not in stored])


@pytest.mark.parametrize("stored, axis", [(s, a) for s in SOLVABLE for a in range(3)])
def test_takahashi_fiducials_shifted_say_moved(takahashi_dir, stored, axis):
    """Calibrated with three photographs, verified with the other two whose fiducials are all shifted along a
    base axis by 5x the combined 3-sigma there (the stored position's, inflated by the images' dispersion,
    times sqrt(2) for the new images' share): 0.2 to 0.7 m, beyond the linearisation at the stored pose. The
    free fit must follow the poses the two placements cannot tell apart, not the stored tangent (where
    (0, 1, 2) along z and (0, 2, 3) along y found no pose that fits and were refused, exit 2)."""
    calibration, new = _takahashi(takahashi_dir, stored)
    R = calibration.R_cam_base
    base_cov = calibration.dispersion.factor * (R.T @ calibration.covariance[3:, 3:] @ R)  # base axes
    direction = np.eye(3)[axis]
    shift = 5.0 * 3.0 * np.sqrt(2.0 * direction @ base_cov @ direction)
    moved = replace(new, fiducials={n: p + shift * direction for n, p in new.fiducials.items()})
    assert verify(calibration, moved).cameras["camera"].verdict == MOVED


@pytest.mark.parametrize("stored", SOLVABLE)
def test_takahashi_unmoved_never_moved(takahashi_dir, stored):
    """The photographs disagree among themselves beyond their noise model (dispersion 2 to 97 on 3 degrees of
    freedom); the F-test on it says `cannot tell` or `not moved`, never `moved` (chi-square: d2 39 to 225)."""
    calibration, new = _takahashi(takahashi_dir, stored)
    assert calibration.dispersion.dof == pytest.approx(3.0) and calibration.dispersion.factor > 1.5
    answer = verify(calibration, new).cameras["camera"]
    assert answer.verdict in (NOT_MOVED, CANNOT_TELL)
    assert answer.dispersion == pytest.approx(calibration.dispersion.factor) and answer.dispersion_dof == pytest.approx(3.0)


def test_takahashi_unsolvable_splits_refused(takahashi_dir):
    """The other three splits never say `moved` either: one calibration is undetermined, two are refused."""
    from itertools import combinations

    for stored in set(combinations(range(5), 3)) - set(SOLVABLE):
        with pytest.raises((DatasetError, SolveError)):
            calibration, new = _takahashi(takahashi_dir, stored)
            verify(calibration, new)


def test_dispersion_is_one_with_the_right_noise_model():
    """Simulated images with the noise the model says: ``B / nu ~ chi2_nu / nu`` with ``nu = 3 n - 6``;
    the mean over 8 calibrations of 20 images (sd 0.07) is 1."""
    from mirror_fg.solver.fit.dispersion import dispersion_of_calibration

    factors = []
    for seed in range(8):
        data, _ = simulate_base_case(num_images=20, num_mirrors=1, num_fiducials=4, seed=seed)
        calibration = calibrate(data)
        assert calibration.dispersion.dof == pytest.approx(54.0)
        assert calibration.dispersion == dispersion_of_calibration(data, calibration)
        factors.append(calibration.dispersion.factor)
    assert abs(np.mean(factors) - 1.0) < 0.2


def test_dispersion_sees_a_per_image_bias():
    """Each image's corners offset by its own 10 px (sd; a detector's bias): the images disagree beyond their
    noise model. Clean, the factor is below chi2_54's 99.9 % point over 54 (1.66); biased, above 2."""
    data, _ = simulate_base_case(num_images=20, num_mirrors=1, num_fiducials=4, seed=0)
    rng = np.random.default_rng(0)
    offsets = rng.normal(0.0, 10.0, (len(data.images), 2))
    biased = replace(data, images=[replace(im, observations={n: z + offset for n, z in im.observations.items()})
                                   for im, offset in zip(data.images, offsets)])
    assert calibrate(data).dispersion.factor < stats.chi2.isf(0.001, 54) / 54
    assert calibrate(biased).dispersion.factor > 2.0


def test_unchecked_bounds_cannot_say_not_moved():
    """A result whose images cannot be checked against each other (nu = 0) says `cannot tell` where the
    chi-square alone would say `not moved`; a result without dispersion is tested by the chi-square."""
    stored, new, _ = _scene()
    document = stored.to_dict()
    document["dispersion"] = {"factor": None, "dof": 0.0, "cost": 0.0, "images": 20}
    answer = verify(document, new, tolerance_mm=1000.0, tolerance_deg=50.0).cameras["camera"]
    assert answer.verdict == CANNOT_TELL and "checked" in answer.advice
    del document["dispersion"]
    answer = verify(document, new, tolerance_mm=1000.0, tolerance_deg=50.0).cameras["camera"]
    assert answer.verdict == NOT_MOVED and answer.dispersion_dof is None
    assert answer.p_value == pytest.approx(stats.chi2.sf(answer.mahalanobis2, answer.dof))


def test_an_arm_against_a_fixed_camera_is_refused_in_words(tmp_path, capsys):
    """An arm's result (with mounts) is tested against images with joint states (analysis/verify_arm.py);
    against a fixed camera's images, or a fixed camera's result against an arm's images: one line saying
    so, not a "different set-ups" from fitting them as a fixed camera."""
    from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation

    for name, seed in (("stored", 1), ("new", 2)):
        dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=6, seed=seed)
        write_arm_simulation(str(tmp_path / f"{name}.json"), dataset, truth)
    assert main(["calibrate", str(tmp_path / "stored.json"), "-o", str(tmp_path / "r.json"), "--no-ros", "-q"]) == 0
    (tmp_path / "fixed").mkdir()
    fixed_result, new_data = _files(tmp_path / "fixed")  # a camera fixed in the base frame
    capsys.readouterr()
    assert main(["verify", str(tmp_path / "r.json"), str(tmp_path / "new.json"), "-q"]) in (0, 5)
    assert main(["verify", str(tmp_path / "r.json"), str(new_data)]) == 2
    assert main(["verify", str(fixed_result), str(tmp_path / "new.json")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2, errors
    assert "an arm's result (mounts) needs new images with joint states" in errors[0]
    assert "images with joint states, but" in errors[1] and "is not an arm's result" in errors[1]


def test_data_that_do_not_fit_the_stored_target_are_refused(tmp_path, capsys):
    """Reconstruction points of another scene (another seed) under the same names: not even a free camera
    fits them, so the result and the data are not of one set-up (exit 2), never a `moved`."""
    stored_data, _ = simulate_base_case(num_images=20, num_mirrors=1, num_fiducials=4, num_points=5, seed=1)
    other, _ = simulate_base_case(num_images=3, num_mirrors=1, num_fiducials=4, num_points=5, mirror1_placements=1,
                                  seed=2)
    write_result(tmp_path / "r.json", calibrate(stored_data).to_dict())
    save_dataset(tmp_path / "d.json", other)
    assert main(["verify", str(tmp_path / "r.json"), str(tmp_path / "d.json")]) == 2
    assert "different set-ups" in capsys.readouterr().err


def test_readme_section_runs(tmp_path):
    """The README's "Has it moved?" commands run from a clone and say what the README prints."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = re.split(r"\n##+ ", text.split("## Has it moved?", 1)[1], maxsplit=1)[0]  # up to its Registry
    (block,) = re.findall(r"```bash\n(.*?)\n```", section, flags=re.S)
    commands = [line for line in block.splitlines() if line.startswith("mirror-fg ")]
    program = f"{sys.executable} -c 'import sys; from mirror_fg.cli import main; sys.exit(main())'"
    for command in commands:
        run = subprocess.run(command.replace("mirror-fg ", f"{program} ", 1), shell=True, cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, (command, run.stderr[-2000:])
    assert "NOT MOVED" in run.stdout and "p = 0.0243" in run.stdout
    assert (tmp_path / "verification.json").exists() and (tmp_path / "updated.result.json").exists()


def test_rig_each_camera_tested():
    """A rig: each camera has its own verdict; a camera without new images cannot tell, and says so."""
    from mirror_fg.io.dataset import dataset_from_dict
    from mirror_fg.simulate.rig import simulate_rig_tree

    stored_dict, _ = simulate_rig_tree(num_mirrors=1, own=[20, 20], shared=4, num_fiducials=4, seed=1)
    stored = calibrate(dataset_from_dict(stored_dict))
    new_dict, _ = simulate_rig_tree(num_mirrors=1, own=[3, 3], shared=0, num_fiducials=4, seed=2)
    answer = verify(stored, dataset_from_dict(new_dict), tolerance_mm=1000.0, tolerance_deg=50.0)
    assert [(v.name, v.dof, v.verdict) for v in answer.cameras.values()] == [("cam0", 6, NOT_MOVED),
                                                                           ("cam1", 6, NOT_MOVED)]
    only_cam0 = dict(new_dict, images=[im for im in new_dict["images"] if im["camera"] == "cam0"])
    answer = verify(stored, dataset_from_dict(only_cam0), tolerance_mm=1000.0, tolerance_deg=50.0)
    assert answer.cameras["cam0"].verdict == NOT_MOVED
    assert answer.cameras["cam1"].verdict == CANNOT_TELL and "no new image" in answer.cameras["cam1"].advice
