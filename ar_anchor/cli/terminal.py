"""The command's hold on the process and the terminal: signals, stdout, library noise.

* :class:`Signals`: SIGINT and SIGTERM alike, from the first line of :func:`~.main.main`. Before the
  command starts (imports, parsing) and after it ended, a signal ends the process at once with one line
  and exit code 130: nothing is half written then, and a ``KeyboardInterrupt`` raised inside an import of
  OpenCV or numpy can be swallowed or turned into a misleading error. While the command runs, a signal
  is a ``KeyboardInterrupt``: the run loop closes its outputs (:mod:`ar_anchor.run.loop`).
* :func:`guarded_stdout`: a reader that went away (``| head``), a full device (``> /dev/full``) or an
  encoding that lacks a character (``PYTHONIOENCODING=ascii``) does not turn a finished run into a
  traceback: what cannot be shown is escaped, and a stdout that cannot be written is given up quietly.
* :func:`quiet_libraries_early`, :func:`quiet_libraries` and :func:`warnings_to_log`: OpenCV's, FFmpeg's
  and rerun's own log lines, and Python warnings (numpy's RuntimeWarnings with their file paths), reach
  stderr only with ``-vv``.

Standard library only: this runs before anything heavy is imported.
"""

from __future__ import annotations

import io
import os
import signal
import sys
import warnings
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from ..errors import EXIT_INTERRUPTED, printable

if TYPE_CHECKING:
    import logging
    from collections.abc import Iterator

__all__ = [
    "Signals",
    "escaped_message",
    "guarded_stdout",
    "interrupted_outputs",
    "quiet_libraries",
    "quiet_libraries_early",
    "warnings_to_log",
]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _log() -> Any:
    import logging  # not at import: this module is loaded before anything but the signal handling

    return logging.getLogger("ar_anchor")


def _exit_now(_signum: int, _frame: object) -> None:
    """Nothing is being written: say so in one line and end the process (no cleanup to cut short)."""
    try:
        os.write(2, b"ar-anchor: interrupted\n")
    except OSError:
        pass
    os._exit(EXIT_INTERRUPTED)


def _raise_interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


class Signals:
    """SIGINT and SIGTERM for one command (a context manager; the previous handlers come back on exit).

    Entered, a signal ends the process at once (:func:`_exit_now`); after :meth:`running` it raises
    ``KeyboardInterrupt``; after :meth:`finishing` it ends the process at once again. Off the main
    thread (an embedding program) signals are left alone, and so is a signal the parent process ignored
    (a background job's Ctrl-C)."""

    def __init__(self) -> None:
        self._previous: dict[int, Any] = {}

    def _install(self, handler: Any) -> None:
        for signum in _SIGNALS:
            if signal.getsignal(signum) is signal.SIG_IGN and signum not in self._previous:
                continue  # ignored by whoever started us (a background job, nohup): it stays ignored
            try:
                previous = signal.signal(signum, handler)
            except ValueError:  # not the main thread: the embedding program's signals
                return
            self._previous.setdefault(signum, previous)

    def __enter__(self) -> Signals:
        self._install(_exit_now)
        return self

    def running(self) -> None:
        """The command runs: a signal is a ``KeyboardInterrupt`` from now on."""
        self._install(_raise_interrupt)

    def finishing(self) -> None:
        """The command ended: a signal ends the process at once (the outputs are closed)."""
        self._install(_exit_now)

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()


def interrupted_outputs(err: BaseException) -> str:
    """What the interrupted run leaves: complete outputs, or (a second Ctrl-C cut the closing short) the
    files that may be incomplete, as the run loop names them in ``err.incomplete``; and where (``err.out_dir``)."""
    incomplete = getattr(err, "incomplete", None)
    out_dir = getattr(err, "out_dir", None)
    where = f" in {printable(out_dir)}/" if out_dir is not None else ""
    note = getattr(err, "note", None)  # what the run says its outputs are (the run loop's offline replay)
    if note and not incomplete:
        return note
    if incomplete:
        return f"closing cut short: {', '.join(incomplete)} may be incomplete; the other outputs{where} are complete"
    return f"outputs written so far{where} are complete"


class _QuietStdout(io.TextIOBase):
    """``sys.stdout`` for one command: writes go to ``stream`` until it fails (EPIPE, ENOSPC, ...); then
    its file descriptor is pointed at /dev/null (so that no later flush, not even the interpreter's
    last, fails again) and the rest is dropped."""

    def __init__(self, stream: Any) -> None:
        super().__init__()
        self.stream = stream
        self.broken = False

    def _give_up(self, err: OSError) -> None:
        self.broken = True
        _log().debug("stdout cannot be written (%s): the rest of it is dropped", err.strerror or err)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(devnull, self.stream.fileno())
            finally:
                os.close(devnull)
        except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
            pass

    def write(self, text: str) -> int:
        """Write ``text``; its length, also when it was dropped."""
        if not self.broken:
            try:
                self.stream.write(text)
            except OSError as err:
                self._give_up(err)
        return len(text)

    def flush(self) -> None:
        """Flush the stream; a failure gives it up."""
        if not self.broken:
            try:
                self.stream.flush()
            except OSError as err:
                self._give_up(err)

    def isatty(self) -> bool:
        """Whether the stream is a terminal."""
        return not self.broken and self.stream.isatty()

    def fileno(self) -> int:
        """The stream's file descriptor."""
        return self.stream.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        """The stream's encoding."""
        return getattr(self.stream, "encoding", "utf-8")


@contextmanager
def guarded_stdout() -> Iterator[_QuietStdout]:
    """``sys.stdout`` guarded for the duration (see :class:`_QuietStdout`); characters its encoding lacks
    are written escaped (``\\xe9``) instead of failing."""
    original = sys.stdout
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.reconfigure(errors="backslashreplace")  # type: ignore[union-attr]
        except (AttributeError, ValueError, io.UnsupportedOperation):
            pass
    guarded = _QuietStdout(original)
    sys.stdout = guarded
    try:
        yield guarded
    finally:
        guarded.flush()
        if sys.stdout is guarded:
            sys.stdout = original


_QUIET_ENV = {
    "OPENCV_LOG_LEVEL": "SILENT",  # read when cv2 is imported
    "OPENCV_FFMPEG_LOGLEVEL": "-8",  # AV_LOG_QUIET, read when a capture opens
    "RUST_LOG": "off",  # rerun's own log lines, e.g. a file sink that hit a full disk: our error names the file
}


def quiet_libraries_early() -> None:
    """Before OpenCV, FFmpeg and rerun are imported: their own log lines off (:func:`quiet_libraries` turns
    them back on for -vv). Variables the user set are left as they are."""
    for name, value in _QUIET_ENV.items():
        os.environ.setdefault(name, value)


def quiet_libraries(verbosity: int) -> None:
    """OpenCV, FFmpeg and rerun print their own lines to stderr; ours say what matters, in one line. Theirs
    show with -vv. Variables the user set are left as they are."""
    ours = {name for name, value in _QUIET_ENV.items() if os.environ.get(name) == value}
    if verbosity >= 2:
        for name in ours:
            del os.environ[name]
    if "OPENCV_LOG_LEVEL" in ours:
        import cv2

        levels = cv2.utils.logging
        levels.setLogLevel(levels.LOG_LEVEL_INFO if verbosity >= 2 else levels.LOG_LEVEL_SILENT)


def _log_warning(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None, line: Any = None
) -> None:
    _log().debug("%s: %s (%s:%d)", category.__name__, message, filename, lineno)


@contextmanager
def warnings_to_log() -> Iterator[None]:
    """Python warnings (numpy's RuntimeWarnings and the like) go to the debug log, not to stderr."""
    with warnings.catch_warnings():
        warnings.showwarning = _log_warning
        yield


def escaped_message(record: logging.LogRecord) -> bool:
    """A logging filter: the message escaped (:func:`~ar_anchor.errors.printable`), so that a file name holding
    a newline or an ANSI escape is shown, not obeyed (a -vv traceback below it stays as it is)."""
    record.msg, record.args = printable(record.getMessage()), None
    return True
