"""The run loop's threads (ar_anchor.run.threads) and what the run reports about them."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from ar_anchor.run.threads import OutputStage, Prefetcher
from ar_anchor.sources.base import Frame


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
