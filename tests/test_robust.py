"""factors/robust.py, the one home of the robust kernels."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

from mirror_fg.factors.robust import (
    KERNELS, ROBUST_K, check_kernel, robust_noise_model, robust_row_scales, robust_weight_and_loss,
)
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.simulate.tree import simulate_base_case

ROOT = Path(__file__).resolve().parents[1]
ESTIMATORS = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}


def test_kernel_names_are_checked_in_one_place():
    assert set(KERNELS) == set(ESTIMATORS)
    for name in (None, *KERNELS):
        check_kernel(name)
    with pytest.raises(ValueError, match=r"unknown robust kernel 'tukey': use 'huber' or 'cauchy'"):
        check_kernel("tukey")
    with pytest.raises(ValueError, match="unknown robust kernel"):
        robust_weight_and_loss("tukey", np.zeros(1))
    with pytest.raises(ValueError, match="unknown robust kernel"):
        robust_noise_model(gtsam.noiseModel.Unit.Create(2), "tukey")


def test_row_scales_reproduce_gtsams_robust_factor():
    """Rows scaled by ``sqrt_w`` give GTSAM's weight; by ``loss_scale`` a half squared norm equal to its loss."""
    r = np.array([0.0, 0.2, ROBUST_K, 1.9, 6.0, 55.0])
    for kind, estimator in ESTIMATORS.items():
        kernel = estimator.Create(ROBUST_K)
        sqrt_w, loss_scale = robust_row_scales(kind, r)
        np.testing.assert_allclose(sqrt_w ** 2, [kernel.weight(e) for e in r], rtol=1e-14)
        np.testing.assert_allclose(0.5 * (loss_scale * r) ** 2, [kernel.loss(e) for e in r], rtol=1e-13, atol=1e-300)
        assert loss_scale[0] == 1.0


def test_robust_noise_model_is_gtsams():
    base = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5, 2.0]))
    assert robust_noise_model(base, None) is base
    whitened = np.array([3.0, 4.0])  # norm 5: beyond the threshold of either kernel
    error = whitened * [0.5, 2.0]
    for kind, estimator in ESTIMATORS.items():
        model = robust_noise_model(base, kind)
        assert isinstance(model, gtsam.noiseModel.Robust)
        assert np.isclose(model.loss(model.squaredMahalanobisDistance(error)), estimator.Create(ROBUST_K).loss(5.0))


def test_robust_module_loads_neither_numpy_nor_gtsam():
    probe = "import sys, json, mirror_fg.factors.robust; print(json.dumps(sorted(sys.modules)))"
    loaded = json.loads(subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True,
                                       check=True).stdout)
    assert not {m.split(".")[0] for m in loaded} & {"numpy", "gtsam"}


def test_calibrate_refuses_an_unknown_kernel_before_solving(monkeypatch):
    dataset, _ = simulate_base_case(num_images=6, seed=3)
    import mirror_fg.solver.batch.tree_problem as pipeline  # the tree problem runs the checks

    def no_solve(*args, **kwargs):
        raise AssertionError("solved with an unknown kernel")

    monkeypatch.setattr(pipeline, "check_images", no_solve)
    with pytest.raises(ValueError, match="unknown robust kernel 'tukey'"):
        calibrate(dataset, robust="tukey")
