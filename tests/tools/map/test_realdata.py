"""The map of the real chessboard video (an 18-marker sheet moved by hand in front of a webcam) against the
ArUco library's own map of that sheet (skips when ../shared/realdata is absent)."""

from __future__ import annotations

import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.tools.map import aligned_errors, build_map, observe_sources, rms_m

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def chessboard_map(realdata):
    folder = realdata / "aruco_testdata" / "chessboard"
    camera = CameraModel.from_yaml(folder / "intrinsics.yml")
    observed = observe_sources([str(folder / "chessboard.avi")], camera, "DICT_ARUCO_ORIGINAL", 0.034)
    truth = {marker_id: np.array(corners) for marker_id, corners in read_layout(folder / "chessboardinfo_meters.yml")}
    return observed, build_map(observed.frames, observed.cameras, 0.034), truth


def test_chessboard_video_map_agrees_with_the_aruco_library(realdata):
    # given the video's frames, searched for the sheet's DICT_ARUCO_ORIGINAL markers of 34 mm
    observed, solution, truth = chessboard_map(realdata)
    # then all 18 markers are mapped and reproject the video's corners to half a pixel (median)
    assert solution.map.ids == sorted(truth)
    assert float(np.median(solution.corner_errors_px)) <= 0.5
    # and after a similarity alignment the map is within 3 mm RMS of the library's layout
    alignment, residuals = aligned_errors(solution.map.all_corners(), truth)
    assert 1000.0 * rms_m(residuals) <= 3.0
    assert alignment.scale == pytest.approx(1.0, abs=0.03)
