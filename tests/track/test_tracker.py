"""Tracker, used directly (not through the CLI): one frame in, one FrameResult out."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from ar_anchor import SyntheticSource, Tracker, demo_scene
from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.geometry import angle_between_deg
from ar_anchor.sources.base import Frame
from ar_anchor.targets import TargetId, TrackState


def _frames(count: int, seed: int = 0):
    config, camera = demo_config(), CameraModel.default_synthetic()
    return config, camera, list(SyntheticSource(demo_scene(config, camera, frames=count, seed=seed)))


@functools.cache
def _ten_frames():
    """``_frames(10)``, rendered once for the two tests of a reset (read-only images)."""
    config, camera, frames = _frames(10)
    for frame in frames:
        frame.image.flags.writeable = False
    return config, camera, tuple(frames)


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
    config, camera, frames = _ten_frames()
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
    config, camera, frames = _ten_frames()
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


# ---- the API's boundary (issue 34): a malformed frame is refused, typed, before it touches any state


@pytest.mark.parametrize("stamp", [float("nan"), float("inf"), -float("inf"), "0", None, True, 2**63, 1j])
def test_frame_refuses_a_timestamp_that_is_not_a_finite_number_of_nanoseconds(stamp):
    from ar_anchor.errors import FrameError, InputError

    with pytest.raises(FrameError, match="Frame.timestamp_ns") as caught:
        Frame(np.zeros((8, 8, 3), np.uint8), 0, stamp)
    assert isinstance(caught.value, InputError) and isinstance(caught.value, ValueError)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((8, 8), np.uint8),  # grey
        np.zeros((8, 8, 4), np.uint8),  # BGRA
        np.zeros((8, 8, 3), np.float32),
        np.zeros((8, 8, 3), np.uint16),
        np.zeros((0, 8, 3), np.uint8),  # empty (was an OpenCV assertion in Tracker.process)
        np.zeros((8, 0, 3), np.uint8),
        np.zeros((2, 8, 8, 3), np.uint8),
        [[[0, 0, 0]]],
        None,
    ],
)
def test_frame_refuses_a_malformed_image(image):
    from ar_anchor.errors import FrameError

    with pytest.raises(FrameError, match="Frame.image"):
        Frame(image, 0, 0)


def test_frame_refuses_a_negative_or_non_integer_index():
    from ar_anchor.errors import FrameError

    for index in (-1, 1.0, "1", None):
        with pytest.raises(FrameError, match="Frame.index"):
            Frame(np.zeros((8, 8, 3), np.uint8), index, 0)
    assert Frame(np.zeros((8, 8, 3), np.uint8), np.int64(3), np.int64(5)).index == 3  # numpy integers are fine


def test_process_refuses_a_frame_spoiled_after_it_was_made_and_keeps_its_state():
    """A NaN timestamp smuggled past Frame (object.__setattr__ on the frozen dataclass), or no Frame at all:
    Tracker.process (and detect) refuse it, and the tracker goes on exactly as if it had never been given."""
    from ar_anchor.errors import FrameError

    config, camera, frames = _frames(6)
    tracker, fresh = Tracker(config, camera), Tracker(config, camera)
    for frame in frames[:3]:
        assert _same(tracker.process(frame), fresh.process(frame))
    spoiled = dataclasses.replace(frames[3])
    object.__setattr__(spoiled, "timestamp_ns", float("nan"))
    for bad in (spoiled, frames[3].image, None):
        with pytest.raises(FrameError):
            tracker.process(bad)
        with pytest.raises(FrameError):
            tracker.detect(bad)
    for frame in frames[3:]:
        result = tracker.process(frame)
        assert _same(result, fresh.process(frame))
        assert all(np.isfinite(t.pose.tvec).all() and np.isfinite(t.pose.rvec).all() for t in result.targets.values())


def test_a_non_contiguous_image_is_tracked_as_its_contiguous_copy():
    config, camera, frames = _frames(2)
    padded = np.zeros((frames[0].image.shape[0], frames[0].image.shape[1] * 2, 3), np.uint8)
    padded[:, ::2] = frames[0].image
    view = padded[:, ::2]
    assert not view.flags.c_contiguous
    a = Tracker(config, camera).process(Frame(view, 0, 0))
    b = Tracker(config, camera).process(Frame(np.ascontiguousarray(view), 0, 0))
    assert a.targets and _same(a, b)


def test_checking_a_frame_costs_microseconds():
    import timeit

    from ar_anchor.sources.base import check_frame

    frame = Frame(np.zeros((720, 1280, 3), np.uint8), 1, 33_333_333)
    per_call = min(timeit.repeat(lambda: check_frame(frame), number=2000, repeat=5)) / 2000
    assert per_call < 20e-6, f"{per_call * 1e6:.1f} us per frame"
