"""``--focal-px`` / ``--hfov-deg``: a photo from a camera without a calibration file. The pinhole is built at the
source's size, said in one warning line and in summary.json; a synthetic photo of known focal length and
distance gives that distance back; each bad value or combination is one error line, exit 2."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, error_lines, run_main

WIDTH, HEIGHT, FOCAL_PX = 1280, 960, 1100.0
MARKER_M, DICTIONARY = 0.08, "DICT_6X6_250"
HFOV_DEG = math.degrees(2 * math.atan(WIDTH / 2 / FOCAL_PX))  # the same camera, by its field of view


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> tuple[Path, float]:
    """A folder with one photo of an 8 cm marker, off the image centre, taken with a 1100 px lens (no file
    describes it); and the marker's true distance from the camera, metres."""
    root = tmp_path_factory.mktemp("uncalibrated")
    (root / "shots").mkdir()
    scene = SyntheticScene(
        camera=CameraModel.from_fov(WIDTH, HEIGHT, FOCAL_PX),
        dictionary=DICTIONARY,
        markers=(PlacedMarker(7, MARKER_M, Pose(np.zeros(3), np.array([0.12, 0.06, 0.0]))),),
        trajectory=Trajectory(kind="static", near_m=0.9, azimuth_deg=25.0, elevation_deg=10.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        blur_sigma=0.5,
        seed=5,
    )
    (frame,) = SyntheticSource(scene)
    assert cv2.imwrite(str(root / "shots" / "photo.png"), frame.image)
    return root, float(np.linalg.norm(frame.truth["marker:7"].tvec))


def _replay_process(root: Path, name: str, *camera: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    out = root / name
    args = [str(root / "shots"), *camera, "--marker-length", f"{MARKER_M * 100:g}cm", "--dictionary", DICTIONARY]
    result = subprocess.run(
        [sys.executable, "-m", "ar_anchor", "replay", *args, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    return result, out


@pytest.mark.parametrize(
    ("option", "given"),
    [
        pytest.param(["--focal-px", f"{FOCAL_PX:g}"], f"--focal-px {FOCAL_PX:g}", id="focal-px"),
        pytest.param(["--hfov-deg", f"{HFOV_DEG:.4f}"], f"--hfov-deg {HFOV_DEG:.4f}", id="hfov-deg"),
    ],
)
def test_a_photo_without_calibration_gives_its_distance(photo, option, given):
    root, truth_m = photo
    # when the photo is replayed with only the lens's focal length (or field of view) known
    result, out = _replay_process(root, option[0].strip("-"), *option)
    assert result.returncode == 0, result.stderr
    # then the marker's distance is the true one (within 10 %: the acceptance; a synthetic photo gives ~1 %)
    with open(out / "poses.csv", newline="") as file:
        (row,) = [r for r in csv.DictReader(file) if r["target"] == "marker:7"]
    distance = math.dist((0, 0, 0), [float(row[f"tvec_{axis}"]) for axis in "xyz"])
    assert abs(distance - truth_m) < 0.02 * truth_m, (distance, truth_m)
    # and one warning line says the distances are approximate
    warnings = [line for line in result.stderr.splitlines() if "WARNING" in line]
    assert len(warnings) == 1 and "distances are approximate" in warnings[0] and given in warnings[0], result.stderr
    # and summary.json says how the camera was given, and what it was: fx, cx, cy at the photo's size
    camera = json.loads((out / "summary.json").read_text())["camera"]
    assert camera["from"] == given
    assert (camera["image_width"], camera["image_height"]) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(
        camera["camera_matrix"], [[FOCAL_PX, 0, 639.5], [0, FOCAL_PX, 479.5], [0, 0, 1]], rtol=1e-4
    )
    assert camera["distortion_coefficients"] == []


# (options, text the one error line must hold)
BAD_OPTIONS = [
    pytest.param(["--focal-px", "900", "--hfov-deg", "60"], "--focal-px and --hfov-deg: give one", id="both"),
    pytest.param(
        ["--focal-px", "900", "--camera", "CAMERA"], "--focal-px with --camera: give one", id="focal-and-camera"
    ),
    pytest.param(
        ["--hfov-deg", "60", "--camera", "CAMERA"], "--hfov-deg with --camera: give one", id="hfov-and-camera"
    ),
    pytest.param(["--focal-px", "0"], "--focal-px 0: must be a focal length in pixels, > 0", id="focal-zero"),
    pytest.param(["--focal-px", "-800"], "--focal-px -800: must be", id="focal-negative"),
    pytest.param(
        ["--hfov-deg", "180"], "--hfov-deg 180: must be a horizontal field of view between 1 and 179", id="hfov-180"
    ),
    pytest.param(["--hfov-deg", "0.5"], "--hfov-deg 0.5: must be", id="hfov-tiny"),
    pytest.param(["--focal-px", "4.2"], "did you give millimetres?", id="focal-in-mm"),
    pytest.param(["--focal-px", "35"], "--focal-px 35: a focal length of 35 px would see 174 deg", id="focal-35mm"),
    pytest.param(["--focal-px", "1e6"], "less than 1 deg", id="focal-too-long"),
]


@pytest.mark.parametrize(("options", "expected"), BAD_OPTIONS)
def test_a_bad_assumed_camera_is_one_error_line_exit_2(photo, tmp_path, options, expected):
    root, _ = photo
    CameraModel.from_fov(WIDTH, HEIGHT, FOCAL_PX).to_yaml(tmp_path / "camera.yml")
    options = [str(tmp_path / "camera.yml") if o == "CAMERA" else o for o in options]
    result = run_main(["-q", "replay", str(root / "shots"), *options, "--out", str(tmp_path / "out")])
    assert_clean_exit(result, {2})
    assert not result.system_exit, result.describe()  # (ours, not argparse's usage block)
    (line,) = error_lines(result.stderr)
    assert expected in line, line
    assert not (tmp_path / "out").exists()


def test_without_any_camera_the_error_suggests_the_quick_route(photo, tmp_path):
    root, _ = photo
    result = run_main(["-q", "replay", str(root / "shots"), "--out", str(tmp_path / "out")])
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "--camera FILE is required" in line and "--focal-px F or --hfov-deg A" in line, line


def test_a_calibration_of_another_aspect_suggests_the_quick_route(photo, tmp_path):
    root, _ = photo
    CameraModel.default_synthetic().to_yaml(tmp_path / "camera.yml")  # 1280x720 against a 1280x960 photo
    result = run_main(
        ["-q", "replay", str(root / "shots"), "--camera", str(tmp_path / "camera.yml"), "--out", str(tmp_path / "out")]
    )
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "calibrate at this resolution" in line and "--focal-px F or --hfov-deg A instead" in line, line


def test_batch_says_it_once_and_every_replay_uses_it(photo, tmp_path):
    root, truth_m = photo
    result = run_main(
        ["batch", str(root / "shots"), "--focal-px", f"{FOCAL_PX:g}", "--marker-length", str(MARKER_M),
         "--dictionary", DICTIONARY, "--jobs", "1", "--out", str(tmp_path / "batch")]
    )  # fmt: skip
    assert_clean_exit(result, {0})
    assert sum("distances are approximate" in line for line in result.stderr.splitlines()) == 1, result.stderr
    summary = json.loads((tmp_path / "batch" / "shots" / "summary.json").read_text())
    assert summary["camera"]["from"] == f"--focal-px {FOCAL_PX:g}"
    assert summary["camera"]["camera_matrix"][0][0] == FOCAL_PX


def test_live_synthetic_renders_and_tracks_through_the_assumed_pinhole(tmp_path):
    result = run_main(
        ["-q", "live", "--device", "synthetic", "--hfov-deg", "60", "--width", "640", "--height", "480",
         "--max-frames", "3", "--out", str(tmp_path / "live")]
    )  # fmt: skip
    assert_clean_exit(result, {0})
    camera = json.loads((tmp_path / "live" / "summary.json").read_text())["camera"]
    assert camera["from"] == "--hfov-deg 60"
    assert camera["camera_matrix"][0][0] == pytest.approx(320.0 / math.tan(math.radians(30.0)))
    assert (camera["image_width"], camera["image_height"]) == (640, 480)


def test_the_newcomers_photo_in_one_command(photo):
    """The first-hour route for someone else's photo, in one command: no calibration file (a focal length), a
    length with its unit, an annotated copy of the photo, and the distance on the console."""
    root, truth_m = photo
    images = root / "annotated"
    # when
    result, out = _replay_process(root, "newcomer", "--focal-px", f"{FOCAL_PX:g}", "--images-out", str(images))
    assert result.returncode == 0, result.stderr
    # then the console says where the marker was, within 10 % of the truth
    lines = result.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:1] == ["target"] and "distance m" in line)
    (row,) = [line for line in lines[header + 2 :] if line.startswith("marker:7")]
    distance = float(row.split()[2])
    assert abs(distance - truth_m) < 0.10 * truth_m, (row, truth_m)
    # and the photo is written back under its own name, annotated (the marker outlined: it differs from the source)
    source = cv2.imread(str(root / "shots" / "photo.png"))
    annotated = cv2.imread(str(images / "photo.png"))
    assert annotated is not None and annotated.shape == source.shape
    assert np.count_nonzero(np.any(annotated != source, axis=2)) > 500
    # and the last line names both the run's files and the annotated images
    assert "annotated images:" in lines[-1] and "recording.rrd" in lines[-1]
