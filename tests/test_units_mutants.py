"""Expected costs are GTSAM's half chi-square: the joint solve of two screens that share no placement
expects what the two screens' own solves expect together (measurements and unknowns add up), and its
final cost is near it with the right noise model."""
from __future__ import annotations

import numpy as np
from test_screens import datasets_of, scene  # noqa: F401  (the module's scene fixture)

from mirror_fg.solver.screens import calibrate_screens


def test_the_screens_expected_cost_is_the_sum_of_each_screens_own(scene):  # noqa: F811
    cal = calibrate_screens(datasets_of(scene, np.random.default_rng(1)))
    alone = sum(cal.alone[name].expected_final_error for name in cal.names)
    assert cal.expected_final_error == alone
    assert 0.5 < cal.final_error / cal.expected_final_error < 1.5
