"""``ar-anchor``: the command-line front. Each command lives in its own module (demo, replay, live, bench,
tools) with its options (``add_parser``) and its function; this one builds the parser and maps errors to
exit codes: 0 success; 1 run-time failure (outputs written so far stay valid); 2 bad input or usage
(config, camera file, option); 130 interrupted (Ctrl-C)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from collections.abc import Sequence

from .. import __version__
from ..errors import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE, ArAnchorError, InputError
from . import bench, demo, live, replay, tools
from .options import add_common_options
from .report import format_summary

__all__ = ["build_parser", "format_summary", "main"]

log = logging.getLogger("ar_anchor")


def build_parser() -> argparse.ArgumentParser:
    """The ``ar-anchor`` parser: the common options and every command's subparser."""
    parser = argparse.ArgumentParser(
        prog="ar-anchor",
        description="Real-time fiducial-marker AR tracker (ArUco + IPPE + rerun).",
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"ar-anchor {__version__}")
    add_common_options(parser, defaults=True)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in (demo, replay, live, bench):
        command.add_parser(commands)
    tools.add_parsers(commands)
    return parser


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("ar-anchor: %(levelname)s: %(message)s"))
    root = logging.getLogger("ar_anchor")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _interrupt_on_sigterm() -> None:
    """SIGTERM ends a run like Ctrl-C: outputs are closed and stay valid."""

    def handler(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (embedded use): leave signals alone
        pass


def _steady_malloc() -> None:
    """glibc: allocations of 1 MiB and more always come from (and go back to) the system.

    By default glibc raises that threshold as large blocks are freed, after which whole video frames
    (6 MB at 1080p), allocated and freed from three threads, are carved from its heaps, which then
    fragment: a long live run's memory creeps up. A fixed threshold keeps it flat. Nothing elsewhere.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD (fixing it also stops the dynamic adjustment)
    except (OSError, AttributeError):  # not glibc (e.g. musl): its allocator, its behaviour
        pass


def _quiet_opencv(verbosity: int) -> None:
    """OpenCV, FFmpeg and rerun print their own warnings to stderr; ours say what matters, in one line.
    Theirs show with -vv."""
    if verbosity >= 2:
        return
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET, read when a capture opens
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    # rerun's own (Rust) log lines, e.g. a file sink that hit a full disk: the error we raise names the file
    os.environ.setdefault("RUST_LOG", "off")
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command in ``argv`` (default ``sys.argv``); errors become one line on stderr and an exit code."""
    _interrupt_on_sigterm()
    _steady_malloc()
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    _quiet_opencv(args.verbose)
    try:
        return int(args.func(args))
    except InputError as err:
        print(f"ar-anchor: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except ArAnchorError as err:
        print(f"ar-anchor: error: {err}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print("ar-anchor: interrupted; outputs written so far are complete", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as err:  # a bug: say so in one line, show the traceback only when asked
        log.debug("internal error", exc_info=True)
        print(
            f"ar-anchor: internal error: {type(err).__name__}: {err} (rerun with -vv for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
