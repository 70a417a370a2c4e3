"""The clips of issue 19 in ``bench speed --stages`` and ``bench run``: the 50-marker scene, chessboard.avi (skipped
cleanly without the real data), the new columns on a tiny run, ``--clips``, and the plain-loop process.

Timings are for the reports only: nothing here asserts on speed.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.bench.run import RUN_PARTS, run_markdown, run_run_benchmark
from ar_anchor.bench.speed import CLIP_NAMES, PIPELINES, render_clip, speed_scene, split_clips, write_stages_report
from ar_anchor.bench.speed.real_clip import chessboard_files
from ar_anchor.bench.speed.scenes import FIFTY, FIFTY_SIZE
from ar_anchor.bench.speed.stages_run import run_stages_benchmark
from ar_anchor.camera import CameraModel
from ar_anchor.cli.main import main
from ar_anchor.sources.synthetic import SyntheticSource

PLAIN_LOOP = Path(__file__).resolve().parents[2] / "ar_anchor" / "bench" / "speed" / "plain_loop.py"


@pytest.fixture
def no_realdata(monkeypatch, tmp_path):
    """$AR_ANCHOR_REALDATA pointing at an empty folder: chessboard.avi is absent."""
    empty = tmp_path / "no_realdata"
    empty.mkdir()
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(empty))
    return empty


def test_fifty_marker_scene_all_in_view_with_truth():
    # given the 720p many-marker clip
    width, height, fx = FIFTY_SIZE
    scene = speed_scene(FIFTY, CameraModel.from_fov(width, height, fx), 300)
    source = SyntheticSource(scene)
    # then: 50 markers (all of DICT_4X4_50), every one fully in view with its truth in every frame
    assert len(scene.markers) == 50 and {m.marker_id for m in scene.markers} == set(range(50))
    assert scene.trajectory.kind == "handheld"
    for index in range(scene.frames):
        assert len(scene.truth(source.camera_from_world(index))) == 50, index
    # and the camera moves (hand-held, not a still)
    first, last = source.camera_from_world(0), source.camera_from_world(299)
    assert np.linalg.norm(np.asarray(first.tvec) - np.asarray(last.tvec)) > 0.01


def test_fifty_marker_render_detected_by_plain_opencv():
    width, height, fx = FIFTY_SIZE
    frame = render_clip(speed_scene(FIFTY, CameraModel.from_fov(width, height, fx), 1))[0]
    assert len(frame.truth) == 50
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    _, ids, _ = detector.detectMarkers(cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY))
    assert ids is not None and sorted(ids.ravel().tolist()) == list(range(50))


def test_chessboard_skipped_with_a_note_when_absent(no_realdata):
    # when only the real clip is asked for and the real data is absent
    results = run_stages_benchmark(2, [], [], extra=("chessboard",), end_to_end=False)
    # then no clip, one one-line note naming the missing file and how to point at the data
    assert results["clips"] == [] and results["end_to_end"] is None
    (note,) = results["notes"]
    assert "\n" not in note and "chessboard.avi" in note and "AR_ANCHOR_REALDATA" in note
    assert isinstance(chessboard_files(), str)


def test_chessboard_skipped_in_the_cli(no_realdata, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["bench", "speed", "--stages", "-q", "--clips", "chessboard", "--frames", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "note: chessboard clip skipped" in err and len([ln for ln in err.splitlines() if "note:" in ln]) == 1
    text = (out / "speed_stages.md").read_text()
    assert "Note: chessboard clip skipped" in text and "--stages --clips chessboard --frames 2" in text
    assert json.loads((out / "speed_stages.json").read_text())["clips"] == []


def test_bench_run_chessboard_skipped_when_absent(no_realdata):
    results = run_run_benchmark(minutes=0, parts=("chessboard",))
    assert "skipped" in results["chessboard"] and len(results["notes"]) == 1
    text = run_markdown(results, "ar-anchor bench run --clips chessboard")
    assert "Note: chessboard clip skipped" in text and "## Replay: chessboard.avi" not in text


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["bench", "speed", "--stages", "--clips", "nine"], "--clips: unknown clip 'nine'"),
        (["bench", "speed", "--clips", "one"], "--clips: unknown part 'one' of bench speed"),
        (["bench", "speed", "--stages", "--repeats", "2"], "--repeats: bench speed --stages does not take it"),
        (["bench", "stability", "--stages"], "--stages: only bench speed takes it"),
        (["bench", "run", "--repeats", "2"], "--repeats: only bench speed takes it"),
        (["bench", "run", "--clips", "one"], "--clips: unknown part 'one' of bench run"),
        (["bench", "stability", "--clips", "one"], "--clips: only bench speed and bench run"),
        (["bench", "boards", "--frames", "3"], "--frames: only bench speed and bench run"),
    ],
)
def test_clips_option_errors(argv, expected, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 2
    assert expected in capsys.readouterr().err
    assert not out.exists()  # refused before anything was written


def test_split_clips():
    assert split_clips("chessboard,50markers") == ((), ("50markers", "chessboard"))
    assert split_clips(" board , one") == (("one", "board"), ())
    assert set(CLIP_NAMES) == {"one", "eight", "board", "50markers", "chessboard"}
    assert set(RUN_PARTS) == {"1080p", "live", "chessboard", "50markers"}
    for bad in ("", ",", "one,two"):
        with pytest.raises(ValueError, match="any of one,eight,board,50markers,chessboard"):
            split_clips(bad)


def _check_new_columns(clip: dict) -> None:
    assert set(clip["pipelines"]) == set(PIPELINES)
    assert set(clip["ratios"]) == {
        "tracker_roi/opencv_subpix",
        "tracker_roi/opencv",
        "tracker_full/opencv_subpix",
        "tracker_full/opencv",
    }
    assert all(math.isfinite(r) and r > 0 for r in clip["ratios"].values()), clip["ratios"]
    assert set(clip["peak_mb"]) == set(PIPELINES) and all(mb > 0 for mb in clip["peak_mb"].values())
    for key, pipe in clip["pipelines"].items():
        assert pipe["found_per_frame"]["max"] > 0, key
        stages = ("detect_ms", "pose_ms", "total_ms") + (() if key.startswith("opencv") else ("filter_ms",))
        for stage in stages:
            assert stage in pipe["per_marker_ms"], (key, stage)
        assert pipe["per_marker_ms"]["total_ms"] > 0, key


@pytest.mark.slow
def test_smoke_fifty_markers(tmp_path):
    # a tiny run of the 50-marker clip alone
    results = write_stages_report(
        tmp_path, frames=4, sizes=[], scenes=[], extra=(FIFTY,), one_thread=False, end_to_end=False, command="t"
    )
    (clip,) = results["clips"]
    assert clip["label"] == "720p 50 markers" and clip["frames"] == 4 and clip["has_truth"]
    _check_new_columns(clip)
    for key in PIPELINES:
        pipe = clip["pipelines"][key]
        assert pipe["found_per_frame"]["min"] == 50, key  # every marker found in every frame
        assert pipe["accuracy"]["marker"]["in_view"] == 200 and pipe["accuracy"]["marker"]["found_pct"] == 100.0
    text = (tmp_path / "speed_stages.md").read_text()
    for heading in ("## Per marker", "## Peak memory per pipeline", "ROI / SUBPIX", "720p 50 markers"):
        assert heading in text


@pytest.mark.slow
def test_smoke_chessboard(realdata, monkeypatch, tmp_path):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(realdata))
    results = write_stages_report(
        tmp_path,
        frames=8,
        sizes=[],
        scenes=[],
        extra=("chessboard",),
        one_thread=False,
        end_to_end=False,
        command="t",
    )
    assert results["notes"] == []
    (clip,) = results["clips"]
    assert clip["label"] == "480p chessboard.avi" and clip["frames"] == 8 and not clip["has_truth"]
    _check_new_columns(clip)
    for pipe in clip["pipelines"].values():
        assert pipe["accuracy"]["marker"] == {"in_view": 0}  # no truth: the accuracy columns stay empty
    assert "- (no truth)" in (tmp_path / "speed_stages.md").read_text()


def test_plain_loop_process(tmp_path):
    # given a tiny H.264 clip of one marker and its camera
    import av

    camera = CameraModel.from_fov(320, 240, 300.0)
    camera.to_yaml(tmp_path / "camera.yml")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    image = np.full((240, 320, 3), 255, np.uint8)
    image[70:170, 110:210] = cv2.cvtColor(cv2.aruco.generateImageMarker(dictionary, 3, 100), cv2.COLOR_GRAY2BGR)
    with av.open(str(tmp_path / "clip.mp4"), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuv420p"
        for _ in range(5):
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    # when the plain loop runs as its own process
    command = [sys.executable, str(PLAIN_LOOP), str(tmp_path / "clip.mp4"), str(tmp_path / "camera.yml")]
    done = subprocess.run([*command, "DICT_4X4_50", "0.05"], capture_output=True, text=True, timeout=60)
    # then it prints one JSON line: every frame decoded, the marker found in each
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["frames"] == 5 and result["markers"] == 5 and result["loop_wall_s"] > 0


def test_run_markdown_new_sections():
    replay = {
        "command": "ar-anchor replay clip_1080p.mp4",
        "frames": 10,
        "video_mb": 1.0,
        "rrd_mb": 2.0,
        "fps_run": 40.0,
        "fps_process": 20.0,
        "process_wall_s": 0.5,
        "image_logging": "video_asset",
        "stages": {},
        "runs": 3,
    }
    versus = {
        "plain_command": "python plain_loop.py",
        "plain_decode": "PyAV",
        "frames": 10,
        "replay_wall_s": [0.5, 0.6, 0.4],
        "plain_wall_s": [0.25, 0.2, 0.3],
        "replay_wall_median_s": 0.5,
        "plain_wall_median_s": 0.25,
        "replay_fps_median": 20.0,
        "plain_fps_median": 40.0,
        "plain_markers": [10, 10, 10],
        "ratio_replay_over_plain_wall": 2.0,
    }
    stages = {"detect": {"median": 5.0}, "pose": {"median": 1.0}, "filter": {"median": 2.0}}
    fifty = {**replay, "command": "ar-anchor replay clip_50markers_720p.mp4", "stages": stages}
    meta = {
        "processor": "x",
        "usable_cpus": 2,
        "python": "3",
        "opencv": "5",
        "opencv_threads": 2,
        "load_average_start": None,
        "load_average_end": None,
    }
    text = run_markdown({"meta": meta, "notes": [], "replay": replay, "replay_vs_plain": versus, "fifty": fifty}, "cmd")
    assert "the median of 3 runs" in text and "**Replay / plain loop wall time: 2.00x**" in text
    assert "| replay | 0.5, 0.6, 0.4 | 0.50 | 20.0 |" in text
    assert "## Replay: synthetic 720p H.264, 50 markers" in text
    assert "detect 5.00 + pose 1.00 + filter 2.00 ms" in text
