"""The synthetic renderer is our measuring instrument: it must be exact, unbiased and deterministic."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ar_anchor.config import BoardConfig, DetectorConfig, demo_config
from ar_anchor.geometry import Pose, look_at, marker_corners_in_marker
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory, board_marker_poses, demo_scene
from ar_anchor.track.detection import Detector
from tests.helpers import LENGTH, random_view


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
    scene = demo_scene(demo_config(), camera, frames=10, seed=5, noise_sigma=3.0)
    first = SyntheticSource(scene).frame(7)
    again = SyntheticSource(scene).frame(7)
    np.testing.assert_array_equal(first.image, again.image)
    other = SyntheticSource(demo_scene(demo_config(), camera, frames=10, seed=6, noise_sigma=3.0)).frame(7)
    assert not np.array_equal(first.image, other.image)


def test_frames_carry_index_timestamp_and_truth_for_every_target(camera):
    scene = demo_scene(demo_config(), camera, frames=4)
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


def test_a_cameras_undistortion_maps_are_made_once_and_cannot_be_written():
    from ar_anchor.camera import CameraModel
    from ar_anchor.synthetic import pinhole_canvas

    def camera(k1: float) -> CameraModel:
        return CameraModel(
            np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.array([k1, 0, 0, 0, 0]), 640, 480
        )

    # given the same distorted camera twice (two objects), and another
    pinhole, maps = pinhole_canvas(camera(0.1))
    again_pinhole, again = pinhole_canvas(camera(0.1))
    _, other = pinhole_canvas(camera(-0.15))
    # then the maps are computed once (the same arrays), read-only, and another lens has its own
    assert again[0] is maps[0] and again[1] is maps[1] and again_pinhole is pinhole
    assert not maps[0].flags.writeable and not maps[1].flags.writeable
    with pytest.raises(ValueError):
        maps[0][0, 0] = 0.0
    assert not np.array_equal(other[0], maps[0])
    # and the maps send each output pixel to where the pinhole canvas sees the lens's ray
    u, v = 600.0, 40.0
    x, y = (maps[0][int(v), int(u)], maps[1][int(v), int(u)])
    ray = cv2.undistortPoints(np.array([[[u, v]]]), camera(0.1).camera_matrix, camera(0.1).dist_coeffs).reshape(2)
    k = pinhole.camera_matrix
    assert (x, y) == pytest.approx((k[0, 0] * ray[0] + k[0, 2], k[1, 1] * ray[1] + k[1, 2]), abs=1e-3)


# ---------------------------------------------------------------------------- hand-held webcam realism

from ar_anchor.geometry import angle_between_deg  # noqa: E402
from ar_anchor.synthetic import Lighting, Occluder, marker_sheet, webcam_camera  # noqa: E402


def angular_speeds(trajectory: Trajectory, seconds: float, dt: float = 0.001) -> tuple[np.ndarray, list[Pose]]:
    poses = [trajectory.at_time(t) for t in np.arange(0.0, seconds, dt)]
    steps = np.array([angle_between_deg(a.rotation, b.rotation) for a, b in zip(poses, poses[1:])])
    return steps / dt, poses


@pytest.mark.slow
def test_handheld_trajectory_is_smooth_and_turns_at_the_requested_peak_speed():
    # given a hand-held path with quick turns up to 150 deg/s, one every 1.5 s
    trajectory = Trajectory(kind="handheld", near_m=0.4, far_m=0.9, turn_peak_deg_s=150.0, turn_every_s=1.5, seed=3)
    speeds, poses = angular_speeds(trajectory, 6.0)
    # then the turns reach the requested peak and nothing goes much faster (sway and tremor add a little)
    assert 150.0 <= speeds.max() <= 150.0 * 1.25
    assert np.sum(speeds > 100.0) > 50  # several bursts, not one sample
    # and the path is smooth: no jump in angle or position between 1 ms samples, speed changes gradually
    # (raised-cosine bursts: at most 2 pi peak / duration ~ 6000 deg/s^2 for the shortest turn)
    assert np.abs(np.diff(speeds)).max() < 10.0  # deg/s per ms
    centres = np.array([p.camera_centre() for p in poses])
    assert np.linalg.norm(np.diff(centres, axis=0), axis=1).max() < 1e-3
    # and the camera stays between near and far, in front of the targets, looking roughly at them
    distances = np.linalg.norm(centres, axis=1)
    assert distances.min() >= 0.4 - 1e-9 and distances.max() <= 0.9 + 1e-9
    assert distances.max() - distances.min() > 0.15  # it approaches and retreats
    origin = np.array([p.apply(np.zeros((1, 3)))[0] for p in poses])
    assert np.all(origin[:, 2] > 0.3)
    off_axis = np.degrees(np.arctan2(np.linalg.norm(origin[:, :2], axis=1), origin[:, 2]))
    assert np.median(off_axis) < 5.0 and off_axis.max() < 25.0


def test_handheld_without_turns_sways_slowly_and_trembles_fast():
    trajectory = Trajectory(kind="handheld", near_m=0.5, far_m=0.5, turn_peak_deg_s=0.0, tremor_deg=0.0, seed=1)
    calm, _ = angular_speeds(trajectory, 5.0, dt=0.005)
    shaky = Trajectory(kind="handheld", near_m=0.5, far_m=0.5, turn_peak_deg_s=0.0, tremor_deg=0.3, seed=1)
    tremor, _ = angular_speeds(shaky, 5.0, dt=0.005)
    # sway alone (0.1-0.5 Hz, 35 deg azimuth at most) stays far below the quick turns' speeds
    assert calm.max() < 80.0
    # tremor (5-10 Hz, 0.3 deg) adds at most 2 pi 10 Hz 0.3 deg ~ 19 deg/s per axis
    assert 3.0 < np.abs(tremor - calm).max() < 35.0


def test_handheld_motion_is_a_function_of_time_not_of_the_frame_rate():
    markers, _ = marker_sheet((0, 1))
    trajectory = Trajectory(kind="handheld", near_m=0.5, far_m=0.8, seed=2)
    camera = webcam_camera(160, 120)
    slow = SyntheticSource(SyntheticScene(camera=camera, markers=markers, trajectory=trajectory, fps=15))
    fast = SyntheticSource(SyntheticScene(camera=camera, markers=markers, trajectory=trajectory, fps=60))
    for k in (0, 7, 40):
        a, b = slow.camera_from_world(k), fast.camera_from_world(4 * k)
        np.testing.assert_allclose(a.as_homogeneous(), b.as_homogeneous(), atol=1e-12)


def edge_width_px(image: np.ndarray) -> float:
    """Width of the steepest ink-paper edge along the image's middle rows: contrast / steepest slope."""
    rows = image[image.shape[0] // 2 - 5 : image.shape[0] // 2 + 5, :, 1].astype(float)
    return float((rows.max() - rows.min()) / np.abs(np.diff(rows, axis=1)).max())


def test_motion_blur_averages_sub_frames_along_the_motion():
    # given a head-on marker and a hand-held camera that turns quickly (200 deg/s at the peak)
    camera = webcam_camera(320, 240)
    trajectory = Trajectory(kind="handheld", near_m=0.4, far_m=0.4, azimuth_deg=0.0, elevation_deg=0.0,
                            roll_deg=0.0, tremor_deg=0.0, turn_peak_deg_s=200.0, turn_deg=6.0, turn_every_s=1.0,
                            aim_m=0.0, seed=2)  # fmt: skip
    speeds, _ = angular_speeds(trajectory, 1.0, dt=0.01)
    fastest = int(np.argmax(speeds))  # a frame index at 100 fps
    base = dict(camera=camera, markers=(PlacedMarker(0, 0.08, Pose.identity()),), trajectory=trajectory, frames=100,
                fps=100.0, clutter=False)  # fmt: skip
    sharp = SyntheticSource(SyntheticScene(**base))
    blurred = SyntheticSource(SyntheticScene(**base, exposure_s=0.03))
    # when the frame at full speed is rendered with and without an exposure
    t = blurred.scene.content_time(fastest)
    nodes, weights = blurred.exposure_samples(t)
    # then several sub-frames (capped) spanning the exposure are averaged, weights summing to 1 on every row
    assert 3 <= len(nodes) <= blurred.scene.max_subframes
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert nodes[0] == pytest.approx(t - 0.015) and nodes[-1] == pytest.approx(t + 0.015)
    # and the marker's edges are wider (smeared along the motion)
    sharp_image, blurred_image = sharp.frame(fastest).image, blurred.frame(fastest).image
    assert edge_width_px(blurred_image) > 2 * edge_width_px(sharp_image), (edge_width_px(sharp_image),
                                                                          edge_width_px(blurred_image))  # fmt: skip
    assert np.abs(blurred_image.astype(float) - sharp_image).mean() > 1.0
    # while a camera at rest needs a single render
    assert len(blurred.exposure_samples(0.0)[0]) == 1


def test_rolling_shutter_sees_lower_rows_later():
    camera = webcam_camera(160, 120)
    trajectory = Trajectory(kind="handheld", near_m=0.4, far_m=0.4, turn_peak_deg_s=200.0, turn_every_s=0.5, seed=1)
    scene = SyntheticScene(camera=camera, markers=(PlacedMarker(0, 0.08, Pose.identity()),), trajectory=trajectory,
                           frames=10, rolling_shutter_s=0.03)  # fmt: skip
    nodes, weights = SyntheticSource(scene).exposure_samples(0.25)
    times = weights @ nodes  # each row's mean time
    assert times[0] == pytest.approx(0.25, abs=1e-9)
    assert times[-1] == pytest.approx(0.25 + 0.03 * 119 / 120, abs=1e-9)
    assert np.all(np.diff(times) >= -1e-12)


def test_duplicated_frames_repeat_pixels_and_truth_with_new_timestamps():
    # given a 30 fps container whose content is 10 fps, with sensor noise
    markers, sheet = marker_sheet((0, 1, 2), cols=3)
    trajectory = Trajectory(kind="handheld", near_m=0.4, far_m=0.6, seed=4)
    scene = SyntheticScene(camera=webcam_camera(160, 120), markers=markers, sheets=(sheet,), trajectory=trajectory,
                           frames=7, fps=30.0, content_fps=10.0, noise_sigma=3.0)  # fmt: skip
    frames = list(SyntheticSource(scene))
    assert len(frames) == 7 and [f.index for f in frames] == list(range(7))
    # then frames 0-2 (and 3-5) are one rendered frame, repeated with their own timestamps
    assert [f.timestamp_ns for f in frames] == [round(i * 1e9 / 30) for i in range(7)]
    for group in ((0, 1, 2), (3, 4, 5)):
        for i in group[1:]:
            np.testing.assert_array_equal(frames[i].image, frames[group[0]].image)
            assert frames[i].truth.keys() == frames[group[0]].truth.keys()
            for name in frames[i].truth:
                np.testing.assert_array_equal(frames[i].truth[name].rvec, frames[group[0]].truth[name].rvec)
    assert not np.array_equal(frames[2].image, frames[3].image)
    # and the content frame is the one taken at its own time (1/10 s steps)
    source = SyntheticSource(scene)
    np.testing.assert_allclose(source.camera_from_world(4).rvec, trajectory.at_time(0.1).rvec)


@pytest.mark.parametrize("compression", ["jpeg", "h264"])
def test_compression_round_trip_keeps_size_count_and_order(compression):
    markers, _ = marker_sheet((0, 1))
    trajectory = Trajectory(kind="handheld", near_m=0.4, far_m=0.6, seed=5)
    base = dict(camera=webcam_camera(320, 240), markers=markers, trajectory=trajectory, frames=12, noise_sigma=2.0)
    plain = list(SyntheticSource(SyntheticScene(**base)))
    scene = SyntheticScene(**base, compression=compression, jpeg_quality=60, h264_kbps=300.0)
    source = SyntheticSource(scene)
    coded = list(source)
    assert len(coded) == 12 and [f.index for f in coded] == list(range(12))
    for a, b in zip(plain, coded):
        assert b.image.shape == (240, 320, 3) and b.image.dtype == np.uint8
        difference = np.abs(a.image.astype(float) - b.image).mean()
        assert 0.1 < difference < 8.0  # compressed, and still the same picture (order kept)
        assert a.truth.keys() == b.truth.keys()
    # random access gives the same frame as the stream (H.264: the codec replays from frame 0)
    np.testing.assert_array_equal(SyntheticSource(scene).frame(5).image, coded[5].image)


def test_marker_sheet_truth_is_one_rigid_sheet():
    # given six 5 cm markers, 2 cm apart, on a sheet turned and moved in the world
    world_from_sheet = Pose(np.array([0.1, -0.2, 0.3]), np.array([0.02, -0.01, 0.0]))
    markers, sheet = marker_sheet(range(6), length_m=0.05, cols=3, gap_m=0.02, world_from_sheet=world_from_sheet)
    assert [m.marker_id for m in markers] == list(range(6)) and sheet.width_m == pytest.approx(0.19 + 0.05)
    # then the layout holds in the sheet frame: rows of three, 7 cm steps, ids row-major from the top left
    sheet_from_world = world_from_sheet.inverse()
    centres = np.array([sheet_from_world.compose(m.world_from_target).tvec for m in markers])
    np.testing.assert_allclose(centres[:, 0], [-0.07, 0, 0.07] * 2, atol=1e-12)
    np.testing.assert_allclose(centres[:, 1], [0.035] * 3 + [-0.035] * 3, atol=1e-12)
    # and every frame's truth is rigid: the markers share one rotation and keep their spacing
    static = Trajectory(kind="static", near_m=0.5, azimuth_deg=15.0, look_at=(0.02, -0.01, 0))
    scene = SyntheticScene(camera=webcam_camera(640, 480), markers=markers, frames=1, trajectory=static)
    frame = SyntheticSource(scene).frame(0)
    truth = [frame.truth[m.target] for m in markers]
    for pose in truth[1:]:
        assert angle_between_deg(pose.rotation, truth[0].rotation) < 1e-9
    assert np.linalg.norm(truth[1].tvec - truth[0].tvec) == pytest.approx(0.07)
    assert np.linalg.norm(truth[3].tvec - truth[0].tvec) == pytest.approx(0.07)
    # and the rendered sheet is detected where the truth says
    detections = Detector(DetectorConfig()).detect(frame.image)
    assert sorted(detections.ids.tolist()) == list(range(6))
    for marker_id, corners in zip(detections.ids, detections.corners):
        expected = scene.camera.project(truth[int(marker_id)].apply(marker_corners_in_marker(0.05)))
        np.testing.assert_allclose(corners, expected, atol=0.5)


def test_occluder_and_lighting_change_pixels_only_where_and_when_asked():
    markers, _ = marker_sheet((0, 1, 2), cols=3)
    trajectory = Trajectory(kind="static", near_m=0.5, azimuth_deg=0.0, elevation_deg=0.0, roll_deg=0.0)
    base = dict(camera=webcam_camera(320, 240), markers=markers, trajectory=trajectory, frames=6)
    plain = SyntheticSource(SyntheticScene(**base))
    hand = Occluder(2, 4, from_xy=(0.5, 0.5), to_xy=(0.5, 0.5), size=0.5)
    lighting = Lighting(gain_drift=0.0, offset_drift=0.0, steps=((3.5 / 30, 0.5),))
    scene = SyntheticScene(**base, occluders=(hand,), lighting=lighting)
    source = SyntheticSource(scene)
    images = [source.frame(i).image.astype(float) for i in range(6)]
    reference = plain.frame(0).image.astype(float)
    assert np.abs(images[0] - reference).max() <= 1  # before the hand and the step: the same image
    centre = images[2][100:140, 140:180]
    assert np.allclose(centre.mean(axis=(0, 1)), np.array(_skin()) * np.linspace(1.08, 0.85, 240)[120], atol=12)
    assert source.frame(2).truth.keys() == plain.frame(2).truth.keys()  # occluded targets keep their truth
    assert np.abs(images[1] - reference).max() <= 1  # the hand is gone... not yet there at frame 1
    assert images[4].mean() == pytest.approx(0.5 * reference.mean(), rel=0.03)  # after the step: half as bright


def _skin() -> tuple[float, float, float]:
    from ar_anchor.synthetic import SKIN_BGR

    return SKIN_BGR


def test_webcam_camera_and_handheld_defaults_validate():
    camera = webcam_camera(1280, 720, hfov_deg=60.0, k1=-0.1)
    assert camera.size == (1280, 720) and camera.has_distortion
    assert camera.camera_matrix[0, 0] == pytest.approx(640 / math.tan(math.radians(30)))
    with pytest.raises(ValueError):
        SyntheticScene(camera=camera, compression="png")
    with pytest.raises(ValueError):
        SyntheticScene(camera=camera, fps=30, content_fps=60)
    with pytest.raises(ValueError):
        Trajectory(kind="handheld", near_m=1.0, far_m=0.5)
