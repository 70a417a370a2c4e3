"""Annotated video output: the overlay frames of a run as a small video file anyone can play.

:class:`AnnotatedVideoWriter` takes BGR ``uint8`` frames (the images drawn by the viewer) and
writes them to a file meant for sharing, not for replay (a lossless, frame-exact recording is
:class:`~ar_anchor.run.outputs.RawVideoWriter`'s job).

Codec choice, by file extension:

``.mp4``, ``.mov``, ``.mkv``
    H.264 (``libx264`` through PyAV, ``yuv420p``, CRF 20, preset ``veryfast``). H.264 in 4:2:0
    is what browsers, messengers and video players accept most widely; CRF 20 keeps the
    overlay's thin lines and text close to the input at a small file size, and ``veryfast``
    keeps encoding cheap enough to run alongside the tracker. The stream is tagged BT.601
    limited range, the conversion PyAV applies, so players do not guess BT.709 for HD sizes.
    If PyAV is not installed or was built without ``libx264``, the writer falls back to OpenCV's
    ``cv2.VideoWriter`` with MPEG-4 Part 2 (``mp4v``), which far fewer players accept (browsers
    do not), and logs one warning saying so.
``.avi``
    Motion JPEG through ``cv2.VideoWriter`` (``MJPG``): large files, but every frame is a
    keyframe and any player opens it.

Odd frame sizes: all three codecs store chroma at half resolution (4:2:0), so width and height
must be even (libx264 refuses odd sizes, OpenCV's writer silently drops the last row/column).
A frame with an odd width (height) is therefore padded by one column (row) on the right
(bottom) that repeats the edge pixels: a 321x241 input becomes a 322x242 video.

The file is opened at the first frame, whose size fixes the size of the video. :meth:`close`
flushes the encoder and finalises the container even if flushing fails half-way, so a run that
is interrupted by an exception still leaves a playable file when it closes the writer from a
``finally`` block or a ``with`` statement. A process that is killed outright (SIGKILL,
``os._exit``) never closes the writer and leaves an unplayable file: the encoder still holds
the last frames and the container has no index.
"""

from __future__ import annotations

import logging
import math
import os
from fractions import Fraction
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ..errors import OutputError
from ..lazy import import_held

__all__ = ["SUPPORTED_EXTENSIONS", "AnnotatedVideoWriter"]

log = logging.getLogger(__name__)

#: File extension -> preferred codec. ``h264`` falls back to ``mp4v`` without PyAV/libx264.
SUPPORTED_EXTENSIONS: dict[str, str] = {".mp4": "h264", ".mov": "h264", ".mkv": "h264", ".avi": "mjpg"}

_H264_ENCODER = "libx264"
_H264_OPTIONS = {"crf": "20", "preset": "veryfast"}
_FALLBACK_FOURCC = "mp4v"
_AVCOL_SPC_SMPTE170M = 6  # FFmpeg's AVColorSpace for the BT.601 matrix
_AVCOL_RANGE_MPEG = 1  # FFmpeg's AVColorRange for limited range (Y 16-235)


def _load_pyav() -> ModuleType:
    """Return the ``av`` module if it can encode H.264 with ``libx264``.

    The one place the writer looks for PyAV (tests replace it to simulate its absence).

    Raises
    ------
    ImportError
        PyAV is not installed, or its FFmpeg build has no ``libx264`` encoder; the message
        says which.
    """
    av = import_held("av")  # only runs that write a video need it; whole: a Ctrl-C waits until it is loaded

    try:
        av.codec.Codec(_H264_ENCODER, "w")
    except Exception as err:  # av.codec.codec.UnknownCodecError, or anything an odd build raises
        raise ImportError(f"PyAV {av.__version__} has no {_H264_ENCODER} encoder") from err
    return av


def _reason(err: BaseException) -> str:
    """One line saying why an OS / FFmpeg call failed, without the path or a traceback."""
    reason = getattr(err, "strerror", None) or str(err) or type(err).__name__
    return " ".join(str(reason).split())


class AnnotatedVideoWriter:
    """Writes BGR ``uint8`` frames to a shareable video file (H.264 where possible).

    Parameters
    ----------
    path
        Output file; the extension picks the codec (see the module docstring). Supported:
        ``.mp4``, ``.mov``, ``.mkv`` (H.264, or ``mp4v`` as a fallback) and ``.avi`` (MJPG).
    fps
        Frame rate written into the file; every frame lasts ``1 / fps`` seconds.

    Attributes
    ----------
    path : pathlib.Path
        The output file.
    fps : float
        The frame rate.
    frames : int
        Number of frames written so far.
    codec : str or None
        ``"h264"``, ``"mp4v"`` or ``"mjpg"`` once the first frame is written, ``None`` before.
    size : tuple of int or None
        ``(width, height)`` of the frames passed in (before any padding), fixed by the first frame.

    Raises
    ------
    OutputError
        ``fps`` is not a finite positive number, or the extension is not supported.

    Notes
    -----
    Nothing is created on disk until the first :meth:`write`. Use the writer as a context
    manager, or call :meth:`close` in a ``finally`` block, so that an interrupted run still
    leaves a playable file.
    """

    def __init__(self, path: str | os.PathLike[str], fps: float = 30.0) -> None:
        self.path = Path(path)
        try:
            valid = math.isfinite(fps) and fps > 0
        except TypeError:
            valid = False
        if not valid:
            raise OutputError(f"{self.path}: frame rate must be a finite number > 0, got {fps!r}")
        suffix = self.path.suffix.lower()
        if suffix not in SUPPORTED_EXTENSIONS:
            raise OutputError(
                f"{self.path}: unsupported video extension {suffix or '(none)'!r}; "
                f"supported: {', '.join(SUPPORTED_EXTENSIONS)}"
            )
        self.fps = float(fps)
        self.frames = 0
        self.codec: str | None = None
        self.size: tuple[int, int] | None = None
        self._preferred = SUPPORTED_EXTENSIONS[suffix]
        self._pad = (0, 0)  # extra (columns, rows) added to each frame
        self._container: Any = None  # av.container.OutputContainer (H.264)
        self._stream: Any = None  # av.video.stream.VideoStream (H.264)
        self._av: ModuleType | None = None
        self._cv_writer: Any = None  # cv2.VideoWriter (mp4v, MJPG)
        self._created = False  # the file exists because we made it
        self._closed = False

    # -- opening --------------------------------------------------------------------------

    def _open(self, width: int, height: int) -> None:
        """Create the file for ``width`` x ``height`` frames, choosing the backend."""
        self._pad = (width % 2, height % 2)
        # Create the file ourselves first: this reports the OS reason for a missing directory or
        # a read-only location (cv2.VideoWriter only says "not opened").
        try:
            with open(self.path, "wb"):
                pass
        except OSError as err:
            raise OutputError(f"{self.path}: cannot write ({_reason(err)})") from err
        self._created = True
        if self._preferred == "h264":
            try:
                av = _load_pyav()
            except ImportError as err:
                log.warning(
                    "%s: H.264 is unavailable (%s); writing MPEG-4 Part 2 (%s) with OpenCV instead, "
                    "which browsers and some players cannot play",
                    self.path,
                    _reason(err),
                    _FALLBACK_FOURCC,
                )
                self._open_cv(_FALLBACK_FOURCC, width, height)
                self.codec = _FALLBACK_FOURCC
            else:
                self._open_av(av, width, height)
                self.codec = "h264"
        else:
            self._open_cv("MJPG", width, height)
            self.codec = "mjpg"
        self.size = (width, height)

    def _open_av(self, av: ModuleType, width: int, height: int) -> None:
        rate = Fraction(self.fps).limit_denominator(1001)
        try:
            container = av.open(str(self.path), mode="w")
        except (av.FFmpegError, OSError) as err:
            self._abandon()
            raise OutputError(f"{self.path}: cannot write ({_reason(err)})") from err
        try:
            stream = container.add_stream(_H264_ENCODER, rate=rate)
            stream.width = width + self._pad[0]
            stream.height = height + self._pad[1]
            stream.pix_fmt = "yuv420p"
            # PyAV converts BGR with swscale's default BT.601 limited-range matrix; say so in the
            # stream, or players assume BT.709 for HD sizes and shift the colours.
            stream.codec_context.colorspace = _AVCOL_SPC_SMPTE170M
            stream.codec_context.color_range = _AVCOL_RANGE_MPEG
            stream.codec_context.time_base = 1 / rate
            stream.options = dict(_H264_OPTIONS)
            # Open the file and the encoder and write the header now: errors surface at the first
            # write, not at close() (libx264 buffers frames, so the first packet comes much later).
            container.start_encoding()
        except (av.FFmpegError, OSError, ValueError) as err:
            self._container = container
            self._abandon()
            raise OutputError(f"{self.path}: cannot start the H.264 encoder ({_reason(err)})") from err
        self._av, self._container, self._stream = av, container, stream

    def _open_cv(self, fourcc: str, width: int, height: int) -> None:
        import cv2  # noqa: PLC0415 - keep `import ar_anchor.render.video` cheap

        size = (width + self._pad[0], height + self._pad[1])
        writer = cv2.VideoWriter(str(self.path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*fourcc), self.fps, size)
        if not writer.isOpened():
            writer.release()
            self._abandon()
            raise OutputError(f"{self.path}: OpenCV cannot open a {fourcc} video writer for {size[0]}x{size[1]}")
        self._cv_writer = writer

    # -- writing --------------------------------------------------------------------------

    def write(self, image: np.ndarray) -> None:
        """Append one frame.

        Parameters
        ----------
        image
            BGR ``uint8`` array of shape ``(H, W, 3)``. All frames must have the size of the first.

        Raises
        ------
        OutputError
            The writer is closed, the frame is not ``(H, W, 3)`` ``uint8``, its size differs from
            the first frame's, or the file cannot be created or written.
        """
        if self._closed:
            raise OutputError(f"{self.path}: cannot write frame {self.frames}, the writer is closed")
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
            raise OutputError(
                f"{self.path}: frame {self.frames} must be a non-empty (H, W, 3) uint8 BGR image, "
                f"got shape {image.shape} {image.dtype}"
            )
        height, width = image.shape[:2]
        if self.size is None:
            self._open(width, height)
        elif (width, height) != self.size:
            raise OutputError(
                f"{self.path}: frame {self.frames} is {width}x{height}, "
                f"the video is {self.size[0]}x{self.size[1]} (set by frame 0)"
            )
        pad_x, pad_y = self._pad
        if pad_x or pad_y:
            image = np.pad(image, ((0, pad_y), (0, pad_x), (0, 0)), mode="edge")
        image = np.ascontiguousarray(image)
        if self._stream is not None:
            self._encode_av(image)
        else:
            self._cv_writer.write(image)
        self.frames += 1

    def _encode_av(self, image: np.ndarray) -> None:
        av = self._av
        assert av is not None
        frame = av.VideoFrame.from_ndarray(image, format="bgr24")
        frame.pts = self.frames
        frame.time_base = self._stream.codec_context.time_base
        try:
            for packet in self._stream.encode(frame):
                self._container.mux(packet)
        except (av.FFmpegError, OSError) as err:
            raise OutputError(f"{self.path}: writing frame {self.frames} failed ({_reason(err)})") from err

    # -- closing --------------------------------------------------------------------------

    def close(self) -> None:
        """Flush the encoder and finalise the file; idempotent.

        The container is closed (its index / trailer written) even if flushing the encoder fails,
        so the frames muxed so far stay playable. If no frame was written, no file is left.

        Raises
        ------
        OutputError
            Flushing or finalising the file failed (after the file was closed as far as possible).
        """
        if self._closed:
            return
        self._closed = True
        error: BaseException | None = None
        if self._container is not None:
            container, stream = self._container, self._stream
            self._container = self._stream = None
            try:
                if stream is not None and self.frames:
                    for packet in stream.encode(None):
                        container.mux(packet)
            except Exception as err:  # noqa: BLE001 - reported below, after the container is closed
                error = err
            finally:
                try:
                    container.close()
                except Exception as err:  # noqa: BLE001
                    error = error or err
        if self._cv_writer is not None:
            writer, self._cv_writer = self._cv_writer, None
            writer.release()
        if self.frames == 0:
            self._remove_created_file()
        if error is not None:
            raise OutputError(f"{self.path}: finishing the video failed ({_reason(error)})") from error

    def _abandon(self) -> None:
        """Drop a half-opened container and the file it created (opening failed)."""
        container, self._container, self._stream = self._container, None, None
        if container is not None:
            try:
                container.close()
            except Exception:  # noqa: BLE001 - already reporting the reason opening failed
                pass
        self._remove_created_file()

    def _remove_created_file(self) -> None:
        if self._created:
            self._created = False
            try:
                self.path.unlink(missing_ok=True)
            except OSError as err:
                log.debug("%s: cannot remove the empty video file (%s)", self.path, _reason(err))

    def __enter__(self) -> AnnotatedVideoWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
