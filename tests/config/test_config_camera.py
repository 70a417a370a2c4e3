"""Config (TOML) and camera (OpenCV YAML) parsing: defaults, round trips, one-line errors."""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import (
    BoardConfig,
    ConfigValueError,
    DetectorConfig,
    PoseConfig,
    RecordingConfig,
    TrackerConfig,
    demo_config,
    load_config,
    parse_config,
)
from ar_anchor.errors import CameraError, ConfigError, InputError

REPO = Path(__file__).resolve().parents[2]
DEFAULT_TOML = REPO / "configs" / "default.toml"
SYNTHETIC_YAML = REPO / "configs" / "camera_synthetic.yml"


def assert_same_camera(actual: CameraModel, expected: CameraModel) -> None:
    """Field-wise equality (the dataclass's own == is ambiguous on numpy arrays)."""
    assert actual.size == expected.size
    np.testing.assert_array_equal(actual.camera_matrix, expected.camera_matrix)
    np.testing.assert_array_equal(actual.dist_coeffs, expected.dist_coeffs)


# ============================================================================ config: defaults


def test_default_toml_equals_dataclass_defaults():
    # given the shipped default config file
    # when it is loaded
    loaded = load_config(DEFAULT_TOML)
    # then it is the dataclass defaults in every field except where it came from
    assert loaded.source == str(DEFAULT_TOML)
    assert dataclasses.replace(loaded, source="x") == dataclasses.replace(TrackerConfig(), source="x")
    # (spot-check the parts most likely to drift, so a failure says which): lone markers of one size,
    # no demo board and no per-id sizes leak into a real run
    assert loaded.boards == ()
    assert dict(loaded.markers.lengths_m) == {}
    assert loaded.marker_length(7) == 0.05
    assert loaded.marker_length(12) == 0.05
    assert loaded.board_of(12) is None


def test_demo_toml_equals_demo_defaults():
    # given the shipped demo config file
    loaded = load_config(REPO / "configs" / "demo.toml")
    # then it is what `ar-anchor demo` uses without --config: the defaults plus the desk board and marker 7
    assert dataclasses.replace(loaded, source="x") == dataclasses.replace(demo_config(), source="x")
    assert load_config(None, demo=True) == demo_config()
    assert loaded.boards == (
        BoardConfig(name="desk", cols=2, rows=2, marker_length_m=0.04, separation_m=0.02, first_id=10),
    )
    assert dict(loaded.markers.lengths_m) == {7: 0.04}
    assert loaded.marker_length(7) == 0.04
    assert loaded.marker_length(12) == 0.04  # a desk-board member
    assert loaded.marker_length(3) == 0.05


def test_no_config_path_gives_dataclass_defaults():
    assert load_config(None) == TrackerConfig()


def test_empty_toml_gives_scalar_defaults_and_no_boards_or_per_id_lengths(tmp_path):
    # given an empty config file
    path = tmp_path / "empty.toml"
    path.write_text("")
    # when it is loaded
    config = load_config(path)
    # then every scalar takes its default, but the collections (boards, per-id sizes, lone-marker
    # ids) are empty: omitting [[boards]] means "no boards", not "the example desk board"
    assert config.source == str(path)
    assert config.detector == DetectorConfig()
    assert config.pose == PoseConfig()
    assert config.recording == RecordingConfig()
    assert config.markers.length_m == TrackerConfig().markers.length_m
    assert config.markers.ids == ()
    assert dict(config.markers.lengths_m) == {}
    assert config.boards == ()
    # so marker 7 and the former desk-board ids are plain lone markers of the default size
    assert config.marker_length(7) == 0.05
    assert config.board_of(10) is None
    assert config.tracks_marker(10)


def test_partial_toml_keeps_unmentioned_scalars_at_their_defaults(tmp_path):
    # given a config that sets one value in one table
    path = tmp_path / "partial.toml"
    path.write_text("[pose]\nmax_reproj_px = 1.5\n")
    # when loaded
    config = load_config(path)
    # then only that value differs from the defaults
    assert config.pose.max_reproj_px == 1.5
    assert config.detector == DetectorConfig()
    assert config.recording == RecordingConfig()
    assert config.markers.length_m == 0.05


def test_integer_where_number_expected_is_accepted_as_float(tmp_path):
    path = tmp_path / "int.toml"
    path.write_text("[markers]\nlength_m = 1\n")
    config = load_config(path)
    assert config.markers.length_m == 1.0
    assert isinstance(config.markers.length_m, float)


# ============================================================================ config: errors

_BOARD_A = "[[boards]]\nname = 'a'\n"

# (id, file content, regex the message must match after the file path)
CONFIG_ERRORS = [
    ("unknown-top-level-key", "colour = 'red'\n", r"top level.*unknown key.*\bcolour\b"),
    ("unknown-top-level-table", "[detecter]\ndictionary = 'DICT_4X4_50'\n", r"top level.*unknown key.*\bdetecter\b"),
    ("unknown-markers-key", "[markers]\nlenght_m = 0.05\n", r"\[markers\].*unknown key.*\blenght_m\b"),
    ("negative-length", "[markers]\nlength_m = -1\n", r"\[markers\] length_m: must be > 0, got -1"),
    ("zero-length", "[markers]\nlength_m = 0\n", r"\[markers\] length_m: must be > 0, got 0"),
    ("nan-length", "[markers]\nlength_m = nan\n", r"\[markers\] length_m: must be finite"),
    ("string-for-number", "[markers]\nlength_m = '0.05'\n", r"\[markers\] length_m: must be a number, got '0.05'"),
    ("string-for-number-pose", "[pose]\nmax_reproj_px = 'three'\n", r"\[pose\] max_reproj_px: must be a number"),
    ("bool-for-number", "[markers]\nlength_m = true\n", r"\[markers\] length_m: must be a number, got True"),
    ("bool-for-int", "[recording]\njpeg_quality = true\n", r"\[recording\] jpeg_quality: must be an integer, got True"),
    ("bool-for-int-board", _BOARD_A + "cols = true\n", r"\[\[boards\]\] 'a' cols: must be an integer, got True"),
    ("float-for-int", "[recording]\nimage_every = 1.5\n", r"\[recording\] image_every: must be an integer"),
    ("out-of-range-int", "[recording]\njpeg_quality = 101\n", r"\[recording\] jpeg_quality: must be in \[1, 100\]"),
    ("unknown-dictionary", "[detector]\ndictionary = 'DICT_9X9_1'\n", r"\[detector\] dictionary:.*DICT_9X9_1"),
    ("non-string-dictionary", "[detector]\ndictionary = 50\n", r"\[detector\] dictionary: must be a string"),
    ("unknown-refinement", "[detector]\ncorner_refinement = 'best'\n", r"\[detector\] corner_refinement:.*'best'"),
    ("table-is-scalar", "detector = 3\n", r"\[detector\] must be a table"),
    (
        "lengths-key-not-id",
        "[markers.lengths_m]\nseven = 0.04\n",
        r"\[markers\.lengths_m\] seven: keys must be marker ids",
    ),
    ("lengths-key-negative", "[markers.lengths_m]\n-1 = 0.04\n", r"\[markers\.lengths_m\] -1: keys must be marker ids"),
    (
        "lengths-key-outside-dict",
        "[markers.lengths_m]\n50 = 0.04\n",
        r"\[markers\.lengths_m\] 50: keys must be marker ids 0\.\.49",
    ),
    (
        "lengths-key-unicode-digit",
        '[markers.lengths_m]\n"\u00b2" = 0.04\n',
        r"\[markers\.lengths_m\] \u00b2: keys must be marker ids",
    ),
    ("lengths-value-negative", "[markers.lengths_m]\n3 = -0.04\n", r"\[markers\.lengths_m\] 3: must be > 0"),
    ("markers-ids-outside-dict", "[markers]\nids = [0, 50]\n", r"\[markers\] ids: ids \[50\] are outside"),
    ("markers-ids-duplicate", "[markers]\nids = [1, 1]\n", r"\[markers\] ids: ids must be unique"),
    ("markers-ids-not-list", "[markers]\nids = 3\n", r"\[markers\] ids: must be a list"),
    ("board-cols-zero", _BOARD_A + "cols = 0\n", r"\[\[boards\]\] 'a' cols: must be in \[1, 100\], got 0"),
    ("board-rows-negative", _BOARD_A + "rows = -2\n", r"\[\[boards\]\] 'a' rows: must be in \[1, 100\], got -2"),
    ("board-no-name", "[[boards]]\ncols = 2\n", r"\[\[boards\]\] #1 name: is required"),
    (
        "board-bad-kind",
        _BOARD_A + "kind = 'hexagon'\n",
        r"\[\[boards\]\] 'a' kind: must be one of grid, charuco, custom",
    ),
    ("board-unknown-key", _BOARD_A + "colums = 2\n", r"\[\[boards\]\] 'a'.*unknown key.*\bcolums\b"),
    (
        "board-ids-overlap",
        "[[boards]]\nname = 'a'\nfirst_id = 10\n[[boards]]\nname = 'b'\nfirst_id = 11\n",
        r"\[\[boards\]\] 'b' ids: marker id 11 is already used by board 'a'",
    ),
    (
        "board-explicit-ids-overlap",
        "[[boards]]\nname = 'a'\nids = [1, 2, 3, 4]\n[[boards]]\nname = 'b'\nids = [5, 6, 7, 4]\n",
        r"\[\[boards\]\] 'b' ids: marker id 4 is already used by board 'a'",
    ),
    (
        "board-duplicate-name",
        "[[boards]]\nname = 'a'\n[[boards]]\nname = 'a'\nfirst_id = 20\n",
        r"\[\[boards\]\] 'a' name: duplicate board name",
    ),
    (
        "board-ids-wrong-length",
        _BOARD_A + "ids = [1, 2, 3]\n",
        r"\[\[boards\]\] 'a' ids: needs cols\*rows = 4 ids, got 3",
    ),
    ("board-ids-past-dictionary", _BOARD_A + "first_id = 48\n", r"\[\[boards\]\] 'a' first_id: ids 48\.\.51 exceed"),
    (
        "board-length-conflict",
        "[markers.lengths_m]\n1 = 0.03\n" + _BOARD_A + "first_id = 0\n",
        r"\[\[boards\]\] 'a' marker_length_m: marker 1",
    ),
    ("boards-not-array", "boards = 3\n", r"boards must be an array of tables"),
    ("invalid-toml-syntax", "[markers\nlength_m = 0.05\n", r"invalid TOML.*line 1"),
    ("invalid-toml-duplicate-key", "[pose]\nmax_reproj_px = 1.0\nmax_reproj_px = 2.0\n", r"invalid TOML"),
    ("non-utf8", b"[markers]\nlength_m = 0.05 # \xff\xfe\n", r"not UTF-8"),
]


@pytest.mark.parametrize(
    ("content", "pattern"),
    [pytest.param(content, pattern, id=name) for name, content, pattern in CONFIG_ERRORS],
)
def test_bad_config_raises_one_line_config_error_naming_file_and_key(tmp_path, content, pattern):
    # given a config file with one mistake
    path = tmp_path / "bad.toml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    # when it is loaded, then the error names the file, then the key / problem, on one line
    with pytest.raises(ConfigError, match=re.escape(str(path)) + r"\b.*" + pattern) as info:
        load_config(path)
    assert "\n" not in str(info.value)
    assert isinstance(info.value, InputError)  # the CLI maps it to exit code 2


def test_missing_config_file_is_config_error_naming_it(tmp_path):
    path = tmp_path / "nowhere" / "tracker.toml"
    with pytest.raises(ConfigError, match=re.escape(str(path)) + r".*not found"):
        load_config(path)


def test_directory_as_config_is_config_error(tmp_path):
    with pytest.raises(ConfigError, match=re.escape(str(tmp_path))):
        load_config(tmp_path)


# ============================================================================ camera: reading


def test_synthetic_camera_file_matches_default_synthetic():
    # given the shipped camera file and the built-in synthetic camera
    from_file = CameraModel.from_yaml(SYNTHETIC_YAML)
    built_in = CameraModel.default_synthetic()
    # then intrinsics and size agree exactly
    assert from_file.size == built_in.size == (1280, 720)
    np.testing.assert_array_equal(from_file.camera_matrix, built_in.camera_matrix)
    np.testing.assert_array_equal(from_file.camera_matrix[:2, 2], [639.5, 359.5])
    # the file spells "no distortion" as five zeros, the built-in as none: the same lens
    assert not from_file.has_distortion and not built_in.has_distortion
    assert from_file.dist_or_none is None and built_in.dist_or_none is None
    np.testing.assert_array_equal(from_file.dist_coeffs, np.zeros(from_file.dist_coeffs.size))


@pytest.mark.parametrize("n_dist", [5, 4, 8, 14])
def test_to_yaml_from_yaml_round_trip(tmp_path, n_dist):
    # given a camera with off-centre principal point, skew-free K and seeded random distortion
    rng = np.random.default_rng(1234 + n_dist)
    matrix = np.array([[812.25, 0.0, 655.125], [0.0, 809.75, 371.5], [0.0, 0.0, 1.0]])
    dist = rng.normal(0.0, 0.03, n_dist)  # 0.05 drew a tangential p2 of 0.086, which folds the image: refused
    camera = CameraModel(matrix, dist, 1296, 728)
    path = tmp_path / "cam.yml"
    # when written (with extra scalars, as a calibration tool would) and read back
    camera.to_yaml(path, rms_px=0.31, note="bench")
    loaded = CameraModel.from_yaml(path)
    # then nothing is lost
    assert_same_camera(loaded, camera)
    assert loaded.dist_coeffs.shape == (n_dist,)
    assert loaded.has_distortion


def test_round_trip_without_distortion_stays_distortion_free(tmp_path):
    camera = CameraModel.from_fov(640, 480, 500.0)
    path = tmp_path / "cam.yml"
    camera.to_yaml(path)
    loaded = CameraModel.from_yaml(path)
    np.testing.assert_array_equal(loaded.camera_matrix, camera.camera_matrix)
    assert loaded.size == (640, 480)
    assert not loaded.has_distortion


# ============================================================================ camera: errors

_K_OK = "500., 0., 319.5, 0., 500., 239.5, 0., 0., 1."


def _camera_yaml(
    *,
    matrix: str | None = _K_OK,
    rows: int = 3,
    cols: int = 3,
    width: str | None = "640",
    height: str | None = "480",
    dist: str | None = None,
) -> str:
    lines = ["%YAML 1.2", "---"]
    if width is not None:
        lines.append(f"image_width: {width}")
    if height is not None:
        lines.append(f"image_height: {height}")
    if matrix is not None:
        lines += [
            "camera_matrix: !!opencv-matrix",
            f"   rows: {rows}",
            f"   cols: {cols}",
            "   dt: d",
            f"   data: [ {matrix} ]",
        ]
    if dist is not None:
        n = len(dist.split(","))
        lines += [
            "distortion_coefficients: !!opencv-matrix",
            "   rows: 1",
            f"   cols: {n}",
            "   dt: d",
            f"   data: [ {dist} ]",
        ]
    return "\n".join(lines) + "\n"


# (id, file content, regex the message must match after the file path)
CAMERA_ERRORS = [
    pytest.param("", r"empty", id="empty-file"),
    pytest.param("  \n\n", r"empty", id="blank-file"),
    pytest.param(
        "%YAML 1.2\n---\nimage_width: 640\nimage_height: 480\n", r"missing 'camera_matrix'", id="no-camera-matrix"
    ),
    pytest.param(
        _camera_yaml(matrix="500., 0., 320., 0., 500., 240.", rows=2), r"camera_matrix: expected 3x3", id="matrix-2x3"
    ),
    pytest.param(
        _camera_yaml(matrix="500., 0., 319.5, 0., 500., 239.5", rows=2).replace(
            "!!opencv-matrix\n   rows: 2\n   cols: 3\n   dt: d\n   data:", ""
        ),
        r"camera_matrix: expected 3x3, got shape \(6,\)",
        id="matrix-plain-list-of-6",
    ),
    pytest.param(
        _camera_yaml(matrix="-500., 0., 319.5, 0., 500., 239.5, 0., 0., 1."),
        r"focal lengths must be > 0.*fx=-500",
        id="negative-fx",
    ),
    pytest.param(
        _camera_yaml(matrix="500., 0., 319.5, 0., 0., 239.5, 0., 0., 1."),
        r"focal lengths must be > 0.*fy=0",
        id="zero-fy",
    ),
    pytest.param(
        _camera_yaml(matrix="500., 0., 319.5, 0., 500., 239.5, 0., 1., 1."),
        r"last row must be \[0, 0, 1\]",
        id="bad-last-row",
    ),
    pytest.param(_camera_yaml(width=None), r"missing 'image_width'", id="no-image-width"),
    pytest.param(_camera_yaml(height=None), r"missing 'image_height'", id="no-image-height"),
    pytest.param(_camera_yaml(width="wide"), r"'image_width' must be a number", id="width-not-number"),
    pytest.param(_camera_yaml(width="640.5"), r"'image_width' must be a positive integer", id="width-fractional"),
    pytest.param(_camera_yaml(height="-480"), r"'image_height' must be a positive integer", id="height-negative"),
    pytest.param(
        _camera_yaml(dist="0.1, 0.01, 0.0"), r"distortion_coefficients: expected 4, 5, 8, 12 or 14", id="dist-3-values"
    ),
    pytest.param("this is: not [yaml\n{{{\n", r"", id="garbage-text"),
    pytest.param("hello world\n", r"", id="plain-sentence"),
    pytest.param(np.random.default_rng(7).integers(0, 256, 512, dtype=np.uint8).tobytes(), r"", id="random-bytes"),
    pytest.param("- 1\n- 2\n", r"", id="yaml-list-document"),
    pytest.param(
        "%YAML 1.2\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: identity\n",
        r"camera_matrix",
        id="matrix-is-string",
    ),
]


@pytest.mark.parametrize(("content", "pattern"), CAMERA_ERRORS)
def test_bad_camera_file_raises_one_line_camera_error_naming_file(tmp_path, content, pattern):
    # given a malformed camera file
    path = tmp_path / "cam.yml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    # when read, then a CameraError names the file first, then the problem, on one line
    with pytest.raises(CameraError, match=r"camera file " + re.escape(str(path)) + r": .*" + pattern) as info:
        CameraModel.from_yaml(path)
    assert "\n" not in str(info.value)


def test_missing_camera_file_is_camera_error_naming_it(tmp_path):
    path = tmp_path / "calib" / "cam.yml"
    with pytest.raises(CameraError, match=r"camera file " + re.escape(str(path)) + r": not found"):
        CameraModel.from_yaml(path)


# ============================================================================ camera: scaling


@pytest.fixture
def camera_logs(caplog, monkeypatch):
    # the CLI's logging setup turns propagation off on "ar_anchor"; make sure caplog sees records
    monkeypatch.setattr(logging.getLogger("ar_anchor"), "propagate", True)
    caplog.set_level(logging.WARNING, logger="ar_anchor.camera")
    return caplog


@pytest.mark.parametrize("n_dist", [4, 5, 8, 12, 14])
def test_project_rays_is_project_of_the_rays_at_depth_one(n_dist):
    # given a camera with a skew entry (OpenCV ignores it) and each distortion model, the tilted sensor included
    rng = np.random.default_rng(n_dist)
    k = np.array([[900.0, 0.5, 640.0], [0.0, 880.0, 360.0], [0.0, 0.0, 1.0]])
    camera = CameraModel(k, rng.normal(0.0, 0.02, n_dist), 1280, 720)
    rays = rng.uniform(-0.7, 0.7, (5000, 2))
    # then the rays' pixels are OpenCV's projection of (x, y, 1)
    expected = camera.project(np.column_stack([rays, np.ones(len(rays))]))
    assert np.abs(camera.project_rays(rays) - expected).max() < 1e-9


def test_scaled_to_half_resolution_uses_pixel_centre_convention(camera_logs):
    # given a 1280x720 camera with an off-centre principal point and distortion
    matrix = np.array([[1000.0, 0.0, 600.25], [0.0, 990.0, 340.75], [0.0, 0.0, 1.0]])
    dist = np.array([0.1, -0.05, 0.001, 0.002, 0.01])
    camera = CameraModel(matrix, dist, 1280, 720)
    # when scaled to 640x360
    half = camera.scaled_to(640, 360)
    # then focal lengths halve and the principal point maps with cx' = (cx + 0.5) * s - 0.5
    k = half.camera_matrix
    assert half.size == (640, 360)
    assert k[0, 0] == pytest.approx(500.0)
    assert k[1, 1] == pytest.approx(495.0)
    assert k[0, 2] == pytest.approx((600.25 + 0.5) * 0.5 - 0.5)  # 299.875, not the naive 300.125
    assert k[1, 2] == pytest.approx((340.75 + 0.5) * 0.5 - 0.5)  # 170.125, not the naive 170.375
    np.testing.assert_array_equal(k[2], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(half.dist_coeffs, dist)  # distortion is resolution independent
    # and a warning says the intrinsics were rescaled
    warnings = [r for r in camera_logs.records if r.levelno == logging.WARNING and r.name == "ar_anchor.camera"]
    assert len(warnings) == 1
    assert "1280x720" in warnings[0].getMessage() and "640x360" in warnings[0].getMessage()


def test_scaled_to_keeps_the_image_centre_at_the_centre(camera_logs):
    # given the ideal camera whose principal point is the image centre ((W-1)/2, (H-1)/2)
    camera = CameraModel.default_synthetic()
    # when scaled down by 2 and up by 1.5
    for width, height in [(640, 360), (1920, 1080)]:
        scaled = camera.scaled_to(width, height)
        # then the principal point is still the centre of the new image
        np.testing.assert_allclose(scaled.camera_matrix[:2, 2], [(width - 1) / 2, (height - 1) / 2])


def test_scaled_to_same_size_is_identity_without_warning(camera_logs):
    camera = CameraModel.default_synthetic()
    assert camera.scaled_to(1280, 720) is camera
    assert not [r for r in camera_logs.records if r.levelno >= logging.WARNING]


def test_scaled_to_changed_aspect_ratio_is_an_error():
    camera = CameraModel.default_synthetic()
    with pytest.raises(CameraError, match=r"1280x720 .* cannot be used for 640x480 frames"):
        camera.scaled_to(640, 480)


def test_camera_matrix_as_a_plain_list_of_nine_is_read_row_major(tmp_path):
    # given a hand-written camera file whose camera_matrix is a plain YAML list (no !!opencv-matrix tag)
    text = _camera_yaml().replace("!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data:", "")
    assert "!!opencv-matrix\n   rows: 3" not in text
    path = tmp_path / "plain.yml"
    path.write_text(text)
    # when it is read, then it is the same matrix as the tagged form
    tagged = tmp_path / "tagged.yml"
    tagged.write_text(_camera_yaml())
    np.testing.assert_array_equal(
        CameraModel.from_yaml(path).camera_matrix, CameraModel.from_yaml(tagged).camera_matrix
    )


def test_dictionary_override_checks_board_ids():
    config = parse_config({"boards": [{"name": "far", "kind": "grid", "cols": 2, "rows": 2, "first_id": 40}]}, "x.toml")
    assert config.with_overrides(dictionary="DICT_5X5_100").boards[0].dictionary == "DICT_5X5_100"
    # the error names the key it would set and carries the value; the CLI, which knows the flag, says "--dictionary"
    with pytest.raises(ConfigValueError, match=r"^\[detector\] dictionary: DICT_APRILTAG_16h5 has 30 markers") as info:
        config.with_overrides(dictionary="DICT_APRILTAG_16h5")
    assert (info.value.table, info.value.key, info.value.value) == ("[detector]", "dictionary", "DICT_APRILTAG_16h5")
    assert info.value.problem.startswith("DICT_APRILTAG_16h5 has 30 markers, but board 'far' (x.toml) uses ids [40")
    assert isinstance(info.value, InputError)


@pytest.mark.parametrize(
    ("overrides", "table", "key", "problem"),
    [
        ({"dictionary": "DICT_9X9_1"}, "[detector]", "dictionary", r"unknown dictionary 'DICT_9X9_1' \(known: "),
        ({"marker_length_m": -0.05}, "[markers]", "length_m", r"must be a positive length in metres, got -0.05"),
        ({"marker_length_m": float("nan")}, "[markers]", "length_m", r"must be a positive length in metres, got nan"),
    ],
)
def test_bad_override_names_the_key_not_a_flag(overrides, table, key, problem):
    with pytest.raises(ConfigValueError) as info:
        TrackerConfig().with_overrides(**overrides)
    assert (info.value.table, info.value.key) == (table, key)
    assert re.match(problem, info.value.problem)
    assert str(info.value) == f"{table} {key}: {info.value.problem}"
    assert "--" not in str(info.value)


def test_file_errors_carry_table_key_and_value(tmp_path):
    # given a file with a value out of range
    path = tmp_path / "bad.toml"
    path.write_text("[recording]\njpeg_quality = 101\n")
    # then the error's attributes say where and what, and its message is the one line the user reads
    with pytest.raises(ConfigValueError) as info:
        load_config(path)
    err = info.value
    assert (err.table, err.key, err.value, err.problem) == (
        "[recording]",
        "jpeg_quality",
        101,
        "must be in [1, 100], got 101",
    )
    assert str(err) == f"{path}: [recording] jpeg_quality: must be in [1, 100], got 101"


def test_unknown_key_gets_a_hint(tmp_path):
    path = tmp_path / "typo.toml"
    path.write_text("[markers]\nlenght_m = 0.05\n[[boards]]\nname = 'g'\nsquares_x = 4\n")
    with pytest.raises(ConfigValueError, match=r"\[markers\]: unknown key\(s\): lenght_m \(did you mean length_m\?\)"):
        load_config(path)
    path.write_text("[[boards]]\nname = 'g'\nsquares_x = 4\n")
    with pytest.raises(
        ConfigValueError, match=r"'g': unknown key\(s\): squares_x \(squares_x is a charuco board's key\)"
    ):
        load_config(path)
