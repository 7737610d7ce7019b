"""The general view factor (factors/views.py) against numerical differences and the tree model."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mirror_fg.core.geometry import measurement
from mirror_fg.factors.views import ViewFactor, plane_of, view_model


def _rotation(rng: np.random.Generator, scale: float = 0.3) -> np.ndarray:
    return gtsam.Rot3.Expmap(rng.normal(scale=scale, size=3)).matrix()


def _scene(rng: np.random.Generator):
    poses = {"a": (_rotation(rng), np.array([0.05, -0.02, 0.6])), "b": (_rotation(rng), np.array([-0.2, 0.03, 0.7]))}
    mirrors = {(1, 0): np.array([0.1, 0.05, 0.5]), (2, 0): np.array([-0.3, 0.0, 0.4]), (1, 1): np.array([0.0, 0.2, 0.45])}
    owners = {(1, 0): "a", (2, 0): "b", (1, 1): "a"}
    B = rng.normal(scale=0.1, size=(3, 5))
    return poses, mirrors, owners, B


@pytest.mark.parametrize("camera,reflections", [
    ("a", []), ("a", [(1, 0)]), ("b", [(1, 0)]), ("a", [(2, 0), (1, 0)]), ("b", [(1, 0), (2, 0), (1, 1)]),
    ("a", [(1, 0), (2, 0), (1, 0)]),
])
def test_factor_jacobians_match_numerical_differences(camera, reflections) -> None:
    rng = np.random.default_rng(3)
    poses, mirrors, owners, B = _scene(rng)
    keys = {"a": gtsam.symbol("x", 0), "b": gtsam.symbol("x", 1)}
    mkeys = {p: gtsam.symbol("v", k) for k, p in enumerate(mirrors)}
    lkeys = [-1, gtsam.symbol("l", 0), -1, gtsam.symbol("l", 1), gtsam.symbol("l", 0)]
    B[:, 4] = B[:, 1]
    values = gtsam.Values()
    for name, (R, t) in poses.items():
        values.insert(keys[name], gtsam.Pose3(gtsam.Rot3(R), t))
    for p, v in mirrors.items():
        values.insert(mkeys[p], plane_of(v))
    values.insert(gtsam.symbol("l", 0), B[:, 1])
    values.insert(gtsam.symbol("l", 1), B[:, 3])
    observed = np.zeros((2, 5))
    view = ViewFactor(camera, reflections, keys, {}, mkeys, owners, B, lkeys, observed, np.full((2, 5), 1e-3))
    factor = view.factor()
    linear = factor.linearize(values)
    A, b = linear.jacobian()
    # numerical: perturb each variable of the factor along its local coordinates
    columns = []
    for key in view.keys:
        dim = 6 if gtsam.Symbol(key).chr() == ord("x") else 3
        for i in range(dim):
            delta = np.zeros(dim)
            delta[i] = 1e-6
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            for sign, vals in ((1.0, plus), (-1.0, minus)):
                if dim == 6:
                    vals.update(key, values.atPose3(key).retract(sign * delta))
                elif gtsam.Symbol(key).chr() == ord("v"):
                    vals.update(key, values.atOrientedPlane3(key).retract(sign * delta))
                else:
                    vals.update(key, values.atPoint3(key) + sign * delta)
            columns.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / 2e-6)
    numerical = np.array(columns).T / 1e-3  # whitened like A
    np.testing.assert_allclose(A, numerical, atol=1e-6 * np.abs(numerical).max())


def test_view_model_is_the_tree_model_for_mirror_configs() -> None:
    rng = np.random.default_rng(5)
    poses, mirrors, owners, B = _scene(rng)
    owners = {p: "a" for p in owners}
    z = view_model("a", [(1, 0), (2, 0)], poses, mirrors, owners, B)[0]
    R, t = poses["a"]
    expected = np.array([measurement(R, t, [mirrors[(1, 0)], mirrors[(2, 0)]], B[:, j]) for j in range(B.shape[1])]).T
    np.testing.assert_allclose(z, expected, rtol=1e-12, atol=1e-14)


def test_transferred_plane_is_the_same_plane() -> None:
    """A point reflected in camera b's frame through the owner a's plane equals the reflection done in a."""
    rng = np.random.default_rng(8)
    poses, mirrors, owners, B = _scene(rng)
    owners = {(1, 0): "a"}
    zb = view_model("b", [(1, 0)], poses, mirrors, owners, B)[0]
    (Ra, ta), (Rb, tb) = poses["a"], poses["b"]
    xa = Ra @ B + ta[:, None]
    v = mirrors[(1, 0)]
    ya = xa - 2.0 * v[:, None] * ((v @ xa) / (v @ v) - 1.0)
    yb = Rb @ Ra.T @ (ya - ta[:, None]) + tb[:, None]
    np.testing.assert_allclose(zb, yb[:2] / yb[2], rtol=1e-12)


def test_factor_with_intrinsics_matches_numerical_differences() -> None:
    from mirror_fg.factors.intrinsics import IntrinsicsModel

    rng = np.random.default_rng(11)
    poses, mirrors, owners, B = _scene(rng)
    keys = {"a": gtsam.symbol("x", 0), "b": gtsam.symbol("x", 1)}
    mkeys = {p: gtsam.symbol("v", k) for k, p in enumerate(mirrors)}
    model = IntrinsicsModel(np.array([900.0, 910.0, 640.0, 480.0, -0.1, 0.02, 0.001, -0.002, 0.0]),
                            ("fx", "fy", "cx", "cy", "k1", "k2"))
    kkey = gtsam.symbol("k", 1)
    values = gtsam.Values()
    for name, (R, t) in poses.items():
        values.insert(keys[name], gtsam.Pose3(gtsam.Rot3(R), t))
    for p, v in mirrors.items():
        values.insert(mkeys[p], plane_of(v))
    values.insert(gtsam.symbol("l", 0), B[:, 2])
    values.insert(kkey, np.array([900.0, 910.0, 640.0, 480.0, -0.1, 0.02]))
    view = ViewFactor("b", [(1, 0), (2, 0)], keys, {}, mkeys, owners, B, [-1, -1, gtsam.symbol("l", 0), -1, -1],
                      np.zeros((2, 5)), np.full((2, 5), 0.5), intrinsics=(model, kkey))
    factor = view.factor()
    A, _ = factor.linearize(values).jacobian()
    columns = []
    for key in view.keys:
        chr_ = gtsam.Symbol(key).chr()
        dim = 6 if chr_ == ord("x") else (6 if chr_ == ord("k") else 3)
        for i in range(dim):
            delta = np.zeros(dim)
            delta[i] = 1e-6 if chr_ != ord("k") or i < 4 else 1e-8
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            for sign, vals in ((1.0, plus), (-1.0, minus)):
                if chr_ == ord("x"):
                    vals.update(key, values.atPose3(key).retract(sign * delta))
                elif chr_ == ord("v"):
                    vals.update(key, values.atOrientedPlane3(key).retract(sign * delta))
                elif chr_ == ord("k"):
                    vals.update(key, values.atVector(key) + sign * delta)
                else:
                    vals.update(key, values.atPoint3(key) + sign * delta)
            columns.append((factor.unwhitenedError(plus) - factor.unwhitenedError(minus)) / (2 * delta[i]))
    numerical = np.array(columns).T / 0.5
    np.testing.assert_allclose(A, numerical, rtol=1e-5, atol=1e-6 * np.abs(numerical).max())
