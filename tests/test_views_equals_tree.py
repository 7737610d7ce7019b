"""The general view model solves the paper's tree exactly as the tree's own pipeline does: one model, two
implementations (the tree's stacked / eliminated factors, the general per-image factor with plane
variables), the same MLE and covariances."""
from __future__ import annotations

import numpy as np
import pytest

import mirror_fg
from mirror_fg.solver.batch.views_solve import calibrate_views
from mirror_fg.simulate.tree import simulate_tree


@pytest.mark.parametrize("num_mirrors,points", [(1, 0), (2, 3)])
def test_general_solve_of_tree_data_equals_the_tree_pipeline(num_mirrors, points) -> None:
    dataset, _ = simulate_tree(num_mirrors, num_fiducials=4, num_points=points, pixel_sigma=0.5, seed=3)
    tree = mirror_fg.calibrate(dataset)
    general = calibrate_views(dataset)
    scale = np.abs(tree.covariance).max()
    np.testing.assert_allclose(general.R_cam_base, tree.R_cam_base, atol=1e-8)
    np.testing.assert_allclose(general.t_cam_base, tree.t_cam_base, atol=1e-8)
    np.testing.assert_allclose(general.covariance, tree.covariance, atol=1e-6 * scale)
    for placement, v in tree.mirror_vectors.items():
        np.testing.assert_allclose(general.mirror_vectors[placement], v, atol=1e-8)
        np.testing.assert_allclose(general.mirror_covariances[placement], tree.mirror_covariances[placement],
                                   atol=1e-6 * np.abs(tree.mirror_covariances[placement]).max())
    for name, x in tree.points.items():
        np.testing.assert_allclose(general.points[name], x, atol=1e-8)
    assert general.final_error == pytest.approx(tree.final_error, rel=1e-9)
    assert general.expected_final_error == tree.expected_final_error
