"""``ar-anchor calibrate``: ChArUco calibration recovers a known camera from rendered views, agrees
with OpenCV's own calibration of its tutorial photos, rejects blurry, duplicate and outlier views,
and fails with one-line typed errors.

The synthetic views are rendered exactly: the board image (``CharucoBoard.generateImage`` at 12
px/mm) is mapped through the homography ``K [r1 r2 t]`` into the ideal pinhole image (3x
supersampled, then area-averaged; pixel centres at integer coordinates), and the lens distortion is
applied by resampling that pinhole canvas at each output pixel's undistorted position
(``ar_anchor.synthetic.pinhole_canvas``), so corners land where ``projectPoints`` puts them.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.errors import InputError, OutputError, SourceError
from ar_anchor.sources.live import Captured
from ar_anchor.synthetic import pinhole_canvas
from ar_anchor.tools.calibrate import (
    CharucoSpec,
    View,
    ViewDetector,
    calibrate_source,
    calibrate_views,
    coverage_of,
    edge_width_px,
    format_report,
    select_views,
)
from tests.helpers import run_main

RERUN = Path(sys.executable).with_name("rerun")
TIMEOUT_S = 60

# the camera to recover: off-centre principal point, barrel distortion, slight decentring
WIDTH, HEIGHT = 1280, 720
TRUE_K = np.array([[905.0, 0.0, 643.5], [0.0, 902.0, 356.0], [0.0, 0.0, 1.0]])
TRUE_DIST = np.array([-0.2, 0.05, 0.001, -0.0015, 0.0])

# the board: 9x6 squares of 30 mm, 22 mm DICT_6X6_250 markers (40 chessboard corners)
COLS, ROWS, SQUARE_M, MARKER_M, DICTIONARY = 9, 6, 0.03, 0.022, "DICT_6X6_250"
BOARD_ARGS = ["--charuco", f"{COLS}x{ROWS}", "--square-m", str(SQUARE_M), "--marker-m", str(MARKER_M)]
BOARD_ARGS += ["--dictionary", DICTIONARY]
TEXELS_PER_M = 12000.0  # 12 px/mm
PAPER_MARGIN_M = 0.01
SUPERSAMPLE = 3
VIEWS = 18
RESAMPLES = 10  # bootstrap calibrations where a test checks the calibration, not its uncertainty (default: 100)


def spec() -> CharucoSpec:
    return CharucoSpec.parse(f"{COLS}x{ROWS}", SQUARE_M, MARKER_M, DICTIONARY)


def _rotation(axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    vector = np.asarray(axis, np.float64)
    return cv2.Rodrigues(vector / np.linalg.norm(vector) * math.radians(degrees))[0]


class BoardRenderer:
    """Renders the board seen by the true (distorted) camera; board frame: OpenCV's (origin at the
    chessboard's top-left corner, x right, y down, z into the board)."""

    def __init__(self, camera: CameraModel | None = None) -> None:
        self.camera = camera or CameraModel(TRUE_K, TRUE_DIST, WIDTH, HEIGHT)
        self.pinhole, self.maps = pinhole_canvas(self.camera)
        assert self.maps is not None
        board = spec().build()
        square_px = round(SQUARE_M * TEXELS_PER_M)
        margin = round(PAPER_MARGIN_M * TEXELS_PER_M)
        size = (COLS * square_px + 2 * margin, ROWS * square_px + 2 * margin)
        texture = board.generateImage(size, marginSize=margin, borderBits=1)
        self.texture = (20.0 + texture.astype(np.float32) * (220.0 / 255.0)).astype(np.float32)  # ink, paper
        self.coverage = np.ones(texture.shape, np.float32)
        # board plane (metres) from texel: texel i covers [i - 0.5, i + 0.5]; the board starts at texel edge `margin`
        s = 1.0 / TEXELS_PER_M
        self.plane_from_texel = np.array([[s, 0, (0.5 - margin) * s], [0, s, (0.5 - margin) * s], [0, 0, 1.0]])

    def render(self, rotation: np.ndarray, tvec: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        width, height = self.pinhole.size
        ss = SUPERSAMPLE
        hires_from_image = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
        image_from_plane = self.pinhole.camera_matrix @ np.column_stack([rotation[:, 0], rotation[:, 1], tvec])
        homography = hires_from_image @ image_from_plane @ self.plane_from_texel
        size = (width * ss, height * ss)
        paper, cover = (
            cv2.resize(
                cv2.warpPerspective(layer, homography, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
                (width, height),
                interpolation=cv2.INTER_AREA,
            )
            for layer in (self.texture, self.coverage)
        )
        canvas = paper + (1.0 - cover) * 90.0  # a grey background around the paper
        image = cv2.remap(canvas, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        image = cv2.GaussianBlur(image, (0, 0), 0.5)
        image += rng.standard_normal(image.shape).astype(np.float32) * np.float32(1.5)
        return cv2.cvtColor(np.clip(image + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)

    def outline(self, rotation: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        w, h = COLS * SQUARE_M, ROWS * SQUARE_M
        corners = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], np.float64)
        k, dist = self.camera.camera_matrix, self.camera.dist_coeffs
        pixels, _ = cv2.projectPoints(corners, cv2.Rodrigues(rotation)[0], tvec, k, dist)
        return pixels.reshape(-1, 2)


def board_poses(renderer: BoardRenderer, count: int, seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Varied poses: tilted 20-50 degrees about a random in-plane axis, rolled up to 30 degrees, centred
    around ten image positions (centre, the corners, the sides), as large as fits in the image."""
    rng = np.random.default_rng(seed)
    width, height = renderer.camera.size
    anchors = [(0.5, 0.5)] + [(x, y) for y in (0.22, 0.5, 0.78) for x in (0.2, 0.5, 0.8)]
    centre_in_board = np.array([COLS * SQUARE_M / 2, ROWS * SQUARE_M / 2, 0.0])
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    attempt = 0
    while len(poses) < count:
        ax, ay = anchors[attempt % len(anchors)]
        attempt += 1
        u, v = ax * width + rng.uniform(-40, 40) * width / WIDTH, ay * height + rng.uniform(-30, 30) * height / HEIGHT
        azimuth = rng.uniform(0.0, 2 * math.pi)
        rotation = _rotation((math.cos(azimuth), math.sin(azimuth), 0.0), rng.uniform(20, 50))
        rotation = rotation @ _rotation((0, 0, 1), rng.uniform(-30, 30))
        ray = np.linalg.solve(renderer.camera.camera_matrix, [u, v, 1.0])
        for depth in np.linspace(0.25, 0.6, 15):  # nearest (largest) first
            tvec = depth * ray - rotation @ centre_in_board
            box = renderer.outline(rotation, tvec)
            if (
                box[:, 0].min() > 10
                and box[:, 0].max() < width - 10
                and box[:, 1].min() > 10
                and box[:, 1].max() < height - 10
            ):
                poses.append((rotation, tvec))
                break
    return poses


# views_dir (the 18 rendered views, read-only) and six_view_report: tests/tools/conftest.py, shared with
# test_tool_outputs_hostile.py


@pytest.fixture(scope="module")
def detected(views_dir: Path) -> list[View]:
    detector = ViewDetector(spec())
    views = []
    for path in sorted(views_dir.glob("*.png")):
        found = detector.detect(cv2.imread(str(path)), path.name, len(views))
        assert isinstance(found, View), found
        views.append(found)
    return views


def copy_views(views_dir: Path, target: Path, count: int) -> Path:
    target.mkdir(parents=True, exist_ok=True)
    for path in sorted(views_dir.glob("*.png"))[:count]:
        shutil.copy(path, target / path.name)
    return target


def run_process(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``ar-anchor calibrate ARGS`` as its own process, in ``cwd`` (the end-to-end test)."""
    return subprocess.run(
        [sys.executable, "-m", "ar_anchor", "calibrate", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )


def run_cli(args: list[str], cwd: Path, command: str = "calibrate") -> subprocess.CompletedProcess[str]:
    """``ar-anchor calibrate ARGS`` run in-process in ``cwd`` (``tests.helpers.run_main``: the same ``main()``, its
    stdout and stderr captured; stderr is no terminal, as when piped): what it prints, writes and exits with is
    what these tests check, not the process (test_cli_writes_a_camera_file_and_a_recording runs a real one)."""
    result = run_main([command, *args], cwd)
    return subprocess.CompletedProcess([command, *args], result.code, result.stdout, result.stderr)


# ======================================================================== round trip


@pytest.mark.slow
def test_round_trip_recovers_the_rendered_camera(views_dir):
    # given 18 rendered views of a camera with known intrinsics and distortion
    # when they are calibrated through the folder path the CLI uses (its uncertainty: test_calibrate_uncertainty)
    report = calibrate_source(str(views_dir), spec(), max_views=40, min_views=6, resamples=RESAMPLES)
    # then every view is used, fx fy cx cy are within 0.5 % and the RMS is sub-0.3 px
    assert report.considered == VIEWS and len(report.views) == VIEWS and not report.all_rejections
    k = report.camera.camera_matrix
    for name, got, want in (
        ("fx", k[0, 0], TRUE_K[0, 0]),
        ("fy", k[1, 1], TRUE_K[1, 1]),
        ("cx", k[0, 2], TRUE_K[0, 2]),
        ("cy", k[1, 2], TRUE_K[1, 2]),
    ):
        assert abs(got / want - 1) < 0.005, f"{name} {got:.2f} vs {want:.2f}"
    assert report.result.rms < 0.3
    assert report.camera.size == (WIDTH, HEIGHT)
    # and the distortion is recovered too (k1, k2 to a few hundredths)
    assert abs(report.camera.dist_coeffs[0] - TRUE_DIST[0]) < 0.02
    assert abs(report.camera.dist_coeffs[1] - TRUE_DIST[1]) < 0.05
    assert report.coverage.fraction >= 0.75
    assert report.result.model == "k1 k2 p1 p2 k3"
    # and the undistorted corners are straight: projecting with the recovered model matches the truth
    grid = np.stack(np.meshgrid(np.linspace(0, WIDTH - 1, 9), np.linspace(0, HEIGHT - 1, 5)), -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    ideal_true = cv2.undistortPoints(grid, TRUE_K, TRUE_DIST, R=None, P=TRUE_K, criteria=criteria)
    ideal_got = cv2.undistortPoints(grid, k, report.camera.dist_coeffs, R=None, P=TRUE_K, criteria=criteria)
    assert np.abs(ideal_true - ideal_got).max() < 2.0


# ======================================================================== real photos


@pytest.mark.realdata
def test_opencv_tutorial_views_match_opencvs_calibration(realdata):
    # given OpenCV's four ChArUco calibration photos and the calibration OpenCV made of them
    folder = realdata / "opencv_contrib"
    storage = cv2.FileStorage(str(folder / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ)
    reference = storage.getNode("camera_matrix").mat()
    storage.release()
    board = CharucoSpec.parse("5x7", 0.04, 0.02, "DICT_6X6_250")
    # when they are calibrated (4 views: --min-views 4)
    report = calibrate_source(str(folder / "img_0[0-3].jpg"), board, min_views=4, resamples=RESAMPLES)
    # then fx and fy agree within 2 % (measured: 457.3 / 461.3 vs 452.5 / 456.8, about 1 %)
    assert len(report.views) == 4
    k = report.camera.camera_matrix
    assert abs(k[0, 0] / reference[0, 0] - 1) < 0.02, (k[0, 0], reference[0, 0])
    assert abs(k[1, 1] / reference[1, 1] - 1) < 0.02, (k[1, 1], reference[1, 1])
    assert report.result.rms < 0.5
    # and the report is honest about four near-central views: poor coverage, loosely constrained focal length
    assert any("cover only" in w for w in report.warnings)
    assert any("focal length poorly constrained" in w for w in report.warnings)
    # the legacy flag does not matter for this board: it changes the pattern only when rows are even (7 is odd)
    legacy = calibrate_source(
        str(folder / "img_0[0-3].jpg"),
        CharucoSpec.parse("5x7", 0.04, 0.02, "DICT_6X6_250", legacy=True),
        min_views=4,
        resamples=RESAMPLES,
    )
    assert [v.count for v in legacy.views] == [v.count for v in report.views]


# ======================================================================== CLI end to end


@pytest.mark.slow
def test_cli_writes_a_camera_file_and_a_recording(views_dir, tmp_path):
    folder = copy_views(views_dir, tmp_path / "shots", 10)
    result = run_process([str(folder), *BOARD_ARGS, "--out", "calib/camera.yml"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    out = tmp_path / "calib" / "camera.yml"
    camera = CameraModel.from_yaml(out)
    assert camera.size == (WIDTH, HEIGHT)
    assert abs(camera.camera_matrix[0, 0] / TRUE_K[0, 0] - 1) < 0.01
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    try:
        assert 0 < storage.getNode("rms").real() < 0.3
        assert storage.getNode("date").string()[:2] == "20"
        assert storage.getNode("board").string() == "charuco 9x6 square 0.03 marker 0.022 DICT_6X6_250 legacy=false"
        assert int(storage.getNode("views").real()) == 10
        # the uncertainty: one standard deviation of fx fy cx cy k1 k2 p1 p2 k3, and how it was estimated
        std = storage.getNode("std_intrinsics").mat().reshape(-1)
        assert std.shape == (9,) and np.all(np.isfinite(std)) and np.all(std > 0)
        assert std[0] < 0.01 * camera.camera_matrix[0, 0]
        assert "resampled views (of 10)" in storage.getNode("std_intrinsics_method").string()
        assert storage.getNode("std_intrinsics_unreliable").empty()
    finally:
        storage.release()
    assert not list(out.parent.glob(".*tmp*")), "temporary file left behind"
    # the report: counts, intrinsics, distortion, RMS, per-view errors, coverage heat map
    for text in ("10 view(s) considered, 10 used", "fx ", "k1 ", "+- is one standard deviation", "RMS ", "coverage "):
        assert text in result.stdout
    rrd = tmp_path / "calib" / "camera.rrd"
    assert rrd.is_file() and rrd.stat().st_size > 0
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found: recording not verified")
    verify = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0, verify.stderr


def test_each_quality_warning_is_said_once(views_dir, tmp_path):
    """Found by trying the tool as a new user: every warning was printed twice, logged and again in the report."""
    folder = copy_views(views_dir, tmp_path / "shots", 4)
    args = [str(folder), *BOARD_ARGS, "--min-views", "4"]
    result = run_cli([*args, "--out", "calib/camera.yml"], tmp_path)
    assert result.returncode == 0, result.stderr
    warned = [line.removeprefix("warning: ") for line in result.stdout.splitlines() if line.startswith("warning: ")]
    assert warned and "uncertainty (+-) is itself unreliable" in " ".join(warned), result.stdout
    assert not any(warning in result.stderr for warning in warned), result.stderr
    # with -q (no report) they are said on stderr, once each
    quiet = run_main(["-q", "calibrate", *args, "--out", "calib/quiet.yml"], tmp_path)
    assert quiet.code == 0, quiet.describe()
    assert all(quiet.stderr.count(warning) == 1 for warning in warned), quiet.stderr


@pytest.mark.slow
def test_progress_ends_at_the_count_the_summary_gives(views_dir, tmp_path):
    # given 8 views as image files, and as a video showing each of them for 3 frames
    folder = copy_views(views_dir, tmp_path / "shots", 8)
    video = tmp_path / "shots.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (WIDTH, HEIGHT))
    for path in sorted(folder.glob("*.png")):
        for _ in range(3):
            writer.write(cv2.imread(str(path)))
    writer.release()
    for source, frames in ((folder, 8), (video, 24)):
        # when each is calibrated with its output piped (not a terminal)
        result = run_cli([str(source), *BOARD_ARGS, "--out", f"{source.stem}/camera.yml"], tmp_path)
        assert result.returncode == 0, result.stderr
        # then the last progress line counts the frames the summary counts
        counts = re.findall(r"^ar-anchor: considered (?:all )?(\d+)", result.stderr, re.MULTILINE)
        summary = re.search(r"(\d+) view\(s\) considered", result.stdout)
        assert counts and summary, (result.stderr, result.stdout)
        assert int(counts[-1]) == int(summary.group(1)) == frames, (counts, summary.group(0))
        # and the uncertainty's last progress line counts the calibrations the report used
        runs = re.findall(r"^ar-anchor: uncertainty: (\d+)/(\d+)", result.stderr, re.MULTILINE)
        used = re.search(r"spread over (\d+) calibrations on resampled views \(of 8,", result.stdout)
        assert runs and used, (result.stderr, result.stdout)
        assert runs[-1][0] == runs[-1][1] == used.group(1), (runs, used.group(0))


# ======================================================================== view selection


def test_blurry_and_duplicate_views_are_rejected_and_reported(views_dir, detected, tmp_path):
    # given 8 views, a blurred copy of the view with the largest board, and an exact copy of another
    folder = copy_views(views_dir, tmp_path / "shots", 8)
    largest = max(detected[:8], key=lambda v: cv2.contourArea(cv2.convexHull(v.corners.astype(np.float32))))
    blurred = cv2.GaussianBlur(cv2.imread(str(folder / largest.name)), (0, 0), 2.5)
    assert cv2.imwrite(str(folder / "z_blurred.png"), blurred)
    assert isinstance(ViewDetector(spec()).detect(blurred, "z_blurred.png", 0), View)  # still detected
    shutil.copy(folder / "view_03.png", folder / "z_copy.png")
    # when the folder is calibrated
    report = calibrate_source(str(folder), spec(), min_views=6, resamples=RESAMPLES)
    # then the blurred copy is rejected as blurry, the copy as a duplicate, and the rest are used
    assert [r.name for r in report.rejected("blur")] == ["z_blurred.png"]
    duplicates = report.rejected("duplicate")
    assert [r.name for r in duplicates] == ["z_copy.png"] and "view_03.png" in duplicates[0].detail
    assert len(report.views) == 8 and report.considered == 10
    text = format_report(report)
    assert "2 rejected (1 blurry, 1 duplicate)" in text
    assert "z_blurred.png: blurry" in text and "z_copy.png: duplicate" in text


def test_edge_width_measures_blur_and_ignores_board_scale(views_dir, detected):
    image = cv2.imread(str(views_dir / detected[0].name), cv2.IMREAD_GRAYSCALE)
    view = detected[0]

    def width(img: np.ndarray) -> float:
        return edge_width_px(img, view.corners, view.ids, COLS)

    sharp = width(image)
    assert 0.6 < sharp < 1.3
    widths = [width(cv2.GaussianBlur(image, (0, 0), sigma)) for sigma in (1.0, 2.0, 3.0)]
    assert sharp < widths[0] < widths[1] < widths[2]
    assert abs(widths[2] - 3.0) < 0.6
    # motion blur along either board axis counts, though edges across it stay sharp
    kernel = np.zeros((9, 9), np.float32)
    kernel[4, :] = 1 / 9
    assert width(cv2.filter2D(image, -1, kernel)) > 2.0
    assert width(cv2.filter2D(image, -1, kernel.T)) > 2.0
    # every sharp view measures alike, whatever the board's size in the image
    all_widths = [v.edge_width_px for v in detected]
    assert max(all_widths) < 1.4 and max(all_widths) / min(all_widths) < 1.4


def test_selection_prefers_views_that_add_coverage(detected):
    size = (WIDTH, HEIGHT)
    kept, rejected = select_views(detected, size, max_views=6)
    assert len(kept) == 6 and len(rejected) == VIEWS - 6
    assert {r.reason for r in rejected} == {"surplus"}
    assert coverage_of(kept, size).fraction > coverage_of(detected[:6], size).fraction


def test_outlier_views_are_dropped_then_recalibrated(detected):
    views = list(detected[:12])
    rng = np.random.default_rng(3)
    bad = views[4]
    views[4] = View(bad.name, bad.frame, bad.corners + rng.normal(0, 3.0, bad.corners.shape), bad.ids, 1.0)
    result = calibrate_views(spec(), views, (WIDTH, HEIGHT), min_views=6)
    assert [d.name for d in result.dropped] == [bad.name] and result.dropped[0].reason == "outlier"
    assert len(result.views) == 11 and result.rms < 0.3 < result.first_rms
    assert abs(result.camera.camera_matrix[0, 0] / TRUE_K[0, 0] - 1) < 0.01
    # never below --min-views: with 12 views required, the outlier stays
    kept = calibrate_views(spec(), views, (WIDTH, HEIGHT), min_views=12)
    assert not kept.dropped and len(kept.views) == 12


def test_k3_is_fixed_only_when_the_radial_model_folds_inside_the_image():
    from ar_anchor.tools.calibrate.solve import radial_folds

    assert not radial_folds(TRUE_K, TRUE_DIST, (WIDTH, HEIGHT))
    # OpenCV's calibration of its tutorial webcam: large k2, k3, still monotonic over the image
    assert not radial_folds(
        np.array([[452.5, 0, 317.7], [0, 456.8, 277.8], [0, 0, 1]]), np.array([0.12, -1.09, 0, 0, 2.95]), (640, 480)
    )
    # r (1 - 0.9 r^2) peaks at r = 0.61, below the corners' radius 0.82: the model folds
    assert radial_folds(TRUE_K, np.array([-0.9, 0.0, 0.0, 0.0, 0.0]), (WIDTH, HEIGHT))


def test_coverage_warns_about_a_central_cluster():
    centre = np.stack(np.meshgrid(np.linspace(500, 780, 6), np.linspace(280, 440, 5)), -1).reshape(-1, 2)
    central = coverage_of([View("a", 0, centre, np.arange(30), 1.0)], (WIDTH, HEIGHT))
    assert central.fraction < 0.5
    assert any("cover only" in w for w in central.warnings)
    assert any("outer third" in w and "left" in w and "bottom" in w for w in central.warnings)
    # 20 of 48 cells, reaching every outer third but no edge cell
    middle = np.stack(np.meshgrid(np.linspace(170, 950, 12), np.linspace(130, 500, 8)), -1).reshape(-1, 2)
    wide = coverage_of([View("m", 0, middle, np.arange(len(middle)), 1.0)], (WIDTH, HEIGHT))
    assert wide.fraction == pytest.approx(20 / 48)
    assert any("cover only 42%" in w for w in wide.warnings)
    assert not any("outer third" in w for w in wide.warnings)
    assert any("never reach the left, right, top, bottom edge cells" in w for w in wide.warnings)
    full = np.stack(np.meshgrid(np.linspace(5, WIDTH - 5, 16), np.linspace(5, HEIGHT - 5, 12)), -1).reshape(-1, 2)
    whole = coverage_of([View("b", 0, full, np.arange(len(full)), 1.0)], (WIDTH, HEIGHT))
    assert whole.fraction == 1.0 and not whole.warnings
    assert "@@" in whole.heat_map() and whole.heat_map().count("\n") == 7


class FakeCamera:
    """A device stand-in for LiveSource: the rendered views in turn, 8 frames each, at 100 frames a second."""

    name = "fake0"

    def __init__(self, images: list[np.ndarray]) -> None:
        self.images = images
        self.index = 0
        self.lock = threading.Lock()

    def open(self) -> tuple[int, int]:
        return WIDTH, HEIGHT

    def read(self) -> Captured:
        time.sleep(0.01)
        with self.lock:
            index = self.index
            self.index += 1
        return Captured(self.images[(index // 8) % len(self.images)], (index + 1) * 33_333_333)

    def close(self) -> None:
        pass


def test_device_capture_keeps_distinct_views_until_max_views(views_dir):
    images = [cv2.imread(str(p)) for p in sorted(views_dir.glob("*.png"))]
    messages: list[str] = []
    started = time.monotonic()
    report = calibrate_source(
        "fake0",
        spec(),
        max_views=6,
        min_views=6,
        duration_s=30,
        grabber=FakeCamera(images),
        progress=messages.append,
        resamples=RESAMPLES,
    )
    assert time.monotonic() - started < 20
    assert len(report.views) == 6
    assert sum("kept" in m for m in messages) == 6
    # the capture's last line counts the frames the report counts
    assert [m for m in messages if m.startswith("capture ended")] == [
        f"capture ended: {report.considered} frames considered, 6/6 views"
    ]
    frames = [v.frame for v in report.views]
    assert all(b - a >= 15 for a, b in zip(frames, frames[1:]))  # at least 0.5 s of capture time apart
    assert abs(report.camera.camera_matrix[0, 0] / TRUE_K[0, 0] - 1) < 0.02


# ======================================================================== errors


def test_no_board_and_too_few_views_are_input_errors(views_dir, tmp_path):
    with pytest.raises(InputError, match=r"no ChArUco board .* check --charuco/--dictionary/--legacy"):
        calibrate_source(
            str(copy_views(views_dir, tmp_path / "a", 2)), CharucoSpec.parse("9x6", 0.03, 0.022, "DICT_4X4_50")
        )
    with pytest.raises(InputError, match=r"only 3 usable view\(s\) of 3 considered .* --min-views is 6"):
        calibrate_source(str(copy_views(views_dir, tmp_path / "b", 3)), spec(), min_views=6)
    with pytest.raises(SourceError, match="nowhere"):
        calibrate_source(str(tmp_path / "nowhere"), spec())
    with pytest.raises(InputError, match="--marker-m"):
        CharucoSpec.parse("5x7", 0.04, 0.04, "DICT_6X6_250")
    with pytest.raises(InputError, match="--dictionary: DICT_4X4_50 has 50 markers"):
        CharucoSpec.parse("11x11", 0.04, 0.02, "DICT_4X4_50")
    with pytest.raises(InputError, match="--charuco"):
        CharucoSpec.parse("1x7", 0.04, 0.02, "DICT_6X6_250")


def test_unwritable_out_is_an_output_error_and_leaves_nothing(six_view_report, tmp_path):
    from ar_anchor.tools.calibrate import write_camera_yaml

    report = six_view_report  # calibrate_source of 6 rendered views (tests/tools/conftest.py)
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match="--out"):
        write_camera_yaml(blocker / "camera.yml", report)
    out = tmp_path / "ok" / "camera.yml"
    write_camera_yaml(out, report)
    assert CameraModel.from_yaml(out).size == (WIDTH, HEIGHT)
    assert [p.name for p in out.parent.iterdir()] == ["camera.yml"]


@pytest.fixture(scope="module")
def noise_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("noise")
    rng = np.random.default_rng(0)
    for index in range(3):
        image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 1.0)
        cv2.imwrite(str(folder / f"noise_{index}.png"), image)
    return folder


@pytest.mark.slow
@pytest.mark.parametrize(
    ("case", "code", "expected"),
    [
        ("no-board", 2, ["no ChArUco board", "noise", "check --charuco/--dictionary/--legacy"]),
        ("too-few", 2, ["only 3 usable view(s)", "--min-views is 6"]),
        ("missing", 2, ["missing_folder", "not found"]),
        ("bad-charuco", 2, ["--charuco", "5by7"]),
        ("marker-too-big", 2, ["--marker-m"]),
        ("bad-dictionary", 2, ["--dictionary", "DICT_5X5_51"]),
        ("out-unwritable", 1, ["--out"]),
    ],
)
def test_cli_errors_are_one_line_without_traceback(case, code, expected, views_dir, noise_dir, tmp_path):
    source, board = str(copy_views(views_dir, tmp_path / "few", 3)), list(BOARD_ARGS)
    out = "camera.yml"
    if case == "no-board":
        source = str(noise_dir)
    elif case == "missing":
        source = "missing_folder"
    elif case == "bad-charuco":
        board[1] = "5by7"
    elif case == "marker-too-big":
        board[5] = "0.03"
    elif case == "bad-dictionary":
        board[7] = "DICT_5X5_51"
    elif case == "out-unwritable":
        source = str(copy_views(views_dir, tmp_path / "six", 6))
        (tmp_path / "blocker").write_text("a file, not a folder")
        out = "blocker/camera.yml"
    result = run_cli([source, *board, "--out", out], tmp_path)
    assert result.returncode == code, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    errors = [line for line in result.stderr.splitlines() if line.startswith("ar-anchor: error:")]
    assert len(errors) == 1, result.stderr
    for text in expected:
        assert text in errors[0], errors[0]
    assert not (tmp_path / "camera.yml").exists() and not (tmp_path / "camera.rrd").exists()
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


# ======================================================================== --board FILE.toml


def _markers(args: list[str], cwd: Path) -> Path:
    """Run ``ar-anchor markers`` (in-process, as :func:`run_cli`) and return the board TOML it wrote beside the
    sheet."""
    result = run_cli(["-q", *args, "--out", "sheet"], cwd, command="markers")
    assert result.returncode == 0, result.stderr
    (toml,) = (cwd / "sheet").glob("*.toml")
    return toml


@pytest.mark.slow
def test_board_file_from_markers_gives_the_same_calibration_as_the_long_form(views_dir, tmp_path):
    # given the board of the rendered views printed by `ar-anchor markers` (9x6 squares, DICT_6X6_250, the views'
    # marker/square ratio; at 15/11 mm instead of 30/22 mm so that it fits on A4: the scale of the board does
    # not change the intrinsics) and the TOML it wrote beside the sheet
    toml = _markers(
        [
            "--board",
            "charuco",
            "--cols",
            "9",
            "--rows",
            "6",
            "--square-length",
            "15mm",
            "--marker-length",
            "11mm",
            "--dictionary",
            "6x6_250",
        ],
        tmp_path,
    )
    folder = copy_views(views_dir, tmp_path / "shots", 8)
    # when the views are calibrated with --board, and with the long form of the same board
    short = run_cli([str(folder), "--board", str(toml), "--out", "board.yml"], tmp_path)
    long_form = ["--charuco", "9x6", "--square-m", "0.015", "--marker-length", "11mm", "--dictionary", "DICT_6X6_250"]
    long = run_cli([str(folder), *long_form, "--out", "long.yml"], tmp_path)
    # then both succeed with the same camera, to 1e-9, and the same board
    assert short.returncode == 0, short.stderr
    assert long.returncode == 0, long.stderr
    by_board, by_options = (CameraModel.from_yaml(tmp_path / name) for name in ("board.yml", "long.yml"))
    np.testing.assert_allclose(by_board.camera_matrix, by_options.camera_matrix, rtol=0, atol=1e-9)
    np.testing.assert_allclose(by_board.dist_coeffs, by_options.dist_coeffs, rtol=0, atol=1e-9)
    assert abs(by_board.camera_matrix[0, 0] / TRUE_K[0, 0] - 1) < 0.01  # and it is the rendered camera
    boards = []
    for name in ("board.yml", "long.yml"):
        storage = cv2.FileStorage(str(tmp_path / name), cv2.FILE_STORAGE_READ)
        boards.append(storage.getNode("board").string())
        storage.release()
    assert boards[0] == boards[1] == "charuco 9x6 square 0.015 marker 0.011 DICT_6X6_250 legacy=false"
    # and a long option that agrees with the file may stay; one that disagrees is refused, naming both
    agree = run_cli([str(folder), "--board", str(toml), "--dictionary", "DICT_6X6_250", "--out", "again.yml"], tmp_path)
    assert agree.returncode == 0, agree.stderr
    clash = run_cli([str(folder), "--board", str(toml), "--marker-m", "0.012", "--out", "clash.yml"], tmp_path)
    assert clash.returncode == 2, clash.stderr
    errors = [line for line in clash.stderr.splitlines() if line.startswith("ar-anchor: error:")]
    assert len(errors) == 1 and "--board" in errors[0] and "--marker-m disagree" in errors[0], clash.stderr
    assert "0.011 m" in errors[0] and "0.012 m" in errors[0]
    assert not (tmp_path / "clash.yml").exists()


@pytest.mark.parametrize(
    ("sheet", "expected"),
    [
        (["--board", "grid", "--cols", "2", "--rows", "2", "--marker-length", "4cm", "--gap-mm", "10"], "a grid board"),
        (["--ids", "0-3", "--marker-length", "5cm"], "no [[boards]] table"),
        (
            [
                "--board",
                "charuco",
                "--cols",
                "5",
                "--rows",
                "7",
                "--square-mm",
                "30",
                "--size-mm",
                "20",
                "--first-id",
                "10",
            ],
            "ids 10..26",
        ),
    ],
)
def test_board_file_without_a_charuco_board_from_0_is_one_line(sheet, expected, views_dir, tmp_path):
    toml = _markers(sheet, tmp_path)
    folder = copy_views(views_dir, tmp_path / "shots", 3)
    result = run_cli([str(folder), "--board", str(toml), "--out", "camera.yml"], tmp_path)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("ar-anchor: error:")]
    assert len(errors) == 1 and errors[0].startswith(f"ar-anchor: error: --board {toml}: "), result.stderr
    assert expected in errors[0], errors[0]
    assert "ChArUco" in errors[0]


def test_without_board_the_long_options_are_required(views_dir, tmp_path):
    folder = copy_views(views_dir, tmp_path / "shots", 3)
    result = run_cli([str(folder), "--charuco", "9x6", "--out", "camera.yml"], tmp_path)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("ar-anchor: error:")]
    assert errors == [
        "ar-anchor: error: --square-length, --marker-length, --dictionary: required, or --board FILE.toml "
        "(the board file ar-anchor markers wrote beside the sheet)"
    ], result.stderr
