"""Frames and the contract every frame source meets."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np

from ..camera import CameraModel
from ..errors import FrameError, SourceError
from ..geometry import Pose

__all__ = ["ClosingSource", "Frame", "FrameError", "FrameSource", "SourceError", "SourceInfo", "check_frame"]

# a timestamp beyond +-2^63 ns (292 years) fits no int64 (numpy, the recording's time columns)
_MAX_TIMESTAMP_NS = 2**63 - 1


@dataclass(frozen=True)
class Frame:
    """One image and when it was taken.

    Attributes
    ----------
    image : (H, W, 3) uint8, BGR.
    index : position in the stream, 0-based, strictly increasing.
    timestamp_ns : capture time in nanoseconds (monotonic clock live, container time for
        video, synthetic clock for renders).
    truth : ground truth ``camera_from_target`` per target name (``marker:<id>``,
        ``board:<name>``) for targets in view, when the source knows it (synthetic renders).
    arrived_ns : ``time.monotonic_ns()`` when the frame was ready for the tracker (delivered by the
        device, or decoded), for latency measurements; None when nobody stamped it.
    """

    image: np.ndarray
    index: int
    timestamp_ns: int
    truth: Mapping[str, Pose] | None = field(default=None)
    arrived_ns: int | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        """Refuses (:class:`~ar_anchor.errors.FrameError`, a ValueError) an image that is not a non-empty
        (H, W, 3) uint8 array, an index that is not an integer >= 0, and a timestamp that is not a finite
        number of nanoseconds within int64 (a NaN or inf timestamp would make every later pose non-finite).
        A few hundred nanoseconds: it runs for every frame."""
        check_frame(self)

    @property
    def timestamp_s(self) -> float:
        return self.timestamp_ns * 1e-9

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.image.shape[1], self.image.shape[0]


def check_frame(frame: object) -> None:
    """:class:`~ar_anchor.errors.FrameError` unless ``frame`` is a :class:`Frame` whose image, index and
    timestamp are valid (see :meth:`Frame.__post_init__`; :meth:`Tracker.detect
    <ar_anchor.track.tracker.Tracker.detect>` checks again what it is given, whatever happened to it since)."""
    if not isinstance(frame, Frame):
        raise FrameError(f"expected an ar_anchor Frame, got {type(frame).__name__}")
    image = frame.image
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise FrameError(
            f"Frame.image: expected a non-empty (H, W, 3) uint8 BGR array, got "
            f"{getattr(image, 'shape', None)} {getattr(image, 'dtype', type(image).__name__)}"
        )
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise FrameError(f"Frame.image: empty ({image.shape[1]}x{image.shape[0]} pixels)")
    index = frame.index
    if type(index) is not int and (isinstance(index, bool) or not isinstance(index, numbers.Integral)):
        raise FrameError(f"Frame.index: expected an integer >= 0, got {index!r}")
    if index < 0:
        raise FrameError(f"Frame.index: expected an integer >= 0, got {index!r}")
    stamp = frame.timestamp_ns
    if type(stamp) is not int and (
        isinstance(stamp, bool) or not isinstance(stamp, numbers.Real) or not math.isfinite(stamp)
    ):
        raise FrameError(f"Frame.timestamp_ns: expected a finite number of nanoseconds, got {stamp!r}")
    if not -_MAX_TIMESTAMP_NS <= stamp <= _MAX_TIMESTAMP_NS:
        raise FrameError(f"Frame.timestamp_ns: {stamp!r} ns is beyond int64 (+-292 years)")


@dataclass(frozen=True)
class SourceInfo:
    """What a source is, as it declares it (:attr:`FrameSource.info`); a snapshot, taken when asked.

    Attributes
    ----------
    live : frames come from a device at its own pace (a capture thread hands over the newest): the run
        loop neither reads ahead of it nor makes it wait for the outputs.
    fps : nominal frame rate (the container's, the one asked of a device or an image sequence's), None when unknown.
    frame_count : frames in the stream, None when unknown or endless (live).
    frame_count_estimated : ``frame_count`` is the container's guess (duration x rate, as in MKV and WebM):
        good for progress, no evidence that a stream which ends before it was damaged.
    video_path : a video file whose frame ``i`` is this source's frame ``i`` (a recording can reference it
        instead of holding the images); None otherwise.
    ended_early : the stream stopped before its announced end (a damaged or truncated file, or a frame
        size that changes mid-stream).
    ended_because : why it stopped early, one line for the user ("" when it did not).
    stills : the frames are separate image files (a folder or a glob): photos that may be unrelated, which a
        replay decides each alone unless told they are one video's frames (``--sequence``).
    """

    live: bool = False
    fps: float | None = None
    frame_count: int | None = None
    frame_count_estimated: bool = False
    video_path: Path | None = None
    ended_early: bool = False
    ended_because: str = ""
    stills: bool = False


@runtime_checkable
class FrameSource(Protocol):
    """An iterator of :class:`Frame` and a context manager that releases the device or file.

    End of stream ends the iteration. ``resolution`` is (width, height); ``camera`` is the
    source's own calibration when it knows one (synthetic renders), else None; ``info`` declares
    the rest of what the source is (:class:`SourceInfo`).
    """

    @property
    def resolution(self) -> tuple[int, int]: ...

    @property
    def camera(self) -> CameraModel | None: ...

    @property
    def info(self) -> SourceInfo: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def __enter__(self) -> FrameSource: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...

    def close(self) -> None: ...


_Source = TypeVar("_Source", bound="ClosingSource")


class ClosingSource:
    """The context-manager side of a :class:`FrameSource`, shared by the sources: ``with`` gives the
    source itself and closes it on the way out (``close`` is the source's own)."""

    def __enter__(self: _Source) -> _Source:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:  # pragma: no cover - overridden
        pass
