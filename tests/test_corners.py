"""Corners fitted to the markers' edges (ar_anchor.corners) and the distorted synthetic camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import DetectorConfig
from ar_anchor.corners import refine_corners_by_edges
from ar_anchor.detection import Detector
from ar_anchor.geometry import Pose, look_at, marker_corners_in_marker
from ar_anchor.layouts import read_layout
from ar_anchor.sources.synthetic import PlacedMarker, SyntheticScene, SyntheticSource, Trajectory

CELLS = 6  # DICT_4X4_50: 4 bits + the border on each side


def far_marker_frames(distance_m: float, frames: int = 8):
    """A 4 cm marker seen by a 1080p camera (fx 1480) from ``distance_m``, 15 deg off-axis, with noise and blur."""
    camera = CameraModel.from_fov(1920, 1080, 1480.0)
    scene = SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(0, 0.04, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=distance_m, azimuth_deg=15.0, elevation_deg=5.0, roll_deg=0.0),
        frames=frames,
        seed=3,
        noise_sigma=2.0,
        blur_sigma=0.6,
    )
    return camera, list(SyntheticSource(scene))


def corner_errors(refinement: str, camera: CameraModel, frames) -> np.ndarray:
    detector = Detector(DetectorConfig(corner_refinement=refinement, min_perimeter_rate=0.02))
    errors = []
    for frame in frames:
        detections = detector.detect(frame.image, camera)
        assert detections.ids.tolist() == [0]
        truth = camera.project(frame.truth["marker:0"].apply(marker_corners_in_marker(0.04)))
        errors.append(detections.corners[0] - truth)
    return np.concatenate(errors)


@pytest.mark.parametrize("distance_m", [1.5, 3.0])
def test_edge_corners_beat_opencv_subpix_on_far_markers(distance_m):
    # given a far 4 cm marker (about 40 and 20 px wide), rendered with noise and blur
    camera, frames = far_marker_frames(distance_m)
    # when its corners are refined from the edges and by OpenCV's cornerSubPix
    edges = corner_errors("edges", camera, frames)
    subpix = corner_errors("subpix", camera, frames)
    rms_edges, rms_subpix = np.sqrt((edges**2).mean()), np.sqrt((subpix**2).mean())
    # then the edge fit is a tenth of a pixel or better, and well below cornerSubPix's error
    assert rms_edges < 0.12, rms_edges
    assert rms_edges < 0.5 * rms_subpix, (rms_edges, rms_subpix)
    assert np.all(np.abs(edges.mean(axis=0)) < 0.08)  # no systematic shift


def distorted_camera() -> CameraModel:
    k = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
    return CameraModel(k, np.array([-0.32, 0.12, 0.0005, -0.0004, 0.0]), 640, 480)


def corner_view(camera: CameraModel) -> tuple[SyntheticSource, Pose]:
    """A 20 cm marker placed in the image's top-left corner region, where barrel distortion bends its sides."""
    scene = SyntheticScene(camera=camera, markers=(PlacedMarker(5, 0.2, Pose.identity()),), frames=1, seed=1)
    # the camera looks at a point right of and below the marker, so the marker lands top-left
    camera_from_world = look_at((0.22, -0.16, 0.6), (0.22, -0.16, 0.0))
    return SyntheticSource(scene), camera_from_world


def test_distorted_rendering_follows_project_points():
    # given a camera with strong barrel distortion and a marker near the image's corner
    camera = distorted_camera()
    source, camera_from_world = corner_view(camera)
    image = source.render_view(camera_from_world)
    truth = camera.project(camera_from_world.apply(marker_corners_in_marker(0.2)))
    assert truth[:, 0].min() < 100 and truth[:, 1].min() < 60  # really in the distorted corner
    # when it is detected with edge corners that know the lens
    detections = Detector(DetectorConfig()).detect(image, camera)
    assert detections.ids.tolist() == [5]
    error = np.linalg.norm(detections.corners[0] - truth, axis=1)
    # then the corners land where projectPoints puts them (the renderer bends the sides correctly)
    assert error.max() < 0.1, error
    # and fitting straight lines in the distorted image instead would be visibly worse
    naive = np.linalg.norm(Detector(DetectorConfig()).detect(image).corners[0] - truth, axis=1)
    assert naive.max() > 2 * error.max(), (naive, error)


def test_refinement_keeps_corners_it_cannot_trust():
    # a flat grey image has no edges: the input corners come back unchanged
    grey = np.full((200, 200), 128, np.uint8)
    square = np.array([[[50.0, 50.0], [150.0, 50.0], [150.0, 150.0], [50.0, 150.0]]])
    np.testing.assert_array_equal(refine_corners_by_edges(grey, square, CELLS), square)
    # a marker too small to sample, and non-finite corners, likewise
    tiny = np.array([[[50.0, 50.0], [53.0, 50.0], [53.0, 53.0], [50.0, 53.0]]])
    np.testing.assert_array_equal(refine_corners_by_edges(grey, tiny, CELLS), tiny)
    broken = square.copy()
    broken[0, 2] = np.nan
    out = refine_corners_by_edges(grey, broken, CELLS)
    assert np.isnan(out[0, 2, 0]) and np.array_equal(out[0, :2], broken[0, :2])
    assert refine_corners_by_edges(grey, np.zeros((0, 4, 2)), CELLS).shape == (0, 4, 2)


def test_refinement_moves_a_corner_by_at_most_half_a_cell():
    # given a dark square and its corners given 6 px off (more than half of its 13 px cells)
    grey = np.full((200, 200), 230, np.uint8)
    cv2.rectangle(grey, (60, 60), (139, 139), 20, -1)
    truth = np.array([[59.5, 59.5], [139.5, 59.5], [139.5, 139.5], [59.5, 139.5]])
    near = refine_corners_by_edges(grey, (truth + 0.8)[None], CELLS)[0]
    far = refine_corners_by_edges(grey, (truth + 8.0)[None], CELLS)[0]
    # then small errors are corrected to the square's true corners and large ones are left alone
    assert np.abs(near - truth).max() < 0.05, near - truth
    np.testing.assert_array_equal(far, truth + 8.0)


@pytest.mark.parametrize(
    "folder, image_name, layout_name",
    [
        ("board", "image-test.png", "board_meters.yml"),
        ("chessboard", "chessboard_frame.png", "chessboardinfo_meters.yml"),
    ],
)
def test_edge_corners_fit_a_real_rigid_board_better(realdata, folder, image_name, layout_name):
    # given a real photo of a printed rigid board (no ground truth, but every marker lies on one plane)
    base = realdata / "aruco_testdata" / folder
    image = cv2.imread(str(base / image_name))
    camera = CameraModel.from_yaml(base / "intrinsics.yml")
    layout = {marker_id: np.array(corners) for marker_id, corners in read_layout(base / layout_name)}

    def residual_median(refinement: str) -> float:
        detections = Detector(DetectorConfig(dictionary="DICT_ARUCO_ORIGINAL", corner_refinement=refinement)).detect(
            image, camera
        )
        pairs = [(layout[i], c) for i, c in zip(detections.ids.tolist(), detections.corners) if i in layout]
        assert len(pairs) >= 10
        board = np.concatenate([p[0] for p in pairs])
        pixels = np.concatenate([p[1] for p in pairs])
        k, dist = camera.camera_matrix, camera.dist_coeffs
        _, rvec, tvec = cv2.solvePnP(board, pixels, k, dist, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(board, pixels, k, dist, rvec, tvec)
        projected = cv2.projectPoints(board, rvec, tvec, k, dist)[0].reshape(-1, 2)
        return float(np.median(np.linalg.norm(projected - pixels, axis=1)))

    # then the edge-fitted corners agree with one rigid board pose better than cornerSubPix's
    edges, subpix = residual_median("edges"), residual_median("subpix")
    assert edges < 0.9 * subpix, (edges, subpix)
