"""Rigid multi-marker boards: config (TOML, layout files), geometry, joint solver, tracker, real photos."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.boards import layout_from_mapping, read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.config import BoardConfig, DetectorConfig, TrackerConfig, load_config
from ar_anchor.errors import CameraError, ConfigError, InputError
from ar_anchor.geometry import Pose, angle_between_deg, look_at
from ar_anchor.sources.base import Frame
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedBoard, SyntheticScene, Trajectory
from ar_anchor.track.detection import Detector, MarkerDetections
from ar_anchor.track.pose import BoardPose, BoardSolver, reprojection_rms
from ar_anchor.track.tracker import Tracker
from tests.helpers import run_main

# ============================================================================ helpers

SQUARE = [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.05, 0.05, 0.0], [0.0, 0.05, 0.0]]


def toml_corners(corners) -> str:
    return "[" + ", ".join("[" + ", ".join(f"{float(v)!r}" for v in point) + "]" for point in corners) + "]"


def aruco_marker_map(markers: dict[int, list[list[float]]]) -> str:
    """An ArUco library marker map (``MarkerMap::saveToFile`` layout), metres."""
    lines = ["%YAML:1.0", f"aruco_bc_nmarkers: {len(markers)}", "aruco_bc_mInfoType: 1", "aruco_bc_markers:"]
    for marker_id, corners in markers.items():
        points = ", ".join("[ " + ", ".join(f"{float(v)!r}" for v in point) + " ]" for point in corners)
        lines.append(f"   - {{ id:{marker_id}, corners:[ {points} ] }}")
    return "\n".join(lines) + "\n"


def face_markers(
    origin, right, down, length: float, offsets: list[tuple[float, float]]
) -> list[tuple[np.ndarray, ...]]:
    """Markers on one face: TL at origin + a*right + b*down, printed side toward -(right x down)."""
    origin, right, down = (np.asarray(v, dtype=np.float64) for v in (origin, right, down))
    out = []
    for a, b in offsets:
        tl = origin + a * right + b * down
        out.append(np.array([tl, tl + length * right, tl + length * (right + down), tl + length * down]))
    return out


def cube_layout(side: float = 0.1, length: float = 0.04) -> tuple:
    """Markers on three faces of a cube [0, side]^3 (front z=0, left x=0, top y=0), all facing outward."""
    m = 0.005
    quads = (
        face_markers((0, 0, 0), (1, 0, 0), (0, 1, 0), length, [(m, m), (side - m - length, side - m - length)])
        + face_markers((0, 0, side), (0, 0, -1), (0, 1, 0), length, [(m, m), (side - m - length, side - m - length)])
        + face_markers((0, 0, side), (1, 0, 0), (0, 0, -1), length, [(0.03, 0.03)])
    )
    return tuple((20 + i, tuple(tuple(float(v) for v in p) for p in quad)) for i, quad in enumerate(quads))


def project_board(
    board: BoardConfig, pose: Pose, camera: CameraModel, rng: np.random.Generator | None = None, sigma: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """(ids, corners (N, 4, 2)) of every board marker, exact projections plus seeded gaussian noise."""
    layout = board.corners_in_board()
    ids = np.array(board.marker_ids, dtype=np.int32)
    corners = []
    for marker_id in ids:
        pixels, _ = cv2.projectPoints(layout[int(marker_id)], pose.rvec, pose.tvec, camera.camera_matrix, None)
        corners.append(pixels.reshape(4, 2))
    corners = np.array(corners)
    if rng is not None:
        corners = corners + rng.normal(0.0, sigma, corners.shape)
    return ids, corners


def board_view(board: BoardConfig, distance: float, offset=(0.15, -0.1)) -> Pose:
    """camera_from_board looking at the board's centre from its printed (-z) side, obliquely."""
    width, height = board.size_m
    centre = np.array([width / 2, height / 2, 0.0])
    eye = centre + np.array([offset[0], offset[1], -distance])
    return look_at(eye, centre, up=(0.0, -1.0, 0.0))


def pose_errors(estimate: Pose, truth: Pose) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres)."""
    return angle_between_deg(estimate.rotation, truth.rotation), float(np.linalg.norm(estimate.tvec - truth.tvec))


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


# ============================================================================ config: parsing


def test_grid_and_charuco_boards_parse_with_first_id_or_ids(tmp_path):
    # given a config with a grid board (first_id), a grid board (explicit ids) and a legacy ChArUco board
    path = write(
        tmp_path / "boards.toml",
        """
[detector]
dictionary = "DICT_5X5_100"

[[boards]]
name = "grid"
kind = "grid"
cols = 3
rows = 2
marker_length_m = 0.05
separation_m = 0.01
first_id = 5

[[boards]]
name = "picked"
cols = 2
rows = 1
marker_length_m = 0.03
separation_m = 0.0
ids = [42, 17]

[[boards]]
name = "cha"
kind = "charuco"
squares_x = 4
squares_y = 6
square_length_m = 0.04
marker_length_m = 0.03
legacy = true
dictionary = "DICT_5X5_100"
first_id = 60
""",
    )
    # when loaded
    config = load_config(path)
    grid, picked, cha = config.boards
    # then every value is where it belongs
    assert grid == BoardConfig(
        name="grid",
        kind="grid",
        cols=3,
        rows=2,
        marker_length_m=0.05,
        separation_m=0.01,
        first_id=5,
        dictionary="DICT_5X5_100",
    )
    assert grid.marker_ids == (5, 6, 7, 8, 9, 10)
    assert grid.size_m == pytest.approx((0.17, 0.11))
    assert picked.kind == "grid" and picked.marker_ids == (42, 17) and picked.separation_m == 0.0
    assert (cha.kind, cha.cols, cha.rows, cha.square_length_m, cha.marker_length_m) == ("charuco", 4, 6, 0.04, 0.03)
    assert cha.legacy is True and cha.dictionary == "DICT_5X5_100"
    assert cha.marker_ids == tuple(range(60, 72))  # squares_x * squares_y // 2 markers
    assert cha.size_m == pytest.approx((0.16, 0.24))
    # and board members are tracked and sized as the board says
    assert config.board_of(7) is grid and config.board_of(17) is picked and config.board_of(71) is cha
    assert config.marker_length(42) == 0.03 and config.marker_length(65) == 0.03
    assert all(b.planar for b in config.boards)


def test_custom_board_inline_markers(tmp_path):
    path = write(
        tmp_path / "inline.toml",
        f"""
[[boards]]
name = "inline"
kind = "custom"

[[boards.markers]]
id = 7
corners = {toml_corners(SQUARE)}

[[boards.markers]]
id = 3
corners = {toml_corners(np.array(SQUARE) + [0.1, 0.0, 0.0])}
""",
    )
    board = load_config(path).boards[0]
    assert board.kind == "custom" and board.layout_source == "inline"
    assert set(board.marker_ids) == {3, 7}
    corners = board.corners_in_board()
    assert corners[7].shape == (4, 3) and corners[7].dtype == np.float64
    np.testing.assert_allclose(corners[7], SQUARE)
    np.testing.assert_allclose(corners[3], np.array(SQUARE) + [0.1, 0.0, 0.0])
    assert board.planar
    assert board.marker_length_of(3) == pytest.approx(0.05)
    assert board.size_m == pytest.approx((0.15, 0.05))


@pytest.mark.parametrize("layout_format", ["toml", "aruco_yaml"])
def test_custom_board_layout_file_is_relative_to_the_config_file(tmp_path, monkeypatch, layout_format):
    # given a layout file next to the config (in a sub-folder), in either format
    cube = dict(cube_layout())
    if layout_format == "toml":
        text = "".join(f"[[markers]]\nid = {i}\ncorners = {toml_corners(c)}\n\n" for i, c in cube.items())
        name = "layouts/cube.toml"
    else:
        text = aruco_marker_map(cube)
        name = "layouts/cube.yml"
    layout_path = write(tmp_path / "conf" / name, text)
    config_path = write(
        tmp_path / "conf" / "tracker.toml",
        f'[detector]\ndictionary = "DICT_4X4_50"\n[[boards]]\nname = "cube"\nkind = "custom"\nlayout = "{name}"\n',
    )
    # and a working directory somewhere else (the path must not be resolved against it)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    # when the config is loaded
    board = load_config(config_path).boards[0]
    # then the layout is the file's, corner for corner
    assert board.kind == "custom"
    assert Path(board.layout_source).resolve() == layout_path.resolve()
    assert board.marker_ids == tuple(sorted(cube))
    got = board.corners_in_board()
    for marker_id, corners in cube.items():
        np.testing.assert_allclose(got[marker_id], corners, atol=1e-12)
    assert board.planar is False
    # and reading the file directly gives the same layout
    assert read_layout(layout_path) == board.layout


def test_read_layout_tells_formats_by_content_not_extension(tmp_path):
    yaml_as_txt = write(tmp_path / "map.txt", aruco_marker_map({4: SQUARE}))
    toml_as_yml = write(tmp_path / "ours.yml", f"[[markers]]\nid = 4\ncorners = {toml_corners(SQUARE)}\n")
    assert read_layout(yaml_as_txt) == read_layout(toml_as_yml)
    assert read_layout(yaml_as_txt)[0][0] == 4


# ============================================================================ config: errors

_TWO = "[[boards]]\nname = 'a'\nfirst_id = 0\n"  # ids 0..3
_CHARUCO = (
    "[[boards]]\nname = 'ch'\nkind = 'charuco'\nsquares_x = 5\nsquares_y = 7\nsquare_length_m = 0.04\n"
    "marker_length_m = {marker}\n"
)
_CUSTOM = "[[boards]]\nname = 'cu'\nkind = 'custom'\n"
_INLINE_MARKER = "[[boards.markers]]\nid = {id}\ncorners = " + toml_corners(SQUARE) + "\n"

# (id, config text, regex after the file path)
BOARD_CONFIG_ERRORS = [
    (
        "ids-overlap-grid-then-charuco",
        _TWO + _CHARUCO.format(marker=0.02) + "first_id = 3\n",
        r"\[\[boards\]\] 'ch' ids: marker id 3 is already used by board 'a'",
    ),
    (
        "ids-overlap-grid-then-custom",
        _TWO + _CUSTOM + _INLINE_MARKER.format(id=2),
        r"\[\[boards\]\] 'cu' ids: marker id 2 is already used by board 'a'",
    ),
    (
        "grid-explicit-id-outside-dictionary",
        "[[boards]]\nname = 'g'\nids = [0, 1, 2, 99]\n",
        r"\[\[boards\]\] 'g' ids: ids \[99\] are outside the dictionary \(0\.\.49\)",
    ),
    (
        "charuco-ids-past-dictionary",
        _CHARUCO.format(marker=0.02) + "first_id = 40\n",
        r"\[\[boards\]\] 'ch' first_id: ids 40\.\.56 exceed the dictionary's 50 markers",
    ),
    (
        "charuco-ids-wrong-count",
        _CHARUCO.format(marker=0.02) + "ids = [1, 2, 3]\n",
        r"\[\[boards\]\] 'ch' ids: needs squares_x\*squares_y//2 = 17 ids, got 3",
    ),
    (
        "custom-inline-id-outside-dictionary",
        _CUSTOM + _INLINE_MARKER.format(id=60),
        r"\[\[boards\]\] 'cu' markers: marker ids \[60\] are outside the dictionary \(0\.\.49\)",
    ),
    (
        "charuco-marker-equals-square",
        _CHARUCO.format(marker=0.04),
        r"\[\[boards\]\] 'ch' marker_length_m: must be smaller than square_length_m \(0\.04\), got 0\.04",
    ),
    (
        "charuco-marker-larger-than-square",
        _CHARUCO.format(marker=0.05),
        r"\[\[boards\]\] 'ch' marker_length_m: must be smaller than square_length_m",
    ),
    (
        "charuco-missing-square",
        "[[boards]]\nname = 'ch'\nkind = 'charuco'\nmarker_length_m = 0.02\n",
        r"\[\[boards\]\] 'ch' square_length_m: is required",
    ),
    (
        "charuco-dictionary-mismatch",
        "[detector]\ndictionary = 'DICT_4X4_50'\n" + _CHARUCO.format(marker=0.02) + "dictionary = 'DICT_6X6_250'\n",
        r"\[\[boards\]\] 'ch' dictionary: must be the detector's dictionary \(DICT_4X4_50\), got 'DICT_6X6_250'",
    ),
    (
        "grid-with-charuco-key",
        "[[boards]]\nname = 'g'\nsquare_length_m = 0.04\n",
        r"\[\[boards\]\] 'g'.*unknown key.*\bsquare_length_m\b",
    ),
    (
        "custom-both-layout-and-markers",
        _CUSTOM + "layout = 'x.toml'\n" + _INLINE_MARKER.format(id=1),
        r"\[\[boards\]\] 'cu' layout: a custom board needs either layout",
    ),
    ("custom-neither-layout-nor-markers", _CUSTOM, r"\[\[boards\]\] 'cu' layout: a custom board needs either layout"),
    (
        "custom-inline-three-corners",
        _CUSTOM + "[[boards.markers]]\nid = 1\ncorners = " + toml_corners(SQUARE[:3]) + "\n",
        r"\[\[boards\]\] 'cu' markers: inline markers: marker 1: corners must be 4 \[x, y, z\] points",
    ),
    (
        "custom-inline-extra-key",
        _CUSTOM + _INLINE_MARKER.format(id=1) + "size = 0.05\n",
        r"\[\[boards\]\] 'cu' markers: .*exactly the keys id and corners",
    ),
    (
        "custom-inline-duplicate-id",
        _CUSTOM + _INLINE_MARKER.format(id=1) + _INLINE_MARKER.format(id=1),
        r"\[\[boards\]\] 'cu' markers: .*marker id 1 appears twice",
    ),
    (
        "custom-with-grid-key",
        _CUSTOM + "cols = 3\n" + _INLINE_MARKER.format(id=1),
        r"\[\[boards\]\] 'cu'.*unknown key.*\bcols\b",
    ),
]


def assert_one_line_config_error(path: Path, pattern: str) -> ConfigError:
    with pytest.raises(ConfigError, match=re.escape(str(path)) + r"\b.*" + pattern) as info:
        load_config(path)
    assert "\n" not in str(info.value)
    assert isinstance(info.value, InputError)
    return info.value


@pytest.mark.parametrize(
    ("content", "pattern"),
    [pytest.param(content, pattern, id=name) for name, content, pattern in BOARD_CONFIG_ERRORS],
)
def test_bad_board_config_is_one_line_error_naming_file_board_and_key(tmp_path, content, pattern):
    path = write(tmp_path / "bad.toml", content)
    assert_one_line_config_error(path, pattern)


# (id, file name, file content, regex of the layout problem after "layout: layout file <path>: ")
LAYOUT_FILE_ERRORS = [
    (
        "toml-three-corners",
        "l.toml",
        f"[[markers]]\nid = 1\ncorners = {toml_corners(SQUARE[:3])}\n",
        r"marker 1: corners must be 4",
    ),
    (
        "toml-not-a-square",
        "l.toml",
        "[[markers]]\nid = 1\ncorners = [[0,0,0],[1,0,0],[1,0.01,0],[0,0.01,0]]\n",
        r"square-like",
    ),
    ("toml-no-markers", "l.toml", "title = 'cube'\n", r"expected \[\[markers\]\]"),
    ("toml-syntax", "l.toml", "[[markers]\nid = 1\n", r"neither an ArUco marker map \(YAML\) nor a TOML layout"),
    (
        "yaml-three-corners",
        "l.yml",
        aruco_marker_map({1: SQUARE[:3]}),
        r"aruco_bc_markers entry #1 needs an id and 4 corners",
    ),
    (
        "yaml-2d-corners",
        "l.yml",
        aruco_marker_map({1: [p[:2] for p in SQUARE]}),
        r"marker 1: corner 1 must be \[x, y, z\]",
    ),
    ("yaml-in-pixels", "l.yml", aruco_marker_map({1: SQUARE}).replace("mInfoType: 1", "mInfoType: 0"), r"pixels"),
    ("yaml-no-markers", "l.yml", "%YAML:1.0\nsomething_else: 3\n", r"no aruco_bc_markers sequence"),
    ("yaml-id-past-dictionary", "l.yml", aruco_marker_map({77: SQUARE}), None),
]


@pytest.mark.parametrize(
    ("name", "text", "pattern"),
    [pytest.param(name, text, pattern, id=case) for case, name, text, pattern in LAYOUT_FILE_ERRORS],
)
def test_malformed_layout_file_is_config_error_naming_board_key_and_file(tmp_path, name, text, pattern):
    layout = write(tmp_path / "layouts" / name, text)
    path = write(tmp_path / "bad.toml", f"[[boards]]\nname = 'cube'\nkind = 'custom'\nlayout = 'layouts/{name}'\n")
    if pattern is None:  # a well-formed file whose ids the dictionary does not have
        assert_one_line_config_error(path, r"\[\[boards\]\] 'cube' layout: marker ids \[77\] are outside")
    else:
        assert_one_line_config_error(
            path, r"\[\[boards\]\] 'cube' layout: layout file " + re.escape(str(layout)) + r": .*" + pattern
        )


def test_missing_layout_file_is_config_error_naming_board_key_and_file(tmp_path):
    path = write(tmp_path / "c.toml", "[[boards]]\nname = 'cube'\nkind = 'custom'\nlayout = 'nowhere/cube.toml'\n")
    assert_one_line_config_error(
        path,
        r"\[\[boards\]\] 'cube' layout: layout file "
        + re.escape(str(tmp_path / "nowhere" / "cube.toml"))
        + r".*not found",
    )


@pytest.mark.parametrize(
    "text",
    [
        "%YAML:1.0\naruco_bc_markers:\n   - { id:3, corners:[ [ 0., 0., 0. ], [ 0.05, 0.",  # truncated
        "%YAML:1.0\naruco_bc_markers: {\n",  # unclosed
    ],
    ids=["truncated", "unclosed-brace"],
)
def test_unparseable_yaml_layout_file_is_config_error(tmp_path, text):
    layout = write(tmp_path / "broken.yml", text)
    path = write(tmp_path / "c.toml", "[[boards]]\nname = 'cube'\nkind = 'custom'\nlayout = 'broken.yml'\n")
    assert_one_line_config_error(
        path, r"\[\[boards\]\] 'cube' layout: layout file " + re.escape(str(layout)) + r": not a readable"
    )


# ============================================================================ geometry


@pytest.mark.parametrize(
    ("cols", "rows", "length", "separation", "ids"),
    [(2, 2, 0.04, 0.02, None), (3, 5, 0.05, 0.01, None), (4, 3, 0.033, 0.005, [9, 3, 27, 1, 2, 4, 5, 6, 7, 8, 10, 11])],
)
def test_grid_corners_are_opencv_gridboard_object_points(cols, rows, length, separation, ids):
    board = BoardConfig(
        name="g",
        cols=cols,
        rows=rows,
        marker_length_m=length,
        separation_m=separation,
        first_id=7,
        ids=tuple(ids) if ids else (),
    )
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    expected_ids = np.array(ids if ids else range(7, 7 + cols * rows), dtype=np.int32)
    grid = cv2.aruco.GridBoard((cols, rows), length, separation, dictionary, expected_ids)
    got = board.corners_in_board()
    assert list(got) == grid.getIds().ravel().tolist()
    np.testing.assert_allclose(np.stack(list(got.values())), np.asarray(grid.getObjPoints()), atol=1e-6)
    # and the OpenCV board built from the config is the same board
    np.testing.assert_allclose(np.asarray(board.cv_board().getObjPoints()), np.asarray(grid.getObjPoints()), atol=1e-6)
    assert board.size_m == pytest.approx(
        (cols * length + (cols - 1) * separation, rows * length + (rows - 1) * separation)
    )


@pytest.mark.parametrize(
    ("cols", "rows", "legacy"), [(5, 7, False), (5, 7, True), (4, 6, False), (4, 6, True), (3, 3, False)]
)
def test_charuco_corners_are_opencv_charucoboard_object_points(cols, rows, legacy):
    board = BoardConfig(
        name="c",
        kind="charuco",
        cols=cols,
        rows=rows,
        square_length_m=0.04,
        marker_length_m=0.025,
        legacy=legacy,
        first_id=3,
        dictionary="DICT_6X6_250",
    )
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    count = cols * rows // 2
    charuco = cv2.aruco.CharucoBoard((cols, rows), 0.04, 0.025, dictionary, np.arange(3, 3 + count))
    charuco.setLegacyPattern(legacy)
    got = board.corners_in_board()
    assert list(got) == list(range(3, 3 + count))
    np.testing.assert_allclose(np.stack(list(got.values())), np.asarray(charuco.getObjPoints()), atol=1e-6)
    assert board.size_m == pytest.approx((cols * 0.04, rows * 0.04))
    assert board.planar


def test_legacy_flag_changes_an_even_row_charuco_board():
    # (guards the test above against comparing a board with itself)
    new, old = (
        BoardConfig(name="c", kind="charuco", cols=4, rows=6, square_length_m=0.04, marker_length_m=0.02, legacy=flag)
        for flag in (False, True)
    )
    assert not np.allclose(
        np.stack(list(new.corners_in_board().values())), np.stack(list(old.corners_in_board().values()))
    )


def test_custom_cube_layout_is_not_planar_and_a_flat_one_is():
    cube = BoardConfig(name="cube", kind="custom", layout=cube_layout())
    assert cube.planar is False
    flat_layout = tuple(
        (marker_id, corners) for marker_id, corners in cube_layout() if all(p[2] == 0.0 for p in corners)
    )
    assert len(flat_layout) == 2
    assert BoardConfig(name="flat", kind="custom", layout=flat_layout).planar is True
    # a tilted plane is still a plane
    tilt = cv2.Rodrigues(np.array([0.3, -0.5, 0.2]))[0]
    tilted = tuple((i, tuple(tuple(tilt @ np.array(p)) for p in c)) for i, c in flat_layout)
    assert BoardConfig(name="tilted", kind="custom", layout=tilted).planar is True
    assert cube.marker_length_of(20) == pytest.approx(0.04)


# ============================================================================ solver: synthetic projections

GRID_3X3 = BoardConfig(name="g9", cols=3, rows=3, marker_length_m=0.05, separation_m=0.01, first_id=0)


@pytest.fixture(scope="module")
def clean_grid_case():
    """The 3x3 grid at 0.5 m, obliquely, 0.1 px noise: truth, detections and the clean solution's errors."""
    camera = CameraModel.default_synthetic()
    truth = board_view(GRID_3X3, 0.5)
    ids, corners = project_board(GRID_3X3, truth, camera, np.random.default_rng(7))
    solved = BoardSolver(GRID_3X3).solve(ids, corners, camera)
    assert isinstance(solved, BoardPose)
    return camera, truth, ids, corners, pose_errors(solved.best.pose, truth)


def test_board_pose_from_exact_projections_is_accurate(clean_grid_case):
    camera, truth, ids, corners, _ = clean_grid_case
    solved = BoardSolver(GRID_3X3).solve(ids, corners, camera)
    assert isinstance(solved, BoardPose)
    assert solved.solver == "markers" and solved.name == "g9" and solved.target == "board:g9"
    assert solved.markers_used == tuple(range(9)) and solved.outlier_ids == ()
    assert solved.inliers == 36 and solved.points_in_target.shape == (36, 3) and solved.points_in_image.shape == (36, 2)
    assert len(solved.outlier_points_in_image) == 0
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error < 0.2 and translation_error < 0.002
    assert solved.best.reproj_px < 0.3  # 0.1 px noise
    assert solved.best.reproj_px == pytest.approx(
        reprojection_rms(solved.best.pose, solved.points_in_target, solved.points_in_image, camera)
    )
    # hypotheses are sorted, and a well-seen board's other solution (if kept) is clearly worse
    errors = [h.reproj_px for h in solved.hypotheses]
    assert errors == sorted(errors)
    assert all(e > 3 * errors[0] for e in errors[1:])


@pytest.mark.parametrize("name", ["charuco", "custom_planar"])
def test_other_planar_board_kinds_solve_from_marker_corners(name):
    camera = CameraModel.default_synthetic()
    if name == "charuco":
        board = BoardConfig(name="c", kind="charuco", cols=5, rows=7, square_length_m=0.04, marker_length_m=0.02)
    else:
        flat = face_markers((0, 0, 0), (1, 0, 0), (0, 1, 0), 0.04, [(0.0, 0.0), (0.1, 0.0), (0.02, 0.12)])
        board = BoardConfig(
            name="f", kind="custom", layout=tuple((30 + i, tuple(map(tuple, q))) for i, q in enumerate(flat))
        )
    truth = board_view(board, 0.6)
    ids, corners = project_board(board, truth, camera, np.random.default_rng(3))
    solved = BoardSolver(board).solve(ids, corners, camera)  # no image: no ChArUco interpolation
    assert isinstance(solved, BoardPose) and solved.solver == "markers"
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error < 0.2 and translation_error < 0.002


def corrupt(
    ids: np.ndarray, corners: np.ndarray, count: int, mode: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, set[int], set[int]]:
    """Spoil ``count`` markers' detections. Returns (ids, corners, bad ids reported, ids that remain good)."""
    ids, corners = ids.copy(), corners.copy()
    chosen = [int(i) for i in rng.choice(len(ids), count, replace=False)]
    if mode == "random_quad":
        for index in chosen:  # a plausible square somewhere left or right of the board
            centre = np.array(
                [rng.uniform(80, 350) if rng.random() < 0.5 else rng.uniform(930, 1200), rng.uniform(80, 640)]
            )
            angle, half = rng.uniform(0, 2 * np.pi), rng.uniform(20, 60)
            directions = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
            rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            corners[index] = centre + half * directions @ rotation.T + rng.normal(0, 3, (4, 2))
        bad = {int(ids[i]) for i in chosen}
        return ids, corners, bad, set(ids.tolist()) - bad
    # swapped ids: a marker decoded as another board marker
    if count == 1:
        # marker A is read as B, and B itself is not detected
        a = chosen[0]
        b = int(rng.choice([i for i in range(len(ids)) if i != a]))
        good = set(ids.tolist()) - {int(ids[a]), int(ids[b])}
        ids[a] = ids[b]
        keep = np.arange(len(ids)) != b
        return ids[keep], corners[keep], {int(ids[a])}, good
    # several markers' ids permuted cyclically among them
    original = ids[chosen].copy()
    ids[chosen] = np.roll(original, 1)
    bad = {int(i) for i in original}
    return ids, corners, bad, set(ids.tolist()) - bad


@pytest.mark.parametrize("mode", ["random_quad", "swapped_ids"])
@pytest.mark.parametrize("count", [1, 2, 3])
def test_outlier_markers_are_rejected_and_do_not_bias_the_pose(clean_grid_case, count, mode):
    # given the clean 3x3 case and its errors
    camera, truth, ids, corners, (clean_rotation, clean_translation) = clean_grid_case
    # when 1..3 markers get wrong corners or wrong ids
    rng = np.random.default_rng([count, mode == "swapped_ids"])
    bad_ids, bad_corners, bad, good = corrupt(ids, corners, count, mode, rng)
    solved = BoardSolver(GRID_3X3).solve(bad_ids, bad_corners, camera)
    # then the bad markers are the outliers, the rest are used
    assert isinstance(solved, BoardPose), solved
    assert set(solved.outlier_ids) == bad
    assert set(solved.markers_used) == good
    assert solved.inliers == 4 * len(good)
    # and the pose is as good as without them (within 2x, plus a floor against tiny numbers)
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error <= 2 * clean_rotation + 0.05, (rotation_error, clean_rotation)
    assert translation_error <= 2 * clean_translation + 0.0005, (translation_error, clean_translation)
    assert solved.best.reproj_px < 0.3


def test_other_ids_and_broken_quads_are_ignored_and_no_board_marker_gives_none(clean_grid_case):
    camera, truth, ids, corners, _ = clean_grid_case
    solver = BoardSolver(GRID_3X3)
    # markers of other boards / lone markers are not the board's business
    assert solver.solve(np.array([20, 30]), corners[:2], camera) is None
    assert solver.solve(np.zeros(0, np.int32), np.zeros((0, 4, 2)), camera) is None
    # a degenerate (collapsed) quad is dropped, not an outlier that breaks the solve
    spoiled = corners.copy()
    spoiled[4] = spoiled[4][0]
    solved = solver.solve(ids, spoiled, camera)
    assert isinstance(solved, BoardPose)
    assert 4 not in solved.markers_used
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error < 0.2 and translation_error < 0.002


SMALL_FAR = BoardConfig(name="far", cols=2, rows=2, marker_length_m=0.03, separation_m=0.01, first_id=0)


def small_far_view() -> Pose:
    return board_view(SMALL_FAR, 2.5, offset=(0.08, -0.05))  # nearly fronto-parallel, 12 px markers


def test_single_visible_marker_gives_an_ambiguous_board_pose_with_two_hypotheses():
    camera = CameraModel.default_synthetic()
    truth = small_far_view()
    ids, corners = project_board(SMALL_FAR, truth, camera, np.random.default_rng(11))
    solved = BoardSolver(SMALL_FAR).solve(ids[2:3], corners[2:3], camera)
    assert isinstance(solved, BoardPose)
    assert solved.markers_used == (2,) and solved.outlier_ids == () and solved.inliers == 4
    assert len(solved.hypotheses) == 2
    first, second = solved.hypotheses
    assert first.reproj_px <= second.reproj_px < 0.5  # both explain the corners
    assert angle_between_deg(first.pose.rotation, second.pose.rotation) > 0.5  # two different solutions
    # one of them is the truth (to what 12 px and 0.1 px of noise allow), both at the right distance
    assert min(angle_between_deg(h.pose.rotation, truth.rotation) for h in solved.hypotheses) < 10.0
    for hypothesis in solved.hypotheses:
        assert np.linalg.norm(hypothesis.pose.tvec - truth.tvec) < 0.05 * np.linalg.norm(truth.tvec)


class _FixedDetections:
    """Stands in for the tracker's detector: returns given detections instead of looking at the image."""

    def __init__(self, detector: Detector, frames: list[MarkerDetections]) -> None:
        self.inner = detector
        self.cells = detector.cells
        self.frames = iter(frames)

    def detect(self, image: np.ndarray, camera=None) -> MarkerDetections:
        return next(self.frames)

    def detect_regions(self, image: np.ndarray, regions, camera=None) -> MarkerDetections:
        return next(self.frames)

    def recover(self, image, detections, *args, **kwargs) -> MarkerDetections:
        return detections


def test_tracker_reports_a_board_seen_by_one_marker_as_ambiguous(camera):
    # given a small far board of which only one marker is detected, frame after frame
    config = dataclasses.replace(TrackerConfig(), boards=(SMALL_FAR,))
    tracker = Tracker(config, camera)
    truth = small_far_view()
    rng = np.random.default_rng(5)
    frames = []
    for _ in range(3):
        ids, corners = project_board(SMALL_FAR, truth, camera, rng)
        frames.append(MarkerDetections(ids[1:2], corners[1:2]))
    tracker.detector = _FixedDetections(tracker.detector, frames)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index in range(3):
        result = tracker.process(Frame(image, index, index * 33_333_333))
        # then the board is reported, from that one marker, but not vouched for
        board = result.targets["board:far"]
        assert board.state == "ambiguous", (index, board.state)
        assert board.markers_used == (1,)
        assert len(board.hypotheses) == 2
        assert "marker:1" in result.targets


def test_non_planar_cube_board_solves_accurately():
    camera = CameraModel.default_synthetic()
    cube = BoardConfig(name="cube", kind="custom", layout=cube_layout())
    assert not cube.planar
    # seen from the front-left-top so that all three faces show
    truth = look_at((-0.25, -0.2, -0.35), (0.05, 0.05, 0.05), up=(0.0, -1.0, 0.0))
    ids, corners = project_board(cube, truth, camera, np.random.default_rng(21))
    solved = BoardSolver(cube).solve(ids, corners, camera)
    assert isinstance(solved, BoardPose), solved
    assert set(solved.markers_used) == set(cube.marker_ids)
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error < 0.5 and translation_error < 0.003
    # a non-planar board has no mirror solution to offer
    assert len(solved.hypotheses) == 1 or solved.hypotheses[1].reproj_px > 10 * solved.best.reproj_px
    # and with one face's markers spoiled (moved 80 px), the other faces still carry the pose
    spoiled = corners.copy()
    spoiled[:2] += 80.0
    solved = BoardSolver(cube).solve(ids, spoiled, camera)
    assert isinstance(solved, BoardPose)
    assert set(solved.outlier_ids) == {20, 21}
    rotation_error, translation_error = pose_errors(solved.best.pose, truth)
    assert rotation_error < 1.0 and translation_error < 0.005


# ============================================================================ tracker end to end


def test_tracker_on_rendered_grid_board(camera):
    # given a rendered static scene of the 2x2 desk board (ids 10..13) with sensor noise and blur
    board = BoardConfig(name="desk", cols=2, rows=2, marker_length_m=0.04, separation_m=0.02, first_id=10)
    placed = PlacedBoard(board, Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), np.zeros(3)))  # top-left at the origin
    scene = SyntheticScene(
        camera=camera,
        boards=(placed,),
        trajectory=Trajectory(
            kind="static", near_m=0.4, azimuth_deg=25.0, elevation_deg=10.0, roll_deg=5.0, look_at=(0.05, -0.05, 0.0)
        ),
        frames=10,
        noise_sigma=1.5,
        blur_sigma=0.5,
        seed=3,
    )
    config = dataclasses.replace(TrackerConfig(), boards=(board,))
    tracker = Tracker(config, camera)
    # when tracked
    with SyntheticSource(scene) as source:
        for frame in source:
            result = tracker.process(frame)
            # then the board is there, close to the truth, from all four markers
            assert "board:desk" in result.targets, (frame.index, result.failures)
            target = result.targets["board:desk"]
            assert target.markers_used == (10, 11, 12, 13) and target.outlier_ids == ()
            assert target.inliers == 16
            truth = frame.truth["board:desk"]
            rotation_error, translation_error = pose_errors(target.raw, truth)
            assert rotation_error < 1.0 and translation_error < 0.003, (frame.index, rotation_error, translation_error)
            rotation_error, translation_error = pose_errors(target.pose, truth)
            assert rotation_error < 1.0 and translation_error < 0.003, (frame.index, rotation_error, translation_error)
            assert target.reproj_px < 1.0
            # and its markers are reported on their own too
            for marker_id in range(10, 14):
                marker = result.targets[f"marker:{marker_id}"]
                assert marker.length_m == 0.04
                assert np.linalg.norm(marker.raw.tvec - frame.truth[f"marker:{marker_id}"].tvec) < 0.005
    assert target.state == "tracked"  # four markers of a tilted board: no flip to resolve


# ============================================================================ real photos

realdata_only = pytest.mark.realdata


def read_vector(node: cv2.FileNode) -> np.ndarray:
    try:
        matrix = node.mat()
    except cv2.error:
        matrix = None
    if matrix is None:
        return np.array([node.at(i).real() for i in range(node.size())], dtype=np.float64)
    return np.asarray(matrix, dtype=np.float64).reshape(-1)


def read_camera(path: Path, size: tuple[int, int]) -> CameraModel:
    """CameraModel.from_yaml, or (for calibrations without image_width/height) the matrices at ``size``."""
    try:
        return CameraModel.from_yaml(path)
    except CameraError as err:
        assert "image_width" in str(err), err  # the only thing such a file may lack
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        matrix = storage.getNode("camera_matrix").mat()
        dist = storage.getNode("distortion_coefficients").mat()
    finally:
        storage.release()
    return CameraModel(matrix, dist.reshape(-1), *size)


def read_dictionary(path: Path) -> cv2.aruco.Dictionary:
    dictionary = cv2.aruco.Dictionary()
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # keep it open while the node is read
    try:
        assert dictionary.readDictionary(storage.root())
    finally:
        storage.release()
    return dictionary


@realdata_only
def test_aruco_library_board_photo_pose_matches_reference(realdata, tmp_path):
    folder = realdata / "aruco_testdata" / "board"
    # given the board as a custom layout read from ArUco's own marker map, through a config file
    config_path = write(
        tmp_path / "tracker.toml",
        f'[detector]\ndictionary = "DICT_ARUCO_ORIGINAL"\n[[boards]]\nname = "desk"\nkind = "custom"\n'
        f'layout = "{(folder / "board_meters.yml").as_posix()}"\n',
    )
    config = load_config(config_path)
    board = config.boards[0]
    assert len(board.marker_ids) == 24 and board.planar
    assert board.marker_length_of(board.marker_ids[0]) == pytest.approx(0.039, abs=1e-6)
    camera = CameraModel.from_yaml(folder / "intrinsics.yml")
    image = cv2.imread(str(folder / "image-test.png"))
    detections = Detector(DetectorConfig(dictionary="DICT_ARUCO_ORIGINAL")).detect(image)
    # when the board is solved
    solved = BoardSolver(board, config.pose.board_inlier_px).solve(
        detections.ids, detections.corners, camera, config.pose.max_reproj_px, image=image
    )
    # then it agrees with the ArUco library's own pose
    storage = cv2.FileStorage(str(folder / "expected.yml"), cv2.FILE_STORAGE_READ)
    try:
        node = storage.getNode("Board")
        expected = Pose(read_vector(node.getNode("Rvec")), read_vector(node.getNode("Tvec")) * 0.039)
    finally:
        storage.release()
    assert isinstance(solved, BoardPose), solved
    assert len(solved.markers_used) >= 20
    rotation_error, translation_error = pose_errors(solved.best.pose, expected)
    assert rotation_error < 0.5 and translation_error < 0.002, (rotation_error, translation_error)
    assert solved.best.reproj_px < 2.0


@realdata_only
def test_occluded_grid_board_photo_with_custom_dictionary(realdata):
    folder = realdata / "opencv_contrib"
    image = cv2.imread(str(folder / "gbocclusion.png"))
    height, width = image.shape[:2]
    camera = read_camera(folder / "tutorial_camera_params.yml", (width, height))
    dictionary = read_dictionary(folder / "tutorial_dict.yml")
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters()).detectMarkers(image)
    assert sorted(np.ravel(ids).tolist()) == [1, 16, 21, 26]
    # (the config's dictionary only builds cv_board(); ids and geometry are what the solve uses)
    board = BoardConfig(
        name="gb",
        kind="grid",
        cols=5,
        rows=7,
        marker_length_m=0.04,
        separation_m=0.01,
        first_id=0,
        dictionary="DICT_6X6_250",
    )
    solved = BoardSolver(board).solve(np.ravel(ids), np.asarray(corners).reshape(-1, 4, 2), camera)
    assert isinstance(solved, BoardPose), solved
    assert solved.best.reproj_px < 2.0
    assert len(solved.markers_used) >= 2 and set(solved.markers_used) | set(solved.outlier_ids) == {1, 16, 21, 26}
    assert 0.3 < solved.best.pose.tvec[2] < 1.0
    # and it is about where OpenCV's own solve over all four markers puts the board
    grid = cv2.aruco.GridBoard((5, 7), 0.04, 0.01, dictionary)
    object_points, image_points = grid.matchImagePoints(corners, ids)
    ok, rvec, tvec = cv2.solvePnP(object_points, image_points, camera.camera_matrix, camera.dist_coeffs)
    assert ok
    rotation_error, translation_error = pose_errors(solved.best.pose, Pose(rvec.ravel(), tvec.ravel()))
    assert rotation_error < 3.0 and translation_error < 0.03


@realdata_only
@pytest.mark.parametrize(("name", "min_markers"), [("choriginal.jpg", 17), ("chocclusion_original.jpg", 13)])
def test_charuco_photos_solve_from_chessboard_corners(realdata, name, min_markers):
    folder = realdata / "opencv_contrib"
    image = cv2.imread(str(folder / name))
    camera = CameraModel.from_yaml(folder / "tutorial_camera_charuco.yml")
    board = BoardConfig(
        name="ch",
        kind="charuco",
        cols=5,
        rows=7,
        square_length_m=0.04,
        marker_length_m=0.02,
        dictionary="DICT_6X6_250",
    )
    detections = Detector(DetectorConfig(dictionary="DICT_6X6_250")).detect(image)
    assert len(detections) >= min_markers
    solver = BoardSolver(board)
    solved = solver.solve(detections.ids, detections.corners, camera, image=image)
    assert isinstance(solved, BoardPose), solved
    assert solved.solver == "charuco"
    assert solved.best.reproj_px < 1.0
    assert len(solved.markers_used) >= min_markers - 1
    assert solved.inliers >= 6
    # the inlier points are chessboard corners (z = 0 on the square grid), not marker corners
    np.testing.assert_allclose(solved.points_in_target[:, 2], 0.0)
    np.testing.assert_allclose(
        np.round(solved.points_in_target[:, :2] / 0.04) * 0.04, solved.points_in_target[:, :2], atol=1e-6
    )
    # and the marker-corner solution (no image) agrees with it
    from_markers = solver.solve(detections.ids, detections.corners, camera)
    assert isinstance(from_markers, BoardPose) and from_markers.solver == "markers"
    rotation_error, translation_error = pose_errors(from_markers.best.pose, solved.best.pose)
    assert rotation_error < 2.0 and translation_error < 0.005


# ============================================================================ coincident markers (issue 34)


def _shifted(corners, dx: float = 0.0, dy: float = 0.0):
    return [[x + dx, y + dy, z] for x, y, z in corners]


@pytest.mark.parametrize("form", ["toml", "aruco-yaml"])
def test_a_layout_with_two_markers_at_the_same_place_is_refused_naming_file_and_markers(tmp_path, form):
    """Two markers at one place made a board `tracked` whose pose jumped 8 cm a frame: refused at load."""
    markers = {3: SQUARE, 4: _shifted(SQUARE, 0.1), 9: _shifted(SQUARE, 0.01)}  # 9: 10 mm from 3, both 50 mm
    if form == "toml":
        text = "".join(f"[[markers]]\nid = {i}\ncorners = {toml_corners(c)}\n" for i, c in markers.items())
        name = "layout.toml"
    else:
        text, name = aruco_marker_map(markers), "layout.yml"
    layout = write(tmp_path / name, text)
    path = write(tmp_path / "c.toml", f"[[boards]]\nname = 'b'\nkind = 'custom'\nlayout = '{name}'\n")
    assert_one_line_config_error(
        path,
        r"\[\[boards\]\] 'b' layout: layout file "
        + re.escape(str(layout))
        + r": markers 3 and 9 are at the same place \(centres 10\.0 mm apart, markers 50\.0 mm wide\)",
    )
    result = run_main(["-q", "demo", "--config", str(path), "--max-frames", "1", "--out", str(tmp_path / "o")])
    assert result.code == 2 and result.stderr.count("\n") == 1, result.describe()
    assert "markers 3 and 9 are at the same place" in result.stderr and str(layout) in result.stderr
    assert not (tmp_path / "o").exists()


def test_inline_markers_at_the_same_place_are_refused_and_a_cube_is_not():
    same = {"markers": [{"id": 1, "corners": SQUARE}, {"id": 2, "corners": _shifted(SQUARE, 0.0, 0.0)}]}
    with pytest.raises(ConfigError, match="inline markers: markers 1 and 2 are at the same place"):
        layout_from_mapping(same, "inline markers")
    # a cube's faces: markers on adjacent faces are 0.7 of a side apart, on one edge: accepted
    s = 0.05
    cube = {
        "markers": [
            {"id": 1, "corners": [[0, 0, 0], [s, 0, 0], [s, s, 0], [0, s, 0]]},
            {"id": 2, "corners": [[0, 0, 0], [0, s, 0], [0, s, s], [0, 0, s]]},
            {"id": 3, "corners": [[0, 0, 0], [0, 0, s], [s, 0, s], [s, 0, 0]]},
        ]
    }
    assert len(layout_from_mapping(cube, "cube")) == 3
