"""ViewProblem's view factors, built for most images from the first factor of their shape
(solver/model/views.py ``view_factor_like``), against ``ViewFactor.__init__`` called for every image: every
attribute equal, on the paper's tree, a kaleidoscope with repeated placements and reconstruction points, a
rig whose second camera sees placements the first camera owns, intrinsics estimated and a robust kernel."""
from __future__ import annotations

import numpy as np
import pytest

import views_scenes as scenes
from mirror_fg.factors.views import ViewFactor, ViewSlots
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.batch.views_solve import _intrinsics_models
from mirror_fg.solver.model.views import ViewProblem


def _reference(problem: ViewProblem, k: int) -> ViewFactor:
    """The factor of image ``k`` as ``ViewFactor.__init__`` builds it."""
    built = problem.factors[k]
    landmarks = [int(key) for key in built.landmark_keys]
    return ViewFactor(built.camera, problem.views[k].reflections, problem.pose_keys, problem.fixed, problem.mirror_keys,
                      problem.owners, built.base_points, landmarks, built.observed, built.sigmas, problem.robust,
                      intrinsics=built.intrinsics)


def _equal(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True) and np.asarray(a).dtype == np.asarray(b).dtype
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, ViewSlots):
        return _equal(vars(a), vars(b))
    return a == b


def _tree():
    return simulate_base_case(num_images=12, num_points=2, mirror1_placements=3, pixel_sigma=1.0, mirror_distance=0.5,
                              tilt_deg=30.0, seed=0, num_mirrors=2, num_fiducials=3)[0], {}


def _kaleidoscope():
    return dataset_from_dict(scenes.kaleidoscope_three_mirrors_one_point(0)[0]), {}


def _rig():
    return dataset_from_dict(simulate_rig_mixed(3, own=[3, 3, 3], shared=3, seed=2)[0]), {}


def _intrinsics():
    data = scenes.kaleidoscope_two_mirrors(1)[0]
    data["camera"]["estimate"] = ["fx", "fy", "cx", "cy"]
    dataset = dataset_from_dict(data)
    return dataset, {"intrinsics": _intrinsics_models(dataset)}


def _robust():
    return dataset_from_dict(scenes.kaleidoscope_two_mirrors(1)[0]), {"robust": "huber"}


@pytest.mark.parametrize("make", [_tree, _kaleidoscope, _rig, _intrinsics, _robust],
                         ids=["tree", "kaleidoscope", "rig", "intrinsics", "robust"])
def test_factors_as_their_constructor(make):
    dataset, options = make()
    problem = ViewProblem(dataset, **options)
    assert len({id(f.slots) for f in problem.factors}) == len(problem.factors)  # each view its own columns
    for k, factor in enumerate(problem.factors):
        reference = _reference(problem, k)
        assert vars(factor).keys() == vars(reference).keys()
        for name, value in vars(reference).items():
            assert _equal(getattr(factor, name), value), (k, name)
