"""mirror_fg's MLE for views of any reflection order (docs/formats.md "Views of any reflection order") against the
independent reference (views_reference.py), bad input, and ``reflections`` = ``mirror_configs``.

``vr.compare`` reads from a ``mirror_fg.Calibration``: ``R_cam_base``, ``t_cam_base``, ``covariance``
(6 x 6, docs/formats.md), ``mirror_vectors[(l, m)]``, ``mirror_covariances[(l, m)]`` (owner camera's frame),
``points[name]``, ``point_covariances[name]`` (base frame); with several cameras ``cameras[name]``.
Run one case by name: ``pytest tests/test_views_mle.py -k kaleidoscope_two_mirrors``.
"""
import copy
import json

import numpy as np
import pytest

import mirror_fg
import views_reference as vr
from mirror_fg.cli import main
from mirror_fg.io.dataset import dataset_to_dict
from mirror_fg.simulate.tree import simulate_tree

#: The MLE is one optimum: the solver's and the reference's differ by rounding and stopping tolerances.
ESTIMATE_SIGMAS = 0.05
#: Its covariance (inverse Fisher information at that optimum) is the reference's.
SIGMA_RATIO = (0.85, 1.15)
#: The solver's final cost is the reference's 0.5 sum of squared whitened residuals at the same optimum.
COST_RTOL = 1e-4

SINGLE_CAMERA_CASES = ["kaleidoscope_two_mirrors", "mixed_two_handheld", "mixed_one_mirror_gives_pose",
                       "kaleidoscope_three_mirrors_one_point"]


def check_against_reference(dataset, truth):
    """calibrate(dataset) against the reference MLE; returns (calibration, reference, comparison)."""
    reference = vr.reference_mle(dataset, truth)
    calibration = mirror_fg.calibrate(copy.deepcopy(dataset))
    comparison = vr.compare(calibration, reference, dataset)
    where = f"worst {comparison.worst_sigmas:.3g} sigma at {comparison.worst_label}"
    assert comparison.worst_sigmas < ESTIMATE_SIGMAS, where
    assert SIGMA_RATIO[0] < comparison.ratio_min and comparison.ratio_max < SIGMA_RATIO[1], \
        f"sigma ratios {comparison.ratio_min:.3f}..{comparison.ratio_max:.3f}"
    assert comparison.gauge_error < 1e-9, f"gauge moved by {comparison.gauge_error:.3g}"
    assert set(calibration.mirror_vectors) == set(reference.mirrors)
    assert set(calibration.points) == set(reference.points)
    assert abs(calibration.final_error - reference.cost) <= COST_RTOL * reference.cost
    return calibration, reference, comparison


@pytest.mark.parametrize("name", SINGLE_CAMERA_CASES)
def test_mle_equals_reference(name):
    dataset, truth = vr.CASES[name](0)
    check_against_reference(dataset, truth)


def test_mle_equals_reference_scale_by_points():
    dataset, truth = vr.kaleidoscope_three_mirrors_one_point(0, scale_by_points=True)
    calibration, _, _ = check_against_reference(dataset, truth)
    d = np.linalg.norm(calibration.points["P1"] - calibration.points["P0"])
    assert abs(d - dataset["scale"]["distance"]) < 1e-9


def test_no_fiducials_base_is_the_camera_and_scale_is_held():
    dataset, truth = vr.kaleidoscope_three_mirrors_one_point(0)
    calibration = mirror_fg.calibrate(copy.deepcopy(dataset))
    np.testing.assert_array_equal(calibration.R_cam_base, np.eye(3))
    np.testing.assert_array_equal(calibration.t_cam_base, np.zeros(3))
    assert abs(np.linalg.norm(calibration.mirror_vectors[(1, 0)]) - dataset["scale"]["distance"]) < 1e-12


# --- bad input: one line, naming the image ---

def _raises(dataset, match):
    """calibrate(dataset) refuses it in one line matching ``match`` (the dataset before the change is
    checked valid by each test, so the error is the change's)."""
    with pytest.raises(mirror_fg.DatasetError, match=match) as err:
        mirror_fg.calibrate(dataset)
    assert "\n" not in str(err.value)
    return err


def _image(dataset, image_id):
    return next(im for im in dataset["images"] if im["id"] == image_id)


def test_bad_input_same_mirror_twice_in_a_row():
    dataset, _ = vr.kaleidoscope_two_mirrors(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    _image(dataset, "m1m2")["reflections"] = [[1, 0], [1, 0]]
    _raises(dataset, "image 'm1m2'")


def test_bad_input_mirror_above_num_mirrors():
    dataset, _ = vr.kaleidoscope_two_mirrors(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    _image(dataset, "m1")["reflections"] = [[3, 0]]
    _raises(dataset, "image 'm1'.*3")


def test_bad_input_mirror_configs_and_reflections_together():
    dataset, _ = vr.kaleidoscope_two_mirrors(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    _image(dataset, "m2")["mirror_configs"] = [0, 0]
    _raises(dataset, "image 'm2'")


def test_bad_input_no_fiducials_without_scale():
    dataset, _ = vr.kaleidoscope_three_mirrors_one_point(0)
    mirror_fg.dataset_from_dict(copy.deepcopy(dataset))  # valid before the change
    del dataset["scale"]
    _raises(dataset, "scale")


def test_bad_input_exits_2_from_the_command_line(tmp_path, capsys):
    dataset, _ = vr.kaleidoscope_two_mirrors(0)
    _image(dataset, "m1m2")["reflections"] = [[2, 0], [2, 0]]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(dataset))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "m1m2" in err and len(err.splitlines()) == 1 and "Traceback" not in err


# --- reflections = mirror_configs on the paper's tree ---

def _tree():
    ds, truth = simulate_tree(2, children=3, images_per_leaf=1, num_fiducials=4, num_points=2, pixel_sigma=0.5,
                              seed=1)
    return dataset_to_dict(ds), truth


def _as_reflections(dataset):
    out = copy.deepcopy(dataset)
    for im in out["images"]:
        im["reflections"] = [[l + 1, m] for l, m in enumerate(im.pop("mirror_configs"))]
    return out


def _assert_same(a, b, rtol=1e-9):
    def close(x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        assert np.abs(x - y).max() <= rtol * max(np.abs(y).max(), 1e-300)

    close(a.R_cam_base, b.R_cam_base)
    close(a.t_cam_base, b.t_cam_base)
    close(a.covariance, b.covariance)
    assert set(a.mirror_vectors) == set(b.mirror_vectors) and set(a.points) == set(b.points)
    for p in b.mirror_vectors:
        close(a.mirror_vectors[p], b.mirror_vectors[p])
        close(a.mirror_covariances[p], b.mirror_covariances[p])
    for n in b.points:
        close(a.points[n], b.points[n])
        close(a.point_covariances[n], b.point_covariances[n])
    close(a.final_error, b.final_error)


def test_reflections_equal_mirror_configs_on_the_tree():
    dataset, _ = _tree()
    by_configs = mirror_fg.calibrate(copy.deepcopy(dataset))
    by_reflections = mirror_fg.calibrate(_as_reflections(dataset))
    _assert_same(by_reflections, by_configs)


def test_reflections_equal_mirror_configs_on_the_base_case_example():
    dataset = json.loads((vr_root() / "examples" / "base_case.json").read_text())
    _assert_same(mirror_fg.calibrate(_as_reflections(dataset)), mirror_fg.calibrate(copy.deepcopy(dataset)))


def vr_root():
    from pathlib import Path

    return Path(__file__).resolve().parents[1]


def test_reference_agrees_with_mirror_fg_on_the_tree():
    """The reference (which reads mirror_configs as reflections) against the existing tree solver: a check
    of the reference itself on data mirror_fg already solves."""
    dataset, gt = _tree()
    truth = vr.Truth({vr.SINGLE: (gt.R_cam_base, gt.t_cam_base)}, dict(gt.mirror_vectors),
                     {p: vr.SINGLE for p in gt.mirror_vectors}, dict(gt.points))
    check_against_reference(dataset, truth)
