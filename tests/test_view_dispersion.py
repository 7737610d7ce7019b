"""The image-level dispersion in one vectorised pass of the view model (solver/fit/view_dispersion.py) gives
what GTSAM's factors linearised one by one give (solver/fit/dispersion.py's dense route and its route
through GTSAM's marginals): the paper's tree with images left out, three mirrors, reconstruction points
seen by some views only, a three-camera rig; the shared columns inverted densely and cluster by cluster."""
from dataclasses import replace

import pytest

from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.simulate.views import simulate_kaleidoscope
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.fit import dispersion, view_dispersion
from mirror_fg.solver.fit.validation import estimate_of_calibration, used_images
from mirror_fg.solver.model.views import ViewProblem


def _both(data, monkeypatch, left_out=()):
    """The dispersion by the vectorised pass and by GTSAM's factors, and whether the pass was taken."""
    calibration = calibrate(data, diagnose=False)
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded] + [(image, None) for image in left_out]
    taken = []
    real = view_dispersion.view_dispersion
    with monkeypatch.context() as patch:
        patch.setattr(dispersion, "view_dispersion", lambda *args: taken.append(1) or real(*args))
        fast = dispersion.image_dispersion(data, estimate, excluded, estimated)
    assert taken, "the vectorised pass was not taken"
    with monkeypatch.context() as patch:
        patch.setattr(dispersion, "VECTORISED", False)
        factors = dispersion.image_dispersion(data, estimate, excluded, estimated)
    return fast, factors


def _same(fast, factors, images):
    assert fast.images == factors.images == images
    assert fast.cost == pytest.approx(factors.cost, rel=1e-10)
    assert fast.dof == pytest.approx(factors.dof, rel=1e-10)


@pytest.mark.parametrize("limit", [10**6, 25])
def test_tree_with_images_left_out(monkeypatch, limit):
    data, _ = simulate_base_case(num_images=60, num_mirrors=2, mirror1_placements=3, num_fiducials=3, seed=2)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", limit)
    _same(*_both(data, monkeypatch, left_out=["img00004", "img00031"]), min(58, limit))


def test_three_mirrors_four_fiducials(monkeypatch):
    data, _ = simulate_base_case(num_images=45, num_mirrors=3, mirror1_placements=3, num_fiducials=4, seed=5)
    _same(*_both(data, monkeypatch), 45)


@pytest.mark.parametrize("clustered_from", [10**6, 0])
def test_reconstruction_points(monkeypatch, clustered_from):
    """Points seen by every view (shared columns), by all but some, views of one shape seeing different
    points (P0 missing from some, P1 from others: as many measurements), and a point that only one of the
    views counted sees (eliminated with that view's own placement); inverted densely and by clusters."""
    data, _ = simulate_base_case(num_images=40, num_points=6, mirror1_placements=3, seed=4)

    def kept(name, k):
        return not ((name == "P0" and (k == 5 or 10 <= k < 15)) or (name == "P1" and k not in (7, 8))
                    or (name == "P2" and 15 <= k < 20))

    images = [replace(image, observations={n: z for n, z in image.observations.items() if kept(n, k)})
              for k, image in enumerate(data.images)]
    monkeypatch.setattr(view_dispersion, "CLUSTERED_FROM", clustered_from)
    _same(*_both(replace(data, images=images), monkeypatch, left_out=["img00008"]), 39)


@pytest.fixture(scope="module")
def rig():
    return dataset_from_dict(simulate_rig_mixed(3, own=[4] * 3, shared=4, seed=3)[0])


@pytest.mark.parametrize("clustered_from", [10**6, 0])
@pytest.mark.parametrize("limit", [10**6, 10])
def test_three_camera_rig(rig, monkeypatch, clustered_from, limit):
    """A photograph's placements seen by several cameras (shared, a cluster each), two hand-held mirrors;
    every view, and ten of them (GTSAM's marginals then)."""
    monkeypatch.setattr(view_dispersion, "CLUSTERED_FROM", clustered_from)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", limit)
    _same(*_both(rig, monkeypatch), min(len(rig.images), limit))


def test_too_many_shared_columns_falls_back_to_gtsam(rig, monkeypatch):
    calibration = calibrate(rig, diagnose=False)
    estimate, _ = estimate_of_calibration(calibration)
    problem = ViewProblem(used_images(rig, estimate, []))
    assert view_dispersion.view_dispersion(problem, estimate, 10**6, 10**6) is not None
    assert view_dispersion.view_dispersion(problem, estimate, 10**6, 20) is None
    monkeypatch.setattr(dispersion, "MAX_DENSE_COLUMNS", 20)
    fast = dispersion.image_dispersion(rig, estimate, [])
    monkeypatch.setattr(dispersion, "VECTORISED", False)
    _same(fast, dispersion.image_dispersion(rig, estimate, []), fast.images)


def test_kaleidoscope_with_points(monkeypatch):
    """Fixed mirrors seen by views of the first and second order (placements repeated in a view's
    reflections), points seen through them."""
    data = dataset_from_dict(simulate_kaleidoscope(3, target=True, num_points=4, seed=1)[0])
    _same(*_both(data, monkeypatch), len(data.images))


def test_not_taken_where_a_view_is_not_a_plain_gaussian_factor():
    data, _ = simulate_base_case(num_images=12, seed=1)
    assert view_dispersion.view_dispersion_applies(ViewProblem(data))
    assert not view_dispersion.view_dispersion_applies(ViewProblem(data, robust="huber"))
    no_target = dataset_from_dict(simulate_kaleidoscope(2, target=False, seed=2)[0])  # the scale's prior
    assert no_target.scale is not None
    assert not view_dispersion.view_dispersion_applies(ViewProblem(no_target))
