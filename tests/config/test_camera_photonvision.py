"""Camera files from PhotonVision (its calibration JSON, both the current and the pre-2024 form, and a camera
settings file holding its calibrations), the error that lists the formats read, and the pinhole assumed for a
camera without a file (:meth:`CameraModel.assumed`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.camera.files import FORMATS_READ
from ar_anchor.errors import CameraError

K = [905.25, 0.0, 641.5, 0.0, 903.75, 398.25, 0.0, 0.0, 1.0]
DIST8 = [0.051, -0.083, 0.0012, -0.0007, 0.021, 0.003, -0.002, 0.001]
DIST5 = [0.14, -0.98, -0.018, 0.011, 1.98]


def current_export(dist: list[float] = DIST8, **changes: object) -> dict:
    """A calibration as PhotonVision's calibration page exports it (2024 on: distCoeffs, mrcal fields)."""
    document = {
        "resolution": {"width": 1280.0, "height": 800.0},
        "cameraIntrinsics": {"rows": 3, "cols": 3, "type": 6, "data": K},
        "distCoeffs": {"rows": 1, "cols": len(dist), "type": 6, "data": dist},
        "observations": [
            {
                "locationInObjectSpace": [{"x": 0.0, "y": 0.0, "z": 0.0}, {"x": 0.0254, "y": 0.0, "z": 0.0}],
                "locationInImageSpace": [{"x": 402.1, "y": 300.7}, {"x": 431.9, "y": 301.2}],
                "reprojectionErrors": [{"x": 0.1, "y": -0.05}, {"x": -0.02, "y": 0.08}],
                "optimisedCameraToObject": {
                    "translation": {"x": 0.1, "y": 0.0, "z": 0.6},
                    "rotation": {"quaternion": {"W": 1.0, "X": 0.0, "Y": 0.0, "Z": 0.0}},
                },
                "includeObservationInCalibration": True,
                "snapshotName": "img0.png",
                "snapshotDataLocation": "/opt/photonvision/photonvision_config/imgSaves/img0.png",
            }
        ],
        "calobjectWarp": [0.00046, 0.00097],
        "calobjectSize": {"width": 7.0, "height": 7.0},
        "calobjectSpacing": 0.0254,
        "lensmodel": "LENSMODEL_OPENCV",
    }
    document.update(changes)
    return document


def older_export() -> dict:
    """The pre-2024 form: the distortion under the name cameraExtrinsics, per-view errors, no lens model."""
    return {
        "resolution": {"width": 640.0, "height": 480.0},
        "cameraIntrinsics": {"rows": 3, "cols": 3, "type": 6, "data": [699.4, 0.0, 345.6, 0.0, 677.7, 207.1, 0, 0, 1]},
        "cameraExtrinsics": {"rows": 1, "cols": 5, "type": 6, "data": DIST5},
        "perViewErrors": [0.31, 0.28, 0.35],
        "standardDeviation": 0.04,
        "isFisheye": False,
    }


def write(tmp_path: Path, document: object, name: str = "photon_calibration.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(document, indent=2), encoding="utf-8")
    return path


def test_the_current_export_loads_its_matrix_distortion_and_size(tmp_path):
    camera = CameraModel.from_yaml(write(tmp_path, current_export()))
    assert camera.size == (1280, 800)
    np.testing.assert_array_equal(camera.camera_matrix, np.reshape(K, (3, 3)))
    np.testing.assert_array_equal(camera.dist_coeffs, DIST8)


def test_the_older_export_reads_its_distortion_from_camera_extrinsics(tmp_path):
    camera = CameraModel.from_yaml(write(tmp_path, older_export(), "lifecam640p.json"))
    assert camera.size == (640, 480)
    np.testing.assert_array_equal(camera.camera_matrix, [[699.4, 0, 345.6], [0, 677.7, 207.1], [0, 0, 1]])
    np.testing.assert_array_equal(camera.dist_coeffs, DIST5)


def test_a_camera_settings_file_with_one_calibration_loads_it(tmp_path):
    settings = {"nickname": "front", "FOV": 70.0, "calibrations": [current_export(DIST5)]}
    camera = CameraModel.from_yaml(write(tmp_path, settings, "config.json"))
    np.testing.assert_array_equal(camera.dist_coeffs, DIST5)


def test_the_same_calibration_projects_as_the_opencv_file_it_matches(tmp_path):
    # given the same intrinsics written as PhotonVision JSON and by CameraModel.to_yaml
    photon = CameraModel.from_yaml(write(tmp_path, current_export()))
    photon.to_yaml(tmp_path / "camera.yml")
    opencv = CameraModel.from_yaml(tmp_path / "camera.yml")
    # then a point off-axis lands on the same pixel through both
    points = np.array([[0.2, -0.1, 0.8], [-0.3, 0.2, 1.5]])
    np.testing.assert_allclose(photon.project(points), opencv.project(points), atol=1e-9)


PHOTON_ERRORS = [
    pytest.param(
        current_export(lensmodel="LENSMODEL_STERIOGRAPHIC"),
        r"lensmodel 'LENSMODEL_STERIOGRAPHIC' is not",
        id="mrcal-lens",
    ),
    pytest.param({**older_export(), "isFisheye": True}, r"fisheye calibration", id="fisheye"),
    pytest.param(current_export(resolution=None), r"missing 'resolution'", id="no-resolution"),
    pytest.param(
        current_export(resolution={"width": 1280.5, "height": 800}),
        r"'resolution' width must be a positive integer",
        id="odd-width",
    ),
    pytest.param(
        current_export(distCoeffs={"rows": 1, "cols": 5, "type": 6, "data": [0.1, 0.2]}),
        r"'distCoeffs' is 1x5 but has 2 values",
        id="short-distortion",
    ),
    pytest.param(
        current_export(cameraIntrinsics={"rows": 3, "cols": 3, "type": 6, "data": ["905"] * 9}),
        r"'cameraIntrinsics' data must hold finite numbers only",
        id="text-in-matrix",
    ),
    pytest.param(
        {"calibrations": [current_export(), current_export(resolution={"width": 640.0, "height": 480.0})]},
        r"holds 2 calibrations \(1280x800, 640x480\): export the one",
        id="two-calibrations",
    ),
    pytest.param({"calibrations": []}, r"holds no calibration", id="no-calibration"),
]


@pytest.mark.parametrize(("document", "pattern"), PHOTON_ERRORS)
def test_a_bad_photonvision_file_is_one_line_naming_file_and_field(tmp_path, document, pattern):
    path = write(tmp_path, document)
    with pytest.raises(CameraError, match=pattern) as info:
        CameraModel.from_yaml(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "PhotonVision" in message


@pytest.mark.parametrize(
    ("name", "text"),
    [
        pytest.param("other.json", '{"fx": 900, "fy": 900}', id="json-of-another-tool"),
        pytest.param("other.yml", "%YAML:1.0\n---\nfx: 900\n", id="yaml-without-camera-matrix"),
    ],
)
def test_an_unknown_format_lists_the_formats_read(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(CameraError, match="missing 'camera_matrix'") as info:
        CameraModel.from_yaml(path)
    for fmt in ("OpenCV FileStorage", "ROS camera_info", "PhotonVision calibration JSON"):
        assert fmt in str(info.value) and fmt in FORMATS_READ


def test_opencv_filestorage_json_is_still_read_by_filestorage(tmp_path):
    # given OpenCV's own JSON (FileStorage writes it for a .json name)
    CameraModel.from_fov(640, 480, 500.0).to_yaml(tmp_path / "camera.json")
    camera = CameraModel.from_yaml(tmp_path / "camera.json")
    assert camera.size == (640, 480) and camera.camera_matrix[0, 0] == 500.0


# ---------------------------------------------------------------------------- a camera without a file


def test_the_assumed_camera_from_a_field_of_view():
    camera = CameraModel.assumed(1920, 1080, hfov_deg=70.0)
    f = 960.0 / math.tan(math.radians(35.0))
    np.testing.assert_allclose(camera.camera_matrix, [[f, 0, 959.5], [0, f, 539.5], [0, 0, 1]])
    assert camera.size == (1920, 1080) and not camera.has_distortion
    # the image's edges (pixel edges at -0.5 and width - 0.5) are 35 deg off-axis
    edge = np.array([[math.tan(math.radians(35.0)), 0.0, 1.0]])
    np.testing.assert_allclose(camera.project(edge), [[1919.5, 539.5]])


def test_the_assumed_camera_from_a_focal_length():
    camera = CameraModel.assumed(640, 480, focal_px=525.0)
    np.testing.assert_array_equal(camera.camera_matrix, [[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="exactly one"):
        CameraModel.assumed(640, 480, focal_px=525.0, hfov_deg=60.0)
