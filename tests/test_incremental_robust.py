"""iSAM2 with a robust kernel reaches the batch's robust MLE (each relinearisation also re-weights: the
polish needs more passes than without a kernel; with five it stalled on a clean 60-image tree)."""
import numpy as np
import pytest

from mirror_fg import calibrate, calibrate_incremental
from mirror_fg.simulate.tree import simulate_base_case


@pytest.mark.parametrize("kernel", ["huber"])  # convex: one optimum to meet
def test_incremental_with_a_kernel_converges_to_the_batch(kernel):
    data, _ = simulate_base_case(num_images=60, pixel_sigma=1.0, seed=0)
    batch = calibrate(data, robust=kernel)
    incremental = calibrate_incremental(data, robust=kernel)
    assert incremental.converged
    sigma = np.sqrt(np.diag(batch.covariance)[3:])
    assert np.all(np.abs(incremental.t_cam_base - batch.t_cam_base) < 0.01 * sigma)
