"""The synthetic renderer is our measuring instrument: it must be exact, unbiased and deterministic."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ar_anchor.config import BoardConfig, DetectorConfig, TrackerConfig
from ar_anchor.detection import Detector
from ar_anchor.geometry import Pose, look_at, marker_corners_in_marker
from ar_anchor.sources.synthetic import (
    PlacedBoard,
    PlacedMarker,
    SyntheticScene,
    SyntheticSource,
    Trajectory,
    board_marker_poses,
    demo_scene,
)

LENGTH = 0.05


def random_view(rng: np.random.Generator, near: float, far: float, tilt_deg: float = 50.0) -> Pose:
    """camera_from_world looking at the origin from a random direction, with a random roll."""
    distance = rng.uniform(near, far)
    az, el = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2))
    eye = distance * np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    look = np.array([*rng.uniform(-0.03, 0.03, 2), 0.0])
    roll = Pose(np.array([0.0, 0.0, rng.uniform(-math.pi, math.pi)]), np.zeros(3))
    return roll.compose(look_at(eye, look))


def single_marker_source(camera, **kwargs) -> SyntheticSource:
    scene = SyntheticScene(camera=camera, markers=(PlacedMarker(3, LENGTH, Pose.identity()),), frames=1, **kwargs)
    return SyntheticSource(scene)


def test_renderer_is_unbiased_under_the_pixel_centre_convention(camera):
    # given 24 random noise-free views of a marker at least 80 px wide
    source = single_marker_source(camera, noise_sigma=0.0, blur_sigma=0.0)
    detector = Detector(DetectorConfig(corner_refinement="subpix"))
    rng = np.random.default_rng(0)
    errors, sides = [], []
    for _ in range(24):
        camera_from_world = random_view(rng, 0.2, 0.4)
        truth = camera.project(camera_from_world.apply(marker_corners_in_marker(LENGTH)))
        # when it is rendered and detected
        detections = detector.detect(source.render_view(camera_from_world))
        assert detections.ids.tolist() == [3]
        errors.append(detections.corners[0] - truth)
        sides.append(np.linalg.norm(np.roll(truth, -1, axis=0) - truth, axis=1).min())
    errors = np.concatenate(errors)
    # then detected corners agree with the projected ground truth, without bias
    assert min(sides) >= 80.0
    mean = np.abs(errors.mean(axis=0))
    rms = np.sqrt((errors**2).mean(axis=0))
    assert np.all(mean < 0.05), f"corner bias {mean} px"
    assert np.all(rms < 0.3), f"corner RMS {rms} px"


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.0123, 0.0071), (-0.0031, 0.0203)])
def test_renderer_covers_pixels_exactly_along_a_row(camera, offset):
    # given a head-on marker 100 px wide whose edges fall at arbitrary sub-pixel positions
    source = single_marker_source(camera, noise_sigma=0.0, blur_sigma=0.0, clutter=False)
    camera_from_world = Pose(np.array([math.pi, 0.0, 0.0]), np.array([offset[0], offset[1], 0.5]))
    truth = camera.project(camera_from_world.apply(marker_corners_in_marker(LENGTH)))
    x_left, x_right = truth[:, 0].min(), truth[:, 0].max()
    y_mid = truth[:, 1].mean()
    # when a row through the black border (no bits there: the top border cell) is rendered
    row = int(round(truth[:, 1].min() + 100 / 12))
    grey = source.render_view(camera_from_world)[row, :, 1].astype(float)
    paper = grey[int(x_left) - 6]
    ink = grey[int(round((x_left + x_right) / 2))]
    ink_fraction = np.clip((paper - grey) / (paper - ink), 0, 1)
    ink_fraction[: int(x_left) - 4] = 0
    ink_fraction[int(x_right) + 5 :] = 0
    # then the inked length and its centre along the row are exact to a few hundredths of a pixel
    columns = np.arange(grey.size)
    assert ink_fraction.sum() == pytest.approx(x_right - x_left, abs=0.05)
    assert (ink_fraction * columns).sum() / ink_fraction.sum() == pytest.approx((x_left + x_right) / 2, abs=0.02)
    assert y_mid > row


def test_rendering_is_deterministic_for_a_seed(camera):
    scene = demo_scene(TrackerConfig(), camera, frames=10, seed=5, noise_sigma=3.0)
    first = SyntheticSource(scene).frame(7)
    again = SyntheticSource(scene).frame(7)
    np.testing.assert_array_equal(first.image, again.image)
    other = SyntheticSource(demo_scene(TrackerConfig(), camera, frames=10, seed=6, noise_sigma=3.0)).frame(7)
    assert not np.array_equal(first.image, other.image)


def test_frames_carry_index_timestamp_and_truth_for_every_target(camera):
    scene = demo_scene(TrackerConfig(), camera, frames=4)
    with SyntheticSource(scene) as source:
        frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.timestamp_ns for f in frames] == [0, 33_333_333, 66_666_667, 100_000_000]
    assert set(frames[0].truth) == {
        "marker:0",
        "marker:7",
        "board:desk",
        "marker:10",
        "marker:11",
        "marker:12",
        "marker:13",
    }
    assert frames[0].image.shape == (720, 1280, 3) and frames[0].image.dtype == np.uint8


def test_board_truth_follows_opencv_board_frame(camera):
    # given a board placed at the world origin (frame: top-left of marker 0, y down, z into the board)
    board = BoardConfig(name="b", cols=2, rows=2, marker_length_m=0.04, separation_m=0.02, first_id=10)
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    grid = cv2.aruco.GridBoard((2, 2), 0.04, 0.02, dictionary, np.arange(10, 14))
    poses = board_marker_poses(board)
    # then each marker's corners (TL, TR, BR, BL in its own frame) are OpenCV's object points
    for marker_id, object_points in zip(grid.getIds().ravel(), grid.getObjPoints()):
        np.testing.assert_allclose(
            poses[int(marker_id)].apply(marker_corners_in_marker(0.04)), object_points, atol=1e-12
        )
    # and the rendered board is detected where its truth says
    flip = Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    scene = SyntheticScene(camera=camera, boards=(PlacedBoard(board, flip),), frames=1, noise_sigma=0, blur_sigma=0)
    source = SyntheticSource(scene)
    camera_from_world = look_at((0.05, -0.03, 0.4), (0.05, -0.05, 0.0))
    detections = Detector(DetectorConfig()).detect(source.render_view(camera_from_world))
    truth = source.truth(camera_from_world)
    assert sorted(detections.ids.tolist()) == [10, 11, 12, 13]
    for marker_id, corners in zip(detections.ids, detections.corners):
        expected = camera.project(truth[f"marker:{marker_id}"].apply(marker_corners_in_marker(0.04)))
        np.testing.assert_allclose(corners, expected, atol=0.5)


def test_wall_behind_the_camera_is_not_mirrored_into_view(camera):
    # a camera looking along the wall sees sky above the horizon, not a mirrored copy of the wall
    scene = SyntheticScene(camera=camera, frames=1, noise_sigma=0, blur_sigma=0)
    camera_from_world = look_at((0.0, -1.0, 0.3), (0.0, 1.0, 0.3), up=(0.0, 0.0, 1.0))
    image = SyntheticSource(scene).render_view(camera_from_world)
    assert np.all(image[0, 0] == image[0, -1])  # both top corners are sky


@pytest.mark.parametrize("kind", ["sweep", "orbit", "static"])
def test_trajectories_keep_the_scene_in_front_of_the_camera(kind, camera):
    trajectory = Trajectory(kind=kind, near_m=0.4, far_m=2.0)
    for u in np.linspace(0, 1, 11):
        camera_from_world = trajectory.camera_from_world(u)
        assert camera_from_world.apply(np.zeros((1, 3)))[0, 2] > 0.3
    if kind == "sweep":
        near = np.linalg.norm(trajectory.camera_from_world(0.0).camera_centre())
        far = np.linalg.norm(trajectory.camera_from_world(1.0).camera_centre())
        assert near == pytest.approx(0.4) and far == pytest.approx(2.0)


@pytest.mark.parametrize("k1, renders", [(0.1, True), (-0.15, True), (-0.4, False), (-3.0, False)])
def test_distorted_cameras_render_unless_the_model_folds_over(k1, renders):
    from ar_anchor.camera import CameraModel
    from ar_anchor.errors import SourceError

    camera = CameraModel(
        np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.array([k1, 0, 0, 0, 0]), 640, 480
    )
    scene = SyntheticScene(camera=camera, markers=(PlacedMarker(3, LENGTH, Pose.identity()),), frames=1)
    if renders:
        assert SyntheticSource(scene).frame(0).image.shape == (480, 640, 3)
    else:  # r (1 + k1 r^2) peaks below the image corner's radius (0.8): no inverse exists there
        with pytest.raises(SourceError, match="distortion"):
            SyntheticSource(scene)
