"""Tracker, used directly (not through the CLI): one frame in, one FrameResult out."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ar_anchor import SyntheticSource, Tracker, demo_scene
from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.geometry import angle_between_deg
from ar_anchor.targets import TargetId, TrackState


def _frames(count: int, seed: int = 0):
    config, camera = demo_config(), CameraModel.default_synthetic()
    return config, camera, list(SyntheticSource(demo_scene(config, camera, frames=count, seed=seed)))


def _same(a, b) -> bool:
    return list(a.targets) == list(b.targets) and all(
        a.targets[n].state == b.targets[n].state
        and np.array_equal(a.targets[n].pose.rvec, b.targets[n].pose.rvec)
        and np.array_equal(a.targets[n].pose.tvec, b.targets[n].pose.tvec)
        for n in a.targets
    )


def test_process_returns_poses_close_to_truth_for_every_target():
    config, camera, frames = _frames(8)
    tracker = Tracker(config, camera)
    for frame in frames:
        result = tracker.process(frame)
        assert result.index == frame.index and result.timestamp_ns == frame.timestamp_ns
        assert set(result.latency_ms) >= {"detect_ms", "pose_ms", "filter_ms"}
        for name, target in result.targets.items():
            assert isinstance(name, TargetId) and target.target == name
            assert isinstance(target.state, TrackState)
            truth = frame.truth[name]
            if target.state is TrackState.TRACKED:
                assert angle_between_deg(target.pose.rotation, truth.rotation) < 2.0
                assert np.linalg.norm(target.pose.tvec - truth.tvec) < 0.01 * np.linalg.norm(truth.tvec)
    assert "board:desk" in result.targets and "marker:7" in result.targets


def test_reset_makes_the_next_frame_a_first_frame():
    config, camera, frames = _frames(10)
    used = Tracker(config, camera)
    for frame in frames[:6]:
        used.process(frame)
    used.reset()
    assert not used.tracks
    fresh = Tracker(config, camera)
    for frame in frames[6:]:
        assert _same(used.process(frame), fresh.process(frame))


def test_without_reset_history_matters():
    """The reset test above can fail: a tracker with history answers differently from a fresh one."""
    config, camera, frames = _frames(10)
    used = Tracker(config, camera)
    for frame in frames[:6]:
        used.process(frame)
    fresh = Tracker(config, camera)
    assert not all(_same(used.process(f), fresh.process(f)) for f in frames[6:])


def test_a_repeated_frame_is_the_previous_answer():
    config, camera, frames = _frames(3)
    tracker = Tracker(config, camera)
    first = tracker.process(frames[1])
    again = tracker.process(dataclasses.replace(frames[1], index=2, timestamp_ns=frames[2].timestamp_ns))
    assert again.repeated and not first.repeated and list(again.targets) == list(first.targets)


@pytest.mark.parametrize("shape", [(1080, 1920, 3), (480, 640), (481, 643, 3), (6, 5, 3), (3, 3)])
def test_the_fingerprint_is_every_4th_pixel_whatever_the_size(shape):
    from ar_anchor.track.tracker import _every_4th_pixel

    image = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    fingerprint = _every_4th_pixel(image)
    np.testing.assert_array_equal(fingerprint, image[::4, ::4])
    assert fingerprint.flags.c_contiguous
