"""The end-of-run summary explains itself: where each target was (distance, tilt) for a few frames or stills,
the table's columns in words, and frames whose markers all shared an id counted as such."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.cli.report import FEW_FRAMES, format_summary
from ar_anchor.geometry import Pose, matrix_from_rvec
from ar_anchor.run.outputs import distance_and_tilt
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, run_main

CAMERA = CameraModel.from_fov(640, 480, 600.0)
TURNS = (-30.0, 0.0, 30.0)
DISTANCE_M = 0.5


def _still(markers: tuple[PlacedMarker, ...], turn_deg: float, seed: int) -> np.ndarray:
    scene = SyntheticScene(
        camera=CAMERA,
        markers=markers,
        trajectory=Trajectory(kind="static", near_m=DISTANCE_M, azimuth_deg=turn_deg, elevation_deg=0.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        blur_sigma=0.5,
        seed=seed,
    )
    (frame,) = SyntheticSource(scene)
    return frame.image


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> Path:
    """``turns/``: a 6 cm marker at 0.5 m turned -30, 0, 30 deg; ``twins/``: two markers of id 0 in each image."""
    root = tmp_path_factory.mktemp("summary")
    (root / "turns").mkdir()
    (root / "twins").mkdir()
    lone = (PlacedMarker(0, 0.06, Pose.identity()),)
    twins = tuple(PlacedMarker(0, 0.05, Pose.from_matrix(np.eye(3), np.array([x, 0.0, 0.0]))) for x in (-0.05, 0.05))
    for index, turn in enumerate(TURNS):
        assert cv2.imwrite(str(root / "turns" / f"turn_{index}.png"), _still(lone, turn, index))
        assert cv2.imwrite(str(root / "twins" / f"twin_{index}.png"), _still(twins, turn, index))
    CAMERA.to_yaml(root / "cam.yml")
    return root


def _replay(folders: Path, source: Path, out: Path, *options: str):
    result = run_main(
        [
            "replay",
            str(source),
            "--camera",
            str(folders / "cam.yml"),
            "--marker-length",
            "0.06",
            "--out",
            str(out),
            *options,
        ]
    )
    assert_clean_exit(result, {0})
    return result, json.loads((out / "summary.json").read_text())


def test_distance_and_tilt_of_known_poses() -> None:
    # a marker straight ahead, turned 40 deg about the vertical: 2 m away, tilted 40 deg
    turned = Pose.from_matrix(matrix_from_rvec(np.array([0.0, math.radians(40.0), 0.0])), np.array([0.0, 0.0, 2.0]))
    distance, tilt = distance_and_tilt(turned)
    assert distance == pytest.approx(2.0) and tilt == pytest.approx(40.0)
    # a marker parallel to the image, off to the side: seen at atan(x / z) from its normal; facing away alike
    for flip in (np.eye(3), np.diag([1.0, -1.0, -1.0])):
        aside = Pose.from_matrix(flip, np.array([1.0, 0.0, 1.0]))
        distance, tilt = distance_and_tilt(aside)
        assert distance == pytest.approx(math.sqrt(2.0)) and tilt == pytest.approx(45.0)


def test_stills_say_where_each_target_was(folders: Path, tmp_path: Path) -> None:
    # given three photos of one marker at 0.5 m, turned -30, 0 and 30 deg
    result, summary = _replay(folders, folders / "turns", tmp_path / "run")
    # then summary.json holds the median and last distance and tilt, and the console says them, one line a target
    entry = summary["targets"]["marker:0"]
    assert entry["distance_m"]["median"] == pytest.approx(DISTANCE_M, rel=0.02)
    assert entry["tilt_deg"]["median"] == pytest.approx(sorted(abs(t) for t in TURNS)[1], abs=2.0)
    assert entry["tilt_deg"]["last"] == pytest.approx(abs(TURNS[-1]), abs=2.0)
    (row,) = [line for line in result.stdout.splitlines() if line.startswith("marker:0") and " of 3 frames" in line]
    state, distance, tilt = row.split()[1:4]
    assert state == entry["last_state"]
    assert float(distance) == pytest.approx(entry["distance_m"]["median"], abs=5e-4)
    assert float(tilt) == pytest.approx(entry["tilt_deg"]["median"], abs=0.05)
    assert "median over the frames it had a pose in" in result.stdout
    assert "0 = facing the camera" in result.stdout


def test_one_photo_gives_its_own_distance_and_quiet_hides_it(folders: Path, tmp_path: Path) -> None:
    result, summary = _replay(folders, folders / "turns" / "turn_1.png", tmp_path / "one")
    assert "in that frame" in result.stdout and "1 of 1 frames" in result.stdout
    assert summary["targets"]["marker:0"]["tilt_deg"]["median"] == pytest.approx(0.0, abs=2.0)
    quiet, _ = _replay(folders, folders / "turns" / "turn_1.png", tmp_path / "quiet", "-q")
    assert "distance" not in quiet.stdout and "columns:" not in quiet.stdout


def test_a_long_run_has_no_where_table_and_the_columns_are_explained() -> None:
    entry = {
        "frames_measured": 40,
        "states": {"tracked": 38, "ambiguous": 2},
        "distance_m": {"median": 1.0, "last": 1.0},
        "tilt_deg": {"median": 10.0, "last": 10.0},
        "last_state": "tracked",
    }
    summary = {
        "frames": FEW_FRAMES + 10,
        "wall_time_s": 1.0,
        "fps": 40.0,
        "frames_with_markers": 40,
        "frames_with_pose": 40,
        "ground_truth": False,
        "targets": {"marker:3": entry},
        "decided_with": "the whole recording",
    }
    text = format_summary(summary)
    assert "distance =" not in text
    assert "tracked/ambig/gap = frames whose pose was tracked" in text
    assert "distance =" in format_summary({**summary, "frames": FEW_FRAMES})


def test_ids_seen_twice_in_every_frame_are_counted_as_such(folders: Path, tmp_path: Path) -> None:
    # given photos whose two markers both have id 0
    result, summary = _replay(folders, folders / "twins", tmp_path / "twins")
    # then the run does not say that no markers were found: it says they were, and why none was used
    assert summary["frames_with_markers"] == 0
    assert summary["frames_with_duplicated_ids"] == 3 and summary["frames_with_only_duplicated_ids"] == 3
    assert summary["duplicated_ids"] == [0]
    assert "markers found in 0 of 3" not in result.stdout
    line = next(line for line in result.stdout.splitlines() if line.startswith("markers detected"))
    assert "in 3 of 3 frames" in line and "every one id 0 appeared more than once" in line
    assert "give each marker its own id" in line


def test_a_demo_explains_its_ground_truth_columns(tmp_path: Path) -> None:
    result = run_main(["demo", "--max-frames", "3", "--out", str(tmp_path / "demo")])
    assert_clean_exit(result, {0})
    assert "rot med/p95 deg = rotation error to the ground truth, degrees" in result.stdout
    assert "trans med/p95 % = position error, % of the true distance" in result.stdout


def test_a_piped_run_prints_a_plain_progress_line_now_and_then(folders: Path, tmp_path: Path, monkeypatch) -> None:
    from ar_anchor.cli import report

    # given stderr that is no terminal (captured) and a line due at every frame
    monkeypatch.setattr(report, "PLAIN_EVERY_S", 0.0)
    result, _ = _replay(folders, folders / "turns", tmp_path / "piped", "--sequence")
    # then each pass says how far it got, in plain lines (no bar, no carriage return)
    lines = [line for line in result.stderr.splitlines() if " fps, " in line]
    assert "replay 1/3 track: 3 of 3 frames" in "\n".join(lines), result.stderr
    assert any(line.startswith("replay 3/3 write: 1 of 3 frames") for line in lines), result.stderr
    assert "\r" not in result.stderr
    quiet, _ = _replay(folders, folders / "turns", tmp_path / "quiet", "--sequence", "-q")
    assert " fps, " not in quiet.stderr


def test_a_piped_run_shorter_than_the_interval_prints_no_progress(folders: Path, tmp_path: Path) -> None:
    from ar_anchor.cli import report

    assert report.PLAIN_EVERY_S >= 2.0  # a line every few seconds, not every frame
    result, _ = _replay(folders, folders / "turns" / "turn_0.png", tmp_path / "short")
    assert " fps, " not in result.stderr


def test_a_piped_live_run_prints_plain_progress_lines(tmp_path: Path, monkeypatch) -> None:
    from ar_anchor.cli import report

    monkeypatch.setattr(report, "PLAIN_EVERY_S", 0.0)
    argv = ["live", "--device", "synthetic", "--width", "96", "--height", "54", "--max-frames", "3"]
    result = run_main([*argv, "--out", str(tmp_path / "live")])
    assert_clean_exit(result, {0})
    lines = [line for line in result.stderr.splitlines() if line.startswith("live: ")]
    assert lines and lines[-1].startswith("live: 3 frames, "), result.stderr
    assert "\r" not in result.stderr
