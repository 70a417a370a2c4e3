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


# bidirectional controls: a right-to-left override (U+202E) makes "clip\u202egpj.mp4" show as "clip4pm.jpg"
_BIDI = frozenset((0x061C, 0x200E, 0x200F, *range(0x202A, 0x202F), *range(0x2066, 0x206A)))


def printable(text: object) -> str:
    """``text`` (a path, a file name, a value from a file) safe to print on one terminal line: control
    characters (newlines, carriage returns, ANSI escapes), bidirectional controls (U+202A-U+202E,
    U+2066-U+2069, U+200E/U+200F, U+061C: they reorder what follows them) and bytes that are not UTF-8 are
    shown escaped, as Python would spell them (``\\n``, ``\\x1b``, ``\\u202e``, ``\\udcff``); anything else is
    left as it is."""
    out = []
    for ch in str(text):
        code = ord(ch)
        if code < 0x20 or code == 0x7F or 0x80 <= code < 0xA0:
            out.append(repr(ch)[1:-1])
        elif 0xD800 <= code < 0xE000 or code in _BIDI:
            out.append(f"\\u{code:04x}")
        else:
            out.append(ch)
    return "".join(out)
