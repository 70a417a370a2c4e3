"""The outputs in a process of their own: the same recording as the in-process thread made, the tracker's
outputs complete whatever happens to the child (killed, Ctrl-C, SIGTERM), ``--no-recording``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.errors import EXIT_FAILURE, EXIT_INTERRUPTED, InputError, OutputError
from ar_anchor.run.loop import run_session
from ar_anchor.run.options import RunOptions
from ar_anchor.run.output_process import OutputProcess
from ar_anchor.run.output_worker import OutputSpec
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene
from ar_anchor.track.tracker import Tracker
from tests.helpers import assert_no_traceback, describe, error_lines, verify_rrd

POSES_FRAME = 0  # poses.csv's frame column


def small_scene(frames: int = 8):
    return demo_scene(demo_config(), CameraModel.from_fov(320, 240, 300.0), frames=frames, blur_sigma=0.0)


def _recording(path: Path) -> tuple[set[str], int]:
    """The entities with data in the recording, and how many frames of the ``frame`` timeline it holds."""
    store = RrdReader(path).store()
    entities = {e.strip("/") for e in store.schema().entity_paths() if not e.strip("/").startswith("__properties")}
    frames = set()
    for chunk in store.stream():
        if "frame" in chunk.timeline_names:
            frames.update(chunk.to_record_batch().column("frame").to_pylist())
    return entities, len(frames)


def _poses_frames(path: Path) -> list[int]:
    rows = path.read_text().splitlines()[1:]
    return sorted({int(row.split(",")[POSES_FRAME]) for row in rows})


def test_the_process_records_what_the_thread_recorded(tmp_path):
    # given one scene run twice: the outputs in a process of their own, and in a thread of this process
    scene = small_scene()
    runs = {}
    for name, process in (("process", True), ("thread", False)):
        options = RunOptions(output_process=process, video_out=tmp_path / f"{name}.mp4")
        result = run_session(SyntheticSource(scene), Tracker(demo_config(), scene.camera), tmp_path / name, options)
        runs[name] = result
        verify_rrd(result.recording_rrd)
    # then both recordings hold the same entities and frames, the videos as many frames, the summaries agree
    assert _recording(runs["process"].recording_rrd) == _recording(runs["thread"].recording_rrd)
    process, thread = runs["process"].summary, runs["thread"].summary
    assert process["frames_logged"] == thread["frames_logged"] == 8
    assert process["video_out"]["frames"] == thread["video_out"]["frames"] == 8
    assert process["image_logging"] == thread["image_logging"] == "jpeg"
    assert set(process["latency_ms"]) == set(thread["latency_ms"])  # render_ms and log_ms came back
    assert (tmp_path / "process" / "poses.csv").read_text() == (tmp_path / "thread" / "poses.csv").read_text()


def test_no_recording_writes_poses_and_summary_only(tmp_path):
    scene = small_scene()
    options = RunOptions(recording=False)
    result = run_session(SyntheticSource(scene), Tracker(demo_config(), scene.camera), tmp_path / "out", options)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["poses.csv", "summary.json"]
    assert result.summary["frames"] == 8 and "frames_logged" not in result.summary
    assert result.summary["image_logging"] == "none" and result.summary["recording"] is False
    # and view says why there is nothing to open
    from ar_anchor.cli.view import recording_files

    with pytest.raises(InputError, match="made with --no-recording"):
        recording_files([str(tmp_path / "out")])


def test_a_child_error_is_raised_at_the_next_frame_and_the_rest_dropped(tmp_path):
    # given an output process whose video cannot be written (a folder where the file goes)
    (tmp_path / "v.mp4").mkdir()
    scene = small_scene(3)
    spec = OutputSpec(None, scene.camera, demo_config().recording, None, video_out=tmp_path / "v.mp4")
    stage = OutputProcess(spec, depth=2)
    stage.wait_open()
    frame = next(iter(SyntheticSource(scene)))
    result = Tracker(demo_config(), scene.camera).process(frame)
    # when frames are handed over, then the child's error comes back in this process
    with pytest.raises(OutputError, match="v.mp4"):
        for _ in range(40):
            stage.submit(frame, result, {}, block=True)
            time.sleep(0.05)
    counts = stage.close()  # (the video never opened: nothing to finalise)
    assert stage.done == 0 and counts.video_frames == 0


def _demo(out: Path, frames: int, *extra: str) -> subprocess.Popen[str]:
    argv = [sys.executable, "-m", "ar_anchor", "-q", "demo", "--frames", str(frames), "--out", str(out), *extra]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def _children(pid: int) -> list[int]:
    """The process ids of ``pid``'s children (Linux: /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children = (task / "children").read_text().split()
        found.extend(int(child) for child in children)
    return found


def _wait_for_rows(out: Path, rows: int, process: subprocess.Popen[str], timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    poses = out / "poses.csv"
    while time.monotonic() < deadline and process.poll() is None:
        if poses.is_file() and poses.read_text().count("\n") > rows:
            return
        time.sleep(0.05)
    raise AssertionError(f"no {rows} rows in {poses} within {timeout_s} s: {process.poll()}")


def test_a_killed_output_process_leaves_the_tracking_and_poses_csv_complete(tmp_path):
    # given a demo run whose output process is killed once frames are tracked
    out = tmp_path / "o"
    process = _demo(out, 90)
    _wait_for_rows(out, 20, process)
    children = [pid for pid in _children(process.pid) if "ar_anchor" in Path(f"/proc/{pid}/cmdline").read_text()]
    assert children, "the output process was not found"
    for child in children:  # (the spawned child, and its resource tracker: both gone)
        os.kill(child, signal.SIGKILL)
    stdout, stderr = process.communicate(timeout=180)
    result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    # then every frame was tracked and is in poses.csv, and the run ends with one line naming the recording
    assert result.returncode == EXIT_FAILURE, describe(result)
    assert_no_traceback(result)
    lines = error_lines(stderr)
    assert len(lines) == 1 and "output process" in lines[0] and "recording.rrd" in lines[0], describe(result)
    assert "poses.csv is complete" in lines[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 90 and summary["status"] == "failed"
    assert summary["incomplete"] == ["recording.rrd"]
    assert summary["frames_logged"] + summary["frames_not_logged"] == 90, summary
    assert _poses_frames(out / "poses.csv")[-1] == 89


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_the_process_group_ends_both_and_leaves_every_output_complete(tmp_path, signum):
    # given a demo run with an annotated video, signalled (all of its processes, as a terminal's Ctrl-C is)
    # at a moment that differs from run to run
    out = tmp_path / "o"
    process = _demo(out, 400, "--video-out", str(tmp_path / "a.mp4"))
    _wait_for_rows(out, 10 + int(np.random.default_rng().integers(0, 40)), process)
    os.killpg(process.pid, signum)
    stdout, stderr = process.communicate(timeout=180)
    result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    # then both processes ended, exit 130, and the recording, video and poses.csv end on the same frame
    assert result.returncode == EXIT_INTERRUPTED, describe(result)
    assert_no_traceback(result)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    frames = summary["frames"]
    assert 1 <= frames < 400 and summary["frames_logged"] == frames
    assert summary["video_out"]["frames"] == frames
    assert len(_poses_frames(out / "poses.csv")) == frames
    verify_rrd(out / "recording.rrd")
    assert _recording(out / "recording.rrd")[1] == frames
    assert not _children(process.pid) if Path(f"/proc/{process.pid}").exists() else True
