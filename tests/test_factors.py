"""Factor Jacobians against central finite differences on GTSAM's own retractions."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, V, X
from gtsam.utils.numerical_derivative import numericalDerivative11

from reference.reflection import ReflectionFactor, noise_model
from mirror_fg.core.geometry import measurement, so3_exp


def _scene(num_mirrors, rng):
    R = so3_exp(rng.normal(size=3) * 0.5)
    t = np.array([0.05, -0.1, -0.2]) + 0.05 * rng.normal(size=3)
    vectors = []
    for level in range(1, num_mirrors + 1):
        sign = 1.0 if (num_mirrors - level) % 2 == 0 else -1.0
        normal = so3_exp(np.r_[rng.normal(size=2) * 0.3, 0.0]) @ np.array([0.0, 0.0, sign])
        vectors.append(0.5 * normal)
    point = np.array([0.1, 0.05, 0.02]) + 0.05 * rng.normal(size=3)
    return R, t, vectors, point


def _numerical_jacobians(factor, values, keys, step=1e-6):
    """Central differences of the unwhitened error over each key's tangent space (GTSAM's retractions)."""
    jacobians = []
    for key in keys:

        def error_at(x, key=key):
            perturbed = gtsam.Values(values)
            perturbed.update(key, x)
            return factor.unwhitenedError(perturbed)

        x = values.atPose3(key) if key == X(0) else values.atPoint3(key)
        jacobians.append(numericalDerivative11(error_at, x, step))
    return jacobians


@pytest.mark.parametrize("num_mirrors", [1, 2, 3])
@pytest.mark.parametrize("landmark", [False, True])
def test_jacobians_match_numerical(num_mirrors, landmark):
    rng = np.random.default_rng(10 * num_mirrors + landmark)
    for _ in range(5):
        R, t, vectors, point = _scene(num_mirrors, rng)
        z = measurement(R, t, vectors, point) + rng.normal(size=2) * 1e-3
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), t))
        mirror_keys = [V(k) for k in range(num_mirrors)]
        for key, v in zip(mirror_keys, vectors):
            values.insert(key, v)
        noise = noise_model(np.array([1e-3, 1e-3]))
        if landmark:
            values.insert(L(0), point)
            factor = ReflectionFactor(noise, X(0), mirror_keys, z, landmark_key=L(0))
        else:
            factor = ReflectionFactor(noise, X(0), mirror_keys, z, fiducial=point)
        keys = list(factor.keys())
        # error is h(x) - z
        np.testing.assert_allclose(factor.unwhitenedError(values), measurement(R, t, vectors, point) - z, atol=1e-15)
        whitened = factor.linearize(values).jacobian()[0]
        analytic = whitened * 1e-3  # undo whitening by sigma
        numeric = np.hstack(_numerical_jacobians(factor, values, keys))
        scale = np.abs(numeric).max()
        assert np.abs(analytic - numeric).max() <= 1e-6 * scale


def test_robust_kernel_and_unknown_kernel():
    assert isinstance(noise_model(np.ones(2), "huber"), gtsam.noiseModel.Robust)
    assert isinstance(noise_model(np.ones(2), "cauchy"), gtsam.noiseModel.Robust)
    with pytest.raises(ValueError, match="unknown robust kernel"):
        noise_model(np.ones(2), "tukey-ish")
