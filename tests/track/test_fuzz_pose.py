"""Property tests of the pose layer fed random, degenerate and adversarial corner sets.

``solve_marker`` and ``BoardSolver.solve`` get collinear, coincident, self-intersecting, mirrored,
tiny, huge, NaN/inf, out-of-image and wrongly shaped corners, near-degenerate projections (grazing
views, sub-pixel quads), wrong ids and duplicate ids, through cameras with and without strong lens
distortion. The outcome is always a typed failure (``PoseFailure`` with a reason, or ``None`` for a
board none of whose markers was seen) or poses that pass validation: finite rvec/tvec, |rvec| <= pi,
every target point in front of the camera (z > 0), the printed side facing the camera, and a
finite reprojection error within the limit that is the real one. Never an exception or a hang.

Budgets: tests/helpers.py (CI: the counts below; ``HYPOTHESIS_PROFILE=long``: 20x).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ar_anchor.camera import CameraModel
from ar_anchor.config import BoardConfig
from ar_anchor.geometry import Pose, marker_corners_in_marker, matrix_from_rvec
from ar_anchor.track.pose import (
    BoardPose,
    BoardSolver,
    MarkerPose,
    PoseFailure,
    _quad_problem,
    check_pose,
    reprojection_rms,
    solve_marker,
)
from tests.helpers import fuzz_settings, outcome, time_limit

pytestmark = pytest.mark.slow  # fuzzing and end-to-end CLI runs: the full suite, not the fast tier

EPS = 1e-9
PER_CALL_S = 20.0

# ============================================================================ cameras

DIST_LENGTHS = st.sampled_from([0, 4, 5, 8, 12, 14])


@st.composite
def cameras(draw) -> CameraModel:
    """Valid cameras: any focal length and principal point a calibration could produce, with no, mild,
    strong or absurd distortion."""
    width = draw(st.sampled_from([64, 320, 640, 1280, 4000]))
    height = draw(st.sampled_from([48, 240, 480, 720, 3000]))
    fx = draw(st.floats(20.0, 20_000.0))
    fy = fx * draw(st.floats(0.5, 2.0))
    cx = draw(st.floats(-0.5 * width, 1.5 * width))
    cy = draw(st.floats(-0.5 * height, 1.5 * height))
    skew = draw(st.sampled_from([0.0, 0.0, 0.0, 1.5, -40.0]))
    n = draw(DIST_LENGTHS)
    scale = draw(st.sampled_from([0.0, 0.01, 0.2, 1.0, 50.0]))
    dist = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=n, max_size=n))) * scale
    return CameraModel(np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), dist, width, height)


DEFAULT_CAMERA = CameraModel.default_synthetic()
ANY_CAMERA = st.one_of(st.just(DEFAULT_CAMERA), cameras())

# ============================================================================ corner sets

COORDINATE = st.one_of(
    st.floats(-2000, 3000, allow_nan=False),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e6, -1e6, 1e6 + 1, 1e300, -1e300, math.nan, math.inf, -math.inf]),
)
LENGTH = st.one_of(
    st.floats(0.001, 1.0),
    st.sampled_from([1e-9, 1e-6, 1e3, 1e6, 0.0, -0.05, math.nan, math.inf, -math.inf]),
)


def _square(cx: float, cy: float, side: float, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    unit = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) * side
    return unit @ np.array([[c, s], [-s, c]]) + [cx, cy]


@st.composite
def true_projection(draw, camera: CameraModel, length: float) -> np.ndarray:
    """Corners of a real marker pose: grazing angles, far or near, partly behind the camera, noisy."""
    tilt = draw(st.floats(0.0, 1.5707))  # up to 90 degrees from facing the camera
    axis = draw(st.floats(0.0, 2 * math.pi))
    spin = draw(st.floats(-math.pi, math.pi))
    facing = np.diag([1.0, -1.0, -1.0])
    rotation = (
        matrix_from_rvec(np.array([math.cos(axis), math.sin(axis), 0.0]) * tilt)
        @ facing
        @ matrix_from_rvec(np.array([0.0, 0.0, spin]))
    )
    z = draw(st.one_of(st.floats(length * 0.2, length * 500), st.sampled_from([length * 1e-3, -length, 0.0])))
    xy = draw(st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0))) if z > 0 else (0.0, 0.0)
    truth = Pose.from_matrix(rotation, np.array([xy[0] * z, xy[1] * z, z]))
    points = truth.apply(marker_corners_in_marker(length))
    if np.any(points[:, 2] <= 0):
        # behind the camera: the pinhole formula anyway (the "projection" a broken detector could give)
        k = camera.camera_matrix
        pixels = points[:, :2] / np.where(points[:, 2:] == 0, 1e-12, points[:, 2:]) * [k[0, 0], k[1, 1]] + k[:2, 2]
    else:
        pixels = camera.project(points)
    noise = draw(st.sampled_from([0.0, 0.0, 0.3, 2.0, 30.0]))
    return pixels + np.array(draw(st.lists(st.floats(-1, 1), min_size=8, max_size=8))).reshape(4, 2) * noise


@st.composite
def adversarial_corners(draw, camera: CameraModel, length: float) -> np.ndarray:
    kind = draw(
        st.sampled_from(
            [
                "random",
                "projection",
                "projection",
                "collinear",
                "near-collinear",
                "coincident",
                "three-coincident",
                "bow-tie",
                "mirrored",
                "concave",
                "tiny",
                "huge",
                "out-of-image",
                "one-bad-value",
                "rotated-order",
            ]
        )
    )
    outcome(f"corners: {kind}")
    cx, cy = draw(st.floats(-500, 2500)), draw(st.floats(-500, 1500))
    side = draw(st.floats(1.0, 400.0))
    square = _square(cx, cy, side, draw(st.floats(-math.pi, math.pi)))
    if kind == "random":
        return np.array(draw(st.lists(COORDINATE, min_size=8, max_size=8)), dtype=float).reshape(4, 2)
    if kind == "projection":
        return draw(true_projection(camera, length if math.isfinite(length) and length > 0 else 0.05))
    if kind == "collinear":
        t = np.sort(np.array(draw(st.lists(st.floats(-3, 3), min_size=4, max_size=4))))
        direction = np.array([math.cos(cx), math.sin(cx)])
        return np.array([cx, cy]) + t[:, None] * direction * side
    if kind == "near-collinear":
        square[:, 1] = cy + (square[:, 1] - cy) * draw(st.sampled_from([1e-3, 1e-6, 1e-9, 1e-12]))
        return square
    if kind == "coincident":
        return np.repeat(square[:1], 4, axis=0)
    if kind == "three-coincident":
        square[1:] = square[1]
        return square
    if kind == "bow-tie":
        return square[[0, 2, 1, 3]]
    if kind == "mirrored":
        return square[::-1]
    if kind == "concave":
        square[2] = (square[0] * draw(st.floats(0.5, 0.95)) + square[2] * 0.05) / draw(st.floats(0.55, 1.0))
        return square
    if kind == "tiny":
        return _square(cx, cy, draw(st.sampled_from([1e-6, 0.1, 0.9, 1.0, 1.01, 1.5])), 0.3)
    if kind == "huge":
        return _square(cx, cy, draw(st.sampled_from([1e4, 1e5, 9e5, 1.9e6, 1e9])), 0.2)
    if kind == "out-of-image":
        return square + draw(st.sampled_from([[-1e5, 0], [0, 9e5], [camera.width * 3, camera.height * 3]]))
    if kind == "one-bad-value":
        square[draw(st.integers(0, 3)), draw(st.integers(0, 1))] = draw(st.sampled_from([math.nan, math.inf, 1e300]))
        return square
    return np.roll(square, draw(st.integers(1, 3)), axis=0)


SHAPES = st.sampled_from(["(4,2)", "(4,2)", "(4,2)", "(1,4,2)", "(8,)", "float32", "int", "list", "(3,2)", "(5,2)"])


def reshape(corners: np.ndarray, form: str):
    if form == "(1,4,2)":
        return corners.reshape(1, 4, 2)
    if form == "(8,)":
        return corners.reshape(8)
    if form == "float32":
        with np.errstate(over="ignore", invalid="ignore"):
            return corners.astype(np.float32)
    if form == "int":
        finite = np.nan_to_num(corners, nan=0.0, posinf=2**31 - 1, neginf=-(2**31))
        return np.clip(finite, -(2**31), 2**31 - 1).astype(np.int32)
    if form == "list":
        return corners.tolist()
    if form == "(3,2)":
        return corners[:3]
    if form == "(5,2)":
        return np.concatenate([corners, corners[:1]])
    return corners


# ============================================================================ validation


def assert_valid_hypotheses(hypotheses, points_in_target, points_in_image, camera, max_reproj, *, front: bool):
    assert 1 <= len(hypotheses) <= 2
    errors = [h.reproj_px for h in hypotheses]
    assert errors == sorted(errors)
    for hypothesis in hypotheses:
        pose = hypothesis.pose
        assert pose.is_finite(), pose
        assert np.linalg.norm(pose.rvec) <= math.pi + EPS
        depth = pose.apply(points_in_target)[:, 2]
        assert np.all(depth > 0), f"target behind the camera: {depth}"
        if front:
            assert pose.camera_centre()[2] > 0, "marker seen from behind"
        assert math.isfinite(hypothesis.reproj_px) and 0 <= hypothesis.reproj_px <= max_reproj
        actual = reprojection_rms(pose, points_in_target, points_in_image, camera)
        assert actual == pytest.approx(hypothesis.reproj_px, rel=1e-6, abs=1e-9), "reported error is not the real one"
        # and check_pose itself agrees
        _error, reason = check_pose(pose, points_in_target, points_in_image, camera, max_reproj, require_front=front)
        assert reason is None, reason


def assert_marker_outcome(solved, corners, length, camera, max_reproj) -> None:
    if isinstance(solved, PoseFailure):
        assert isinstance(solved.reason, str) and solved.reason
        assert solved.target.startswith("marker:")
        outcome("failure")
        return
    assert isinstance(solved, MarkerPose), type(solved)
    outcome(f"pose ({solved.solver})")
    assert solved.length_m == length and math.isfinite(length) and length > 0
    image = np.asarray(solved.corners_in_image, np.float64)
    assert image.shape == (4, 2) and np.all(np.isfinite(image))
    np.testing.assert_array_equal(image, np.asarray(corners, np.float64).reshape(4, 2))
    assert _quad_problem(image) is None
    assert math.isnan(solved.ambiguity) or solved.ambiguity >= 1.0
    assert_valid_hypotheses(solved.hypotheses, marker_corners_in_marker(length), image, camera, max_reproj, front=True)


MAX_REPROJ = st.one_of(st.just(3.0), st.floats(0.01, 50.0))

# ============================================================================ solve_marker


@fuzz_settings(400)
@given(data=st.data(), camera=ANY_CAMERA, length=LENGTH, max_reproj=MAX_REPROJ, form=SHAPES)
def test_solve_marker_on_adversarial_corners_is_failure_or_valid(data, camera, length, max_reproj, form):
    corners = data.draw(adversarial_corners(camera, length))
    given_corners = reshape(corners, form)
    with time_limit(PER_CALL_S), np.errstate(all="ignore"):
        solved = solve_marker(7, given_corners, length, camera, max_reproj)
    assert_marker_outcome(solved, given_corners, length, camera, max_reproj)


@fuzz_settings(200)
@given(data=st.data(), camera=cameras(), length=st.floats(0.005, 0.5))
def test_solve_marker_on_real_projections_through_distorting_lenses(data, camera, length):
    # the common case, with every lens a calibration file can describe: a pose or a reasoned failure
    corners = data.draw(true_projection(camera, length))
    with time_limit(PER_CALL_S), np.errstate(all="ignore"):
        solved = solve_marker(3, corners, length, camera, 3.0)
    assert_marker_outcome(solved, corners, length, camera, 3.0)


@pytest.mark.parametrize(
    "corners",
    [
        pytest.param(np.zeros((0, 2)), id="empty"),
        pytest.param(np.full((4, 2), np.nan), id="all-nan"),
        pytest.param(np.array([[0, 0], [1e6, 0], [1e6, 1e6], [0, 1e6]], float), id="at-the-range-limit"),
        pytest.param(np.array([[0, 0], [2, 0], [2, 0.5], [0, 0.5]], float), id="area-exactly-1"),
        pytest.param(np.array([[600.0, 320.0], [680.0, 320.0], [680.0, 400.0], [600.0, 400.0]]) + 1e6 - 700, id="far"),
    ],
)
def test_solve_marker_on_odd_inputs(corners):
    solved = solve_marker(1, corners, 0.05, DEFAULT_CAMERA)
    assert_marker_outcome(solved, corners, 0.05, DEFAULT_CAMERA, 3.0)


# ============================================================================ boards


def _cube_layout() -> tuple:
    """Markers on three outward faces of a 10 cm cube (a non-planar custom board)."""
    length, m = 0.04, 0.005
    quads = []
    for origin, right, down in [
        ((0, 0, 0), (1, 0, 0), (0, 1, 0)),
        ((0, 0, 0.1), (0, 0, -1), (0, 1, 0)),
        ((0, 0, 0.1), (1, 0, 0), (0, 0, -1)),
    ]:
        o, r, d = (np.array(v, float) for v in (origin, right, down))
        tl = o + m * r + m * d
        quads.append(np.array([tl, tl + length * r, tl + length * (r + d), tl + length * d]))
    return tuple((20 + i, tuple(map(tuple, q))) for i, q in enumerate(quads))


BOARDS = {
    "grid": BoardConfig(name="g", cols=3, rows=2, marker_length_m=0.04, separation_m=0.01, first_id=0),
    "charuco": BoardConfig(
        name="c", kind="charuco", cols=4, rows=3, square_length_m=0.04, marker_length_m=0.03, first_id=10
    ),
    "cube": BoardConfig(name="k", kind="custom", layout=_cube_layout()),
    "single": BoardConfig(name="s", cols=1, rows=1, marker_length_m=0.05, first_id=40),
}
SOLVERS = {name: BoardSolver(board) for name, board in BOARDS.items()}


@st.composite
def board_detections(draw, name: str, camera: CameraModel):
    """ids and corners of one frame: a real view of the board, its markers kept, dropped, duplicated,
    swapped with other ids, or replaced by adversarial corners; or nothing like the board at all."""
    solver = SOLVERS[name]
    ids = list(solver.corners)
    tilt = draw(st.floats(0.0, 1.4))
    axis = draw(st.floats(0.0, 2 * math.pi))
    # board frames: z into the board, so a camera looking along +z sees the printed side; the cube's
    # other faces are seen from (-1, -1, -1)
    facing = matrix_from_rvec(np.array([-0.4636, 0.6155, 0.0])) if name == "cube" else np.eye(3)
    rotation = matrix_from_rvec(np.array([math.cos(axis), math.sin(axis), 0.0]) * tilt) @ facing
    distance = draw(st.one_of(st.floats(0.1, 5.0), st.sampled_from([1e-3, 50.0, -0.5])))
    centre = np.mean(np.concatenate(list(solver.corners.values())), axis=0)
    truth = Pose.from_matrix(rotation, np.array([0.0, 0.0, distance]) - rotation @ centre)
    out_ids, out_corners = [], []
    for marker_id in ids:
        action = draw(st.sampled_from(["keep", "keep", "keep", "drop", "duplicate", "wrong-id", "adversarial"]))
        quad = solver.corners[marker_id]
        normal = np.cross(quad[1] - quad[0], quad[0] - quad[3])
        if normal @ (truth.camera_centre() - quad.mean(axis=0)) <= 0 and action == "keep":
            action = draw(st.sampled_from(["drop", "keep"]))  # seen from behind: a detector cannot see it, mostly
        points = truth.apply(quad)
        if np.any(points[:, 2] <= 0):
            pixels = np.full((4, 2), draw(st.sampled_from([np.nan, -5.0, 1e7])))
        else:
            pixels = camera.project(points) + draw(st.sampled_from([0.0, 0.0, 0.5, 5.0])) * np.array(
                draw(st.lists(st.floats(-1, 1), min_size=8, max_size=8))
            ).reshape(4, 2)
        if action == "drop":
            continue
        if action == "wrong-id":
            marker_id = draw(st.sampled_from([*ids, 999, -1]))
        if action == "adversarial":
            pixels = draw(adversarial_corners(camera, 0.04))
        out_ids.append(marker_id)
        out_corners.append(pixels)
        if action == "duplicate":
            out_ids.append(marker_id)
            out_corners.append(pixels + draw(st.sampled_from([0.0, 3.0, 300.0])))
    if not out_ids:
        return np.zeros(0, np.int32), np.zeros((0, 4, 2))
    order = draw(st.permutations(range(len(out_ids))))
    return np.array(out_ids)[list(order)], np.array(out_corners, dtype=np.float64)[list(order)]


def assert_board_outcome(result, solver: BoardSolver, ids, corners, camera, max_reproj) -> None:
    if result is None:  # no marker of the board with a usable quad
        quads = np.asarray(corners, np.float64).reshape(-1, 4, 2)
        assert not any(
            int(i) in solver.corners and _quad_problem(q) is None for i, q in zip(np.asarray(ids).reshape(-1), quads)
        )
        outcome("none (no board marker)")
        return
    if isinstance(result, PoseFailure):
        assert result.reason and result.target == f"board:{solver.name}"
        outcome("failure")
        return
    assert isinstance(result, BoardPose), type(result)
    outcome(f"pose ({result.solver}, {len(result.hypotheses)} hypotheses)")
    assert set(result.markers_used) <= set(solver.corners)
    assert result.markers_used, "a pose from no marker"
    assert set(result.outlier_ids) <= {int(i) for i in np.asarray(ids).reshape(-1)}
    points_obj, points_img = result.points_in_target, result.points_in_image
    assert len(points_obj) == len(points_img) >= 4
    assert np.all(np.isfinite(points_obj)) and np.all(np.isfinite(points_img))
    assert math.isnan(result.ambiguity) or result.ambiguity >= 1.0
    assert_valid_hypotheses(result.hypotheses, points_obj, points_img, camera, max_reproj, front=False)


@fuzz_settings(60)
@given(data=st.data(), name=st.sampled_from(sorted(BOARDS)), camera=ANY_CAMERA, with_image=st.booleans())
def test_board_solver_on_adversarial_detections_is_failure_or_valid(data, name, camera, with_image):
    ids, corners = data.draw(board_detections(name, camera))
    image = np.full((camera.height, camera.width, 3), 128, np.uint8) if with_image else None
    with time_limit(PER_CALL_S), np.errstate(all="ignore"):
        result = SOLVERS[name].solve(ids, corners, camera, 3.0, image=image)
    assert_board_outcome(result, SOLVERS[name], ids, corners, camera, 3.0)


@fuzz_settings(60)
@given(
    name=st.sampled_from(sorted(BOARDS)),
    ids=st.lists(st.sampled_from([0, 1, 2, 3, 10, 11, 20, 21, 22, 40, 999]), min_size=0, max_size=6),
    values=st.lists(COORDINATE, min_size=48, max_size=48),
)
def test_board_solver_on_random_corners_is_failure_or_valid(name, ids, values):
    corners = np.array(values, dtype=np.float64).reshape(6, 4, 2)[: len(ids)]
    with time_limit(PER_CALL_S), np.errstate(all="ignore"):
        result = SOLVERS[name].solve(np.array(ids, dtype=np.int64), corners, DEFAULT_CAMERA, 3.0)
    assert_board_outcome(result, SOLVERS[name], ids, corners, DEFAULT_CAMERA, 3.0)


VECTOR = st.lists(
    st.one_of(st.floats(-10, 10), st.sampled_from([0.0, math.pi, -math.pi, 1e-300, 1e300, math.nan, math.inf])),
    min_size=3,
    max_size=3,
)


@fuzz_settings(200)
@given(rvec=VECTOR, tvec=VECTOR, corners=st.lists(COORDINATE, min_size=8, max_size=8), camera=ANY_CAMERA)
def test_check_pose_passes_only_valid_poses(rvec, tvec, corners, camera):
    pose = Pose(np.array(rvec), np.array(tvec))
    points = marker_corners_in_marker(0.05)
    image = np.array(corners, dtype=np.float64).reshape(4, 2)
    with time_limit(PER_CALL_S), np.errstate(all="ignore"):
        error, reason = check_pose(pose, points, image, camera, 3.0)
    if reason is not None:
        assert isinstance(reason, str) and reason
        outcome("rejected")
        return
    outcome("accepted")
    assert pose.is_finite() and np.linalg.norm(pose.rvec) <= math.pi + EPS
    assert np.all(pose.apply(points)[:, 2] > 0) and pose.camera_centre()[2] > 0
    assert math.isfinite(error) and 0 <= error <= 3.0


def test_solve_marker_keeps_at_most_two_hypotheses():
    # found by the long run: a valid camera (principal point at the image corner, a little tangential
    # distortion) and a marker far outside its 64x48 image; IPPE_SQUARE misses (22 px), SQPNP returns three
    camera = CameraModel(np.diag([2099.0, 4198.0, 1.0]), np.array([0.0, 0.0, 0.0, 0.0025]), 64, 48)
    corners = np.array(
        [
            [1045.17523239, -16.43911331],
            [1061.69665817, -16.43975388],
            [1061.69665817, 16.43975388],
            [1045.17523239, 16.43911331],
        ]  # fmt: skip
    )
    solved = solve_marker(3, corners, 0.0078125, camera, 3.0)
    assert_marker_outcome(solved, corners, 0.0078125, camera, 3.0)
