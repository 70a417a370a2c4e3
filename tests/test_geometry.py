"""Rigid-body helpers: rvec round trips, inverse, camera centre C = -R^T t."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ar_anchor.geometry import (
    Pose,
    angle_between_deg,
    look_at,
    marker_corners_in_marker,
    matrix_from_rvec,
    rvec_from_matrix,
)

finite = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)
# rotation vectors with angle in [1e-4, pi - 1e-3] (the canonical range Rodrigues returns; below ~1e-5 rad
# cv2.Rodrigues rounds the angle to zero)
axes = st.tuples(finite, finite, finite).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)
rvecs = st.tuples(axes, st.floats(1e-4, math.pi - 1e-3)).map(lambda a: a[0] / np.linalg.norm(a[0]) * a[1])
tvecs = st.tuples(finite, finite, finite).map(np.array)


@settings(max_examples=200, deadline=None)
@given(rvecs)
def test_rvec_matrix_round_trip(rvec):
    rotation = matrix_from_rvec(rvec)
    # given a rotation, then it is orthonormal with det +1 and comes back as the same rvec
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(rvec_from_matrix(rotation), rvec, atol=1e-8)


@settings(max_examples=200, deadline=None)
@given(rvecs, tvecs)
def test_camera_centre_is_minus_rt_t_and_maps_to_camera_origin(rvec, tvec):
    camera_from_target = Pose(rvec, tvec)
    centre = camera_from_target.camera_centre()
    np.testing.assert_allclose(centre, -matrix_from_rvec(rvec).T @ tvec, atol=1e-9)
    # the camera centre expressed in the camera frame is the origin
    np.testing.assert_allclose(camera_from_target.apply(centre[None])[0], np.zeros(3), atol=1e-8)
    # and it is the translation of the inverse transform (target_from_camera)
    np.testing.assert_allclose(camera_from_target.inverse().tvec, centre, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(rvecs, tvecs, rvecs, tvecs)
def test_compose_and_inverse(r1, t1, r2, t2):
    a, b = Pose(r1, t1), Pose(r2, t2)
    points = np.array([[0.1, -0.2, 0.3], [1.0, 2.0, -3.0]])
    np.testing.assert_allclose(a.compose(b).apply(points), a.apply(b.apply(points)), atol=1e-8)
    np.testing.assert_allclose(a.compose(a.inverse()).as_homogeneous(), np.eye(4), atol=1e-9)


def test_angle_between():
    r = matrix_from_rvec(np.array([0.0, 0.0, math.radians(30)]))
    assert angle_between_deg(np.eye(3), r) == pytest.approx(30.0)
    assert angle_between_deg(r, r) == pytest.approx(0.0, abs=1e-6)


def test_look_at_puts_target_on_the_optical_axis_with_world_up_up_in_the_image():
    camera_from_world = look_at(eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(camera_from_world.apply(np.zeros((1, 3)))[0], [0.0, 0.0, 1.0], atol=1e-12)
    # world +y (up) maps to camera -y (image up); world +x stays to the right
    up = camera_from_world.apply(np.array([[0.0, 0.1, 0.0]]))[0]
    right = camera_from_world.apply(np.array([[0.1, 0.0, 0.0]]))[0]
    assert up[1] < 0 and right[0] > 0


def test_marker_corner_order_is_ippe_square_order():
    h = 0.025
    np.testing.assert_array_equal(marker_corners_in_marker(0.05), [[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])


def test_pose_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="rvec: expected 3 values"):
        Pose(np.zeros(2), np.zeros(3))
