"""Corners fitted to the markers' edges (ar_anchor.track.corners) and the distorted synthetic camera."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.config import DetectorConfig
from ar_anchor.geometry import Pose, marker_corners_in_marker
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from ar_anchor.track.corners import FITTED, NOT_TRIED, REJECTED, fit_corners_by_edges, refine_corners_by_edges
from ar_anchor.track.detection import Detector
from tests.helpers import corner_view, distorted_camera

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


@pytest.mark.slow
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
    assert np.all(fit_corners_by_edges(grey, square, CELLS)[1] == REJECTED)
    # a marker too small to sample, and non-finite corners, likewise (not even tried)
    tiny = np.array([[[50.0, 50.0], [53.0, 50.0], [53.0, 53.0], [50.0, 53.0]]])
    np.testing.assert_array_equal(refine_corners_by_edges(grey, tiny, CELLS), tiny)
    assert np.all(fit_corners_by_edges(grey, tiny, CELLS)[1] == NOT_TRIED)
    broken = square.copy()
    broken[0, 2] = np.nan
    out = refine_corners_by_edges(grey, broken, CELLS)
    assert np.isnan(out[0, 2, 0]) and np.array_equal(out[0, :2], broken[0, :2])
    assert refine_corners_by_edges(grey, np.zeros((0, 4, 2)), CELLS).shape == (0, 4, 2)
    assert fit_corners_by_edges(grey, np.zeros((0, 4, 2)), CELLS)[1].shape == (0, 4)


def dark_square(seed: int = 0, extra=None) -> tuple[np.ndarray, np.ndarray]:
    """An 80 px dark square on a light background (true corners returned), ``extra(image, x, y)`` drawn on
    the float image before a slight blur and sensor noise."""
    grey = np.full((200, 200), 230.0, np.float32)
    grey[60:140, 60:140] = 20.0
    if extra is not None:
        y, x = np.mgrid[0:200, 0:200]
        extra(grey, x, y)
    rng = np.random.default_rng(seed)
    grey = cv2.GaussianBlur(grey, (0, 0), 0.8) + rng.normal(0.0, 2.0, grey.shape)
    truth = np.array([[59.5, 59.5], [139.5, 59.5], [139.5, 139.5], [59.5, 139.5]])
    return np.clip(grey, 0, 255).astype(np.uint8), truth


def test_refinement_corrects_corners_and_leaves_those_without_edges_in_reach():
    # given a dark square and its corners given a little off, or 8 px off (no edge within a profile's reach)
    grey, truth = dark_square()
    near, near_status = fit_corners_by_edges(grey, (truth + 0.8)[None], CELLS)
    far, far_status = fit_corners_by_edges(grey, (truth + 8.0)[None], CELLS)
    # then small errors are corrected to the square's true corners and the far ones are left alone
    assert np.all(near_status == FITTED)
    assert np.abs(near[0] - truth).max() < 0.05, near[0] - truth
    assert np.all(far_status == REJECTED)
    np.testing.assert_array_equal(far[0], truth + 8.0)


def _no_edge(grey, x, y):  # the right side merges into a dark area: it has no edge at all
    grey[50:150, 139:] = 20.0


def _wavy_occluder(grey, x, y):  # a dark blob over the right side, its outline wandering 0.5-3.5 px outside
    grey[(x >= 130) & (x < 142.0 + 1.5 * np.sin(y / 3.0)) & (y > 62) & (y < 138)] = 20.0


def _tilted_occluder(grey, x, y):  # a dark band over the right side whose edge crosses it at 25 deg
    band = (x - 139.5 < (y - 100.0) * np.tan(np.radians(25.0)) + 1.0) & (x >= 120) & (y > 40) & (y < 160)
    grey[band] = 20.0


@pytest.mark.parametrize("occlusion", [_no_edge, _wavy_occluder, _tilted_occluder], ids=["no-edge", "wavy", "tilted"])
def test_a_side_that_does_not_fit_a_straight_edge_keeps_its_corners(occlusion):
    # given a dark square whose right side has no edge, or is hidden behind an occluder's irregular or
    # tilted outline, and its corners detected 1.5 px off
    grey, truth = dark_square(extra=occlusion)
    detected = truth + np.random.default_rng(1).uniform(-1.5, 1.5, truth.shape)
    refined, status = fit_corners_by_edges(grey, detected[None], CELLS)
    # then the two corners on the right side are rejected (they keep their detected positions) ...
    assert status[0].tolist() == [FITTED, REJECTED, REJECTED, FITTED]
    np.testing.assert_array_equal(refined[0, 1:3], detected[1:3])
    # ... while the two corners whose sides are clean are fitted exactly
    assert np.abs(refined[0, [0, 3]] - truth[[0, 3]]).max() < 0.05


def touching_markers(seed: int, marker_px: float = 58.0, supersample: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A 3 x 3 chessboard of 4x4 markers on its dark squares (the centre marker touches the four others
    at its corners), about ``marker_px`` per marker, seen slightly rotated and in perspective, with blur and noise.
    Rendered at ``supersample`` times the resolution and averaged down, so the true corners are exact.
    Returns the grey image and the (5, 4, 2) true corners (ids 0..4 in order)."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    side, pad = 60, 60  # board pixels
    size = 3 * side + 2 * pad
    board = np.full((size, size), 255, np.uint8)
    quads = []
    for marker_id, (row, col) in enumerate([(0, 0), (0, 2), (1, 1), (2, 0), (2, 2)]):
        x, y = pad + col * side, pad + row * side
        board[y : y + side, x : x + side] = cv2.aruco.generateImageMarker(dictionary, marker_id, side)
        quads.append(np.array([[x, y], [x + side, y], [x + side, y + side], [x, y + side]], float) - 0.5)
    rng = np.random.default_rng(seed)
    out, angle, scale = 400, np.radians(8.0 + 4.0 * seed), marker_px * supersample / side
    rotate = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    rotate[:2, :2] *= scale
    centre = np.array([[1.0, 0.0, -size / 2], [0.0, 1.0, -size / 2], [0.0, 0.0, 1.0]])
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2e-4 / supersample, 1e-4 / supersample, 1.0]])
    middle = out * supersample / 2
    shift = np.array([[1.0, 0.0, middle + rng.uniform(-5, 5)], [0.0, 1.0, middle], [0.0, 0.0, 1.0]])
    homography = shift @ tilt @ rotate @ centre
    fine = cv2.warpPerspective(board, homography, (out * supersample,) * 2, flags=cv2.INTER_LINEAR, borderValue=255)
    image = cv2.resize(fine, (out, out), interpolation=cv2.INTER_AREA).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 0.7) + rng.normal(0.0, 2.0, image.shape)
    corners = cv2.perspectiveTransform(np.array(quads).reshape(-1, 1, 2), homography).reshape(-1, 4, 2)
    # a fine pixel's centre (i) sits at (i + 0.5) / supersample - 0.5 in the averaged image
    return np.clip(np.round(image), 0, 255).astype(np.uint8), (corners + 0.5) / supersample - 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_corners_where_markers_touch_are_fitted_from_detected_corners_several_pixels_off(seed):
    # given markers touching at their corners (a chessboard-like sheet), their corners given 3-5 px off
    grey, truth = touching_markers(seed)
    rng = np.random.default_rng(seed)
    length, angle = rng.uniform(3.0, 5.0, truth.shape[:2]), rng.uniform(0.0, 2 * np.pi, truth.shape[:2])
    detected = truth + np.stack([length * np.cos(angle), length * np.sin(angle)], axis=-1)
    # when they are refined from their edges
    refined, status = fit_corners_by_edges(grey, detected, CELLS)
    # then every corner is fitted, to within a fifth of a pixel of the truth
    assert np.all(status == FITTED), status
    error = np.linalg.norm(refined - truth, axis=2)
    assert error.max() < 0.2, error


@pytest.mark.parametrize("marker_px, seed", [(36.0, 0), (36.0, 1), (44.0, 0)])
def test_detector_corners_where_markers_touch(marker_px, seed):
    # given such a sheet of smaller markers (cells of 6-7 px), where OpenCV's own corners are pulled more
    # than 3 px off at the shared corners (about half a cell: a limit on the move refused such fits)
    grey, truth = touching_markers(seed, marker_px)
    plain = Detector(DetectorConfig(corner_refinement="none")).detect(grey)
    assert sorted(plain.ids.tolist()) == [0, 1, 2, 3, 4]
    assert np.linalg.norm(plain.corners - truth[plain.ids], axis=2).max() > 3.0
    # then the edge-fitted corners land on the true ones anyway
    detections = Detector(DetectorConfig()).detect(grey)
    assert sorted(detections.ids.tolist()) == [0, 1, 2, 3, 4]
    error = np.linalg.norm(detections.corners - truth[detections.ids], axis=2)
    assert error.max() < 0.2, error


def test_fits_are_kept_on_a_real_chessboard_sheet(realdata):
    # given frames of a real video of markers printed touching at their corners (aruco_testdata chessboard)
    base = realdata / "aruco_testdata" / "chessboard"
    video = base / "chessboard.avi"
    if not video.is_file():
        pytest.skip(f"{video} not found")
    camera = CameraModel.from_yaml(base / "intrinsics.yml")
    detector = Detector(DetectorConfig(dictionary="DICT_ARUCO_ORIGINAL", corner_refinement="none"))
    capture = cv2.VideoCapture(str(video))
    statuses = []
    for index in range(0, 149, 6):
        capture.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, image = capture.read()
        if not ok:
            continue
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        plain = detector.detect(grey)
        if len(plain.ids):
            k, dist = camera.camera_matrix, camera.dist_or_none
            _, status = fit_corners_by_edges(grey, plain.corners, detector.cells, k, dist)
            statuses.append(status.ravel())
    statuses = np.concatenate(statuses)
    assert (statuses != NOT_TRIED).sum() > 500
    # then nearly every corner's fit is kept (a distance limit from OpenCV's corner discarded about 12 %)
    rejected = (statuses == REJECTED).sum() / (statuses != NOT_TRIED).sum()
    assert rejected < 0.02, rejected


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
