"""``ar-anchor bench speed``: issue 33's acceptance rows (their arithmetic on made-up runs), the lossless
loop of a video, the plain SUBPIX loop process, poses.csv's measured markers, and a quick run on tiny clips
(its report's structure and its ratios recomputed from its own runs).

Timings are for the reports only: nothing here asserts on speed.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import av
import cv2
import numpy as np
import pytest

from ar_anchor.bench.speed import PARTS, run_speed_acceptance, speed_markdown, write_speed_report
from ar_anchor.bench.speed.processes import PLAIN_LOOP, measured_markers
from ar_anchor.bench.speed.remux import loop_video
from ar_anchor.bench.speed.rows import TARGETS, acceptance_rows, check, found_comparison, median, ratio, summarise_clip
from ar_anchor.camera import CameraModel
from ar_anchor.cli.main import main
from ar_anchor.run.outputs import POSES_CSV_HEADER

# ---------------------------------------------------------------------------- made-up runs


def _replay(wall: float, frames: int, detect: float, pose: float, filt: float, mode: str = "causal") -> dict:
    return {
        "mode": mode,
        "frames": frames,
        "process_wall_s": wall,
        "fps_process": frames / wall,
        "fps_run": frames / (wall - 1.0),
        "tracker_ms": {"detect": detect, "pose": pose, "filter": filt, "total": detect + pose + filt},
    }


def _plain(wall: float, frames: int, detect: float, pose: float, loop_wall: float) -> dict:
    return {
        "frames": frames,
        "process_wall_s": wall,
        "fps_process": frames / wall,
        "detect_ms": detect,
        "pose_ms": pose,
        "decode_ms": 0.5,
        "loop_ms_per_frame": 1e3 * loop_wall / frames,
    }


FOUND_OK = {
    "frames": 100,
    "frames_fewer": 0,
    "missed_marker_frames": 0,
    "extra_marker_frames": 2,
    "tracker_marker_frames": 1402,
    "plain_marker_frames": 1400,
}


def _clip(
    label: str, causal: list, plain: list, offline: list | None = None, found: dict | None = None, bare: list = ()
) -> dict:
    part = {"label": label, "frames": causal[0]["frames"], "causal": causal, "plain": plain, "found": found or FOUND_OK}
    if offline is not None:
        part["offline"] = offline
    if bare:
        part["causal_no_recording"] = list(bare)
    part["summary"] = summarise_clip(part)
    return part


@pytest.fixture
def parts():
    chess = _clip(
        "chessboard",
        # tracker totals 6, 5, 4 ms: median 5; walls 10, 20, 15 s: median 15
        [_replay(10.0, 1000, 3.0, 1.0, 2.0), _replay(20.0, 1000, 2.5, 1.0, 1.5), _replay(15.0, 1000, 2.0, 1.0, 1.0)],
        # detect + pose 2.5, 4.0, 3.0 ms: median 3.0; loop wall 4, 5, 6 s: 5 ms a frame
        [_plain(4.5, 1000, 2.0, 0.5, 4.0), _plain(5.5, 1000, 3.5, 0.5, 5.0), _plain(6.5, 1000, 2.5, 0.5, 6.0)],
        offline=[_replay(21.0, 1000, 0, 0, 0, "offline"), _replay(25.0, 1000, 0, 0, 0, "offline"),
                 _replay(30.0, 1000, 0, 0, 0, "offline")],
        # --no-recording: tracker totals 4.4, 5.0, 4.0 ms: median 4.4
        bare=[_replay(14.0, 1000, 2.4, 1.0, 1.0), _replay(16.0, 1000, 3.0, 1.0, 1.0),
              _replay(15.0, 1000, 2.0, 1.0, 1.0)],
    )  # fmt: skip
    fifty = _clip(
        "fifty",
        [_replay(10.0, 300, 10.0, 5.0, 6.0)],  # 21 ms, 30 fps
        [_plain(2.0, 300, 9.0, 1.5, 1.5)],  # 10.5 ms
        found={**FOUND_OK, "frames_fewer": 2, "missed_marker_frames": 3},
    )
    one = _clip("one", [_replay(8.0, 800, 1.0, 0.5, 0.5)], [_plain(10.0, 800, 5.0, 0.2, 9.0)])  # 100 vs 80 fps
    startup = {"label": "s", "summary": {"first_pose_s": 0.7, "exit_s": 0.9, "help_s": 0.31, "python_s": 0.02}}
    live = {
        "label": "live",
        "seconds": 20.0,
        "runs": [{}, {}, {}],
        "summary": {
            "capture_to_pose_median_ms": 8.0,
            "capture_to_pose_p95_ms": 15.5,
            "fps": 30.0,
            "no_recording_median_ms": 7.5,
            "no_recording_p95_ms": 12.0,
        },
    }
    return {"chessboard": chess, "50markers": fifty, "1080p": one, "startup": startup, "live": live}


def test_rows_ratios_and_verdicts(parts):
    rows = acceptance_rows(parts)
    by = {(r["id"], r["clip"]): r for r in rows}
    assert [r["id"] for r in rows] == [
        *("1a", "1b", "1c", "1d", "2a", "2b", "3", "4a", "4b", "5a", "5b", "5c", "5d", "6", "6", "6")
    ]
    # 1a: the median tracker total (5 ms) over the median plain detect + pose (3 ms); and over 5 ms a frame
    assert by["1a", "chessboard"]["value"] == pytest.approx(5.0 / 3.0)
    assert by["1a", "chessboard"]["tracker_over_plain_loop"] == pytest.approx(1.0)
    assert by["1a", "chessboard"]["passed"] is False  # 1.67 > 1.5
    # 1b: the median whole-process fps (1000 / 15 s)
    assert by["1b", "chessboard"]["value"] == pytest.approx(1000 / 15.0) and by["1b", "chessboard"]["passed"]
    # 1c: median offline wall 25 s over median causal wall 15 s
    assert by["1c", "chessboard"]["value"] == pytest.approx(25.0 / 15.0) and by["1c", "chessboard"]["passed"] is False
    assert by["2a", "fifty"]["value"] == pytest.approx(2.0) and by["2a", "fifty"]["passed"]  # the bound itself
    assert by["2b", "fifty"]["value"] == pytest.approx(30.0) and by["2b", "fifty"]["passed"]
    assert by["3", "one"]["value"] == pytest.approx(100.0 / 80.0) and by["3", "one"]["passed"]
    assert by["4a", "s"]["value"] == 0.7 and by["4a", "s"]["passed"]
    assert by["4b", "-"]["value"] == 0.31 and by["4b", "-"]["passed"] is False
    assert by["5a", "live"]["passed"] and by["5b", "live"]["passed"] is False
    # 1d: the tracker's median total with default outputs (5 ms) over the same with --no-recording (4.4 ms)
    assert by["1d", "chessboard"]["value"] == pytest.approx(5.0 / 4.4) and by["1d", "chessboard"]["passed"] is False
    # 5c, 5d: live capture-to-pose with the recording over without: 8 / 7.5 passes, 15.5 / 12 does not
    assert by["5c", "live"]["value"] == pytest.approx(8.0 / 7.5) and by["5c", "live"]["passed"]
    assert by["5d", "live"]["value"] == pytest.approx(15.5 / 12.0) and by["5d", "live"]["passed"] is False
    assert [by["6", c]["value"] for c in ("chessboard", "fifty", "one")] == [0.0, 2.0, 0.0]
    assert [by["6", c]["passed"] for c in ("chessboard", "fifty", "one")] == [True, False, True]
    for row in rows:
        op, bound, unit = TARGETS[row["id"]]
        assert (row["op"], row["bound"], row["unit"]) == (op, bound, unit)


def test_rows_of_skipped_and_absent_parts(parts):
    parts["chessboard"] = {"skipped": "chessboard part skipped: not found"}
    del parts["live"]
    ids = [r["id"] for r in acceptance_rows(parts)]
    assert "1a" not in ids and "5a" not in ids and ids.count("6") == 2
    assert acceptance_rows({}) == []


def test_summary_medians(parts):
    s = parts["chessboard"]["summary"]
    assert s["tracker_ms"] == 5.0 and s["tracker_stage_ms"] == {"detect": 2.5, "pose": 1.0, "filter": 1.5}
    assert s["plain_detect_pose_ms"] == 3.0 and s["plain_loop_ms_per_frame"] == pytest.approx(5.0)
    assert s["causal_wall_s"] == 15.0 and s["offline_wall_s"] == 25.0 and s["plain_wall_s"] == 5.5
    assert s["causal_fps_over_plain_fps"] == pytest.approx((1000 / 15.0) / (1000 / 5.5))
    assert "offline_wall_s" not in parts["1080p"]["summary"]


def test_small_helpers():
    assert median([3.0, None, 1.0, 2.0]) == 2.0 and median([None]) is None and median([1.0, 2.0]) == 1.5
    assert ratio(3.0, 2.0) == 1.5 and ratio(None, 2.0) is None and ratio(1.0, 0.0) is None
    assert check(1.5, "<=", 1.5) is True and check(1.51, "<=", 1.5) is False and check(None, "<=", 1.0) is None
    assert check(60.0, ">=", 60.0) is True and check(0.0, "==", 0.0) is True and check(math.nan, ">=", 1.0) is None


def test_found_comparison():
    tracker = {0: {1, 2}, 1: {1}, 3: {5, 6, 7}}
    plain = [[1, 2], [1, 2], [], [5, 6], [9]]
    found = found_comparison(tracker, plain)
    assert found == {
        "frames": 5,
        "frames_fewer": 2,  # frame 1 (1 < 2) and frame 4 (0 < 1)
        "missed_marker_frames": 2,  # marker 2 in frame 1, marker 9 in frame 4
        "extra_marker_frames": 1,  # marker 7 in frame 3
        "tracker_marker_frames": 6,
        "plain_marker_frames": 7,
        "tracker_frames_beyond_plain": 0,
    }
    # a swap of one id for another is no frame with fewer, but a missed and an extra marker-frame
    assert found_comparison({0: {1, 3}}, [[1, 2]])["frames_fewer"] == 0


def test_markdown_from_made_up_results(parts):
    meta = {
        "wall_time_s": 12.0,
        "processor": "cpu",
        "cpu_count": 2,
        "usable_cpus": 2,
        "system": "Linux",
        "python": "3.11",
        "opencv": "5.1.0",
        "opencv_threads": 2,
        "numpy": "2",
        "rerun": "0.41.0",
        "pyav": "18",
        "load_average_start": [1.0, 2.0, 3.0],
        "load_average_end": [1.5, 2.0, 3.0],
        "repeats": 3,
        "help_runs": 5,
    }
    for key in ("chessboard", "50markers", "1080p"):
        parts[key].update(
            video_mb=1.0,
            replay_args=["--camera", "/x/cam.yml"],
            found_fewer_per_round=[0],
            plain_ids_same_every_round=True,
        )
    parts["startup"].update(
        command="replay", runs=[{"first_pose_s": 0.7, "exit_s": 0.9}], help_s=[0.31], python_s=[0.02]
    )
    parts["live"]["command"] = "live"
    stage = {"median": 5.0, "p95": 9.0}
    parts["live"]["runs"] = [{"frames": 600, "fps": 30.0, "live": {}, "stages": {"capture_to_pose": stage}}]
    results = {"meta": meta, "notes": ["a note"], "parts": parts, "rows": acceptance_rows(parts)}
    text = speed_markdown(results, "ar-anchor bench speed")
    assert "OpenCV 5.1.0" in text and "rerun-sdk 0.41.0" in text and "2 CPUs" in text and "1.00 / 2.00 / 3.00" in text
    assert "## Acceptance: 9 of 16 rows pass, 7 fail" in text and "Note: a note." in text
    assert "| replay --causal --no-recording | 14.00, 16.00, 15.00 | 15.00 |" in text
    assert "| 1d | chessboard | " in text and "| 1.14x | <= 1.1x | **FAIL** |" in text
    assert "| 1a | chessboard | " in text and "| 1.67x | <= 1.5x | **FAIL** |" in text
    assert "| 3 | one | " in text and "| 1.25x | >= 1.2x | **pass** |" in text
    assert "/x/" not in text and "--camera cam.yml" in text  # paths shown by their file names
    assert "## Covered elsewhere" in text and "bench run" in text and "bench real" in text


# ---------------------------------------------------------------------------- the pieces


def _marker_clip(path, frames: int, codec: str = "libx264", marker_id: int = 3) -> list[np.ndarray]:
    """A tiny clip of one marker moving across a white frame; its frames as written."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    marker = cv2.cvtColor(cv2.aruco.generateImageMarker(dictionary, marker_id, 100), cv2.COLOR_GRAY2BGR)
    images = []
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=30)
        stream.width, stream.height = 320, 240
        stream.pix_fmt = "yuv420p" if codec == "libx264" else "yuvj420p"
        for index in range(frames):
            image = np.full((240, 320, 3), 255, np.uint8)
            image[70:170, 60 + 10 * index : 160 + 10 * index] = marker
            images.append(image)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return images


def _decoded(path) -> list[tuple[int, np.ndarray]]:
    with av.open(str(path)) as container:
        return [(frame.pts, frame.to_ndarray(format="bgr24")) for frame in container.decode(video=0)]


def test_loop_video_is_lossless(tmp_path):
    _marker_clip(tmp_path / "clip.avi", 5, codec="mjpeg")
    original = _decoded(tmp_path / "clip.avi")
    written = loop_video(tmp_path / "clip.avi", tmp_path / "loop.avi", 12)
    looped = _decoded(tmp_path / "loop.avi")
    assert written == 15 and len(looped) == 15  # three whole copies
    for index, (_, image) in enumerate(looped):
        assert np.array_equal(image, original[index % 5][1]), index  # the very same pixels
    pts = [p for p, _ in looped]
    assert pts == sorted(pts) and len(set(pts)) == 15  # one clip, its timestamps running on
    assert loop_video(tmp_path / "clip.avi", tmp_path / "once.avi", 1) == 5


def test_plain_loop_subpix_with_ids(tmp_path):
    _marker_clip(tmp_path / "clip.mp4", 5)
    CameraModel.from_fov(320, 240, 300.0).to_yaml(tmp_path / "camera.yml")
    command = [sys.executable, str(PLAIN_LOOP), str(tmp_path / "clip.mp4"), str(tmp_path / "camera.yml")]
    done = subprocess.run([*command, "DICT_4X4_50", "0.05", "--subpix", "--ids"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["refine"] == "SUBPIX" and result["frames"] == 5 and result["markers"] == 5
    assert result["ids"] == [[3]] * 5
    for key in ("decode_ms", "detect_ms", "pose_ms", "detect_pose_ms"):
        assert result[key] > 0, key
    assert result["detect_pose_ms"] <= result["loop_wall_s"] * 1e3
    # without the flags: default parameters, no ids (what bench run reads)
    plain = json.loads(subprocess.run([*command, "DICT_4X4_50", "0.05"], capture_output=True, text=True).stdout)
    assert plain["refine"] == "NONE" and "ids" not in plain and plain["markers"] == 5


def test_measured_markers(tmp_path):
    rows = [
        (0, "marker:3", "tracked"),
        (0, "marker:4", "ambiguous"),
        (0, "board:desk", "tracked"),
        (1, "marker:3", "predicted"),
        (2, "marker:3", "interpolated"),
        (2, "marker:5", "tracked"),
    ]
    lines = [",".join(POSES_CSV_HEADER)]
    for frame, target, state in rows:
        lines.append(",".join([str(frame), "0.0", target, state] + ["0"] * (len(POSES_CSV_HEADER) - 4)))
    (tmp_path / "poses.csv").write_text("\n".join(lines) + "\n")
    assert measured_markers(tmp_path / "poses.csv") == {0: {3, 4}, 2: {5}}


@pytest.fixture
def no_realdata(monkeypatch, tmp_path):
    empty = tmp_path / "no_realdata"
    empty.mkdir()
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(empty))
    return empty


def test_chessboard_part_skipped_when_absent(no_realdata):
    results = run_speed_acceptance(("chessboard",))
    (note,) = results["notes"]
    assert "\n" not in note and "chessboard.avi" in note and "AR_ANCHOR_REALDATA" in note
    assert results["rows"] == [] and "skipped" in results["parts"]["chessboard"]


def test_chessboard_skipped_in_the_cli(no_realdata, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["bench", "speed", "-q", "--clips", "chessboard", "--repeats", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "note: chessboard part skipped" in err
    text = (out / "speed.md").read_text()
    assert "Note: chessboard part skipped" in text and "ar-anchor bench speed --clips chessboard --repeats 2" in text
    saved = json.loads((out / "speed.json").read_text())
    assert saved["rows"] == [] and saved["meta"]["repeats"] == 2 and saved["meta"]["parts"] == ["chessboard"]


def test_unknown_part_rejected():
    with pytest.raises(ValueError, match="unknown speed part 'nine'"):
        run_speed_acceptance(("nine",))
    assert set(PARTS) == {"chessboard", "50markers", "1080p", "startup", "live"}


# ---------------------------------------------------------------------------- a quick run


@pytest.mark.slow
def test_quick_run_on_tiny_clips(tmp_path):
    calls = []
    results = write_speed_report(
        tmp_path,
        quick=True,
        progress=lambda i, total, name: calls.append((i, total, name)),
        command="test bench speed",
        parts=("1080p", "startup"),
        frames=4,
        help_runs=1,
    )
    assert [c[0] for c in calls] == list(range(len(calls))) and all(c[1] == len(calls) for c in calls)
    saved = json.loads((tmp_path / "speed.json").read_text())
    assert saved["meta"]["command"] == "test bench speed" and saved["meta"]["repeats"] == 1
    for key in ("opencv", "numpy", "rerun", "python", "cpu_count", "load_average_start", "load_average_end"):
        assert saved["meta"][key] is not None, key
    assert [(r["id"], r["passed"] is not None) for r in saved["rows"]] == [
        ("3", True),
        ("4a", True),
        ("4b", True),
        ("6", True),
    ]
    one = results["parts"]["1080p"]
    (causal,), (plain,) = one["causal"], one["plain"]
    assert causal["frames"] == plain["frames"] == one["frames"] == 4
    assert "_measured" not in causal and "_ids" not in plain  # not written to the JSON
    # the row's ratio, recomputed from the runs themselves
    row3 = next(r for r in results["rows"] if r["id"] == "3")
    assert row3["value"] == pytest.approx((4 / causal["process_wall_s"]) / (4 / plain["process_wall_s"]))
    assert one["summary"]["tracker_ms"] == pytest.approx(
        sum(causal["tracker_ms"][s] for s in ("detect", "pose", "filter"))
    )
    assert one["found"]["frames"] == 4 and one["found"]["plain_marker_frames"] == 4
    startup = results["parts"]["startup"]["summary"]
    assert 0 < startup["first_pose_s"] <= startup["exit_s"] and startup["help_s"] > 0
    text = (tmp_path / "speed.md").read_text()
    assert "test bench speed" in text and "quick mode" in text and "## Acceptance: " in text
    assert "## 1080p one marker" in text and "## Start-up" in text and "| 4b | - |" in text


@pytest.mark.slow
@pytest.mark.realdata
def test_quick_chessboard_loop(realdata, monkeypatch, tmp_path):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(realdata))
    results = write_speed_report(tmp_path, quick=True, parts=("chessboard",), chessboard_frames=10, command="t")
    part = results["parts"]["chessboard"]
    assert part["looped_frames"] == 149 and part["frames"] == 149  # one whole copy: at least 10 frames
    assert [len(part[k]) for k in ("causal", "causal_no_recording", "offline", "plain")] == [1, 1, 1, 1]
    assert [r["id"] for r in results["rows"]] == ["1a", "1b", "1c", "1d", "6"]
    assert part["summary"]["no_recording_tracker_ms"] == pytest.approx(
        part["causal_no_recording"][0]["tracker_ms"]["total"]
    )
    s = part["summary"]
    assert s["offline_over_causal_wall"] == pytest.approx(
        part["offline"][0]["process_wall_s"] / part["causal"][0]["process_wall_s"]
    )
    assert part["found"]["plain_marker_frames"] > 1000  # about 13.5 markers a frame
