"""The run loop's threads (ar_anchor.run.threads), the outputs it owns (ar_anchor.run.run_outputs) and the
loop itself (ar_anchor.run.loop), without the CLI around them."""

from __future__ import annotations

import csv
import dataclasses
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.errors import ArAnchorError
from ar_anchor.render.video import AnnotatedVideoWriter
from ar_anchor.run.loop import OfflineReplay, run_session
from ar_anchor.run.options import RunOptions
from ar_anchor.run.outputs import PosesCsvWriter, RawVideoWriter
from ar_anchor.run.run_outputs import RunOutputs, close_in_order
from ar_anchor.run.threads import OutputStage, Prefetcher
from ar_anchor.sources.base import Frame, SourceInfo
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene
from ar_anchor.track.tracker import Tracker
from ar_anchor.viz.recorder import RerunRecorder


def frames(count: int, fail_at: int | None = None):
    for index in range(count):
        if index == fail_at:
            raise OSError(f"decoder broke at frame {index}")
        yield Frame(np.zeros((4, 4, 3), np.uint8), index, index * 1000)


def test_prefetcher_yields_every_frame_in_order_stamped_with_its_arrival():
    before = time.monotonic_ns()
    got = list(Prefetcher(frames(20), depth=3))
    assert [frame.index for frame, _ in got] == list(range(20))
    assert all(before <= frame.arrived_ns <= time.monotonic_ns() for frame, _ in got)
    assert all(decode_ms >= 0.0 for _, decode_ms in got)


def test_prefetcher_raises_the_sources_error_after_the_frames_before_it():
    seen = []
    with pytest.raises(OSError, match="frame 5"):
        for frame, _ in Prefetcher(frames(10, fail_at=5)):
            seen.append(frame.index)
    assert seen == [0, 1, 2, 3, 4]


def test_prefetcher_close_stops_a_thread_blocked_on_a_full_queue():
    prefetcher = Prefetcher(frames(1000), depth=2)
    iterator = iter(prefetcher)
    next(iterator)
    time.sleep(0.05)  # the reader fills the queue and blocks
    prefetcher.close(timeout_s=2.0)
    assert not any(t.name == "decode" and t.is_alive() for t in threading.enumerate())


def _work(log: list[int], delay: float = 0.0, fail_at: int | None = None):
    def work(frame, result, stages):
        if frame.index == fail_at:
            raise OSError("disk full")
        time.sleep(delay)
        log.append(frame.index)
        return {"log_ms": 1.0}

    return work


def test_output_stage_does_every_frame_in_order_and_close_finishes_the_queue():
    done: list[int] = []
    stage = OutputStage(_work(done, delay=0.002), depth=4)
    for frame in frames(30):
        assert stage.submit(frame, None, {}, block=True)
    stage.close()
    assert done == list(range(30))
    assert stage.done == 30 and stage.skipped == 0
    assert stage.latency_ms["log_ms"] == [1.0] * 30


def test_output_stage_without_blocking_skips_what_it_cannot_take_and_never_waits():
    done: list[int] = []
    stage = OutputStage(_work(done, delay=0.05), depth=2)
    start = time.perf_counter()
    accepted = [stage.submit(frame, None, {}, block=False) for frame in frames(20)]
    assert time.perf_counter() - start < 0.5  # 20 frames of 50 ms work: the caller did not wait for them
    stage.close()
    assert stage.skipped == accepted.count(False) > 0
    assert done == [frame.index for frame, ok in zip(frames(20), accepted) if ok]


def test_output_stage_error_reaches_the_submitting_thread():
    stage = OutputStage(_work([], fail_at=3), depth=8)
    with pytest.raises(OSError, match="disk full"):
        for frame in frames(200):
            stage.submit(frame, None, {}, block=True)
            time.sleep(0.001)
    stage.close()  # the error was raised once; closing afterwards is clean


# ---------------------------------------------------------------------------- the outputs and the loop


def small_scene(frames: int = 8):
    return demo_scene(demo_config(), CameraModel.from_fov(320, 240, 300.0), frames=frames, blur_sigma=0.0)


class FailingSource:
    """A synthetic source whose stream breaks (``error``) when frame ``fail_at`` is due."""

    def __init__(self, scene, fail_at: int, error: BaseException) -> None:
        self._source = SyntheticSource(scene)
        self.fail_at, self.error = fail_at, error
        self.resolution, self.camera, self.info = self._source.resolution, scene.camera, self._source.info

    def __iter__(self):
        for frame in self._source:
            if frame.index == self.fail_at:
                raise self.error
            yield frame

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._source.close()


def test_close_in_order_takes_every_step_and_raises_the_last_failure_chained_to_the_earlier():
    calls: list[str] = []

    def step(name: str, error: BaseException | None = None):
        def run():
            calls.append(name)
            if error is not None:
                raise error

        return run

    first, last = OSError("video"), ValueError("recording")
    with pytest.raises(ValueError, match="recording") as info:
        close_in_order([step("a"), step("b", first), step("c"), step("d", last)])
    assert calls == ["a", "b", "c", "d"]
    assert info.value.__context__ is first


def test_run_outputs_close_in_their_documented_order_even_when_one_fails(tmp_path, monkeypatch):
    # given every output of a run open, and an annotated video that fails to finalise
    closed: list[str] = []
    for cls in (OutputStage, AnnotatedVideoWriter, RawVideoWriter, PosesCsvWriter, RerunRecorder):
        original = cls.close

        def close(self, *args, _original=original, _name=cls.__name__, **kwargs):
            closed.append(_name)
            if _name == "AnnotatedVideoWriter":
                _original(self, *args, **kwargs)
                raise OSError("disk full")
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, "close", close)
    scene = small_scene()
    options = RunOptions(record_raw=True, video_out=tmp_path / "annotated.mp4", output_process=False)
    outputs = RunOutputs(tmp_path, options)
    outputs.open(scene.camera, demo_config().recording, SourceInfo(), renderer=None)
    # when they are closed
    with pytest.raises(OSError, match="disk full"):
        outputs.close()
    # then the output thread stopped first, then the worker's outputs, then the tracker's; none was skipped
    assert closed == ["OutputStage", "AnnotatedVideoWriter", "RerunRecorder", "RawVideoWriter", "PosesCsvWriter"]
    outputs.close()  # closing again does nothing
    assert len(closed) == 5
    summary = outputs.write_summary("failed", 1.0, {"extra": 1})
    assert summary["status"] == "failed" and summary["extra"] == 1
    assert "video_out" not in summary  # no frame reached the annotated video: no file, none named
    assert json.loads((tmp_path / "summary.json").read_text()) == summary


@pytest.mark.parametrize(
    ("error", "status"), [(OSError("decoder broke"), "failed"), (KeyboardInterrupt(), "interrupted")]
)
def test_a_run_that_breaks_leaves_every_output_complete_and_says_how_it_ended(tmp_path, error, status):
    # given a source whose stream breaks at frame 5
    scene = small_scene(frames=8)
    source = FailingSource(scene, fail_at=5, error=error)
    # when a run reads it
    with pytest.raises(type(error)):
        run_session(source, Tracker(demo_config(), scene.camera), tmp_path / "out", RunOptions(record_raw=True))
    # then poses.csv, raw.mkv and the summary agree on the five frames before, and the summary says why it ended
    out = tmp_path / "out"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == status and summary["frames"] == 5 and summary["frames_logged"] == 5
    with (out / "poses.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows and {int(row["frame"]) for row in rows} <= {0, 1, 2, 3, 4}
    with (out / "raw.mkv.timestamps.csv").open() as handle:
        assert [int(row["frame"]) for row in csv.DictReader(handle)] == [0, 1, 2, 3, 4]
    assert (out / "recording.rrd").stat().st_size > 0


def test_a_completed_run_reports_where_its_outputs_are(tmp_path):
    scene = small_scene(frames=4)
    with SyntheticSource(scene) as source:
        result = run_session(source, Tracker(demo_config(), scene.camera), tmp_path, RunOptions(max_frames=3))
    assert result.summary["status"] == "completed" and result.summary["frames"] == 3
    assert (result.out_dir, result.poses_csv, result.raw_video) == (tmp_path, tmp_path / "poses.csv", None)
    assert Path(result.summary_json).is_file() and Path(result.recording_rrd).is_file()


def test_a_signal_raised_between_the_prefetchers_polls_leaves_its_queue_usable():
    # given a prefetcher whose reads are held like an InterruptGuard's critical sections, and a signal
    # that arrives while the third read waits (raised when that hold ends, outside the queue's lock)
    import contextlib

    from ar_anchor.run.threads import Prefetcher
    from ar_anchor.sources.base import Frame

    frames = [Frame(np.zeros((4, 4, 3), np.uint8), i, i) for i in range(50)]
    holds = {"n": 0}

    @contextlib.contextmanager
    def held():
        holds["n"] += 1
        yield
        if holds["n"] == 3:
            raise KeyboardInterrupt("signal 15")

    prefetcher = Prefetcher(frames, depth=2, held=held)
    taken = []
    with pytest.raises(KeyboardInterrupt):
        for frame, _ in prefetcher:
            taken.append(frame.index)
    # then the frames before it were delivered, and the closing (which drains the queue) ends at once
    assert taken == [0, 1]
    started = time.monotonic()
    prefetcher.close(timeout_s=5.0)
    assert time.monotonic() - started < 2.0


def test_an_offline_run_writes_the_offline_answer_for_every_frame_once_decided(tmp_path):
    # given a synthetic clip replayed offline (the same source opened again for the outputs)
    scene = small_scene(frames=12)
    reopened = []

    def reopen() -> SyntheticSource:
        reopened.append(True)
        return SyntheticSource(scene)

    passes_seen: list[str] = []
    progress = lambda name: lambda done, total: passes_seen.append(name) if done == total else None  # noqa: E731
    with SyntheticSource(scene) as source:
        result = run_session(
            source,
            Tracker(demo_config(), scene.camera),
            tmp_path / "out",
            RunOptions(),
            offline=OfflineReplay(reopen, progress),
        )
    # then every frame is written once, from the second decode, after both later passes ran
    assert reopened == [True] and passes_seen == ["decide", "write"]
    summary = result.summary
    assert summary["status"] == "completed" and summary["frames"] == 12
    assert summary["offline"]["done"] == ["track", "decide", "write"] and summary["offline"]["frames"] == 12
    assert all("causal_states" in entry for entry in summary["targets"].values())
    with result.poses_csv.open() as handle:
        frames = {int(row["frame"]) for row in csv.DictReader(handle)}
    assert frames and frames <= set(range(12)) and len(frames) >= summary["frames_with_pose"] > 0


def test_an_offline_run_whose_source_decodes_differently_the_second_time_fails_naming_it(tmp_path):
    # given a source that gives fewer frames the second time it is opened (a file changed under the run)
    scene = small_scene(frames=10)
    with SyntheticSource(scene) as source:
        # when it is replayed offline
        with pytest.raises(ArAnchorError, match="6 frames when decoded again, 10 the first time"):
            run_session(
                source,
                Tracker(demo_config(), scene.camera),
                tmp_path / "out",
                RunOptions(),
                offline=OfflineReplay(lambda: SyntheticSource(dataclasses.replace(scene, frames=6))),
            )
    # then the outputs hold the frames written before it, complete, and the summary says it failed
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["frames"] == 6
    assert summary["offline"]["done"] == ["track", "decide"]
