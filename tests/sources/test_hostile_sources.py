"""Hostile frame sources (issue 18): what the sources do with input built to mislead them.

A video whose frame size changes mid-stream (stopped at the change, not rescaled), a valid
variable-frame-rate MKV (not "damaged"), sidecar timestamps that would collapse or overflow the
timeline (refused naming file and line), a FIFO / socket / huge sparse file where a file is due
(typed and sized before it is read), libjpeg's own lines on stderr (ours only), and frame rates and
device settings out of range (an InputError naming the option, exit 2).
"""

from __future__ import annotations

import csv
import fractions
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.errors import InputError, SourceError
from ar_anchor.sources import DeviceSettings, ImageFolderSource, VideoFileSource, open_source
from ar_anchor.sources.files import MAX_IMAGE_BYTES
from ar_anchor.sources.open import live_demo_scene
from ar_anchor.sources.video import read_timestamps_csv
from tests.helpers import assert_clean_exit, error_lines, run_main

SMALL, LARGE = (320, 240), (480, 360)


def _image(size: tuple[int, int], shade: int) -> np.ndarray:
    width, height = size
    image = np.full((height, width, 3), shade, np.uint8)
    cv2.circle(image, (width // 2, height // 2), height // 4, (255, 255, 255), -1)
    return image


def write_stream(path: Path, parts: list[tuple[tuple[int, int], list[int]]], codec: str = "mjpeg") -> None:
    """One video stream whose frames come from several encoders: ``parts`` lists (size, pts in 1/30 s) for each,
    so the frame size may change mid-stream and the timestamps may be irregular (variable frame rate)."""
    pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=30)
        stream.width, stream.height = parts[0][0]
        stream.pix_fmt = pix_fmt
        for k, (size, times) in enumerate(parts):
            encoder = av.CodecContext.create(codec, "w")
            encoder.width, encoder.height = size
            encoder.pix_fmt = pix_fmt
            encoder.time_base = fractions.Fraction(1, 30)
            encoder.framerate = 30
            for pts in times:
                frame = av.VideoFrame.from_ndarray(_image(size, 60 + 40 * k), format="bgr24")
                frame.pts, frame.time_base = pts, fractions.Fraction(1, 30)
                for packet in encoder.encode(frame):
                    packet.stream = stream
                    out.mux(packet)
            for packet in encoder.encode(None):
                packet.stream = stream
                out.mux(packet)


@pytest.fixture
def camera_file(tmp_path: Path) -> Path:
    path = tmp_path / "cam.yml"
    CameraModel.from_fov(*SMALL, 60.0).to_yaml(path)
    return path


def replay(source: Path, camera: Path, out: Path, *extra: str):
    result = run_main(["-q", "replay", str(source), "--camera", str(camera), "--out", str(out), *extra])
    assert_clean_exit(result)
    return result


def poses_frames(out: Path) -> set[int]:
    with (out / "poses.csv").open(newline="", encoding="utf-8") as handle:
        rows = list(csv.reader(handle))
    assert rows and rows[0][0] == "frame" and all(len(row) == len(rows[0]) for row in rows)
    return {int(row[0]) for row in rows[1:]}


# ============================================================================ 1. frame size changes mid-stream


@pytest.mark.parametrize(("name", "codec"), [("sizes.mkv", "mjpeg"), ("sizes.ts", "libx264"), ("sizes.avi", "mjpeg")])
def test_a_frame_size_change_mid_stream_stops_the_stream_there(tmp_path, name, codec):
    # given 10 frames of 320x240, then 10 of 480x360 in the same stream (OpenCV would rescale them to 320x240)
    path = tmp_path / name
    write_stream(path, [(SMALL, list(range(10))), (LARGE, list(range(10, 20)))], codec)
    # when it is read
    with VideoFileSource(path) as source:
        frames = list(source)
        info = source.info
    # then the 10 frames of the first size are delivered, and the source says where and why it stopped
    assert [f.index for f in frames] == list(range(10)) and all(f.size == SMALL for f in frames)
    assert info.ended_early
    assert "frame 10 is 480x360, the frames before it 320x240" in info.ended_because


def test_replay_of_a_video_that_changes_size_ends_with_one_line_and_complete_outputs(tmp_path, camera_file):
    path = tmp_path / "sizes.mkv"
    write_stream(path, [(SMALL, list(range(8))), (LARGE, list(range(8, 16)))])
    result = replay(path, camera_file, tmp_path / "out")
    errors = error_lines(result.stderr)
    assert result.code == 1 and len(errors) == 1, result.describe()
    assert "sizes.mkv" in errors[0] and "frame 8 is 480x360" in errors[0] and "320x240" in errors[0]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
    assert summary["status"] == "completed" and summary["frames"] == 8 and summary["source_ended_early"] is True
    assert poses_frames(tmp_path / "out") <= set(range(8))


# ============================================================================ 2. variable frame rate


@pytest.mark.parametrize("name", ["vfr.mkv", "vfr.webm"])
def test_a_variable_frame_rate_file_is_not_damaged_because_its_estimated_count_is_not_met(tmp_path, name):
    # given 12 frames at 30 fps, a 3 s pause, 3 more: duration x rate estimates ~100 frames, the file holds 15
    path = tmp_path / name
    codec = "libvpx" if name.endswith(".webm") else "mjpeg"
    write_stream(path, [(SMALL, list(range(12)) + [100, 101, 102])], codec)
    with VideoFileSource(path) as source:
        frames = list(source)
        info = source.info
    assert len(frames) == 15
    assert info.frame_count_estimated and (info.frame_count or 0) > 15  # an estimate, for progress only
    assert not info.ended_early and info.ended_because == ""
    assert frames[12].timestamp_ns - frames[11].timestamp_ns == pytest.approx(89 / 30 * 1e9, abs=1e6)


def test_replay_of_a_variable_frame_rate_mkv_exits_0(tmp_path, camera_file):
    path = tmp_path / "vfr.mkv"
    write_stream(path, [(SMALL, list(range(6)) + [60, 61])])
    result = replay(path, camera_file, tmp_path / "out")
    assert result.code == 0 and not error_lines(result.stderr), result.describe()


# ============================================================================ 3. sidecar timestamps

SIDECARS = {
    "every frame index 0": ("0,0\n0,33333333\n0,66666666\n", "line 3: frame 0 does not follow frame 0"),
    "timestamp 1e30 (digits)": ("0,0\n1," + "1" + "0" * 30 + "\n", "line 3: timestamp_ns 1000"),
    "timestamp near 2^63": (f"0,0\n1,{2**63 - 1}\n", "line 3: timestamp_ns 9223372036854775807 is out of range"),
    "negative timestamp": ("0,-5\n", "line 2: timestamp_ns -5 is out of range"),
    "negative frame": ("-1,5\n", "line 2: frame -1 is out of range"),
    "non-monotonic timestamps": ("0,100\n1,200\n2,150\n", "line 4: timestamp_ns 150 does not follow 200"),
    "NaN": ("0,0\n1,nan\n", "line 3: timestamp_ns 'nan' is not an integer"),
    "1e30 in float notation": ("0,0\n1,1e30\n", "line 3: timestamp_ns '1e30' is not an integer"),
    "empty field": ("0,0\n1,\n", "line 3: timestamp_ns '' is not an integer"),
}


@pytest.mark.parametrize("case", list(SIDECARS))
def test_bad_sidecar_timestamps_are_refused_naming_file_and_line(tmp_path, case):
    body, message = SIDECARS[case]
    path = tmp_path / "clip.mkv.timestamps.csv"
    path.write_text("frame,timestamp_ns\n" + body, encoding="utf-8")
    with pytest.raises(SourceError, match="clip.mkv.timestamps.csv " + message.replace("(", r"\(").replace("^", r"\^")):
        read_timestamps_csv(path)


def test_good_sidecar_timestamps_are_read(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("frame,timestamp_ns\n0,5\n2,40\n7,1000000000000000000\n", encoding="utf-8")
    assert read_timestamps_csv(path) == [(0, 5), (2, 40), (7, 10**18)]


def test_replay_with_an_overflowing_sidecar_exits_2_naming_it(tmp_path, camera_file):
    path = tmp_path / "clip.mkv"
    write_stream(path, [(SMALL, list(range(3)))])
    Path(f"{path}.timestamps.csv").write_text(f"frame,timestamp_ns\n0,0\n1,{10**30}\n2,{10**30 + 1}\n")
    result = replay(path, camera_file, tmp_path / "out")
    errors = error_lines(result.stderr)
    assert result.code == 2 and len(errors) == 1 and "clip.mkv.timestamps.csv line 3" in errors[0], result.describe()
    assert not (tmp_path / "out" / "poses.csv").exists()


# ============================================================================ 4. FIFOs, sockets, huge files


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "pipe.mp4"
    os.mkfifo(path)
    return path


@pytest.fixture
def unix_socket():
    folder = tempfile.mkdtemp(prefix="h3s")  # short: a socket path is at most ~107 bytes
    path = Path(folder) / "sock.avi"
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(path))
    yield path
    server.close()
    shutil.rmtree(folder, ignore_errors=True)


def test_a_fifo_or_a_socket_given_as_source_is_named_for_what_it_is(fifo, unix_socket):
    with pytest.raises(SourceError, match=r"pipe.mp4: is a named pipe \(FIFO\), not a video"):
        open_source(fifo)
    with pytest.raises(SourceError, match=r"sock.avi: is a socket, not a video"):
        open_source(unix_socket)
    with pytest.raises(SourceError, match=r"pipe.mp4: is a named pipe \(FIFO\), not a video"):
        VideoFileSource(fifo)
    with pytest.raises(SourceError, match=r"pipe.mp4: is a named pipe \(FIFO\), not a video device"):
        open_source(fifo, live=True)


def test_a_fifo_as_timestamp_sidecar_is_refused_without_blocking(tmp_path, fifo):
    path = tmp_path / "clip.mkv"
    write_stream(path, [(SMALL, [0, 1])])
    with pytest.raises(SourceError, match=r"pipe.mp4: is a named pipe \(FIFO\), not a timestamp file"):
        VideoFileSource(path, timestamps=fifo)


def test_replay_of_a_fifo_exits_2_saying_what_it_is(tmp_path, fifo, camera_file):
    result = replay(fifo, camera_file, tmp_path / "out")
    errors = error_lines(result.stderr)
    assert result.code == 2 and len(errors) == 1 and "named pipe (FIFO)" in errors[0], result.describe()


def test_a_huge_sparse_image_is_skipped_without_being_read(tmp_path, caplog):
    for index in range(2):
        assert cv2.imwrite(str(tmp_path / f"f_{index}.png"), _image(SMALL, 80))
    with (tmp_path / "f_2.png").open("wb") as handle:  # sparse: takes no disk, would take seconds to read
        handle.truncate(MAX_IMAGE_BYTES + 1)
    with ImageFolderSource(tmp_path) as source:
        frames = list(source)
    assert [f.index for f in frames] == [0, 1] and source.skipped == 1
    assert any("f_2.png: not a readable image" in r.getMessage() for r in caplog.records)


# ============================================================================ 5. libjpeg's own lines


def _corrupt_jpeg_folder(folder: Path) -> Path:
    """Three JPEGs, the middle one with bytes libjpeg calls extraneous (2 of the 3 added) before its end marker."""
    folder.mkdir()
    for index in range(3):
        ok, data = cv2.imencode(".jpg", _image(SMALL, 90))
        assert ok
        blob = data.tobytes()
        if index == 1:
            blob = blob[:-2] + b"\x00\x00\x00" + blob[-2:]
        (folder / f"f_{index}.jpg").write_bytes(blob)
    return folder / "f_1.jpg"


def test_libjpeg_lines_do_not_reach_stderr_ours_names_the_file(tmp_path, capfd, caplog):
    damaged = _corrupt_jpeg_folder(tmp_path / "shots")
    levels = cv2.utils.logging
    previous = levels.getLogLevel()
    levels.setLogLevel(levels.LOG_LEVEL_SILENT)  # as the command line sets it below -vv
    try:
        with ImageFolderSource(tmp_path / "shots") as source:
            frames = list(source)
    finally:
        levels.setLogLevel(previous)
    assert len(frames) == 3
    raw = [line for line in capfd.readouterr().err.splitlines() if line.startswith("Corrupt JPEG data")]
    assert not raw, raw  # libjpeg's own line (our logger's lines may reach stderr too: theirs must not)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(str(damaged) in m and "Corrupt JPEG data: 2 extraneous bytes" in m for m in warnings), warnings


@pytest.mark.slow
@pytest.mark.parametrize(("verbosity", "libjpeg_shown"), [([], False), (["-vv"], True)])
def test_libjpeg_lines_only_at_vv_through_the_command_line(tmp_path, camera_file, verbosity, libjpeg_shown):
    _corrupt_jpeg_folder(tmp_path / "shots")
    command = [sys.executable, "-m", "ar_anchor", *verbosity, "replay", "shots", "--camera", str(camera_file)]
    result = subprocess.run(
        [*command, "--out", "out"], cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False
    )
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if "Corrupt JPEG data" in line]
    ours = [line for line in lines if line.startswith("ar-anchor: WARNING: shots/f_1.jpg: damaged image data")]
    libjpeg = [line for line in lines if line.startswith("Corrupt JPEG data")]
    assert len(ours) == 1, result.stderr
    assert bool(libjpeg) == libjpeg_shown, result.stderr


# ============================================================================ 6. frame rates and device settings


@pytest.mark.parametrize("fps", [1e300, 1e-300, float("nan"), float("inf"), 0.0, -5.0, 5000.0])
def test_live_and_synthetic_frame_rates_are_range_checked_naming_the_option(fps):
    with pytest.raises(InputError, match=r"--fps: must be in \[0.01, 1000\] fps"):
        live_demo_scene(fps=fps)
    with pytest.raises(InputError, match=r"--fps: must be in \[0.01, 1000\] fps"):
        open_source("/dev/video77", fps=fps)


@pytest.mark.parametrize("fps", [1e300, 1e-300, float("nan")])
def test_image_sequence_frame_rates_are_range_checked_naming_the_option(tmp_path, fps):
    assert cv2.imwrite(str(tmp_path / "a.png"), _image(SMALL, 50))
    with pytest.raises(SourceError, match=r"--fps: must be in \[0.001, 1e\+06\]"):
        open_source(tmp_path, fps=fps)


@pytest.mark.parametrize(
    ("settings", "option"),
    [
        ({"width": 10**9}, "--width"),
        ({"height": 0}, "--height"),
        ({"fourcc": "AB"}, "--fourcc"),
        ({"fourcc": "MJPGX"}, "--fourcc"),
        ({"queue_size": 10**9}, "--queue"),
        ({"reconnect_s": float("nan")}, "--reconnect-s"),
        ({"reconnect_s": 1e300}, "--reconnect-s"),
        ({"stall_s": 0.0}, "--stall-s"),
        ({"stall_s": float("inf")}, "--stall-s"),
    ],
)
def test_device_settings_are_range_checked_naming_the_option(settings, option):
    with pytest.raises(InputError, match=f"^{option}: "):
        DeviceSettings(**settings)


@pytest.mark.parametrize("fps", ["1e300", "1e-300"])
def test_live_with_an_absurd_fps_exits_2_naming_it(tmp_path, fps):
    result = run_main(
        ["-q", "live", "--device", "synthetic", "--fps", fps, "--max-frames", "1", "--out", str(tmp_path)]
    )
    assert_clean_exit(result)
    errors = error_lines(result.stderr)
    assert result.code == 2 and len(errors) == 1 and "--fps" in errors[0], result.describe()


# ============================================================================ what did not change


@pytest.mark.parametrize(
    ("codec", "pix_fmt", "size", "colorspace", "rotation"),
    [
        ("libx264", "yuv420p", (1920, 1080), 1, 0),  # BT.709 HD, coded height 1088
        ("libx264", "yuv420p10le", (322, 242), None, 0),
        ("libx264", "yuv444p", (320, 240), None, 90),
        ("ffv1", "gray16le", (320, 240), None, 0),
        ("mjpeg", "yuvj422p", (320, 240), None, -90),
    ],
)
def test_decoded_frames_and_times_are_those_opencv_gives(tmp_path, codec, pix_fmt, size, colorspace, rotation):
    # given a short clip in one of the formats cameras and tools write
    path = tmp_path / ("clip.mp4" if codec != "ffv1" else "clip.mkv")
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur((rng.random((size[1], size[0], 3)) * 255).astype(np.uint8), (0, 0), 2)
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=30)
        stream.width, stream.height = size
        stream.pix_fmt = pix_fmt
        if colorspace is not None:
            stream.codec_context.colorspace = colorspace
        if rotation:
            stream.set_display_rotation(rotation)
        for index in range(4):
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.roll(texture, 5 * index, 1), format="bgr24")):
                out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)
    # when both read it
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    expected, positions = [], []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        expected.append(image)
        positions.append(capture.get(cv2.CAP_PROP_POS_MSEC))
    capture.release()
    with VideoFileSource(path) as source:
        frames = list(source)
    # then the pixels (conversion, rotation) and timestamps are OpenCV's, bit for bit
    assert len(frames) == len(expected) == 4
    assert all(np.array_equal(frame.image, image) for frame, image in zip(frames, expected))
    assert [f.timestamp_ns for f in frames] == [int(round((ms - positions[0]) * 1e6)) for ms in positions]
