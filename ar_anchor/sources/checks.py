"""Checks at the door of the sources: what a file is before it is read, numbers before they are used,
and libraries' own lines on stderr turned into ours.

A path given as a source is typed and sized with one ``stat`` before anything opens it: a named pipe,
a socket, a device or a folder where a file is due is said to be one (opening a FIFO would block,
reading a device would never end), and a file far larger than any frame it could hold is refused
before it is read. A number that enters a source (a frame rate, a size, a timeout) is range-checked
where it enters, and the error names the option it came from.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import stat
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError, SourceError, printable

__all__ = ["file_kind", "in_range", "library_stderr_to_log", "source_file_stat"]

log = logging.getLogger(__name__)

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words: ``"a regular file"``, ``"a named pipe (FIFO)"``, ``"a socket"``, ..."""
    for test, name in _KINDS:
        if test(mode):
            return name
    return "a regular file" if stat.S_ISREG(mode) else "not a regular file"


def source_file_stat(path: Path, *, what: str, max_bytes: int | None = None) -> os.stat_result:
    """``path``'s ``stat`` once it is known to be a readable, non-empty regular file of at most ``max_bytes``.

    ``what`` names what was expected (``"a video"``, ``"an image"``, ``"a timestamp file"``) in the
    :class:`~ar_anchor.errors.SourceError` that says otherwise. Never opens the file: a FIFO is refused
    before anyone blocks on it.
    """
    name = printable(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise SourceError(f"{name}: not found") from None
    except OSError as err:
        raise SourceError(f"{name}: cannot be examined ({err.strerror or err})") from None
    if not stat.S_ISREG(info.st_mode):
        raise SourceError(f"{name}: is {file_kind(info.st_mode)}, not {what}")
    if info.st_size == 0:
        raise SourceError(f"{name}: empty file (0 bytes), not {what}")
    if max_bytes is not None and info.st_size > max_bytes:
        raise SourceError(
            f"{name}: {info.st_size / 2**20:.0f} MiB, too large for {what} (at most {max_bytes >> 20} MiB)"
        )
    if not os.access(path, os.R_OK):
        raise SourceError(f"{name}: not readable (permission denied)")
    return info


def in_range(option: str, value: float, low: float, high: float, *, unit: str = "") -> float:
    """``value`` when it is a finite number in ``[low, high]``, else an :class:`~ar_anchor.errors.InputError`
    naming ``option`` (``"--fps"``) and the range."""
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{option}: expected a number, got {printable(value)!r}") from None
    if not (math.isfinite(number) and low <= number <= high):
        raise InputError(f"{option}: must be in [{low:g}, {high:g}]{unit}, got {number:g}")
    return number


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def library_stderr_to_log(name: str | os.PathLike[str], *, quiet: bool = True) -> Iterator[list[str]]:
    """Hold what C libraries write straight to file descriptor 2 (libjpeg's "Corrupt JPEG data: 3 extraneous
    bytes before marker 0xd9") while the block runs; yields the list that receives their lines.

    The lines are logged at DEBUG naming ``name``; with ``quiet=False`` (their own messages were asked
    for, -vv) they are also passed on to stderr as they were. Anything else written to the descriptor
    meanwhile (another thread's output) is passed on to stderr unchanged when the block ends. One block
    at a time in this process: the descriptor is shared.
    """
    lines: list[str] = []
    with _STDERR_LOCK, tempfile.TemporaryFile() as held:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr at all: nothing to hold
            yield lines
            return
        try:
            os.dup2(held.fileno(), 2)
            try:
                yield lines
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
        held.seek(0)
        text = held.read(1 << 20).decode("utf-8", "replace")
    passed = []
    for line in text.splitlines(keepends=True):
        if _is_codec_line(line):
            lines.append(line.strip())
            log.debug("%s: %s", printable(name), printable(line.strip()))
        if not quiet or not _is_codec_line(line):
            passed.append(line)
    if passed:
        with contextlib.suppress(OSError):
            os.write(2, "".join(passed).encode("utf-8", "replace"))


_CODEC_LINE_STARTS = (
    "corrupt jpeg data",
    "premature end of jpeg",
    "invalid sos parameters",
    "unsupported marker",
    "warning: ",
    "libpng warning",
    "libpng error",
    "jpegxr",
    "tiffreaddirectory",
)


def _is_codec_line(line: str) -> bool:
    """A line in the style of the image libraries' own warnings (libjpeg, libpng, libtiff)."""
    text = line.strip().lower()
    return bool(text) and text.startswith(_CODEC_LINE_STARTS)
