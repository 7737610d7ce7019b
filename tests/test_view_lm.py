"""The paper's tree solved by calibrate() on the general view model (solver/model/view_lm.py, the tree's
analytical start, the view factors with each photograph's own placement eliminated) against the tree's own
factors (tests/reference/: eliminated.py, batched.py): the same estimates, covariances, cost and result
fields."""
from __future__ import annotations

import numpy as np
import pytest

import mirror_fg
from mirror_fg.simulate.tree import simulate_tree
from mirror_fg.solver.model import lm as lm_module, view_lm
from reference.lm import use_tree_factors


@pytest.mark.parametrize("num_mirrors,points,robust", [(1, 0, None), (2, 3, None), (3, 0, None), (2, 0, "huber")])
def test_view_model_run_equals_the_tree_factors(monkeypatch, num_mirrors, points, robust):
    dataset, _ = simulate_tree(num_mirrors, num_fiducials=4, num_points=points, pixel_sigma=0.5, seed=3)
    one_model = lm_module._levenberg_marquardt
    use_tree_factors(monkeypatch)  # the tree's own factors
    tree = mirror_fg.calibrate(dataset, robust=robust)
    monkeypatch.setattr(lm_module, "_levenberg_marquardt", one_model)
    runs = []
    real = view_lm.view_model_run
    monkeypatch.setattr(view_lm, "view_model_run", lambda *args: runs.append(1) or real(*args))
    views = mirror_fg.calibrate(dataset, robust=robust)
    assert runs  # the view model solved it
    tolerance = 1e-8 if robust is None else 1e-6  # the stacked graphs' LM stops ~1e-7 from the optimum
    np.testing.assert_allclose(views.R_cam_base, tree.R_cam_base, atol=tolerance)
    np.testing.assert_allclose(views.t_cam_base, tree.t_cam_base, atol=tolerance)
    np.testing.assert_allclose(views.covariance, tree.covariance, atol=1e-6 * np.abs(tree.covariance).max())
    for placement, v in tree.mirror_vectors.items():
        np.testing.assert_allclose(views.mirror_vectors[placement], v, atol=tolerance)
        C = tree.mirror_covariances[placement]
        np.testing.assert_allclose(views.mirror_covariances[placement], C, atol=1e-6 * np.abs(C).max())
    for name, x in tree.points.items():
        np.testing.assert_allclose(views.points[name], x, atol=tolerance)
    assert views.final_error == pytest.approx(tree.final_error, rel=1e-9 if robust is None else 1e-7)
    assert views.expected_final_error == tree.expected_final_error
    assert views.restarts == tree.restarts and views.iterations <= tree.iterations + 1
    assert set(views.timings) == set(tree.timings)
    assert [(e.image, e.point, e.reason) for e in views.excluded] == [(e.image, e.point, e.reason) for e in tree.excluded]
