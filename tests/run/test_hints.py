"""Hints for the first mistakes: the wrong dictionary (probed once, named with its flag), a marker
length in millimetres (the flag, a config file, poses hundreds of metres away)."""

from __future__ import annotations

import argparse
import logging

import cv2
import numpy as np
import pytest

from ar_anchor.config import DetectorConfig, TrackerConfig, parse_config
from ar_anchor.geometry import Pose
from ar_anchor.run import hints as hints_module
from ar_anchor.run.hints import WINDOW_FRAMES, RunHints
from ar_anchor.sources.base import Frame
from ar_anchor.track.detection import MarkerDetections
from ar_anchor.track.dictionary_probe import dictionary_families, probe_dictionaries
from ar_anchor.track.tracker import FrameResult, TargetResult
from tests.helpers import run_main


def sheet(dictionary: str, ids: list[int], side: int = 90) -> np.ndarray:
    """A white page with the markers ``ids`` of ``dictionary`` in a row (BGR)."""
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    page = np.full((2 * side, (len(ids) + 1) * (side + side // 2), 3), 255, np.uint8)
    for slot, marker_id in enumerate(ids):
        x = side // 2 + slot * (side + side // 2)
        marker = cv2.aruco.generateImageMarker(aruco, marker_id, side)
        page[side // 2 : side // 2 + side, x : x + side] = marker[..., None]
    return page


# ---------------------------------------------------------------------------- the probe


def test_families_chain_prefixes_and_keep_the_lone_dictionaries():
    families = dictionary_families()
    assert ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000") in families
    assert ("DICT_ARUCO_ORIGINAL",) in families
    assert sum(len(f) for f in families) == 22  # every predefined dictionary once


@pytest.mark.parametrize(
    ("printed", "ids", "configured", "named"),
    [
        ("DICT_ARUCO_ORIGINAL", [1, 3, 200], "DICT_4X4_50", "DICT_ARUCO_ORIGINAL"),
        ("DICT_4X4_100", [60, 70], "DICT_4X4_50", "DICT_4X4_100"),  # the smallest that holds every id
        ("DICT_4X4_1000", [3, 7], "DICT_6X6_250", "DICT_4X4_50"),
        ("DICT_6X6_250", [5, 120], "DICT_4X4_50", "DICT_6X6_250"),
        ("DICT_APRILTAG_36H11", [2, 400], "DICT_4X4_50", "DICT_APRILTAG_36H11"),
    ],
)
def test_probe_names_the_dictionary_printed(printed, ids, configured, named):
    # given a page of another dictionary's markers; when probed; then that dictionary is named
    guess = probe_dictionaries([sheet(printed, ids)], DetectorConfig(dictionary=configured))
    assert guess is not None and guess.dictionary == named
    assert set(ids) <= set(guess.ids)


def test_probe_is_silent_on_a_blank_image_and_on_the_configured_dictionary():
    assert probe_dictionaries([np.full((240, 320, 3), 200, np.uint8)], DetectorConfig()) is None
    assert probe_dictionaries([sheet("DICT_4X4_50", [1, 2])], DetectorConfig()) is None


# ---------------------------------------------------------------------------- RunHints


def frame(index: int, image: np.ndarray) -> Frame:
    return Frame(image, index, index * 33_333_333)


def result(index: int, ids: tuple[int, ...] = (), targets: dict | None = None) -> FrameResult:
    corners = np.tile(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]), (len(ids), 1, 1))
    return FrameResult(index, index * 33_333_333, MarkerDetections(np.array(ids, np.int32), corners), targets or {})


def test_a_run_that_finds_markers_keeps_no_frame_and_probes_nothing(monkeypatch):
    calls = []
    monkeypatch.setattr(hints_module, "probe_dictionaries", lambda *a: calls.append(a))
    hints = RunHints(TrackerConfig())
    image = np.zeros((8, 8, 3), np.uint8)
    hints.after_frame(frame(0, image), result(0, (3,)))
    for index in range(1, 2 * WINDOW_FRAMES):
        hints.after_frame(frame(index, image), result(index))
    assert hints.finish() == {} and not calls and not hints._kept


def test_no_marker_in_the_window_probes_once_and_warns(caplog):
    hints = RunHints(TrackerConfig())
    page = sheet("DICT_ARUCO_ORIGINAL", [1, 3])
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        for index in range(WINDOW_FRAMES + 10):
            hints.after_frame(frame(index, page), result(index))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        f"no DICT_4X4_50 marker in the first {WINDOW_FRAMES} frames; they hold DICT_ARUCO_ORIGINAL markers "
        "(ids 1, 3): use --dictionary DICT_ARUCO_ORIGINAL"
    ]
    assert hints.finish()["dictionary_hint"].endswith("use --dictionary DICT_ARUCO_ORIGINAL")
    # markers of the configured dictionary after all: the summary carries no hint
    hints.after_frame(frame(99, page), result(99, (1,)))
    assert hints.finish() == {}


def test_a_run_shorter_than_the_window_is_probed_at_its_end_unless_interrupted(caplog):
    page = sheet("DICT_5X5_50", [4])
    hints = RunHints(TrackerConfig())
    hints.after_frame(frame(0, page), result(0))
    assert hints.finish(probe=False) == {}
    hints = RunHints(TrackerConfig())
    hints.after_frame(frame(0, page), result(0))
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        assert "DICT_5X5_50" in hints.finish()["dictionary_hint"]
    assert "no DICT_4X4_50 marker in the first 1 frames" in caplog.text


def target(distance_m: float, length_m: float = 34.0) -> TargetResult:
    pose = Pose(np.zeros(3), np.array([0.0, 0.0, distance_m]))
    return TargetResult("marker:3", "tracked", pose, pose, 0.1, 2.0, length_m)


def test_a_pose_hundreds_of_metres_away_is_named_once(caplog):
    hints = RunHints(TrackerConfig())
    image = np.zeros((8, 8, 3), np.uint8)
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        hints.after_frame(frame(0, image), result(0, (3,), {"marker:3": target(0.5, 0.05)}))
        assert not caplog.records
        for index in (1, 2):
            hints.after_frame(frame(index, image), result(index, (3,), {"marker:3": target(445.0)}))
    assert len(caplog.records) == 1
    message = caplog.records[0].getMessage()
    assert "marker:3 is 445 m from the camera (frame 1)" in message and "did you give millimetres?" in message


# ---------------------------------------------------------------------------- lengths in millimetres


def test_marker_length_flag_in_millimetres_warns(caplog):
    from ar_anchor.cli.options import load_tracker_config

    args = argparse.Namespace(config=None, dictionary=None, marker_length=34.0, no_filter=False)
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        config = load_tracker_config(args)
    assert config.markers.length_m == 34.0
    assert "--marker-length 34: a marker 34 m wide? did you give millimetres? 34 mm is --marker-length 0.034" in (
        caplog.text
    )
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        load_tracker_config(argparse.Namespace(config=None, dictionary=None, marker_length=0.034, no_filter=False))
    assert not caplog.records


def test_config_lengths_in_millimetres_warn(caplog):
    data = {
        "markers": {"length_m": 50, "lengths_m": {"7": 40.0}},
        "boards": [{"name": "desk", "marker_length_m": 40.0, "first_id": 10}],
    }
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        parse_config(data, "x.toml")
    text = caplog.text
    assert "x.toml: [markers] length_m = 50: a marker 50 m wide?" in text
    assert "[markers.lengths_m] 7 = 40" in text and "[[boards]] 'desk' marker_length_m = 40" in text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        parse_config({"markers": {"length_m": 0.5}}, "y.toml")
    assert not caplog.records


# ---------------------------------------------------------------------------- the acceptance runs


@pytest.mark.slow
def test_replay_of_chessboard_with_the_default_dictionary_names_aruco_original(realdata, tmp_path):
    folder = realdata / "aruco_testdata" / "chessboard"
    out = tmp_path / "run"
    run = run_main(
        [
            "replay",
            str(folder / "chessboard.avi"),
            "--camera",
            str(folder / "intrinsics.yml"),
            "--marker-length",
            "0.034",
            "--out",
            str(out),
        ]
    )
    assert run.code == 0, run.describe()
    assert "use --dictionary DICT_ARUCO_ORIGINAL" in run.stderr, run.describe()
    summary_line = next(line for line in run.stdout.splitlines() if line.startswith("markers found in 0 of"))
    assert "use --dictionary DICT_ARUCO_ORIGINAL" in summary_line
    assert (out / "poses.csv").is_file() and (out / "summary.json").is_file()


@pytest.mark.slow
def test_replay_with_millimetres_warns_about_units_and_distance(realdata, tmp_path):
    folder = realdata / "aruco_testdata" / "chessboard"
    args = ["replay", str(folder / "chessboard.avi"), "--camera", str(folder / "intrinsics.yml")]
    args += ["--out", str(tmp_path / "out")]  # (not recordings/ of the working directory: the repository)
    run = run_main([*args, "--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "34", "--max-frames", "5"])
    assert run.code == 0, run.describe()
    assert "--marker-length 34: a marker 34 m wide? did you give millimetres?" in run.stderr
    assert "m from the camera" in run.stderr and "did you give millimetres?" in run.stderr


# ---------------------------------------------------------------------------- the probe, bounded and interruptible


def squares(width: int = 1920, height: int = 1080, cell: int = 20, seed: int = 0) -> np.ndarray:
    """A page of black squares, each with a random white or black centre: every one a candidate that decodes
    to no marker of any dictionary (the probe's worst case: about 6 s per 1080p image, all ten families)."""
    rng = np.random.default_rng(seed)
    page = np.full((height, width), 255, np.uint8)
    for y in range(10, height - cell - 10, cell + 12):
        for x in range(10, width - cell - 10, cell + 12):
            page[y : y + cell, x : x + cell] = 0
            page[y + cell // 4 : y + 3 * cell // 4, x + cell // 4 : x + 3 * cell // 4] = 255 * (rng.random() < 0.5)
    return cv2.cvtColor(page, cv2.COLOR_GRAY2BGR)


def test_the_probe_starts_no_detection_once_its_budget_is_spent(caplog):
    with caplog.at_level(logging.INFO, logger="ar_anchor"):
        assert probe_dictionaries([sheet("DICT_5X5_50", [4])], DetectorConfig(), budget_s=0.0) is None
    assert "dictionary probe stopped after 0 s (image 1 of 1, 0 of" in caplog.text
    guess = probe_dictionaries([sheet("DICT_5X5_50", [4])], DetectorConfig(), budget_s=hints_module.PROBE_BUDGET_S)
    assert guess is not None and guess.dictionary == "DICT_5X5_50"


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGINT"])
def test_a_signal_during_a_short_runs_probe_ends_the_run_as_interrupted(tmp_path, signum):
    """Issue 34: a run shorter than the window probed after its interrupt guard had closed (9-18 s at 1080p):
    a Ctrl-C or SIGTERM then left summary.json at `running, frames: 0`, the lock and summary.json.tmp."""
    import json
    import signal
    import subprocess
    import time

    from tests.helpers import cli

    (tmp_path / "shots").mkdir()
    for index in range(2):
        cv2.imwrite(str(tmp_path / "shots" / f"f{index}.png"), squares(seed=index))
    out = tmp_path / "out"
    camera = "configs/camera_synthetic.yml"
    argv = ["replay", str(tmp_path / "shots"), "--camera", camera, "--sequence", "--causal", "--out", str(out)]
    process = subprocess.Popen(cli([*argv, "-q", "-v"]), stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in process.stderr:  # wait for the probe to begin
            lines.append(line)
            if "probing the other dictionaries" in line:
                break
        else:
            pytest.fail("no probe: " + "".join(lines))
        time.sleep(0.3)  # (inside OpenCV's detection: the signal is handled when it returns)
        signalled = time.monotonic()
        process.send_signal(getattr(signal, signum))
        rest = process.stderr.read()
        code = process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert code == 130, "".join(lines) + rest
    assert time.monotonic() - signalled < 10
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["frames"] == 2
    left = sorted(p.name for p in out.iterdir())
    assert left == ["frames.csv", "poses.csv", "recording.rrd", "summary.json"], left
    assert "Traceback" not in rest and "internal error" not in rest
