"""Detection one frame ahead (track/ahead.py): the same results as Tracker.process frame by frame."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys

import numpy as np
import pytest

from ar_anchor import SyntheticSource, Tracker, demo_scene
from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.track.ahead import detected_ahead
from ar_anchor.track.tracker import FrameResult


def _frames(content_fps: float | None = None, frames: int = 40):
    """A demo clip at 30 fps (``content_fps``: fewer distinct frames, the rest repeats)."""
    config = demo_config()
    scene = demo_scene(config, CameraModel.from_fov(480, 360, 420.0), frames=frames, seed=3)
    if content_fps is not None:
        scene = dataclasses.replace(scene, content_fps=content_fps)
    with SyntheticSource(scene) as source:
        return config, scene.camera, list(source)


def _same(a: FrameResult, b: FrameResult) -> None:
    assert (a.index, a.repeated, a.blurred, list(a.targets)) == (b.index, b.repeated, b.blurred, list(b.targets))
    assert np.array_equal(a.detections.ids, b.detections.ids)
    assert np.array_equal(a.detections.corners, b.detections.corners)
    for name, target in a.targets.items():
        other = b.targets[name]
        assert (target.state, target.events) == (other.state, other.events)
        assert np.array_equal(target.pose.rvec, other.pose.rvec) and np.array_equal(target.pose.tvec, other.pose.tvec)


@pytest.mark.parametrize("content_fps", [None, 12.0])
def test_detection_ahead_gives_the_results_of_process(content_fps):
    config, camera, frames = _frames(content_fps)
    one = Tracker(config, camera)
    expected = [one.process(frame) for frame in frames]
    two = Tracker(config, camera)
    got = [two.track(detected) for _, _, detected in detected_ahead(two, ((f, None) for f in frames))]
    assert len(got) == len(expected)
    assert any(r.targets for r in expected)
    if content_fps is not None:
        assert any(r.repeated for r in expected)
    for a, b in zip(expected, got):
        _same(a, b)


def test_stills_are_each_decided_alone_ahead_too():
    config, camera, frames = _frames(frames=12)
    frames = frames[::3]  # (unrelated enough: every third frame)
    alone = [Tracker(config, camera).process(frame) for frame in frames]
    tracker = Tracker(config, camera, stills=True)
    got = [tracker.track(d) for _, _, d in detected_ahead(tracker, ((f, None) for f in frames))]
    for a, b in zip(alone, got):
        _same(dataclasses.replace(a, index=b.index), b)


def test_a_broken_source_still_hands_out_the_frame_before():
    config, camera, frames = _frames(frames=6)

    def broken():
        for frame in frames[:4]:
            yield frame, frame.index
        raise OSError("decoder broke")

    tracker = Tracker(config, camera)
    seen = []
    with pytest.raises(OSError, match="decoder broke"):
        for _frame, extra, detected in detected_ahead(tracker, broken()):
            seen.append(extra)
            tracker.track(detected)
    assert seen == [0, 1, 2, 3]


def test_an_early_end_leaves_no_detection_running():
    config, camera, frames = _frames(frames=6)
    tracker = Tracker(config, camera)
    ahead = detected_ahead(tracker, ((f, None) for f in frames))
    first = next(ahead)
    ahead.close()  # waits for frame 1's detection, which began when frame 0 was handed out
    assert first[0].index == 0
    result = tracker.track(first[2])
    assert result.index == 0


_INTERRUPTED_AT_RANDOM = """
import _thread, random, signal, sys, time
from ar_anchor.track.ahead import detected_ahead

class Quick:
    def detect(self, frame):
        time.sleep(0.0002)
        return frame

def interrupt(_signum, _frame):
    raise KeyboardInterrupt

signal.signal(signal.SIGALRM, interrupt)
rng = random.Random(7)
ended = 0
for _ in range(300):
    try:
        signal.setitimer(signal.ITIMER_REAL, rng.uniform(0.0001, 0.003))
        for _item in detected_ahead(Quick(), ((k, k) for k in range(10_000))):
            pass
    except KeyboardInterrupt:
        ended += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    deadline = time.monotonic() + 2.0
    while _thread._count() and time.monotonic() < deadline:  # the threads still running (the main one aside)
        time.sleep(0.001)
    if _thread._count():
        sys.exit("a detecting thread outlived its interrupted iteration")
print("ended", ended)
"""


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs setitimer (POSIX)")
def test_a_ctrl_c_at_any_moment_ends_the_iteration_and_its_thread():
    """A KeyboardInterrupt raised in the main thread between any two bytecodes (as the run's signal handler
    raises it) must leave no lock taken: a replay once hung for ever after its Ctrl-C, its detecting thread
    waiting on a lock the interrupted main thread had taken (a ThreadPoolExecutor's semaphore). 300 iterations
    each interrupted at a random moment, in a fresh interpreter (a hang fails the test at its timeout; with
    the executor, 1 run of 4 hung here)."""
    # given iterations under way, when an interrupt comes at a random moment of each
    result = subprocess.run(
        [sys.executable, "-c", _INTERRUPTED_AT_RANDOM], capture_output=True, text=True, timeout=120, check=False
    )
    # then each ends with the interrupt, its detecting thread with it
    assert result.returncode == 0 and "ended 300" in result.stdout, result.stdout + result.stderr[-3000:]
