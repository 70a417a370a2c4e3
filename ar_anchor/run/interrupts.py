"""Ctrl-C and SIGTERM during a run (:class:`InterruptGuard`): never in the middle of one frame's outputs,
held while the outputs close, and a second one ends the process at once.

Closing can block in native code for a long time (a viewer that stopped reading holds rerun's flush and
disconnect for as long as it stays silent), and Python runs a signal handler only between bytecodes of
the main thread, which is then stuck; two signals that arrive while it is stuck reach the handler once.
So the signals are counted, for the whole run, by a thread of their own, through
:func:`signal.set_wakeup_fd` (the interpreter writes each signal's number there the moment it arrives):
at the run's second signal (the first may have been held while a frame's outputs were written, or while
the main thread waited for the output thread), the thread waits for the closing to begin (at most
:data:`_GRACE_S`: a main thread that never gets there is stuck), calls the run's ``abandon`` (which
writes ``summary.json`` and names the outputs that may be incomplete), says so in one line on stderr,
and ends the process with exit code 130.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..errors import EXIT_INTERRUPTED, printable

__all__ = ["InterruptGuard"]

log = logging.getLogger(__name__)

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_GRACE_S = 2.0  # after the second signal, how long the main thread has to reach the closing


class InterruptGuard:
    """Turns SIGINT/SIGTERM into KeyboardInterrupt, but never in the middle of writing one frame's
    outputs: a signal that arrives there is held until the frame is complete, so ``poses.csv``,
    the recording and ``summary.json`` always agree on the last frame. Once :meth:`hold` is called
    (closing), signals wait until the guard exits. The run's second signal (counted from the guard's
    entry, wherever the first was held) calls ``abandon()`` once the closing has begun (it returns the names
    of the outputs that may be incomplete) and ends the process (exit 130). Main thread only; elsewhere it
    does nothing."""

    def __init__(self, abandon: Callable[[], list[str]] | None = None, out_dir: Path | None = None) -> None:
        self._out_dir = out_dir  # named in the last line, when a second signal ends the process
        self._previous: dict[int, Any] = {}
        self._critical = False
        self._pending: int | None = None
        self._abandon = abandon
        self._closing = threading.Event()  # hold() was called
        self._watch: tuple[socket.socket, socket.socket, int] | None = None

    def __enter__(self) -> InterruptGuard:
        if threading.current_thread() is threading.main_thread():
            for signum in _SIGNALS:
                if signal.getsignal(signum) is not signal.SIG_IGN:  # ignored on purpose (a background job)
                    self._previous[signum] = signal.signal(signum, self._handle)
        if self._previous and self._abandon is not None:
            self._start_watching()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        self._stop_watching()
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        if self._pending is not None and exc_type is None:
            signum, self._pending = self._pending, None
            raise KeyboardInterrupt(f"signal {signum}")

    def hold(self) -> None:
        """From now on (closing the outputs), hold signals until the guard exits: a late Ctrl-C must not
        cut the flush of a recording or the last frames of a video; a second one ends the process."""
        self._critical = True
        self._closing.set()

    def _handle(self, signum: int, _frame: object) -> None:
        if self._critical:
            self._pending = signum
            return
        raise KeyboardInterrupt(f"signal {signum}")

    @contextmanager
    def critical(self) -> Iterator[None]:
        """One frame's outputs are written whole: a signal meanwhile is raised once they are."""
        self._critical = True
        try:
            yield
        finally:
            self._critical = False
        if self._pending is not None:
            signum, self._pending = self._pending, None
            raise KeyboardInterrupt(f"signal {signum}")

    # ------------------------------------------------------------------ the signals, counted
    def _start_watching(self) -> None:
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        try:
            previous_fd = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        except ValueError:  # not the main thread after all
            reader.close()
            writer.close()
            return
        self._watch = (reader, writer, previous_fd)
        threading.Thread(target=self._count, args=(reader,), name="interrupts", daemon=True).start()

    def _stop_watching(self) -> None:
        if self._watch is None:
            return
        _reader, writer, previous_fd = self._watch
        signal.set_wakeup_fd(previous_fd)
        writer.close()  # the watching thread reads the end of its socket and returns
        self._watch = None

    def _count(self, reader: socket.socket) -> None:
        """Count the run's signals as they arrive; at the second, give up once the closing has begun (or the
        main thread, stuck, never begins it)."""
        seen = 0
        with reader:
            while True:
                try:
                    data = reader.recv(64)
                except OSError:
                    return
                if not data:
                    return
                seen += sum(1 for signum in data if signum in _SIGNALS)
                if seen >= 2:
                    self._closing.wait(_GRACE_S)
                    if self._watch is not None:  # the guard has not exited meanwhile (the run ended)
                        self._give_up()

    def _give_up(self) -> None:
        """Write what can be written at once (``abandon``), say what may be incomplete, end the process."""
        try:
            incomplete = self._abandon() if self._abandon is not None else []
        except BaseException:  # noqa: BLE001 - the process ends next, whatever failed here
            log.debug("closing cut short: the summary could not be written", exc_info=True)
            incomplete = ["summary.json"]
        what = ", ".join(printable(name) for name in incomplete) or "no output"
        where = f" in {printable(self._out_dir)}/" if self._out_dir is not None else ""
        line = (
            f"ar-anchor: interrupted again while closing: {what} may be incomplete; "
            f"the other outputs{where} are complete\n"
        )
        try:
            os.write(2, line.encode("utf-8", "backslashreplace"))
        except OSError:
            pass
        os._exit(EXIT_INTERRUPTED)
