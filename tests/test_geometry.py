"""Algebraic identities of the geometry kernel (eqs. 3-9)."""
import gtsam
import numpy as np
from gtsam.utils.numerical_derivative import numericalDerivative11
from hypothesis import given, settings
from hypothesis import strategies as st

from mirror_fg.core.geometry import (
    householder, measurement, measurement_jacobians, nested_transform, project, project_jacobian, project_to_orthogonal,
    reflect, so3_exp,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
mirror = vec3.filter(lambda v: np.linalg.norm(v) > 0.05)


@given(mirror, vec3)
def test_reflection_is_an_involution(v, x):
    np.testing.assert_allclose(reflect(reflect(x, v), v), x, atol=1e-12)


@given(mirror, vec3)
def test_mirror_foot_point_is_fixed_and_distance_preserved(v, x):
    np.testing.assert_allclose(reflect(v, v), v, atol=1e-12)
    # the reflected point is as far from the plane as the original, on the other side
    n = v / np.linalg.norm(v)
    assert abs((reflect(x, v) - v) @ n + (x - v) @ n) < 1e-12


@settings(max_examples=50)
@given(vec3, st.lists(mirror, min_size=0, max_size=4))
def test_nested_transform_is_orthogonal_with_alternating_determinant(w, vectors):
    A, b = nested_transform(so3_exp(w), np.zeros(3), vectors)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-10)
    assert np.isclose(np.linalg.det(A), (-1.0) ** len(vectors))


@given(vec3, st.lists(mirror, min_size=1, max_size=3), vec3)
def test_nested_transform_equals_successive_reflections(w, vectors, point):
    R, t = so3_exp(w), np.array([0.1, -0.2, 0.3])
    A, b = nested_transform(R, t, vectors)
    x = R @ point + t
    for v in vectors:
        x = reflect(x, v)
    np.testing.assert_allclose(A @ point + b, x, atol=1e-10)


def test_householder_matches_eq3():
    v = np.array([0.1, -0.2, 0.5])
    M = householder(v)
    np.testing.assert_allclose(M, np.eye(3) - 2 * np.outer(v, v) / (v @ v))
    np.testing.assert_allclose(M @ v, -v)


def test_projection_and_measurement_jacobian_value():
    np.testing.assert_allclose(project(np.array([1.0, 2.0, 4.0])), [0.25, 0.5])
    point = np.array([0.3, -0.2, 1.5])
    np.testing.assert_allclose(project_jacobian(point), numericalDerivative11(project, point, 1e-6), rtol=1e-8, atol=1e-10)
    R, t, v, p = so3_exp(np.array([0.1, 0.2, 0.3])), np.array([0.0, 0.0, -0.2]), [np.array([0.0, 0.1, 0.5])], np.ones(3) * 0.1
    z, H_pose, H_mirrors, H_point = measurement_jacobians(R, t, v, p)
    np.testing.assert_allclose(z, measurement(R, t, v, p))
    # Jacobians against central differences on GTSAM's Pose3 retraction and on the Point3 vectors
    pose = gtsam.Pose3(gtsam.Rot3(R), t)
    numeric_pose = numericalDerivative11(lambda x: measurement(x.rotation().matrix(), x.translation(), v, p), pose, 1e-6)
    numeric_mirror = numericalDerivative11(lambda x: measurement(R, t, [x], p), v[0], 1e-6)
    numeric_point = numericalDerivative11(lambda x: measurement(R, t, v, x), p, 1e-6)
    for analytic, numeric in ((H_pose, numeric_pose), (H_mirrors[0], numeric_mirror), (H_point, numeric_point)):
        np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-8 * np.abs(numeric).max())


def test_project_to_orthogonal_keeps_requested_determinant():
    Q = project_to_orthogonal(np.diag([1.0, 1.0, 1.0]) + 0.01, determinant=-1.0)
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) < 0
