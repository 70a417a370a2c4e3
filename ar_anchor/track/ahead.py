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

import _thread
import queue
from collections.abc import Generator, Iterable
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
    for the detection under way.

    Nothing here takes a lock written in Python: the detecting thread is started with :mod:`_thread` and
    fed, read and awaited through :class:`queue.SimpleQueue` (both C), so a Ctrl-C, which the run's handler
    raises in this (the main) thread between any two bytecodes, cannot leave one taken. With a
    ``ThreadPoolExecutor`` it once did (a ``KeyboardInterrupt`` inside its semaphore's ``with``): the
    detecting thread then waited on that lock for ever, and the replay, Ctrl-C'd, never ended
    (``threading.Thread.start`` waits on such a lock too)."""
    requests: queue.SimpleQueue[Frame | None] = queue.SimpleQueue()
    answers: queue.SimpleQueue[tuple[bool, object]] = queue.SimpleQueue()
    finished: queue.SimpleQueue[bool] = queue.SimpleQueue()
    started = False
    try:
        _thread.start_new_thread(_detect_each, (tracker, requests, answers, finished))
        started = True
        pending: tuple[Frame, T] | None = None
        frames = iter(items)
        while True:
            try:
                frame, extra = next(frames)
            except StopIteration:
                break
            except BaseException:  # (the source broke: the frame before is still handed out first)
                if pending is not None:
                    yield pending[0], pending[1], _answer(answers)
                raise
            requests.put(frame)
            if pending is not None:
                yield pending[0], pending[1], _answer(answers)
            pending = (frame, extra)
        if pending is not None:
            yield pending[0], pending[1], _answer(answers)
    finally:
        requests.put(None)  # the thread ends after the detection under way ...
        if started:
            finished.get()  # ... which closing the iterator waits for


def _detect_each(
    tracker: Tracker,
    requests: queue.SimpleQueue[Frame | None],
    answers: queue.SimpleQueue[tuple[bool, object]],
    finished: queue.SimpleQueue[bool],
) -> None:
    """The detecting thread: ``(True, detected)`` or ``(False, error)`` for each frame, until ``None``."""
    try:
        while (frame := requests.get()) is not None:
            try:
                answers.put((True, tracker.detect(frame)))
            except BaseException as err:  # noqa: BLE001 - raised in the caller's thread, in order
                answers.put((False, err))
    finally:
        finished.put(True)


def _answer(answers: queue.SimpleQueue[tuple[bool, object]]) -> DetectedFrame:
    """The next frame's detection, or its error raised."""
    ok, value = answers.get()
    if not ok:
        raise value  # type: ignore[misc]
    return value  # type: ignore[return-value]
