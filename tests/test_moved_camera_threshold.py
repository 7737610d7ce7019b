"""The moved-camera test's threshold (solver/screen/consistency.py, ``moved_camera_split``): the difference of
two ``T_cam_base`` has 6 degrees of freedom, so a chi-square statistic between the 3- and 6-dof
thresholds is chance, not a move; a split it reports states a p-value within its own limit.

The two sides of the consistent scene of test_moved_camera.py are solved for real; only the
statistic of their difference is set, to values placed against scipy's chi-square quantiles."""
import re

import pytest
from scipy.stats import chi2

from mirror_fg.solver.screen import consistency
from mirror_fg.solver.screen.consistency import MAX_MOVE_SPLITS, MOVE_SIGNIFICANCE
from test_moved_camera import moved_scene


@pytest.fixture(scope="module")
def still_scene():
    return moved_scene(num_images=120, degrees=0.0, mm=0.0, seed=1)


def split_with_statistic(monkeypatch, scene, statistic: float):
    dataset, truth = scene
    monkeypatch.setattr(consistency, "_pose_mahalanobis", lambda fits, R_reference: statistic)
    return consistency.moved_camera_split(dataset, truth.R_cam_base)


def test_a_statistic_between_the_3_and_6_dof_thresholds_is_not_a_move(monkeypatch, still_scene):
    tested = range(1, MAX_MOVE_SPLITS + 1)  # however many boundaries are tested, 27 lies between the two
    assert all(chi2.isf(MOVE_SIGNIFICANCE / n, 3) < 27.0 < chi2.isf(MOVE_SIGNIFICANCE / n, 6) for n in tested)
    assert split_with_statistic(monkeypatch, still_scene, 27.0) is None


def test_a_statistic_beyond_the_6_dof_threshold_is_a_move_within_its_stated_p_value(monkeypatch, still_scene):
    statistic = chi2.isf(MOVE_SIGNIFICANCE / MAX_MOVE_SPLITS, 6) * 1.05
    found = split_with_statistic(monkeypatch, still_scene, statistic)
    assert found is not None and len(found.groups) == 2
    p_value = float(re.search(r"chi-square\(6\) p = ([0-9.e+-]+)", found.message).group(1))
    assert p_value <= MOVE_SIGNIFICANCE


@pytest.fixture(scope="module")
def many_boundaries():
    """Every image a placement of mirror 1: MAX_MOVE_SPLITS boundaries are tested."""
    from test_consensus import board_scene

    dataset, truth = board_scene(1, num_images=24, seed=2)
    solvable = consistency._solvable_boundaries(dataset)
    tested = [solvable[i] for i in consistency.spread_subset(len(solvable), MAX_MOVE_SPLITS).tolist()]
    assert len(tested) == MAX_MOVE_SPLITS >= 2
    return dataset, truth, tested


def test_the_threshold_grows_with_the_boundaries_tested(monkeypatch, many_boundaries):
    """Bonferroni: with 3 boundaries tested, a statistic above the one-test threshold but below the
    three-test one is chance."""
    dataset, truth, tested = many_boundaries
    statistic = 0.5 * (chi2.isf(MOVE_SIGNIFICANCE, 6) + chi2.isf(MOVE_SIGNIFICANCE / len(tested), 6))
    assert split_with_statistic(monkeypatch, (dataset, truth), statistic) is None


def test_the_split_named_is_the_boundary_of_the_largest_disagreement(monkeypatch, many_boundaries):
    dataset, truth, tested = many_boundaries
    large = chi2.isf(MOVE_SIGNIFICANCE / len(tested), 6) * 2.0
    statistics = iter([5.0, large, 7.0])  # the boundaries in the order they are tested
    monkeypatch.setattr(consistency, "_pose_mahalanobis", lambda fits, R_reference: next(statistics))
    found = consistency.moved_camera_split(dataset, truth.R_cam_base)
    assert found is not None
    assert [len(group) for group in found.groups] == [tested[1], len(dataset.images) - tested[1]]
