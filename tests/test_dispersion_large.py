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


@pytest.mark.parametrize("joint_columns", [0, dispersion.MAX_JOINT_COLUMNS])
def test_one_joint_of_the_shared_columns_equals_a_joint_per_image(rig, monkeypatch, joint_columns):
    """The shared columns' joint marginal with each image's own placement eliminated from its own block
    gives what GTSAM's joint marginal of each image's keys gives (the route used with many shared
    columns), and both what the dense route gives."""
    data, _, estimate, excluded, estimated = rig
    dense = dispersion.image_dispersion(data, estimate, excluded, estimated)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", 10**6)
    monkeypatch.setattr(dispersion, "MAX_JOINT_COLUMNS", joint_columns)
    sampled = dispersion._sampled_dispersion(data, estimate, excluded, estimated)
    assert sampled.cost == pytest.approx(dense.cost, rel=1e-9)
    assert sampled.dof == pytest.approx(dense.dof, rel=1e-6)


def test_a_placement_a_prior_holds_is_not_eliminated_as_the_image_s_own(monkeypatch):
    """A placement one image sees but a prior also holds (the scale prior without a target) carries
    information beyond the image's: eliminating it from the image's block alone would be wrong. A strong
    prior on such a placement: the route through the marginals still equals the dense route."""
    from dataclasses import replace

    from mirror_fg.data import Scale
    from mirror_fg.solver.fit.validation import _problem
    from mirror_fg.solver.model import views as view_model

    from mirror_fg.simulate.tree import simulate_base_case

    data, _ = simulate_base_case(num_images=30, num_points=0, mirror1_placements=3, num_mirrors=2, num_fiducials=3,
                                 pixel_sigma=1.0, seed=0)  # mirror 2: a new placement in every image
    calibration = calibrate(data)
    estimate, estimated = estimate_of_calibration(calibration)
    excluded = [(e.image, e.point) for e in calibration.excluded]
    _, problem, values, _ = _problem(data, estimate, excluded, estimated)
    seen: dict[int, int] = {}
    for factor in problem.factors:
        for key in factor.mirror_keys.values():
            seen[key] = seen.get(key, 0) + 1
    lone = next(key for key, count in seen.items() if count == 1)
    placement = next(p for p, key in problem.mirror_keys.items() if key == lone)
    distance = float(values.atOrientedPlane3(lone).distance())
    original = view_model.scale_prior

    def held(dataset, mirror_keys, point_keys):  # the scale prior a target-less dataset would carry
        return original(replace(dataset, scale=Scale(abs(distance), placement=placement)), mirror_keys, point_keys)

    monkeypatch.setattr(view_model, "scale_prior", held)
    monkeypatch.setattr(dispersion, "scale_prior", held)
    dense = dispersion.image_dispersion(data, estimate, excluded, estimated)
    monkeypatch.setattr(dispersion, "MAX_IMAGES", 10**6)
    sampled = dispersion._sampled_dispersion(data, estimate, excluded, estimated)
    assert sampled.cost == pytest.approx(dense.cost, rel=1e-9)
    assert sampled.dof == pytest.approx(dense.dof, rel=1e-6)
