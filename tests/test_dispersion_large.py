"""The image-level dispersion on large captures (solver/fit/dispersion.py): the route through GTSAM's
marginals gives what the dense route gives, and above MAX_IMAGES the dispersion is summed over an even
subset whose count and dof the result reports."""
import numpy as np
import pytest

from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.fit import dispersion
from mirror_fg.solver.fit.validation import estimate_of_calibration


@pytest.fixture(scope="module")
def rig():
    data = dataset_from_dict(simulate_rig_mixed(3, own=[4] * 3, shared=4, seed=3)[0])
    calibration = calibrate(data)
    estimate, estimated = estimate_of_calibration(calibration)
    return data, calibration, estimate, [(e.image, e.point) for e in calibration.excluded], estimated


def test_marginals_route_equals_the_dense_route_on_every_image(rig, monkeypatch):
    data, calibration, estimate, excluded, estimated = rig
    dense = dispersion.image_dispersion(data, estimate, excluded, estimated)
    assert dense == calibration.dispersion and dense.images == len(data.images)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", 10**6)
    through_marginals = dispersion._sampled_dispersion(data, estimate, excluded, estimated)
    assert through_marginals.images == dense.images
    assert through_marginals.cost == pytest.approx(dense.cost, rel=1e-9)
    assert through_marginals.dof == pytest.approx(dense.dof, rel=1e-6)


def test_above_the_limit_an_even_subset_with_its_own_dof(rig, monkeypatch):
    data, _, estimate, excluded, estimated = rig
    dense = dispersion.image_dispersion(data, estimate, excluded, estimated)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", len(data.images) // 2)
    subset = dispersion.image_dispersion(data, estimate, excluded, estimated)
    assert subset.images == len(data.images) // 2
    assert 0.3 * dense.dof < subset.dof < 0.7 * dense.dof  # about half the images' redundancy
    # the variance factor of half the images: within the chi-square spread of its dof
    assert abs(subset.factor - dense.factor) < 4 * np.sqrt(2 / subset.dof)
