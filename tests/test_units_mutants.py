"""Expected costs are GTSAM's half chi-square: the joint solve of two screens that share no placement
expects what the two screens' own solves expect together (measurements and unknowns add up), and its
final cost is near it with the right noise model."""
from __future__ import annotations

import numpy as np
from test_screens import datasets_of, scene  # noqa: F401  (the module's scene fixture)

from mirror_fg.solver.batch.screens import calibrate_screens


def test_the_screens_expected_cost_is_the_sum_of_each_screens_own(scene):  # noqa: F811
    cal = calibrate_screens(datasets_of(scene, np.random.default_rng(1)))
    alone = sum(cal.alone[name].expected_final_error for name in cal.names)
    assert cal.expected_final_error == alone
    assert 0.5 < cal.final_error / cal.expected_final_error < 1.5


def test_validation_from_an_estimate_near_the_optimum_equals_the_optimum_s():
    """Held-out validation takes one Gauss-Newton step of the full system first (its optimum): started
    0.3 mm off the solve's answer it gives the same ratios as from the answer itself."""
    from dataclasses import replace

    from mirror_fg.solver.calibrate import calibrate
    from mirror_fg.solver.fit.validation import estimate_of_calibration, validate
    from mirror_fg.simulate.tree import simulate_base_case

    dataset, _ = simulate_base_case(num_images=12, seed=5)
    calibration = calibrate(dataset)
    estimate, estimated = estimate_of_calibration(calibration)
    at_optimum = validate(dataset, estimate, [], estimated)
    (name, (R, t)), = estimate.poses.items()
    off = replace(estimate, poses={name: (R, t + np.array([3e-4, -2e-4, 1e-4]))})
    near = validate(dataset, off, [], estimated)
    np.testing.assert_allclose(near.ratios, at_optimum.ratios, rtol=1e-2)
