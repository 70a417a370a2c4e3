"""AnnotatedVideoWriter: shareable H.264 output, its fallbacks, and files that survive interruptions."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.errors import OutputError
from ar_anchor.render import video as video_out
from ar_anchor.render.video import AnnotatedVideoWriter

N = 25
WIDTH, HEIGHT = 320, 240
BACKGROUND = (150, 90, 40)  # BGR: a blue-ish colour, so a channel swap would show up


def pyav_has_libx264() -> bool:
    try:
        import av
    except ImportError:
        return False
    return "libx264" in av.codecs_available


def pattern(i: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """Frame ``i``: a 40x40 white square moving right by 8 px per frame on a coloured background."""
    image = np.empty((height, width, 3), np.uint8)
    image[:] = BACKGROUND
    x = 10 + 8 * i
    image[60:100, x : x + 40] = 255
    return image


def read_all(path: Path) -> list[np.ndarray]:
    """Every frame OpenCV can decode, counted by reading until it fails."""
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened(), f"OpenCV cannot open {path}"
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
    finally:
        cap.release()
    return frames


def mad(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference in grey levels."""
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


def square_left_edge(frame: np.ndarray) -> float:
    """Leftmost column of the white square in a decoded frame (mean over its rows)."""
    bright = frame[60:100].min(axis=2) > 200
    return float(np.mean([np.argmax(row) for row in bright]))


def write_pattern(path: Path, frames: int = N, width: int = WIDTH, height: int = HEIGHT) -> AnnotatedVideoWriter:
    with AnnotatedVideoWriter(path, fps=30.0) as writer:
        for i in range(frames):
            writer.write(pattern(i, width, height))
    return writer


@pytest.fixture
def warnings_log(caplog, monkeypatch):
    # the CLI's logging setup turns propagation off on "ar_anchor"; make sure caplog sees records
    monkeypatch.setattr(logging.getLogger("ar_anchor"), "propagate", True)
    caplog.set_level(logging.WARNING, logger="ar_anchor.render.video")
    return caplog


# ============================================================================ H.264


def test_mp4_reads_back_every_frame_close_to_what_was_written(tmp_path):
    path = tmp_path / "annotated.mp4"
    writer = write_pattern(path)

    assert path.is_file() and path.stat().st_size > 0
    assert writer.frames == N
    if pyav_has_libx264():
        assert writer.codec == "h264"
    else:
        assert writer.codec == "mp4v"
    decoded = read_all(path)
    assert len(decoded) == N
    assert decoded[0].shape == (HEIGHT, WIDTH, 3)
    errors = [mad(frame, pattern(i)) for i, frame in enumerate(decoded)]
    # measured 2.38 for H.264 and mp4v (mostly BGR<->YUV rounding in swscale); swapped B/R channels give ~72
    assert max(errors) < 6, errors
    # frames are in order and not shifted: the square is where frame i put it
    for i, frame in enumerate(decoded):
        assert square_left_edge(frame) == pytest.approx(10 + 8 * i, abs=1), f"frame {i}"


def test_mp4_is_h264_at_the_requested_frame_rate(tmp_path):
    if not pyav_has_libx264():
        pytest.skip("PyAV with libx264 is not installed")
    import av

    path = tmp_path / "annotated.mp4"
    write_pattern(path)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert stream.average_rate == 30
        assert sum(1 for _ in container.decode(stream)) == N


@pytest.mark.parametrize("suffix", [".mkv", ".mov"])
def test_other_h264_containers_read_back(tmp_path, suffix):
    path = tmp_path / f"annotated{suffix}"
    write_pattern(path)
    assert len(read_all(path)) == N


def test_odd_frame_size_is_padded_to_even_by_replicating_the_edge(tmp_path):
    path = tmp_path / "odd.mp4"
    writer = write_pattern(path, width=321, height=241)

    assert writer.size == (321, 241)
    decoded = read_all(path)
    assert len(decoded) == N
    # 4:2:0 needs even sizes: one replicated column and row are added, nothing is cropped
    assert decoded[0].shape == (242, 322, 3), "expected 321x241 padded to 322x242"
    for i, frame in enumerate(decoded):
        assert mad(frame[:241, :321], pattern(i, 321, 241)) < 6
    # the padding repeats the last column / row (the background colour there)
    assert mad(decoded[0][:, 321], decoded[0][:, 320]) < 6
    assert mad(decoded[0][241], decoded[0][240]) < 6


# ============================================================================ errors


def test_frame_size_change_is_refused_and_earlier_frames_survive(tmp_path):
    path = tmp_path / "resize.mp4"
    writer = AnnotatedVideoWriter(path)
    try:
        for i in range(5):
            writer.write(pattern(i))
        with pytest.raises(OutputError) as excinfo:
            writer.write(pattern(5, 160, 120))
    finally:
        writer.close()

    message = str(excinfo.value)
    assert str(path) in message
    assert "frame 5" in message
    assert "160x120" in message and "320x240" in message
    assert "\n" not in message
    assert len(read_all(path)) == 5


@pytest.mark.parametrize("name", ["out.gif", "out.webm", "out"])
def test_unsupported_extension_is_refused_in_init(tmp_path, name):
    path = tmp_path / name
    with pytest.raises(OutputError, match="supported") as excinfo:
        AnnotatedVideoWriter(path)
    assert str(path) in str(excinfo.value)
    assert ".mp4" in str(excinfo.value) and ".avi" in str(excinfo.value)
    assert not path.exists()


@pytest.mark.parametrize("fps", [0, -5.0, float("nan"), float("inf")])
def test_bad_frame_rate_is_refused(tmp_path, fps):
    path = tmp_path / "out.mp4"
    with pytest.raises(OutputError, match="frame rate") as excinfo:
        AnnotatedVideoWriter(path, fps=fps)
    assert str(path) in str(excinfo.value)


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_missing_directory_fails_at_first_write_with_the_os_reason(tmp_path, suffix):
    path = tmp_path / "no_such_dir" / f"out{suffix}"
    writer = AnnotatedVideoWriter(path)  # nothing is opened yet
    with pytest.raises(OutputError) as excinfo:
        writer.write(pattern(0))
    writer.close()

    message = str(excinfo.value)
    assert str(path) in message
    assert "No such file or directory" in message
    assert "\n" not in message and "Traceback" not in message
    assert not path.parent.exists()


def test_encoder_that_refuses_to_start_leaves_no_file(tmp_path, monkeypatch):
    if not pyav_has_libx264():
        pytest.skip("PyAV with libx264 is not installed")
    monkeypatch.setattr(video_out, "_H264_OPTIONS", {"preset": "no-such-preset"})
    path = tmp_path / "out.mp4"
    with AnnotatedVideoWriter(path) as writer:
        with pytest.raises(OutputError, match="H.264 encoder") as excinfo:
            writer.write(pattern(0))
    assert str(path) in str(excinfo.value)
    assert not path.exists()


def test_bad_frames_are_refused(tmp_path):
    path = tmp_path / "out.mp4"
    with AnnotatedVideoWriter(path) as writer:
        with pytest.raises(OutputError, match="uint8"):
            writer.write(pattern(0).astype(np.float32))
        with pytest.raises(OutputError, match=r"\(H, W, 3\)"):
            writer.write(np.zeros((HEIGHT, WIDTH), np.uint8))
        assert writer.frames == 0
    assert not path.exists()


# ============================================================================ closing


def test_close_twice_is_fine_and_writing_after_close_is_refused(tmp_path):
    path = tmp_path / "out.mp4"
    writer = AnnotatedVideoWriter(path)
    for i in range(3):
        writer.write(pattern(i))
    writer.close()
    writer.close()
    assert len(read_all(path)) == 3
    with pytest.raises(OutputError, match="closed"):
        writer.write(pattern(3))


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_closing_without_frames_leaves_no_file(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    with AnnotatedVideoWriter(path) as writer:
        pass
    writer.close()
    assert writer.frames == 0
    assert writer.codec is None
    assert not path.exists()


@pytest.mark.parametrize("suffix", [".mp4", ".mkv", ".avi"])
def test_exception_inside_with_block_still_leaves_a_playable_file(tmp_path, suffix):
    path = tmp_path / f"interrupted{suffix}"
    with pytest.raises(RuntimeError, match="boom"):
        with AnnotatedVideoWriter(path) as writer:
            for i in range(N):
                if i == 10:
                    raise RuntimeError("boom")
                writer.write(pattern(i))

    decoded = read_all(path)
    assert len(decoded) == 10
    assert mad(decoded[9], pattern(9)) < 6


# ============================================================================ fallbacks


def test_avi_uses_opencv_mjpg(tmp_path):
    path = tmp_path / "annotated.avi"
    writer = write_pattern(path)

    assert writer.codec == "mjpg"
    decoded = read_all(path)
    assert len(decoded) == N
    assert max(mad(frame, pattern(i)) for i, frame in enumerate(decoded)) < 6


def _no_pyav(monkeypatch):
    def fail():
        raise ImportError("simulated: PyAV is not installed")

    monkeypatch.setattr(video_out, "_load_pyav", fail)


def _pyav_not_importable(monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)  # `import av` raises ImportError


def _pyav_without_libx264(monkeypatch):
    av = pytest.importorskip("av")

    def no_encoder(name, mode="r"):
        raise av.codec.codec.UnknownCodecError(name)

    monkeypatch.setattr(av.codec, "Codec", no_encoder)


@pytest.mark.parametrize("simulate", [_no_pyav, _pyav_not_importable, _pyav_without_libx264])
def test_without_h264_falls_back_to_mp4v_with_one_warning(tmp_path, monkeypatch, warnings_log, simulate):
    simulate(monkeypatch)
    path = tmp_path / "fallback.mp4"
    writer = write_pattern(path)

    assert writer.codec == "mp4v"
    warnings = [r for r in warnings_log.records if r.name == "ar_anchor.render.video" and r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "H.264 is unavailable" in warnings[0].getMessage()
    assert "mp4v" in warnings[0].getMessage()
    decoded = read_all(path)
    assert len(decoded) == N
    assert max(mad(frame, pattern(i)) for i, frame in enumerate(decoded)) < 6


def test_fallback_pads_odd_sizes_too(tmp_path, monkeypatch, warnings_log):
    # OpenCV's writer would silently crop 321x241 to 320x240; padding keeps every input pixel
    _no_pyav(monkeypatch)
    path = tmp_path / "odd_fallback.mp4"
    write_pattern(path, frames=5, width=321, height=241)
    decoded = read_all(path)
    assert len(decoded) == 5
    assert decoded[0].shape == (242, 322, 3), "expected 321x241 padded to 322x242"
