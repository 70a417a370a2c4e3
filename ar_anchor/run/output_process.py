"""The outputs in a process of their own (:class:`OutputProcess`): the tracker's process tracks, a child
process draws and logs.

Rerun's logging is Python that holds the GIL (tens of microseconds a call, several calls a target), and a
thread that logs beside the tracker makes the tracker's threads wait for it each time they want the GIL
back; a process shares no GIL. The child is a new interpreter (``python -c``, :func:`child_main`) started
with the run: it inherits the run's working directory, environment and limits, imports the worker's modules
(rerun, OpenCV: 0.5-0.7 s of CPU) while the tracker takes on the first frames, opens the outputs of the
:class:`~.output_worker.OutputSpec` the tracker sends it first (the recording, ``--video-out``,
``--images-out``) and runs an :class:`~.output_worker.OutputWorker` on each frame the tracker hands over:

* a frame's results travel pickled through a pipe (the :class:`~ar_anchor.track.results.FrameResult`, its
  stage times, the frame's index, times and truth: 5-25 kB; not the filter's own per-frame solutions,
  ``FrameResult.measurements``, which the worker does not draw); its pixels only when the worker reads them
  (:meth:`~.output_worker.OutputSpec.needs_pixels`: not for a recording that references the source video),
  copied into a slot of shared memory (an anonymous ``memfd`` both processes map; an image larger than a
  slot, or a machine without one, sends them through the pipe);
* the child acknowledges each frame (its slot free again, its ``render_ms``/``log_ms``); at most ``depth``
  frames are unacknowledged (more while it starts: :meth:`OutputProcess._limit`). With ``block`` (replay, demo) the tracker waits for room: nothing is dropped;
  without (live) a frame that finds no room is not drawn or logged (still in ``poses.csv``), and counted;
* the child's log records are said by the tracker's process, as its own; its stdout and stderr go nowhere;
* the child runs at a lower priority (``nice`` 10): where both want a core, the tracker's threads get it.

Faults. An error in the child (a full disk, a viewer gone) is raised in the tracker's process at the next
frame, as the output thread's were. A child that dies (killed, crashed) does not stop the tracking: the
frames after it are counted as not logged, and :meth:`OutputProcess.close` raises one :class:`OutputError`
naming the outputs left incomplete (``poses.csv`` is the tracker's, and complete). The child runs in a
session of its own and ignores SIGINT and SIGTERM: a Ctrl-C or a ``kill`` of the process group reaches the
tracker's process, which tells the child to finish the frames queued and close its outputs; when the
tracker's process is gone (its pipe closes), the child closes them too. A second Ctrl-C while closing
(:meth:`OutputProcess.abandon`) drops the frames still queued; the child still closes its outputs.
"""

from __future__ import annotations

import dataclasses
import fcntl
import logging
import mmap
import os
import resource
import signal
import subprocess
import sys
import time
import traceback
from multiprocessing import connection
from typing import Any

import numpy as np

from ..errors import ArAnchorError, InputError, OutputError
from ..sources.base import Frame
from ..track.results import FrameResult
from .output_worker import OutputSpec, OutputWorker, WorkerCounts
from .outputs import DiskFullError

__all__ = ["OutputProcess"]

log = logging.getLogger(__name__)

_POLL_S = 0.1  # how often a wait looks whether the child is still there
_STAND_IN = np.zeros((1, 1, 3), np.uint8)  # the image of a frame whose pixels the worker does not read
_ABANDON_WAIT_S = 5.0  # after an abandon, how long the child has to close its outputs
_STARTUP_FRAMES = 32  # frames that may wait for the child while it starts (see OutputProcess._limit)
_STARTUP_BYTES = 96 << 20  # and their pixels at most (a 1080p frame is 6 MB: 15 frames)
_CHILD = "from ar_anchor.run.output_process import child_main; child_main()"


class OutputProcess:
    """An :class:`~.output_worker.OutputWorker` for ``spec`` in a child process (see the module doc).

    Use: :meth:`wait_open` (raises what failed to open), :meth:`submit` each frame, :meth:`close` once (its
    :class:`~.output_worker.WorkerCounts`). :attr:`done`, :attr:`skipped` and :attr:`latency_ms` count as
    :class:`~.threads.OutputStage` does."""

    def __init__(self, spec: OutputSpec, depth: int = 8) -> None:
        if depth < 1:
            raise ValueError("depth must be >= 1")
        self.spec = spec
        self._depth = depth
        frame_bytes = spec.camera.width * spec.camera.height * 3
        self._startup_depth = max(depth, min(_STARTUP_FRAMES, _STARTUP_BYTES // max(1, frame_bytes)))
        self._caught_up = False  # the child opened its outputs and took the frames queued meanwhile
        self._ring = _Ring(self._startup_depth + 1, frame_bytes)
        to_child, self._tx_fd = os.pipe()
        _roomy(self._tx_fd)
        self._rx_fd, from_child = os.pipe()
        abandon_child, self._abandon_fd = os.pipe()
        passed = [to_child, from_child, abandon_child, *self._ring.fds()]
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-c", _CHILD, *map(str, [to_child, from_child, abandon_child, self._ring.fd])],
                pass_fds=passed,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,  # Ctrl-C reaches the tracker's process group only: it tells the child
                env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},
            )
        except BaseException:
            for fd in (self._tx_fd, self._rx_fd, self._abandon_fd):
                os.close(fd)
            self._ring.close()
            raise
        finally:
            for fd in (to_child, from_child, abandon_child):
                os.close(fd)  # (the parent's copies: the child's end of a pipe closes when the child dies)
        self._tx = connection.Connection(self._tx_fd, readable=False)
        self._rx = connection.Connection(self._rx_fd, writable=False)
        self._abandon = connection.Connection(self._abandon_fd, readable=False)
        level = logging.getLogger("ar_anchor").getEffectiveLevel()
        self.image_logging: str | None = None  # said by the child once its outputs are open
        self.done = 0
        self.skipped = 0
        self.latency_ms: dict[str, list[float]] = {}
        self._in_flight = 0
        self._open_error: BaseException | None = None
        self._error: BaseException | None = None
        self._closed: tuple[WorkerCounts, BaseException | None] | None = None
        self._gone: str | None = None  # how the child ended, when it ended without closing
        self._ended = False  # "end" sent
        self._send(("start", spec, level, self._ring.slot_bytes))

    @property
    def gone(self) -> str | None:
        """How the child ended when it ended without closing its outputs (killed, crashed), else None."""
        return self._gone

    # ------------------------------------------------------------------ the child's messages
    def _send(self, message: tuple[Any, ...]) -> bool:
        try:
            self._tx.send(message)
            return True
        except OSError:  # (BrokenPipeError: the child is gone)
            self._ended_badly()
            return False

    def _drain(self, timeout_s: float = 0.0) -> None:
        """Take every message the child sent (waiting up to ``timeout_s`` for the first); notice its end."""
        if self._gone is not None or self._closed is not None:
            return
        connection.wait([self._rx], timeout_s)
        try:
            while self._rx.poll():
                self._take(_decoded(self._rx.recv()))
        except (EOFError, OSError):
            if self._closed is None:
                self._ended_badly()

    def _ended_badly(self) -> None:
        """The child ended without closing its outputs: how (its exit code or signal)."""
        if self._gone is not None:
            return
        try:
            code = self._process.wait(_ABANDON_WAIT_S)
        except subprocess.TimeoutExpired:
            code = None
        if code is not None and code < 0:
            self._gone = f"killed by {signal.Signals(-code).name}"
        else:
            self._gone = "it stopped answering" if code is None else f"exit code {code}"
        self.skipped += self._in_flight  # (handed over, never acknowledged: not logged)
        self._in_flight = 0

    def _take(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "done":
            _, slot, measured = message
            self._in_flight -= 1
            self._ring.free(slot)
            if measured is not None:
                for key, value in measured.items():
                    self.latency_ms.setdefault(key, []).append(value)
                self.done += 1
        elif kind == "log":
            record = logging.makeLogRecord(message[1])
            logging.getLogger(record.name).handle(record)
        elif kind == "opened":
            self.image_logging = message[1]
        elif kind == "open_failed":
            self._open_error = message[1]
        elif kind == "error":
            self._error = self._error or message[1]
        elif kind == "closed":
            self._closed = (message[1], message[2])

    def wait_open(self) -> None:
        """Wait until the child opened its outputs; raise what failed to open them (once)."""
        while self.image_logging is None and self._open_error is None and self._gone is None:
            self._drain(_POLL_S)
            if self._closed is not None and self._open_error is None:
                break
        if self._open_error is not None:
            err, self._open_error = self._open_error, None
            raise err
        if self.image_logging is None:
            raise OutputError(f"the output process ended before it opened the outputs ({self._gone})")

    def poll(self) -> None:
        """Take what the child said; raise what it failed to open or to write, once known."""
        self._drain()
        self.check()

    def check(self) -> None:
        """Raise what the child failed to open, or its error (the frames after it are dropped), if it had one."""
        if self._open_error is not None:
            error, self._open_error = self._open_error, None
            raise error
        if self._error is not None:
            error, self._error = self._error, None
            self.abandon()
            raise error

    # ------------------------------------------------------------------ per frame
    def submit(self, frame: Frame, result: FrameResult, stages: dict[str, float], *, block: bool) -> bool:
        """Hand one frame to the child; False when it is not drawn or logged: no room and ``block`` False,
        or the child is gone."""
        self._drain()
        self.check()
        while self._in_flight >= self._limit() and self._gone is None:
            if not block:
                self.skipped += 1
                return False
            self._drain(_POLL_S)
            self.check()
        if self._gone is not None:
            self.skipped += 1
            return False
        pixels: Any = None
        if self.spec.needs_pixels(frame.index, self.image_logging or "jpeg"):
            pixels = self._ring.put(frame.image)
        meta = (frame.index, frame.timestamp_ns, frame.truth, frame.arrived_ns)
        sent = (
            dataclasses.replace(result, measurements={}) if result.measurements else result
        )  # (the filter's: a third)
        if not self._send(("frame", meta, sent, stages, pixels)):
            self._ring.free(pixels)
            self.skipped += 1
            return False
        self._in_flight += 1
        return True

    def _limit(self) -> int:
        """How many frames may be unacknowledged: ``depth``; while the child starts (its imports, the
        recording opened: 0.5-1 s) up to :data:`_STARTUP_FRAMES` (and :data:`_STARTUP_BYTES` of pixels), so
        that neither a replay waits for it nor a live run drops the first second from the recording."""
        if not self._caught_up:
            if self.image_logging is None or self._in_flight > self._depth:
                return self._startup_depth
            self._caught_up = True
        return self._depth

    # ------------------------------------------------------------------ closing
    def abandon(self) -> None:
        """Drop the frames still queued (a second Ctrl-C); the child still closes its outputs."""
        try:
            self._abandon.send_bytes(b"!")
        except OSError:
            pass

    def close(self, timeout_s: float = 60.0) -> WorkerCounts:
        """Let the child finish the queued frames (at most ``timeout_s``) and close its outputs; wait for it;
        raise its error, or say which outputs it left incomplete when it died. Idempotent."""
        if not self._ended:
            self._ended = True
            self._send(("end",))
        try:
            deadline = time.monotonic() + timeout_s
            while self._closed is None and self._gone is None and time.monotonic() < deadline:
                self._drain(_POLL_S)
            if self._closed is None and self._gone is None:
                log.warning("outputs still busy after %.0f s: the last frames are not in the recording", timeout_s)
                self._stop_now()
        except KeyboardInterrupt:
            self._stop_now()
            raise
        finally:
            self._release()
        self.check()
        if self._closed is None:
            raise self._incomplete()
        counts, error = self._closed
        if error is not None:
            raise error
        return counts

    def _stop_now(self) -> None:
        """Abandon the queued frames and give the child a few seconds to close; kill it after that."""
        self.abandon()
        deadline = time.monotonic() + _ABANDON_WAIT_S
        while self._closed is None and self._gone is None and time.monotonic() < deadline:
            self._drain(_POLL_S)
        if self._process.poll() is None:
            self._process.kill()
            self._ended_badly()

    def _release(self) -> None:
        if self._process.poll() is None:
            try:
                self._process.wait(_ABANDON_WAIT_S)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        for end in (self._tx, self._rx, self._abandon):
            end.close()
        self._ring.close()

    def _incomplete(self) -> OutputError:
        names = ", ".join(OutputWorker(self.spec).describe())
        return OutputError(
            f"the output process ended unexpectedly ({self._gone or 'it did not close'}) after {self.done} "
            f"frame(s): {names} incomplete; poses.csv is complete"
        )


def _roomy(fd: int) -> None:
    """The pipe to the child holds up to 1 MiB (Linux; the default 64 kB would make the tracker wait for a
    child still importing once a few frames of many targets are queued)."""
    try:
        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
    except OSError:
        pass  # (a smaller limit: /proc/sys/fs/pipe-max-size)


class _Ring:
    """Slots for the frames' pixels in memory the child maps too (an anonymous ``memfd``, freed with the last
    process that holds it), ``count`` of ``slot_bytes`` (the camera's image size): :meth:`put` copies an
    image into a free slot and says where it is; an image that fits no slot (larger, or none free, or no
    shared memory to be had) is handed back to travel in the pipe."""

    def __init__(self, count: int, slot_bytes: int) -> None:
        self.slot_bytes = slot_bytes
        self.fd = -1
        self._memory: mmap.mmap | None = None
        self._free: list[int] = []
        size = count * slot_bytes
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]  # (shared memory is a file: ulimit -f applies)
        if size == 0 or not hasattr(os, "memfd_create") or (limit != resource.RLIM_INFINITY and limit < size):
            return
        try:
            self.fd = os.memfd_create("ar-anchor-frames", os.MFD_CLOEXEC)
            os.ftruncate(self.fd, size)
            self._memory = mmap.mmap(self.fd, size)
        except OSError as err:
            log.debug("no shared memory for the frames' pixels (%s): they travel in the pipe", err)
            self.close()
            return
        self._free = list(range(count))

    def fds(self) -> list[int]:
        """The file descriptors the child inherits."""
        return [self.fd] if self.fd >= 0 else []

    def put(self, image: np.ndarray) -> Any:
        if self._memory is None or image.nbytes > self.slot_bytes or not self._free or image.dtype != np.uint8:
            return np.ascontiguousarray(image)
        slot = self._free.pop()
        np.ndarray(image.shape, np.uint8, self._memory, slot * self.slot_bytes)[...] = image
        return (slot, image.shape)

    def free(self, where: Any) -> None:
        if isinstance(where, tuple):
            self._free.append(where[0])

    def close(self) -> None:
        if self._memory is not None:
            self._memory.close()
            self._memory = None
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


# ---------------------------------------------------------------------------------------------- errors
_ERRORS = {cls.__name__: cls for cls in (ArAnchorError, InputError, OutputError, DiskFullError)}


def _portable(err: BaseException) -> tuple[str, str, str | None]:
    """``err`` as (its class's name, its message, the file it is about) for the pipe; an error that is not
    one of ar_anchor's own (a bug) comes back as an :class:`OutputError` naming its type."""
    path = getattr(err, "path", None)
    path = None if path is None else str(path)
    if type(err).__name__ in _ERRORS and isinstance(err, ArAnchorError):
        return (type(err).__name__, str(err), path)
    return ("OutputError", f"the output process failed: {type(err).__name__}: {err}", path)


def _rebuilt(portable: tuple[str, str, str | None]) -> BaseException:
    from pathlib import Path

    name, message, path = portable
    err = _ERRORS[name](message)
    err.path = None if path is None else Path(path)  # type: ignore[attr-defined]
    return err


def _decoded(message: tuple[Any, ...]) -> tuple[Any, ...]:
    """A child's message with its errors rebuilt."""
    kind = message[0]
    if kind in ("open_failed", "error"):
        return (kind, _rebuilt(message[1]))
    if kind == "closed" and message[2] is not None:
        return (kind, message[1], _rebuilt(message[2]))
    return message


# ---------------------------------------------------------------------------------------------- the child
class _LogForwarder(logging.Handler):
    """The child's log records, sent to the tracker's process to be said there."""

    def __init__(self, tx: connection.Connection) -> None:
        super().__init__()
        self._tx = tx

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + "".join(traceback.format_exception(*record.exc_info)).rstrip()
            self._tx.send(("log", dict(record.__dict__, msg=message, args=None, exc_info=None, exc_text=None)))
        except Exception:  # noqa: BLE001 - a log line never breaks the outputs
            pass


class _Pixels:
    """The child's view of the tracker's ring (:class:`_Ring`)."""

    def __init__(self, fd: int, slot_bytes: int) -> None:
        self._slot_bytes = slot_bytes
        self._memory = mmap.mmap(fd, 0) if fd >= 0 else None

    def image(self, pixels: Any) -> np.ndarray:
        if pixels is None:
            return _STAND_IN
        if isinstance(pixels, np.ndarray):
            return pixels
        slot, shape = pixels
        return np.ndarray(shape, np.uint8, self._memory, slot * self._slot_bytes)

    def close(self) -> None:
        if self._memory is not None:
            self._memory.close()


def _send(tx: connection.Connection, message: tuple[Any, ...]) -> bool:
    try:
        tx.send(message)
        return True
    except OSError:
        return False


_NICENESS = 10  # the child's scheduling priority below the tracker's (see _yield_to_the_tracker)


def _yield_to_the_tracker() -> None:
    """Where both want a core, the tracker's threads get it first: the child runs at a lower priority
    (``nice``). Live, a child that falls behind drops frames from the recording (counted), never a pose late;
    a replay waits for it only once its queue is full."""
    try:
        os.nice(_NICENESS)
    except OSError:
        pass


def child_main() -> None:
    """The child process (``python -c``, its pipes' and memory's descriptors as arguments): open the outputs
    the tracker's first message describes, draw and log each frame received, close them at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (its own session already: the tracker says when to end)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _yield_to_the_tracker()
    rx_fd, tx_fd, abandon_fd, memory_fd = (int(arg) for arg in sys.argv[1:5])
    rx = connection.Connection(rx_fd, writable=False)
    tx = connection.Connection(tx_fd, readable=False)
    abandon = connection.Connection(abandon_fd, writable=False)
    try:
        _, spec, level, slot_bytes = rx.recv()
    except (EOFError, OSError):
        return
    root = logging.getLogger("ar_anchor")
    root.handlers[:] = [_LogForwarder(tx)]
    root.setLevel(level)
    root.propagate = False
    worker = OutputWorker(spec)
    try:
        worker.open()
    except BaseException as err:  # noqa: BLE001 - said by the tracker's process
        log.debug("the outputs failed to open", exc_info=True)
        _send(tx, ("open_failed", _portable(err)))
    else:
        _send(tx, ("opened", worker.counts.image_logging))
        _frames(worker, rx, tx, abandon, _Pixels(memory_fd, slot_bytes))
    error = None
    try:
        worker.close(timeout_s=1.0 if abandon.poll() else None)
    except BaseException as err:  # noqa: BLE001
        error = _portable(err)
    _send(tx, ("closed", worker.counts, error))


def _frames(
    worker: OutputWorker, rx: connection.Connection, tx: connection.Connection, abandon: Any, pixels: _Pixels
) -> None:
    """Each frame received drawn and logged, until the tracker says ``end`` or is gone; after an error or an
    abandon, the frames are acknowledged but not drawn."""
    failed = False
    try:
        while True:
            try:
                message = rx.recv()
            except (EOFError, OSError):
                return  # the tracker's process is gone: close what was written
            if message[0] == "end":
                return
            _, (index, timestamp_ns, truth, arrived_ns), result, stages, where = message
            measured = None
            if not failed and not abandon.poll():
                try:
                    frame = Frame(pixels.image(where), index, timestamp_ns, truth, arrived_ns)
                    measured = worker.work(frame, result, stages)
                except BaseException as err:  # noqa: BLE001 - raised by the tracker's process
                    failed = True
                    log.debug("the output process failed at frame %d", index, exc_info=True)
                    _send(tx, ("error", _portable(err)))
            if not _send(tx, ("done", where if isinstance(where, tuple) else None, measured)):
                return
    finally:
        pixels.close()
