"""Per-marker pose: accuracy against exact ground truth, both IPPE solutions, and garbage never emitted."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ar_anchor.config import DetectorConfig
from ar_anchor.geometry import Pose, angle_between_deg, marker_corners_in_marker, matrix_from_rvec
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene
from ar_anchor.track.detection import Detector
from ar_anchor.track.pose import MarkerPose, PoseFailure, check_pose, reprojection_rms, solve_marker
from tests.helpers import LENGTH, random_view

MAX_REPROJ = 3.0


def test_pose_is_accurate_on_noise_free_frames(camera):
    # given noise-free renders of a marker 60..200 px wide from random directions
    source = SyntheticSource(
        SyntheticScene(
            camera=camera,
            markers=(PlacedMarker(3, LENGTH, Pose.identity()),),
            frames=1,
            noise_sigma=0.0,
            blur_sigma=0.0,
        )
    )
    detector = Detector(DetectorConfig())
    rng = np.random.default_rng(1)
    rotation_errors, translation_errors = [], []
    for _ in range(30):
        camera_from_world = random_view(rng, 0.25, 0.65, tilt_deg=55)
        truth = camera_from_world  # the marker frame is the world frame
        corners = camera.project(truth.apply(marker_corners_in_marker(LENGTH)))
        assert np.linalg.norm(corners[1] - corners[0]) >= 60 or np.linalg.norm(corners[2] - corners[1]) >= 60
        detections = detector.detect(source.render_view(camera_from_world))
        assert detections.ids.tolist() == [3]
        # when the pose is solved
        solved = solve_marker(3, detections.corners[0], LENGTH, camera, MAX_REPROJ)
        assert isinstance(solved, MarkerPose)
        rotation_errors.append(angle_between_deg(solved.best.pose.rotation, truth.rotation))
        translation_errors.append(np.linalg.norm(solved.best.pose.tvec - truth.tvec) / np.linalg.norm(truth.tvec))
    # then median rotation error < 1 degree and translation error < 1 % of the distance
    assert np.median(rotation_errors) < 1.0, rotation_errors
    assert np.median(translation_errors) < 0.01, translation_errors


def test_both_ippe_solutions_are_kept_sorted_with_their_error_ratio(camera):
    # given exact corners of a marker seen obliquely
    facing_camera = np.diag([1.0, -1.0, -1.0])
    truth = Pose.from_matrix(matrix_from_rvec(np.array([0.5, -0.3, 0.1])) @ facing_camera, np.array([0.02, -0.01, 0.6]))
    corners = camera.project(truth.apply(marker_corners_in_marker(LENGTH)))
    solved = solve_marker(5, corners, LENGTH, camera)
    assert isinstance(solved, MarkerPose) and solved.solver == "ippe_square"
    assert len(solved.hypotheses) == 2
    best, other = solved.hypotheses
    assert best.reproj_px <= other.reproj_px
    assert angle_between_deg(best.pose.rotation, truth.rotation) < 1e-4
    np.testing.assert_allclose(best.pose.tvec, truth.tvec, atol=1e-8)
    assert angle_between_deg(other.pose.rotation, truth.rotation) > 5  # the flipped solution
    assert solved.ambiguity == pytest.approx((other.reproj_px + 1e-3) / (best.reproj_px + 1e-3))
    assert solved.ambiguity > 1.0


def test_reprojection_rms_is_per_point_euclidean(camera):
    truth = Pose(np.array([0.1, 0.2, 0.0]), np.array([0.0, 0.0, 0.5]))
    points = marker_corners_in_marker(LENGTH)
    corners = camera.project(truth.apply(points))
    shifted = corners + np.array([3.0, 4.0])  # every corner 5 px off
    assert reprojection_rms(truth, points, shifted, camera) == pytest.approx(5.0)


def test_fronto_parallel_marker_with_integer_corners(camera):
    # given the classic degenerate case: a square exactly facing the camera, integer pixel corners
    corners = np.array([[600.0, 320.0], [680.0, 320.0], [680.0, 400.0], [600.0, 400.0]])
    solved = solve_marker(0, corners, LENGTH, camera, MAX_REPROJ)
    # then the pose is finite, valid, in front, and facing the camera
    assert isinstance(solved, MarkerPose)
    for hypothesis in solved.hypotheses:
        assert hypothesis.pose.is_finite()
        assert np.linalg.norm(hypothesis.pose.rvec) <= math.pi + 1e-9
        assert hypothesis.reproj_px < 0.1
        assert hypothesis.pose.camera_centre()[2] > 0
    assert solved.best.pose.tvec[2] == pytest.approx(1000 * LENGTH / 80, rel=1e-6)


BROKEN = {
    "collinear": [[100, 100], [200, 100], [300, 100], [400, 100]],
    "coincident": [[100, 100], [100, 100], [100, 100], [100, 100]],
    "three coincident": [[100, 100], [100, 100], [100, 100], [200, 200]],
    "bow tie": [[100, 100], [200, 200], [200, 100], [100, 200]],
    "concave": [[100, 100], [200, 100], [120, 120], [100, 200]],
    "nan": [[100, 100], [200, 100], [np.nan, 200], [100, 200]],
    "inf": [[100, 100], [np.inf, 100], [200, 200], [100, 200]],
    "huge": [[-1e12, -1e12], [1e12, -1e12], [1e12, 1e12], [-1e12, 1e12]],
    "tiny": [[100, 100], [100.1, 100], [100.1, 100.1], [100, 100.1]],
    "far outside the image": [[1e5, 1e5], [1e5 + 80, 1e5], [1e5 + 80, 1e5 + 80], [1e5, 1e5 + 80]],
    "mirrored (seen from behind)": [[680, 320], [600, 320], [600, 400], [680, 400]],
    "not a square's projection": [[600, 300], [900, 320], [610, 330], [590, 700]],
}


@pytest.mark.parametrize("name", list(BROKEN))
def test_broken_corner_sets_never_give_garbage(name, camera):
    corners = np.array(BROKEN[name], dtype=float)
    solved = solve_marker(1, corners, LENGTH, camera, MAX_REPROJ)
    assert_valid_or_failure(solved, corners, camera)


def test_wrong_shapes_and_lengths_are_failures_not_exceptions(camera):
    good = np.array([[600.0, 320.0], [680.0, 320.0], [680.0, 400.0], [600.0, 400.0]])
    assert isinstance(solve_marker(1, good[:3], LENGTH, camera), PoseFailure)
    assert isinstance(solve_marker(1, np.zeros(0), LENGTH, camera), PoseFailure)
    assert isinstance(solve_marker(1, good, 0.0, camera), PoseFailure)
    assert isinstance(solve_marker(1, good, float("nan"), camera), PoseFailure)


def assert_valid_or_failure(solved, corners, camera):
    if isinstance(solved, PoseFailure):
        assert solved.reason
        return
    assert isinstance(solved, MarkerPose)
    for hypothesis in solved.hypotheses:
        pose = hypothesis.pose
        assert pose.is_finite()
        assert np.linalg.norm(pose.rvec) <= math.pi + 1e-9
        assert np.all(pose.apply(marker_corners_in_marker(LENGTH))[:, 2] > 0)
        assert hypothesis.reproj_px <= MAX_REPROJ
        # the reported error is the real one
        assert reprojection_rms(pose, marker_corners_in_marker(LENGTH), corners, camera) == pytest.approx(
            hypothesis.reproj_px, rel=1e-6, abs=1e-9
        )


coordinate = st.one_of(
    st.floats(-2000, 3000, allow_nan=False),
    st.sampled_from([0.0, 1e-300, -1e-300, 1e300, -1e300, float("nan"), float("inf"), float("-inf")]),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(coordinate, coordinate), min_size=4, max_size=4))
def test_fuzzed_corner_sets_never_give_garbage(camera, corners):
    corners = np.array(corners, dtype=float)
    assert_valid_or_failure(solve_marker(2, corners, LENGTH, camera, MAX_REPROJ), corners, camera)


@settings(max_examples=200, deadline=None)
@given(st.tuples(*[st.floats(-1.0, 1.0)] * 3), st.floats(0.15, 4.0), st.tuples(*[st.floats(-2.0, 2.0)] * 8))
def test_perturbed_real_projections_stay_valid(camera, rotation, distance, noise):
    # a plausible marker pose, corners jittered by up to 2 px: a valid pose or a clean failure
    facing_camera = np.diag([1.0, -1.0, -1.0])
    truth = Pose.from_matrix(matrix_from_rvec(np.array(rotation) * 0.9) @ facing_camera, np.array([0.0, 0.0, distance]))
    corners = camera.project(truth.apply(marker_corners_in_marker(LENGTH))) + np.array(noise).reshape(4, 2)
    assert_valid_or_failure(solve_marker(4, corners, LENGTH, camera, MAX_REPROJ), corners, camera)


@pytest.mark.parametrize(
    ("pose", "reason"),
    [
        (Pose(np.array([np.nan, 0, 0]), np.array([0, 0, 1.0])), "non-finite"),
        (Pose(np.array([4.0, 0, 0]), np.array([0, 0, 1.0])), "rvec norm"),
        (Pose(np.zeros(3), np.array([0, 0, 5e3])), "implausible"),
        (Pose(np.zeros(3), np.array([0, 0, -1.0])), "behind the camera"),
        (Pose(np.zeros(3), np.array([0, 0, 1.0])), "from behind"),
    ],
)
def test_check_pose_rejects_garbage_with_a_reason(camera, pose, reason):
    points = marker_corners_in_marker(LENGTH)
    corners = np.array([[600.0, 320.0], [680.0, 320.0], [680.0, 400.0], [600.0, 400.0]])
    _error, why = check_pose(pose, points, corners, camera, MAX_REPROJ)
    assert why is not None and reason in why
