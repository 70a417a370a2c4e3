"""Detection and pose on real photos taken by other projects (skips when ../shared/realdata is absent)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import DetectorConfig
from ar_anchor.track.detection import Detector
from ar_anchor.track.pose import MarkerPose, solve_marker

pytestmark = pytest.mark.realdata


def test_single_markers_photo_matches_opencv_reference_corners(realdata):
    image = cv2.imread(str(realdata / "opencv_contrib" / "singlemarkersoriginal.jpg"))
    detections = Detector(DetectorConfig(dictionary="DICT_6X6_250")).detect(image)
    assert sorted(detections.ids.tolist()) == [23, 40, 62, 98, 124, 203]
    expected = {
        40: [(359, 310), (404, 310), (410, 350), (362, 350)],
        23: [(298, 185), (334, 186), (335, 212), (297, 211)],
    }
    for marker_id, corners in expected.items():
        found = detections.corners[detections.ids.tolist().index(marker_id)]
        np.testing.assert_allclose(found, corners, atol=1.0)


def _corner_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-corner distances after the best cyclic shift (libraries differ in their first corner)."""
    shifts = [np.linalg.norm(np.roll(a, k, axis=0) - b, axis=1) for k in range(4)]
    return min(shifts, key=lambda d: float(d.max()))


def test_aruco_library_board_photo_markers_and_poses(realdata):
    folder = realdata / "aruco_testdata" / "board"
    image = cv2.imread(str(folder / "image-test.png"))
    camera = CameraModel.from_yaml(folder / "intrinsics.yml")
    # given the configured dictionary only (other dictionaries give false positives on this photo)
    detections = Detector(DetectorConfig(dictionary="DICT_ARUCO_ORIGINAL")).detect(image)
    assert len(detections) == 24
    storage = cv2.FileStorage(str(folder / "expected.yml"), cv2.FILE_STORAGE_READ)
    markers = storage.getNode("Board").getNode("Markers")
    reference = {}
    for i in range(markers.size()):
        node = markers.at(i)
        corners_node = node.getNode("corners")
        reference[int(node.getNode("id").real())] = np.array(
            [[corners_node.at(k).at(j).real() for j in range(2)] for k in range(4)]
        )
    storage.release()
    assert set(reference) <= set(detections.ids.tolist())
    # the reference is the ArUco library's own detector, not ground truth: agree to about a pixel
    distances = np.concatenate(
        [
            _corner_distances(corners, reference[marker_id])
            for marker_id, corners in zip(detections.ids.tolist(), detections.corners)
            if marker_id in reference
        ]
    )
    assert np.median(distances) < 1.0
    assert np.mean(distances < 1.5) >= 0.85
    for marker_id, corners in zip(detections.ids.tolist(), detections.corners):
        # every marker of the printed board gets a valid pose through the lens's distortion model
        solved = solve_marker(marker_id, corners, 0.039, camera, max_reproj_px=3.0)
        assert isinstance(solved, MarkerPose), (marker_id, solved)
        assert solved.best.reproj_px < 1.0
        assert 0.2 < solved.best.pose.tvec[2] < 1.0  # the board is about 0.44 m away


def test_wrong_dictionary_finds_nothing_real(realdata):
    image = cv2.imread(str(realdata / "opencv_contrib" / "singlemarkersoriginal.jpg"))
    detections = Detector(DetectorConfig(dictionary="DICT_4X4_50")).detect(image)
    assert len(detections) <= 1  # a 6x6 print is not a 4x4 marker
