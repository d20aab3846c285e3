"""Rigid-transform helpers against numpy's own linear algebra."""

import numpy as np

from monotracker.geometry import (
    apply_transform,
    invert_transform,
    look_at,
    make_transform,
    rotation_about_axis,
    rotation_angle_deg,
)


def test_invert_matches_numpy_inverse():
    rng = np.random.default_rng(0)
    for _ in range(20):
        R = rotation_about_axis(rng.normal(size=3), rng.uniform(-np.pi, np.pi))
        T = make_transform(R, rng.normal(size=3) * 100)
        np.testing.assert_allclose(invert_transform(T), np.linalg.inv(T), atol=1e-9)


def test_rotation_is_orthonormal_with_the_requested_angle():
    R = rotation_about_axis([1.0, 2.0, -0.5], 0.7)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert np.isclose(rotation_angle_deg(np.eye(3), R), np.degrees(0.7))


def test_apply_transform_keeps_shape_and_maps_points():
    T = make_transform(rotation_about_axis([0, 0, 1], np.pi / 2), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(apply_transform(T, np.array([1.0, 0.0, 0.0])), [1.0, 3.0, 3.0])
    assert apply_transform(T, np.zeros((5, 3))).shape == (5, 3)


def test_look_at_points_the_optical_axis_at_the_target():
    eye, target = np.array([100.0, -50.0, 400.0]), np.array([0.0, 10.0, 0.0])
    T_world_cam = look_at(eye, target, up=[0, 0, 1])
    p_cam = apply_transform(invert_transform(T_world_cam), target)
    assert abs(p_cam[0]) < 1e-9 and abs(p_cam[1]) < 1e-9
    assert np.isclose(p_cam[2], np.linalg.norm(target - eye))
