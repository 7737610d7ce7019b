"""One options value for the incremental path (IncrementalOptions), as SolveOptions is for the batch: it
reaches the backend, equals the keywords it replaces, and refuses being given twice."""
import pytest

from mirror_fg import IncrementalCalibrator, IncrementalOptions, calibrate_incremental
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.simulate.views import simulate_mixed
from mirror_fg.solver.incremental.state import RelinearizeThresholds


def test_a_bad_kernel_is_refused_in_the_options():
    with pytest.raises(ValueError, match="robust"):
        IncrementalOptions(robust="tukey")


def test_options_reach_the_views_backend():
    data = dataset_from_dict(simulate_mixed(seed=1)[0])
    thresholds = RelinearizeThresholds(pose=0.5)
    calibrator = IncrementalCalibrator(data, IncrementalOptions(robust="huber", thresholds=thresholds))
    assert calibrator.backend.robust == "huber" and calibrator.backend.thresholds is thresholds
    assert calibrator.options == IncrementalOptions(robust="huber", thresholds=thresholds)


def test_options_and_keywords_give_the_same_estimate():
    data, _ = simulate_base_case(num_images=60, pixel_sigma=1.0, seed=0)
    by_options = calibrate_incremental(data, options=IncrementalOptions(accept_poor_fit=True))
    by_keyword = calibrate_incremental(data, accept_poor_fit=True)
    assert (by_options.t_cam_base == by_keyword.t_cam_base).all()
    assert (by_options.R_cam_base == by_keyword.R_cam_base).all()


def test_settings_given_twice_are_refused():
    data, _ = simulate_base_case(num_images=20, seed=2)
    with pytest.raises(TypeError, match="not both"):
        IncrementalCalibrator(data, IncrementalOptions(), robust="huber")
    with pytest.raises(TypeError, match="not both"):
        calibrate_incremental(data, robust="huber", options=IncrementalOptions())
