"""Detection one frame ahead: :meth:`Tracker.detect` of frame N + 1 in a thread of its own while the
caller takes frame N through :meth:`Tracker.track` (pose, filter, results).

The two halves of :meth:`Tracker.process` keep separate state (the detection's: where markers were,
repeats, sharpness; the rest's: tracks, the last answer), and each runs its frames in order, so the
results are those of ``process`` frame by frame. What overlaps is OpenCV's detection, which releases the
GIL, with the filter's Python. For files and renders (frames waiting in the decoder's queue); a live
camera's frames are tracked as they come (waiting for the next frame to start on the last would add a
frame's time to every pose).
"""

from __future__ import annotations

from collections.abc import Generator, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from ..sources.base import Frame
from .results import DetectedFrame
from .tracker import Tracker

__all__ = ["detected_ahead"]

T = TypeVar("T")


def detected_ahead(
    tracker: Tracker, items: Iterable[tuple[Frame, T]]
) -> Generator[tuple[Frame, T, DetectedFrame], None, None]:
    """``(frame, extra, tracker.detect(frame))`` for each ``(frame, extra)`` of ``items``, in order, each
    frame's detection started as soon as the frame before it was handed out. An exception in a detection
    is raised here, in order; one of ``items`` after the frame before it; closing the iterator early waits
    for the detection under way."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="detect") as pool:
        pending: tuple[Frame, T, Future[DetectedFrame]] | None = None
        frames = iter(items)
        while True:
            try:
                frame, extra = next(frames)
            except StopIteration:
                break
            except BaseException:  # (the source broke: the frame before is still handed out first)
                if pending is not None:
                    yield pending[0], pending[1], pending[2].result()
                raise
            future = pool.submit(tracker.detect, frame)
            if pending is not None:
                yield pending[0], pending[1], pending[2].result()
            pending = (frame, extra, future)
        if pending is not None:
            yield pending[0], pending[1], pending[2].result()
