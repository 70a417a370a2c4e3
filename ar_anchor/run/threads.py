"""The run loop's threads: decoding ahead of the tracker, and the outputs behind it.

A run has three stages: *decode* (read and decode the next frame), *track* (detect, pose, filter;
``poses.csv``), and *output* (draw the overlays, encode and log the images and the 3D scene to
rerun, write ``--video-out``). Run one after the other they add up (about 1 + 4 + 2 + 8 ms per 1080p
frame); here decode and output each run in their own thread, joined to the tracker by bounded
queues, so a frame costs about as long as its slowest stage on a machine with two cores (OpenCV,
PyAV and rerun's encoders release the GIL while they work).

* :class:`Prefetcher` reads a file or synthetic source up to ``depth`` frames ahead. A live source
  has its own capture thread that always hands over the newest frame, and is not prefetched.
* :class:`OutputStage` does the output work for each tracked frame in order. With ``block=True``
  (replay, demo) the tracker waits when the queue is full: nothing is skipped. With
  ``block=False`` (live) the tracker never waits: a frame that finds the queue full is not logged
  or drawn (it is still in ``poses.csv``), and is counted.

Errors in either thread are re-raised in the tracker's thread at the next frame, and
:meth:`OutputStage.close` finishes every frame already queued, so the recording and the video end
on the same frame as ``poses.csv``, even after Ctrl-C.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from ..sources.base import Frame
from ..track.results import FrameResult
from .output_worker import OutputSpec, OutputWorker, WorkerCounts, close_in_order

__all__ = ["OutputStage", "OutputThread", "Prefetcher"]

log = logging.getLogger(__name__)

_END = object()  # the source is exhausted
_POLL_S = 0.1  # how often a blocked thread looks whether it should stop


class Prefetcher:
    """Iterate ``source`` in a thread, up to ``depth`` frames ahead of the consumer.

    Yields ``(frame, decode_ms)``; each frame gets ``arrived_ns`` (when it was ready) unless its
    source set it. An exception in the source is raised to the consumer after the frames before it.
    """

    def __init__(
        self,
        source: Iterable[Frame],
        depth: int = 4,
        held: Callable[[], contextlib.AbstractContextManager[object]] | None = None,
    ) -> None:
        if depth < 1:
            raise ValueError("depth must be >= 1")
        self._source = source
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="decode", daemon=True)
        self._started = False
        self._held = held  # signals held back while the queue is read (see _take)

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            frames = iter(self._source)
            while not self._stop.is_set():
                start = time.perf_counter()
                frame = next(frames, None)
                if frame is None:
                    break
                decode_ms = (time.perf_counter() - start) * 1e3
                if frame.arrived_ns is None:
                    frame = dataclasses.replace(frame, arrived_ns=time.monotonic_ns())
                if not self._put((frame, decode_ms)):
                    return
        except BaseException as err:  # handed to the consumer, which raises it in its own thread
            self._put(err)
            return
        self._put(_END)

    def __iter__(self) -> Iterator[tuple[Frame, float]]:
        if not self._started:
            self._started = True
            self._thread.start()
        while True:
            item = self._take()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def _take(self) -> Any:
        """The next item, read in short polls each with signals held (``held()``, e.g. an
        :class:`~.interrupts.InterruptGuard`'s ``critical``): a ``KeyboardInterrupt`` raised inside the
        queue's lock would leave it locked, and the decoding thread and the closing would wait on it for
        ever (seen once: a replay that never ended after its SIGTERM). A signal is raised between polls."""
        while True:
            with self._held() if self._held is not None else contextlib.nullcontext():
                try:
                    return self._queue.get(timeout=_POLL_S)
                except queue.Empty:
                    pass

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop reading and wait for the thread (so the source can be closed safely afterwards)."""
        self._stop.set()
        while True:  # unblock a producer waiting on a full queue
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        if self._started:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("the decoding thread did not stop within %.0f s", timeout_s)


class OutputStage:
    """Run ``work(frame, result, stages)`` for each submitted frame, in order, in a thread.

    ``work`` returns the per-stage times it measured (ms, e.g. ``render_ms``, ``log_ms``); they are
    collected in :attr:`latency_ms`. ``depth`` bounds the queue; see the module doc for ``block``.
    """

    def __init__(self, work: Callable[[Frame, FrameResult, dict[str, float]], dict[str, float]], depth: int = 8):
        if depth < 1:
            raise ValueError("depth must be >= 1")
        self._work = work
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=depth)
        self._thread = threading.Thread(target=self._run, name="output", daemon=True)
        self._thread.start()
        self._error: BaseException | None = None
        self._abandon = threading.Event()
        self.done = 0  # frames whose output work finished
        self.skipped = 0  # frames not logged because the queue was full (block=False)
        self.latency_ms: dict[str, list[float]] = {}

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _END or self._abandon.is_set():
                return
            if self._error is not None:
                continue  # after a failure the rest is dropped; the tracker's thread raises the error
            frame, result, stages = item
            try:
                measured = self._work(frame, result, stages)
            except BaseException as err:
                self._error = err
                continue
            for key, value in measured.items():
                self.latency_ms.setdefault(key, []).append(value)
            self.done += 1

    def check(self) -> None:
        """Raise the output thread's error, if it had one."""
        if self._error is not None:
            error, self._error = self._error, None
            self._abandon.set()
            raise error

    def submit(self, frame: Frame, result: FrameResult, stages: dict[str, float], *, block: bool) -> bool:
        """Queue one frame's output work; False when it was skipped (queue full and ``block`` False)."""
        self.check()
        item = (frame, result, stages)
        if not block:
            try:
                self._queue.put_nowait(item)
                return True
            except queue.Full:
                self.skipped += 1
                return False
        while True:
            try:
                self._queue.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                self.check()  # the output thread failed while we waited

    def close(self, timeout_s: float = 60.0) -> None:
        """Finish the queued frames (at most ``timeout_s``), stop the thread, and raise its error if any.

        Interrupted while it waits (a second Ctrl-C), it drops what is still queued but lets the frame
        in hand finish, so that the outputs can be closed safely next."""
        deadline = time.monotonic() + timeout_s
        try:
            while self._thread.is_alive():
                try:
                    self._queue.put(_END, timeout=_POLL_S)
                    break
                except queue.Full:
                    if time.monotonic() > deadline:
                        break
            while self._thread.is_alive() and time.monotonic() < deadline:
                self._thread.join(_POLL_S)
        except KeyboardInterrupt:
            self._stop_now(5.0)
            raise
        if self._thread.is_alive():
            log.warning("outputs still busy after %.0f s: the last frames are not in the recording", timeout_s)
            self._stop_now(5.0)
        self.check()

    def _stop_now(self, wait_s: float) -> None:
        self._abandon.set()
        try:
            self._queue.put_nowait(_END)  # wakes a worker waiting for work
        except queue.Full:
            pass  # it is busy, and looks at _abandon before its next item
        self._thread.join(wait_s)


class OutputThread:
    """An :class:`~.output_worker.OutputWorker` behind an :class:`OutputStage` in this process: the same
    interface as :class:`~.output_process.OutputProcess` (``RunOptions(output_process=False)``: an embedding
    that cannot start a process, or a test that watches the worker from inside)."""

    def __init__(self, spec: OutputSpec, depth: int = 8) -> None:
        self.spec = spec
        self.gone: str | None = None  # (a thread does not die alone)
        self._worker = OutputWorker(spec)
        self._stage: OutputStage | None = None
        self.image_logging: str | None = None
        try:
            self._worker.open()
        except BaseException:
            self._worker.close()
            raise
        self.image_logging = self._worker.counts.image_logging
        self._stage = OutputStage(self._worker.work, depth=depth)

    @property
    def done(self) -> int:
        return self._stage.done if self._stage is not None else 0

    @property
    def skipped(self) -> int:
        return self._stage.skipped if self._stage is not None else 0

    @property
    def latency_ms(self) -> dict[str, list[float]]:
        return self._stage.latency_ms if self._stage is not None else {}

    def wait_open(self) -> None:
        """Opened already (in the constructor)."""

    def poll(self) -> None:
        """Raise the thread's error, if it had one."""
        if self._stage is not None:
            self._stage.check()

    def submit(self, frame: Frame, result: FrameResult, stages: dict[str, float], *, block: bool) -> bool:
        assert self._stage is not None
        return self._stage.submit(frame, result, stages, block=block)

    def abandon(self) -> None:
        if self._stage is not None:
            self._stage._stop_now(5.0)

    def close(self, timeout_s: float = 60.0) -> WorkerCounts:
        """The thread stopped (the queued frames finished), then the worker's outputs closed, in order."""
        steps = [lambda: self._stage.close(timeout_s) if self._stage is not None else None, self._worker.close]
        close_in_order(steps)
        return self._worker.counts
