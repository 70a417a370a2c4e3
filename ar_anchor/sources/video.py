"""Video files, decoded by FFmpeg through PyAV, frame by frame as the decoder delivers them.

The pixels are those OpenCV's FFmpeg backend gives (the same libraries, the same BGR conversion,
display rotation applied as OpenCV applies it), and so are the timestamps (``CAP_PROP_POS_MSEC``'s
arithmetic). What PyAV adds is the decoder's own view of each frame: a stream whose frame size
changes mid-stream is stopped at the change (OpenCV would silently rescale every later frame to the
first size, and the poses of those frames would be wrong), and a frame count the container only
estimates (duration x rate, as in MKV and WebM) is used for progress, never as evidence of damage.

A ``<video>.timestamps.csv`` sidecar (``ar-anchor live --record`` writes it) replaces the decode
positions with the recorded frame indices and capture times; each of its rows is checked where it
is read (indices and times strictly increasing, times within 0..2^62 ns) and a bad one is refused
naming the file and line.
"""

from __future__ import annotations

import csv
import logging
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..camera import CameraModel
from ..camera.files import opencv_path_problem
from ..errors import SourceError, printable
from ..lazy import import_held
from .base import ClosingSource, Frame, SourceInfo
from .checks import source_file_stat
from .image_header import MAX_IMAGE_PIXELS, pixel_limit_text

if TYPE_CHECKING:  # PyAV (0.05-0.1 s) is imported when a video is opened: a demo or image folder needs none
    import av

__all__ = ["MAX_SIDECAR_BYTES", "MAX_TIMESTAMP_NS", "VideoFileSource", "read_timestamps_csv"]

log = logging.getLogger(__name__)

MAX_TIMESTAMP_NS = 1 << 62  # 146 years: room for any clock's nanoseconds, and for arithmetic on them in int64
MAX_SIDECAR_BYTES = 1 << 30  # a timestamp row is ~25 bytes: ten hours at 1000 fps fit in a GiB


def read_timestamps_csv(path: Path) -> list[tuple[int, int]]:
    """Rows (frame, timestamp_ns) of a recorded session's timestamp file, each checked: integers, frame
    indices and timestamps strictly increasing, in ``0..MAX_TIMESTAMP_NS``. A
    :class:`~ar_anchor.errors.SourceError` names the file and the line of the first bad row."""
    name = printable(path)
    source_file_stat(path, what="a timestamp file", max_bytes=MAX_SIDECAR_BYTES)
    rows: list[tuple[int, int]] = []
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames is None or not {"frame", "timestamp_ns"} <= set(reader.fieldnames):
                raise SourceError(f"{name}: expected columns frame,timestamp_ns")
            for row in reader:
                rows.append(_timestamp_row(row, rows[-1] if rows else None, f"{name} line {reader.line_num}"))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise SourceError(f"{name}: unreadable timestamp file ({err})") from None
    return rows


def _timestamp_row(row: dict[str, str | None], previous: tuple[int, int] | None, where: str) -> tuple[int, int]:
    """One sidecar row as (frame, timestamp_ns), or a SourceError naming ``where`` (file and line)."""
    values = []
    for column in ("frame", "timestamp_ns"):
        text = (row.get(column) or "").strip()
        try:
            value = int(text)
        except ValueError:
            raise SourceError(f"{where}: {column} {printable(text)[:40]!r} is not an integer") from None
        if not 0 <= value <= MAX_TIMESTAMP_NS:
            raise SourceError(f"{where}: {column} {printable(text)[:40]} is out of range (0 .. 2^62)")
        values.append(value)
    frame, timestamp_ns = values
    if previous is not None and frame <= previous[0]:
        raise SourceError(f"{where}: frame {frame} does not follow frame {previous[0]} (frame indices must increase)")
    if previous is not None and timestamp_ns <= previous[1]:
        raise SourceError(
            f"{where}: timestamp_ns {timestamp_ns} does not follow {previous[1]} (timestamps must increase)"
        )
    return frame, timestamp_ns


class VideoFileSource(ClosingSource):
    """Frames of a video file, with container timestamps.

    Parameters
    ----------
    path : the video.
    timestamps : optional ``frame,timestamp_ns`` CSV (default: ``<video>.timestamps.csv`` when it
        exists, as ``ar-anchor live --record`` writes it): restores a recorded session's original
        frame indices and capture timestamps.
    """

    camera: CameraModel | None = None

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        timestamps: str | os.PathLike[str] | None = None,
        max_pixels: int = MAX_IMAGE_PIXELS,
    ) -> None:
        self.path = Path(path)
        self._max_pixels = int(max_pixels)
        self._name = printable(self.path)
        source_file_stat(self.path, what="a video")
        problem = opencv_path_problem(self.path)
        if problem is not None:
            raise SourceError(f"{self._name}: {problem}")
        sidecar = (
            Path(timestamps) if timestamps is not None else self.path.with_name(self.path.name + ".timestamps.csv")
        )
        self._recorded: list[tuple[int, int]] | None = None
        if timestamps is not None or sidecar.is_file():
            self._recorded = read_timestamps_csv(sidecar)
            log.info("using recorded frame indices and timestamps from %s", printable(sidecar))
        self._container = self._open()
        try:
            self._setup()
        except BaseException:
            self._container.close()
            raise

    def _open(self) -> av.container.InputContainer:
        av = import_held("av")  # whole: a Ctrl-C while it loads is raised once it is loaded (ar_anchor.lazy)
        try:
            container = av.open(str(self.path), "r")
        except (av.FFmpegError, OSError, UnicodeError) as err:
            log.debug("%s: %s", self._name, err)
            raise SourceError(
                f"{self._name}: cannot be opened as a video (not a video, or a codec FFmpeg lacks)"
            ) from None
        if not container.streams.video:
            container.close()
            raise SourceError(f"{self._name}: holds no video stream")
        return container

    def _setup(self) -> None:
        from av.video.reformatter import VideoReformatter

        stream = self._container.streams.video[0]
        width, height = stream.codec_context.width or 0, stream.codec_context.height or 0  # (the header's)
        if width * height > self._max_pixels:
            raise SourceError(
                f"{self._name}: frames of {width}x{height} pixels ({width * height / 1e6:.3g} MP), more than the "
                f"{pixel_limit_text(self._max_pixels)} MP limit (--max-megapixels)"
            )
        stream.thread_type = "AUTO"  # frame and slice threads, as OpenCV decodes
        self._stream = stream
        self._time_base = stream.time_base.numerator / stream.time_base.denominator if stream.time_base else 0.0
        self._start = stream.start_time if stream.start_time is not None else 0
        self._damaged = False
        self._reformatter = VideoReformatter()
        self._decoded = self._frames()
        first = next(self._decoded, None)
        if first is None:
            raise SourceError(f"{self._name}: no frame could be decoded (damaged or not a video)")
        self._first, self._first_ms = self._image(first), self._position_ms(first)
        self._decoded_size = (first.width, first.height)
        self._resolution = (self._first.shape[1], self._first.shape[0])
        rate = stream.guessed_rate
        fps = float(rate) if rate else 0.0
        self._fps: float | None = fps if math.isfinite(fps) and fps > 0 else None
        # the container's count (MP4, AVI headers) is exact; without one (MKV, WebM) duration x rate is a guess
        self._count_exact = stream.frames > 0
        self._count: int | None = stream.frames if self._count_exact else self._estimated_count()
        self._ended_early = False
        self._ended_because = ""

    def _estimated_count(self) -> int | None:
        """Duration x frame rate (what OpenCV reports as the frame count when the container has none)."""
        import av

        if self._stream.duration is not None and self._time_base > 0:
            seconds = self._stream.duration * self._time_base
        elif self._container.duration is not None:
            seconds = self._container.duration / av.time_base
        else:
            return None
        count = int(math.floor(seconds * (self._fps or 0.0) + 0.5)) if self._fps else 0
        return count if count > 0 else None

    def _frames(self) -> Iterator[av.VideoFrame]:
        """Decoded frames, up to the first packet the container cannot read or the decoder refuses: the frames
        after it would be built on broken references, so the stream ends there (and counts as damaged), as
        OpenCV ends it."""
        import av

        packets = self._container.demux(self._stream)
        while True:
            try:
                packet = next(packets)
                frames = packet.decode()
            except StopIteration:
                return
            except (av.FFmpegError, OSError, ValueError) as err:
                log.debug("%s: read or decode error: %s", self._name, err)
                self._damaged = True
                return
            yield from frames

    def _image(self, frame: av.VideoFrame) -> np.ndarray:
        """BGR uint8, as OpenCV's FFmpeg backend converts it (bicubic swscale), turned upright by the display
        rotation the way OpenCV turns it."""
        # one reformatter for the stream keeps its swscale context; one thread: the decoder has the others
        image = self._reformatter.reformat(frame, format="bgr24", interpolation="BICUBIC", threads=1).to_ndarray()
        turns = round((frame.rotation or 0) / 90) % 4
        return np.ascontiguousarray(np.rot90(image, turns)) if turns else image

    def _position_ms(self, frame: av.VideoFrame) -> float:
        """``CAP_PROP_POS_MSEC`` of ``frame``: its pts (its packet's dts when it has none, or 0), from the stream
        start, in milliseconds; 0 when it has neither."""
        pts = frame.pts if frame.pts is not None and frame.pts != 0 else frame.dts
        if pts is None:
            return 0.0
        return (pts - self._start) * self._time_base * 1000

    @property
    def resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def info(self) -> SourceInfo:
        """The container's frame rate and count (``frame_count_estimated`` when it only guesses it);
        ``video_path`` is this file unless recorded indices replace the decode positions."""
        return SourceInfo(
            fps=self._fps,
            frame_count=self._count,
            frame_count_estimated=not self._count_exact,
            video_path=self.path if self._recorded is None else None,
            ended_early=self._ended_early,
            ended_because=self._ended_because,
        )

    def close(self) -> None:
        self._decoded.close()
        self._container.close()

    def __iter__(self) -> Iterator[Frame]:
        image: np.ndarray | None = self._first
        position_ms = self._first_ms
        index = 0
        previous_ns: int | None = None
        while image is not None:
            frame_index, timestamp_ns = self._timestamp(index, position_ms, previous_ns)
            previous_ns = timestamp_ns
            yield Frame(image, frame_index, timestamp_ns)
            index += 1
            image = None
            frame = next(self._decoded, None)
            if frame is not None and (frame.width, frame.height) != self._decoded_size:
                self._stop_at_size_change(index, frame)
                return
            if frame is not None:
                image, position_ms = self._image(frame), self._position_ms(frame)
        self._check_end(index)

    def _stop_at_size_change(self, index: int, frame: av.VideoFrame) -> None:
        because = (
            f"frame {index} is {frame.width}x{frame.height}, the frames before it "
            f"{self._decoded_size[0]}x{self._decoded_size[1]} (the frame size changes mid-stream): stopped there"
        )
        log.warning("%s: %s; outputs cover frames 0..%d", self._name, because, index - 1)
        self._ended_early, self._ended_because = True, because

    def _check_end(self, delivered: int) -> None:
        """Whether the stream ended before its end: fewer frames than the container's exact count, or a
        container that could not be read to its end. An estimated count is no evidence either way."""
        short = self._count_exact and self._count is not None and delivered < self._count
        if not (short or self._damaged):
            return
        of = f" of {self._count}" if short else ""
        log.warning(
            "%s: stream ended after frame %d%s (damaged or truncated file); outputs cover frames 0..%d",
            self._name,
            delivered - 1,
            of,
            delivered - 1,
        )
        self._ended_early = True
        self._ended_because = "the stream ended early (damaged or truncated file)"

    def _timestamp(self, index: int, position_ms: float, previous_ns: int | None) -> tuple[int, int]:
        if self._recorded is not None and index < len(self._recorded):
            return self._recorded[index]
        if self._recorded is not None and index == len(self._recorded):
            log.warning(
                "%s: more frames than its timestamp file lists; using container time from frame %d", self._name, index
            )
        timestamp_ns = int(round((position_ms - self._first_ms) * 1e6)) if math.isfinite(position_ms) else -1
        if previous_ns is not None and timestamp_ns <= previous_ns:
            # containers without usable timestamps: fall back to the nominal frame rate
            step = int(round(1e9 / self._fps)) if self._fps else 33_333_333
            timestamp_ns = previous_ns + step
        return index, max(timestamp_ns, 0)
