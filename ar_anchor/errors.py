"""Typed errors. Each carries one human-readable line naming the file or option at fault.

The CLI maps :class:`InputError` (bad config, camera file, source, option) to exit code 2 and
any other :class:`ArAnchorError` to exit code 1, printing only the message.
"""

from __future__ import annotations

__all__ = [
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "ArAnchorError",
    "CameraError",
    "ConfigError",
    "FrameError",
    "InputError",
    "OutputError",
    "SourceError",
    "printable",
]

# exit codes of the command line: success; a run-time failure (outputs written so far stay valid);
# bad input or usage; interrupted (Ctrl-C, SIGTERM)
EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class ArAnchorError(Exception):
    """Base class of all errors raised on purpose by ar_anchor."""


class InputError(ArAnchorError, ValueError):
    """The user gave us something we cannot use (exit code 2)."""


class ConfigError(InputError):
    """A tracker config file or value is invalid."""


class CameraError(InputError):
    """A camera calibration file is missing or malformed."""


class SourceError(InputError):
    """A frame source cannot be opened."""


class FrameError(InputError):
    """A frame handed to the API (:class:`~ar_anchor.sources.base.Frame`, :meth:`Tracker.process
    <ar_anchor.track.tracker.Tracker.process>`) is malformed: not an (H, W, 3) uint8 image, an empty one, a
    timestamp that is not a finite number of nanoseconds, or something that is not a ``Frame`` at all."""


class OutputError(ArAnchorError):
    """An output (recording, CSV, video) cannot be written."""


def printable(text: object) -> str:
    """``text`` (a path, a file name, a value from a file) safe to print on one terminal line: control
    characters (newlines, carriage returns, ANSI escapes) and bytes that are not UTF-8 are shown escaped,
    as Python would spell them (``\\n``, ``\\x1b``, ``\\udcff``); anything else is left as it is."""
    out = []
    for ch in str(text):
        code = ord(ch)
        if code < 0x20 or code == 0x7F or 0x80 <= code < 0xA0 or 0xD800 <= code < 0xE000:
            out.append(repr(ch)[1:-1] if code < 0xD800 else f"\\u{code:04x}")
        else:
            out.append(ch)
    return "".join(out)
