"""The tree's dispersion in one pass of its own model (solver/fit/tree_dispersion.py) gives what the view
model's routes give (solver/fit/dispersion.py): every image (the dense route) and an even subset (the
route through GTSAM's marginals), with images left out, with three mirrors, with reconstruction points."""
import pytest

from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.fit import dispersion
from mirror_fg.solver.fit.validation import estimate_of_calibration


def _both(data, monkeypatch, left_out=()):
    calibration = calibrate(data, diagnose=False)
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded] + [(image, None) for image in left_out]
    assert dispersion.tree_dispersion_applies(data, excluded, estimated)
    fast = dispersion.image_dispersion(data, estimate, excluded, estimated)
    with monkeypatch.context() as patch:
        patch.setattr(dispersion, "tree_dispersion_applies", lambda *args: False)
        views = dispersion.image_dispersion(data, estimate, excluded, estimated)
    return fast, views


@pytest.mark.parametrize("limit", [10**6, 25])
def test_equals_the_view_model_routes(monkeypatch, limit):
    data, _ = simulate_base_case(num_images=60, num_mirrors=2, mirror1_placements=3, num_fiducials=3, seed=2)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", limit)
    fast, views = _both(data, monkeypatch, left_out=["img00004", "img00031"])
    assert fast.images == views.images == min(58, limit)
    assert fast.cost == pytest.approx(views.cost, rel=1e-10)
    assert fast.dof == pytest.approx(views.dof, rel=1e-10)


def test_three_mirrors_four_fiducials(monkeypatch):
    data, _ = simulate_base_case(num_images=45, num_mirrors=3, mirror1_placements=3, num_fiducials=4, seed=5)
    fast, views = _both(data, monkeypatch)
    assert fast.images == views.images == 45
    assert fast.cost == pytest.approx(views.cost, rel=1e-10)
    assert fast.dof == pytest.approx(views.dof, rel=1e-10)


def test_reconstruction_points(monkeypatch):
    """Points seen by every image (shared columns), by all but one, and a point that only one of the images
    counted sees (eliminated with that image's own placement)."""
    from dataclasses import replace

    data, _ = simulate_base_case(num_images=40, num_points=6, mirror1_placements=3, seed=4)
    images = [replace(image, observations={n: z for n, z in image.observations.items()
                                           if (n != "P0" or k != 5) and (n != "P1" or k in (7, 8))})
              for k, image in enumerate(data.images)]  # P0 not in image 5; P1 in images 7 and 8 alone
    fast, views = _both(replace(data, images=images), monkeypatch, left_out=["img00008"])
    assert fast.images == views.images == 39
    assert fast.cost == pytest.approx(views.cost, rel=1e-10)
    assert fast.dof == pytest.approx(views.dof, rel=1e-10)


def test_not_taken_with_a_point_left_out():
    data, _ = simulate_base_case(num_images=12, seed=1)
    assert dispersion.tree_dispersion_applies(data, [("img00003", None)], {})
    assert not dispersion.tree_dispersion_applies(data, [("img00003", "F0")], {})


def test_plane_coordinates_are_the_view_model_s():
    import numpy as np

    from mirror_fg.factors.views import plane_of, vector_of_plane
    from mirror_fg.solver.fit.tree_dispersion import plane_jacobians

    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(500, 3)) * rng.uniform(0.1, 3.0, (500, 1))
    vectors[:3] = [[0.0, 0.0, 1.0], [0.5, 0.5, 0.0], [-1.0, 1.0, 1.0]]  # ties between the smallest components
    expected = np.array([vector_of_plane(plane_of(v))[1] for v in vectors])
    assert np.allclose(plane_jacobians(vectors), expected, rtol=0, atol=1e-14 * np.abs(expected).max())
