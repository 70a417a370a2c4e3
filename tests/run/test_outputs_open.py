"""RunOutputs.open opens the outputs in a thread of its own while the tracker takes on the first frame
(importing rerun and opening the recording once came before it): what failed to open is raised as before,
before anything is written, and what did open is closed."""

from __future__ import annotations

import json
import threading

import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.errors import OutputError
from ar_anchor.run.loop import OfflineReplay, run_session
from ar_anchor.run.options import RunOptions
from ar_anchor.run.outputs import PosesCsvWriter
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene
from ar_anchor.track.tracker import Tracker
from ar_anchor.viz.recorder import RerunRecorder


def small_scene(frames: int = 6):
    return demo_scene(demo_config(), CameraModel.from_fov(320, 240, 300.0), frames=frames, blur_sigma=0.0)


class CountingTracker(Tracker):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.processed = 0

    def track(self, detected):  # (process is track(detect(frame)); a replay detects ahead and calls track)
        self.processed += 1
        return super().track(detected)


@pytest.mark.parametrize("process", [True, False], ids=["process", "thread"])
def test_the_recording_is_opened_off_the_main_thread_and_the_run_is_the_same(tmp_path, monkeypatch, process):
    threads = []
    original = RerunRecorder.__init__

    def recorder_init(self, *args, **kwargs):
        threads.append(threading.current_thread().name)
        original(self, *args, **kwargs)

    monkeypatch.setattr(RerunRecorder, "__init__", recorder_init)
    scene = small_scene()
    options = RunOptions(output_process=process)
    result = run_session(SyntheticSource(scene), Tracker(demo_config(), scene.camera), tmp_path / "out", options)
    assert threads == ([] if process else ["open-outputs"])  # (a process: opened in the child, not here)
    assert result.summary["status"] == "completed" and result.summary["frames"] == 6
    assert result.summary["frames_logged"] == 6 and result.recording_rrd.stat().st_size > 0
    assert all(thread.name != "open-outputs" for thread in threading.enumerate())  # joined


@pytest.mark.parametrize("offline", [False, True], ids=["causal", "offline"])
def test_an_output_that_fails_to_open_is_raised_at_the_first_frame_and_the_rest_closed(tmp_path, monkeypatch, offline):
    # given poses.csv cannot be opened (the recording, opened before it, can)
    def refuse(self, path):
        raise OutputError(f"{path}: cannot write (refused)")

    monkeypatch.setattr(PosesCsvWriter, "__init__", refuse)
    closed = []
    original_close = RerunRecorder.close

    def close(self, *args, **kwargs):
        closed.append(True)
        return original_close(self, *args, **kwargs)

    monkeypatch.setattr(RerunRecorder, "close", close)
    scene = small_scene()
    tracker = CountingTracker(demo_config(), scene.camera)
    replay = OfflineReplay(lambda: SyntheticSource(scene)) if offline else None
    # when a run starts
    with pytest.raises(OutputError, match="refused"):
        run_session(SyntheticSource(scene), tracker, tmp_path / "out", RunOptions(output_process=False), offline=replay)
    # then it failed at its first frame (an offline replay too, not after its whole first pass), the
    # recording opened before it is closed, and the summary says it failed with no frame written
    assert tracker.processed == 1
    assert closed == [True]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["frames"] == 0
    assert not (tmp_path / "out" / "poses.csv").exists()


def test_an_output_that_fails_to_open_is_raised_by_a_run_of_no_frames(tmp_path, monkeypatch):
    def refuse(self, *args, **kwargs):
        raise OutputError("recording.rrd: cannot write (refused)")

    monkeypatch.setattr(RerunRecorder, "__init__", refuse)
    scene = small_scene()
    with pytest.raises(OutputError, match="refused"):
        run_session(
            SyntheticSource(scene),
            Tracker(demo_config(), scene.camera),
            tmp_path / "out",
            RunOptions(max_frames=0, output_process=False),
        )
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["frames"] == 0


@pytest.mark.parametrize("offline", [False, True], ids=["causal", "offline"])
def test_a_recording_the_output_process_cannot_open_is_raised_once_known_and_poses_csv_stays_whole(tmp_path, offline):
    # given a recording.rrd that cannot be written (a folder of that name), and a scene long enough for the
    # output process to have said so (it opens its outputs while the tracker goes on)
    (tmp_path / "out" / "recording.rrd").mkdir(parents=True)
    scene = small_scene(frames=200)
    tracker = CountingTracker(demo_config(), scene.camera)
    replay = OfflineReplay(lambda: SyntheticSource(scene)) if offline else None
    # when a run starts, its outputs in a process of their own
    with pytest.raises(OutputError, match="recording"):
        run_session(SyntheticSource(scene), tracker, tmp_path / "out", RunOptions(), offline=replay)
    # then the child's failure is raised here before the run ends (an offline replay's too, in its first
    # pass), and poses.csv holds whole rows of the frames written before it
    assert tracker.processed < 200
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "failed"
    rows = (tmp_path / "out" / "poses.csv").read_text().splitlines()
    assert all(len(row.split(",")) == len(rows[0].split(",")) for row in rows)
    assert len({row.split(",")[0] for row in rows[1:]}) == summary["frames"]
