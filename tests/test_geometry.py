"""Euler conventions, wrapping and d_SE3 against gtsam and scipy."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimation.geometry import (
    R_BODY_CAMERA,
    d_se3,
    euler_from_pose3,
    euler_matrix_derivatives,
    euler_rate_matrix,
    euler_rate_matrix_inverse,
    euler_to_matrix,
    matrix_to_euler,
    pose3_from_euler,
    wrap_angle,
)

angle = st.floats(-np.pi + 1e-6, np.pi - 1e-6)
pitch = st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3)


def _random_euler(rng, n):
    return np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.5, 1.5, n),
                            rng.uniform(-np.pi, np.pi, n)])


def test_matrix_equals_gtsam_ypr_and_scipy_zyx(rng):
    for psi, theta, phi in _random_euler(rng, 50):
        R = euler_to_matrix([psi, theta, phi])
        np.testing.assert_allclose(R, gtsam.Rot3.Ypr(phi, theta, psi).matrix(), atol=1e-12)
        np.testing.assert_allclose(
            R, Rotation.from_euler("ZYX", [phi, theta, psi]).as_matrix(), atol=1e-12)


def test_vectorised_matrix_matches_single(rng):
    euler = _random_euler(rng, 7).reshape(7, 3)
    stacked = euler_to_matrix(euler)
    for e, R in zip(euler, stacked):
        np.testing.assert_allclose(R, euler_to_matrix(e), atol=1e-14)
    np.testing.assert_allclose(matrix_to_euler(stacked), euler, atol=1e-10)


@settings(max_examples=200, deadline=None)
@given(angle, pitch, angle)
def test_euler_round_trip(psi, theta, phi):
    e = np.array([psi, theta, phi])
    np.testing.assert_allclose(matrix_to_euler(euler_to_matrix(e)), e, atol=1e-9)


def test_gimbal_lock_gives_same_matrix():
    for theta in (np.pi / 2, -np.pi / 2):
        R = euler_to_matrix([0.4, theta, -1.1])
        e = matrix_to_euler(R)
        assert e[0] == 0.0
        np.testing.assert_allclose(euler_to_matrix(e), R, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.floats(-100.0, 100.0))
def test_wrap_angle_range_and_equivalence(a):
    w = wrap_angle(a)
    assert -np.pi <= w < np.pi
    assert abs(np.sin(w) - np.sin(a)) < 1e-9 and abs(np.cos(w) - np.cos(a)) < 1e-9


def test_wrap_angle_array():
    np.testing.assert_allclose(wrap_angle(np.array([0.0, np.pi, 3 * np.pi + 0.1, -0.2])),
                               [0.0, -np.pi, -np.pi + 0.1, -0.2], atol=1e-12)


def test_matrix_derivatives_numerical(rng):
    h = 1e-6
    for e in _random_euler(rng, 20):
        D = euler_matrix_derivatives(e)
        for k in range(3):
            de = np.zeros(3)
            de[k] = h
            num = (euler_to_matrix(e + de) - euler_to_matrix(e - de)) / (2 * h)
            np.testing.assert_allclose(D[k], num, atol=1e-8)


def test_rate_matrix_is_left_perturbation(rng):
    h = 1e-6
    for e in _random_euler(rng, 20):
        E = euler_rate_matrix(e)
        np.testing.assert_allclose(E @ euler_rate_matrix_inverse(e), np.eye(3), atol=1e-9)
        for k in range(3):
            de = np.zeros(3)
            de[k] = h
            omega = gtsam.Rot3.Logmap(gtsam.Rot3(euler_to_matrix(e + de) @ euler_to_matrix(e).T))
            np.testing.assert_allclose(omega / h, E[:, k], atol=1e-5)


def test_body_camera_rotation_is_proper():
    np.testing.assert_allclose(R_BODY_CAMERA @ R_BODY_CAMERA.T, np.eye(3))
    assert np.linalg.det(R_BODY_CAMERA) == pytest.approx(1.0)
    # The camera looks along the body's x axis (forward).
    np.testing.assert_allclose(R_BODY_CAMERA @ [0, 0, 1], [1, 0, 0])


def test_d_se3_properties(rng):
    for _ in range(20):
        T = pose3_from_euler(rng.normal(size=3), _random_euler(rng, 1)[0])
        assert d_se3(T, T) == pytest.approx(0.0, abs=1e-9)
        xi = rng.normal(scale=0.1, size=6)
        T2 = gtsam.Pose3.Expmap(xi).compose(T)
        assert d_se3(T2, T) == pytest.approx(np.linalg.norm(xi), rel=1e-9)
        assert d_se3(T2.matrix(), T.matrix()) == pytest.approx(np.linalg.norm(xi), rel=1e-9)


def test_pose3_euler_round_trip(rng):
    for e in _random_euler(rng, 10):
        t = rng.normal(size=3)
        pos, e2 = euler_from_pose3(pose3_from_euler(t, e))
        np.testing.assert_allclose(pos, t, atol=1e-12)
        np.testing.assert_allclose(e2, e, atol=1e-9)
