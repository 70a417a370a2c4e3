"""Frame sources: image folders, video files, the live capture thread, and open_source over all of them."""

from __future__ import annotations

import logging
import threading
import time

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.errors import SourceError
from ar_anchor.sources import (
    DeviceSettings,
    FrameSource,
    ImageFolderSource,
    SourceInfo,
    VideoFileSource,
    open_source,
)
from ar_anchor.sources.files import natural_key, to_bgr8
from ar_anchor.sources.live import Captured, LiveSource, SyntheticGrabber, WebcamGrabber
from ar_anchor.sources.open import live_demo_scene
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene


def small_scene(frames: int = 12, fps: float = 30.0):
    camera = CameraModel.from_fov(320, 240, 300.0)
    return demo_scene(demo_config(), camera, frames=frames, fps=fps, noise_sigma=1.0, blur_sigma=0.0)


def test_natural_order_puts_frame_2_before_frame_10():
    names = ["frame_10.png", "frame_2.png", "frame_1.png", "Frame_3.png"]
    assert sorted(names, key=natural_key) == ["frame_1.png", "frame_2.png", "Frame_3.png", "frame_10.png"]


@pytest.mark.parametrize(
    ("image", "shape"),
    [
        (np.zeros((4, 5), np.uint8), (4, 5, 3)),
        (np.zeros((4, 5, 4), np.uint8), (4, 5, 3)),
        (np.full((4, 5), 65535, np.uint16), (4, 5, 3)),
        (np.zeros((4, 5, 1), np.uint8), (4, 5, 3)),
        (np.ones((4, 5, 3), np.float32), (4, 5, 3)),
    ],
)
def test_to_bgr8_accepts_what_opencv_reads(image, shape):
    converted = to_bgr8(image)
    assert converted.shape == shape and converted.dtype == np.uint8


def test_to_bgr8_refuses_what_is_not_an_image():
    assert to_bgr8(np.zeros((4, 5, 2), np.uint8)) is None
    assert to_bgr8(np.zeros((0,), np.uint8)) is None


def test_image_folder_order_timestamps_and_bad_files(tmp_path, caplog):
    # given a folder with frames, a non-image file, a corrupt image and one of another size
    images = [np.full((40, 60, 3), 10 * i, np.uint8) for i in range(12)]
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), image)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "frame_12.png").write_bytes(b"\x89PNG broken")
    cv2.imwrite(str(tmp_path / "frame_13.png"), np.zeros((20, 20, 3), np.uint8))
    # when it is read at 10 fps
    with caplog.at_level(logging.WARNING), ImageFolderSource(tmp_path, fps=10.0) as source:
        frames = list(source)
    # then frames come in natural order with fps timestamps, and the bad ones are skipped by name
    assert [f.index for f in frames] == list(range(12))
    assert [f.timestamp_ns for f in frames] == [i * 100_000_000 for i in range(12)]
    assert all(np.array_equal(f.image, images[f.index]) for f in frames)
    assert source.resolution == (60, 40) and source.skipped == 2
    assert "frame_12.png" in caplog.text and "frame_13.png" in caplog.text


def test_image_glob_selects_matching_files(tmp_path):
    for name in ("a_1.png", "a_2.png", "b_1.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((8, 8, 3), np.uint8))
    source = open_source(str(tmp_path / "a_*.png"))
    assert isinstance(source, ImageFolderSource)
    assert [p.name for p in source.files] == ["a_1.png", "a_2.png"]
    assert source.info == SourceInfo(fps=30.0, frame_count=2, stills=True)


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda d: d / "missing", "not found"),
        (lambda d: d, "no images"),
        (lambda d: (d / "x.txt").write_text("x") and d, "no images"),
        (lambda d: (d / "bad.png").write_bytes(b"nope") and d, "can be decoded"),
    ],
    ids=["missing", "empty-folder", "only-text", "only-corrupt"],
)
def test_image_folder_errors_name_the_folder(tmp_path, setup, message):
    spec = setup(tmp_path)
    with pytest.raises(SourceError, match=message) as info:
        ImageFolderSource(spec)
    assert str(tmp_path) in str(info.value)


def test_a_folder_holding_a_video_says_how_a_video_is_given(tmp_path):
    """Found by trying the tool as a new user: ``replay vids`` (a folder holding a video) said only "no images"."""
    (tmp_path / "vids").mkdir()
    (tmp_path / "vids" / "clip.avi").write_bytes(b"RIFF")
    with pytest.raises(SourceError, match="no images") as info:
        ImageFolderSource(tmp_path / "vids")
    given = f"replay {tmp_path / 'vids' / 'clip.avi'}"
    assert f"1 other file(s) (clip.avi): a video is given as the file itself ({given})" in str(info.value)
    assert "a folder of videos to `ar-anchor batch`" in str(info.value)
    # an empty folder: no other file to speak of
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no images") as empty:
        ImageFolderSource(tmp_path / "empty")
    assert "other file" not in str(empty.value)


def write_video(path, frames, fourcc="FFV1", fps=30.0):
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*fourcc), fps, (width, height))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()


def synthetic_images(count: int) -> list[np.ndarray]:
    from ar_anchor.sources.synthetic import SyntheticSource

    source = SyntheticSource(small_scene(frames=count))
    return [source.frame(i).image for i in range(count)]


def test_lossless_video_round_trip_with_container_timestamps(tmp_path):
    images = synthetic_images(10)
    write_video(tmp_path / "clip.mkv", images, fps=25.0)
    with VideoFileSource(tmp_path / "clip.mkv") as source:
        frames = list(source)
        info = source.info
    assert not info.live and info.fps == pytest.approx(25.0) and info.frame_count == 10
    assert info.video_path == tmp_path / "clip.mkv"  # its frames are the file's: a recording can reference it
    assert not info.ended_early
    assert [f.index for f in frames] == list(range(10))
    assert all(np.array_equal(f.image, images[f.index]) for f in frames)  # lossless: the same pixels
    np.testing.assert_allclose([f.timestamp_ns for f in frames], np.arange(10) * 40e6, atol=1.5e6)


def test_recorded_timestamps_beside_a_video_restore_indices_and_times(tmp_path):
    images = synthetic_images(4)
    write_video(tmp_path / "raw.mkv", images)
    (tmp_path / "raw.mkv.timestamps.csv").write_text("frame,timestamp_ns\n3,100\n5,250\n6,300\n9,700\n")
    with VideoFileSource(tmp_path / "raw.mkv") as source:
        frames = list(source)
        assert source.info.video_path is None  # recorded indices replace the decode positions
    assert [(f.index, f.timestamp_ns) for f in frames] == [(3, 100), (5, 250), (6, 300), (9, 700)]


@pytest.mark.parametrize(
    ("content", "message"),
    [(None, "not found"), (b"", "empty file"), (b"this is text, not a video\n" * 50, "cannot be opened|no frame")],
    ids=["missing", "zero-bytes", "text"],
)
def test_video_errors_name_the_file(tmp_path, content, message):
    path = tmp_path / "clip.mp4"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(SourceError, match=message) as info:
        VideoFileSource(path)
    assert str(path) in str(info.value)


def test_truncated_video_ends_at_the_last_good_frame_with_a_warning(tmp_path, caplog):
    images = synthetic_images(30)
    path = tmp_path / "clip.avi"
    write_video(path, images, fourcc="MJPG")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING), VideoFileSource(path) as source:
        assert not source.info.ended_early
        frames = list(source)
        assert source.info.ended_early
    assert 5 < len(frames) < 30
    assert [f.index for f in frames] == list(range(len(frames)))
    assert f"after frame {len(frames) - 1}" in caplog.text and str(path) in caplog.text


# ---------------------------------------------------------------------------- live


class FakeGrabber:
    """A camera at ``fps`` whose timestamps can be scripted; ``fail_after`` frames it vanishes."""

    name = "fake"
    granted: dict[str, object] = {}

    def __init__(self, fps: float = 200.0, fail_after: int | None = None, timestamps: list[int] | None = None):
        self.fps = fps
        self.fail_after = fail_after
        self.timestamps = timestamps
        self.reads = 0
        self.opens = 0

    def open(self):
        self.opens += 1
        return (16, 12)

    def read(self):
        if self.fail_after is not None and self.reads >= self.fail_after:
            time.sleep(0.01)
            return None
        time.sleep(1.0 / self.fps)
        ts = self.timestamps[self.reads] if self.timestamps else time.monotonic_ns()
        self.reads += 1
        if self.timestamps and self.reads > len(self.timestamps):
            return None
        return Captured(np.full((12, 16, 3), self.reads % 256, np.uint8), ts)

    def close(self):
        pass


def test_slow_consumer_gets_the_newest_frames_and_drops_are_counted():
    # given a 200 fps camera and a tracker that needs 30 ms per frame
    with LiveSource(FakeGrabber(fps=200.0), queue_size=1) as source:
        indices, stamps = [], []
        for frame in source:
            indices.append(frame.index)
            stamps.append(frame.timestamp_ns)
            time.sleep(0.03)
            if len(indices) == 15:
                break
    stats = source.stats.as_dict()
    # then frames were dropped (never queued without bound), counted, and what arrives is in order
    assert stats["dropped_queue"] > 15
    assert np.all(np.diff(indices) >= 1) and max(np.diff(indices)) > 1
    assert np.all(np.diff(stamps) > 0)
    assert stats["captured"] >= stats["delivered"] + stats["dropped_queue"] - 1


def test_non_monotonic_timestamps_are_dropped():
    grabber = FakeGrabber(timestamps=[10, 20, 15, 30, 30, 40])
    with LiveSource(grabber, queue_size=10, reconnect_s=0.2) as source:
        stamps = [f.timestamp_ns for f in source]
    assert stamps == [10, 20, 30, 40]
    assert source.stats.dropped_non_monotonic == 2


def test_a_vanished_device_is_retried_then_the_stream_ends_cleanly():
    grabber = FakeGrabber(fps=500.0, fail_after=5)
    start = time.monotonic()
    with LiveSource(grabber, queue_size=10, reconnect_s=0.5) as source:
        frames = list(source)
    assert len(frames) == 5
    assert grabber.opens > 1  # it tried to reopen the device
    assert "gone" in source.stats.ended_because
    assert time.monotonic() - start < 5.0


class StallingGrabber(FakeGrabber):
    """Delivers one frame, then blocks in read() the way a wedged V4L2 driver does."""

    def read(self):
        if self.reads == 0:
            self.reads = 1
            return Captured(np.zeros((12, 16, 3), np.uint8), time.monotonic_ns())
        time.sleep(1.5)
        return None


def test_a_stalled_device_ends_the_stream_after_the_stall_timeout():
    start = time.monotonic()
    with LiveSource(StallingGrabber(), queue_size=1, reconnect_s=30.0, stall_s=0.6) as source:
        frames = list(source)
    assert len(frames) == 1
    assert "stalled" in source.stats.ended_because
    assert time.monotonic() - start < 5.0


def test_synthetic_camera_runs_in_real_time_and_skips_frames_it_is_late_for():
    scene = small_scene(frames=1000, fps=60.0)
    with LiveSource(SyntheticGrabber(scene), queue_size=1, camera=scene.camera) as source:
        frames = []
        for frame in source:
            frames.append(frame)
            time.sleep(0.05)  # a tracker slower than the camera
            if len(frames) == 8:
                break
    stamps = np.array([f.timestamp_ns for f in frames])
    assert np.all(np.diff(stamps) > 0)
    # frames are 50 ms+ apart in real time, the camera runs at 60 fps: frames were dropped
    assert np.median(np.diff(stamps)) > 40e6
    assert source.stats.dropped_queue > 0
    assert all(frame.truth for frame in frames)


def test_synthetic_camera_plays_its_rendered_clip_forth_and_back_with_the_truth_of_each_frame():
    # given a synthetic camera that renders a 5-frame clip when it opens
    scene = small_scene(frames=40, fps=30.0)
    grabber = SyntheticGrabber(scene, cached=5)
    assert grabber.open() == scene.camera.size
    # then slots run over the clip forth and back: 0 1 2 3 4 3 2 1 0 1 ...
    assert [grabber._clip_index(slot) for slot in range(10)] == [0, 1, 2, 3, 4, 3, 2, 1, 0, 1]
    # and each delivered image is the rendered frame (JPEG 95: within a few grey levels) with its own truth
    source = SyntheticSource(scene)
    captured = grabber.read()
    expected = source.frame(0)
    assert captured.truth.keys() == expected.truth.keys()
    assert np.abs(captured.image.astype(int) - expected.image).mean() < 2.0
    last = source.frame(scene.frames - 1)
    jpeg, truth = grabber._clip[4]
    assert all(np.allclose(truth[k].tvec, last.truth[k].tvec) for k in truth)


def test_a_synthetic_camera_asked_for_few_frames_renders_the_rest_of_its_clip_when_due():
    # given a synthetic camera of a 5-frame clip for a run that takes 2 frames
    scene = small_scene(frames=40, fps=200.0)
    grabber = SyntheticGrabber(scene, cached=5, eager=2)
    grabber.open()
    # then it opens with the clip's first 2 frames rendered, the others not yet
    assert [entry is not None for entry in grabber._clip] == [True, True, False, False, False]
    # and a frame not rendered yet is rendered when due: the same clip frame, with its truth, as an eager one
    eager = SyntheticGrabber(scene, cached=5)
    eager.open()
    grabber._next_slot = 3
    captured = grabber.read()
    assert grabber._clip[3] is not None and grabber._clip[3][0] == eager._clip[3][0]
    truth = eager._clip[3][1]
    assert all(np.allclose(captured.truth[k].tvec, truth[k].tvec) for k in truth)


def test_close_stops_the_capture_thread():
    source = LiveSource(FakeGrabber(fps=100.0))
    source.start()
    time.sleep(0.05)
    source.close()
    assert not any(t.name == "capture:fake" and t.is_alive() for t in threading.enumerate())


def test_missing_webcam_lists_the_devices(monkeypatch):
    monkeypatch.setattr("ar_anchor.sources.live.video_devices", lambda: ["/dev/video0", "/dev/video2"])
    with pytest.raises(SourceError, match=r"^/dev/video77: no such video device .*/dev/video0, /dev/video2"):
        WebcamGrabber("/dev/video77").open()
    monkeypatch.setattr("ar_anchor.sources.live.video_devices", lambda: [])
    with pytest.raises(SourceError, match="there are none"):
        WebcamGrabber("/dev/video77").open()


def test_webcam_grabber_code_path_with_a_video_file_standing_in_for_the_device(tmp_path):
    # no camera on CI machines: drive the same grabber + capture thread with FFmpeg instead of V4L2
    images = synthetic_images(6)
    write_video(tmp_path / "cam.mkv", images)
    grabber = WebcamGrabber(str(tmp_path / "cam.mkv"), fourcc=None, api=cv2.CAP_FFMPEG)
    with LiveSource(grabber, queue_size=10) as source:
        assert source.resolution == (320, 240)
        frames = []
        for frame in source:
            frames.append(frame)
            if len(frames) == 6:
                break
    assert grabber.granted["width"] == 320 and grabber.granted["height"] == 240
    assert all(np.array_equal(f.image, images[i]) for i, f in enumerate(frames))
    assert np.all(np.diff([f.timestamp_ns for f in frames]) > 0)


# ---------------------------------------------------------------------------- what a source is, and open_source


def test_every_source_declares_what_it_is(tmp_path):
    write_video(tmp_path / "clip.mkv", synthetic_images(3), fps=25.0)
    cv2.imwrite(str(tmp_path / "shot.png"), np.zeros((8, 8, 3), np.uint8))
    scene = small_scene(frames=5, fps=20.0)
    with (
        SyntheticSource(scene) as synthetic,
        VideoFileSource(tmp_path / "clip.mkv") as video,
        ImageFolderSource(tmp_path / "shot.png", fps=5.0) as image,
        LiveSource(FakeGrabber(), fps=50.0) as live,
    ):
        assert all(isinstance(source, FrameSource) for source in (synthetic, video, image, live))
        assert synthetic.info == SourceInfo(fps=20.0, frame_count=5)
        assert video.info == SourceInfo(
            fps=pytest.approx(25.0), frame_count=3, frame_count_estimated=True, video_path=tmp_path / "clip.mkv"
        )
        assert image.info == SourceInfo(fps=5.0, frame_count=1, stills=True)
        assert live.info == SourceInfo(live=True, fps=50.0)


def test_open_source_reads_folders_globs_images_and_videos(tmp_path):
    for index in range(3):
        cv2.imwrite(str(tmp_path / f"frame_{index}.png"), np.full((8, 8, 3), index, np.uint8))
    write_video(tmp_path / "clip.mkv", synthetic_images(2))
    with open_source(tmp_path, fps=12.0) as folder:
        assert isinstance(folder, ImageFolderSource) and folder.info == SourceInfo(fps=12.0, frame_count=3, stills=True)
    with open_source(tmp_path / "frame_1.png") as image:
        assert isinstance(image, ImageFolderSource) and image.info.frame_count == 1
    with open_source(str(tmp_path / "clip.mkv")) as video:
        assert isinstance(video, VideoFileSource) and len(list(video)) == 2


def test_open_source_reads_device_specs_as_devices_unless_told_they_are_paths(tmp_path, monkeypatch):
    # given a machine with two cameras, neither of them /dev/video77
    monkeypatch.setattr("ar_anchor.sources.live.video_devices", lambda: ["/dev/video0", "/dev/video2"])
    with pytest.raises(SourceError, match=r"/dev/video77: no such video device .*/dev/video0, /dev/video2"):
        open_source("/dev/video77")
    # live=False: the spec is a path, even one that looks like a device or the synthetic camera
    monkeypatch.chdir(tmp_path)
    for spec in ("synthetic", "7"):
        with pytest.raises(SourceError, match=f"{spec}: not found"):
            open_source(spec, live=False)
    # live=True: the spec is a device, even an existing file
    write_video(tmp_path / "clip.mkv", synthetic_images(2))
    with pytest.raises(SourceError, match="cannot be opened as a V4L2 camera"):
        open_source(str(tmp_path / "clip.mkv"), live=True)


def test_open_source_synthetic_is_the_scene_in_real_time_with_its_camera_and_truth():
    scene = small_scene(frames=6, fps=30.0)
    with open_source("synthetic", scene=scene, device=DeviceSettings(queue_size=2)) as source:
        assert isinstance(source, LiveSource) and source.queue_size == 2
        assert source.info == SourceInfo(live=True, fps=30.0)
        assert source.camera is scene.camera and source.resolution == scene.camera.size
        frame = next(iter(source))
    assert frame.truth and frame.image.shape == (240, 320, 3)


def test_the_synthetic_cameras_default_scene_orbits_the_demo_targets_for_20_seconds():
    scene = live_demo_scene(fps=10.0, seed=3)
    assert (scene.frames, scene.fps, scene.seed) == (200, 10.0, 3)
    assert scene.camera.size == CameraModel.default_synthetic().size
    assert scene.trajectory.kind == "orbit"
