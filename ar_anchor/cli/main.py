"""``ar-anchor``: the command-line front. Each command lives in its own module (demo, replay, live, bench,
tools) with its options (``add_parser``) and its function; this one builds the parser and maps errors to
exit codes: 0 success; 1 run-time failure (outputs written so far stay valid); 2 bad input or usage
(config, camera file, option); 130 interrupted (Ctrl-C, SIGTERM).

The terminal is guarded before anything heavy is imported: this module imports the standard library
only, and :func:`main` installs its SIGINT/SIGTERM handling first thing (:mod:`.terminal`). Until the
command starts, a signal ends the process at once with one line (nothing has been written yet: the
imports of OpenCV, numpy and rerun are never cut halfway, which once turned Ctrl-C into "OpenCV
bindings requires numpy" or swallowed it); while the command runs it is a ``KeyboardInterrupt``,
which the run loop turns into closed outputs, and this module into exit code 130.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from ..errors import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE, ArAnchorError, InputError, printable
from . import terminal

if TYPE_CHECKING:
    import argparse
    from collections.abc import Sequence

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``ar-anchor`` parser: the common options and every command's subparser."""
    from . import batch, bench, demo, export, live, replay, tools, view
    from .options import base_parser

    parser, commands = base_parser()
    for command in (demo, replay, batch, live, bench, export, view):
        command.add_parser(commands)
    tools.add_parsers(commands)
    return parser


def _setup_logging(verbosity: int) -> None:
    import logging

    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("ar-anchor: %(levelname)s: %(message)s"))
    handler.addFilter(terminal.escaped_message)
    root = logging.getLogger("ar_anchor")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


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


def _one_blas_thread() -> None:
    """numpy's (and scipy's) OpenBLAS on one thread, unless ``OPENBLAS_NUM_THREADS`` says otherwise.

    The tracker's linear algebra is on 3x3 to 9x9 matrices, which OpenBLAS never splits, yet its pool of
    one thread per core is started at import and spins after each call, on the cores OpenCV's detector and
    the run's own threads need. Measured on this 2-core machine (docs/development.md): a 2-frame demo took
    1.8 s of CPU with the pool and 1.0 s without; the poses are the same to the byte. Only before numpy is
    imported (the variable is read when its library loads): called by :func:`main`, whose module imports
    the standard library only; a process that has loaded numpy already keeps its pool."""
    import os

    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _preload(command: str | None) -> None:
    """Import what ``command`` needs (OpenCV, numpy, rerun, ...) now, while a signal still ends the process
    at once. A module that fails to import is left to the command, which reports it in its own words.

    Not what only some runs need, nor what a run needs only after its first frame: trimesh (mesh files; the
    default cube and the built-in pin need none), PyAV (video files) are imported where they are first used,
    whole (:func:`~ar_anchor.lazy.import_held`: a Ctrl-C meanwhile is raised once they are loaded; trimesh's
    optional imports catch ``BaseException`` and would swallow it); rerun by the thread that opens a run's
    outputs while the tracker takes on the first frame (:meth:`~ar_anchor.run.run_outputs.RunOutputs.open`),
    where no signal is raised."""
    try:
        if command in ("demo", "replay", "live", "bench", "batch"):
            from ..run import loop  # noqa: F401
            from ..tools.export import run  # noqa: F401 - the camera summary, earlier exports cleared
            from ..track.kernels import compiled_refine

            compiled_refine()  # the pose stage's compiled kernel, loaded once
            if command in ("demo", "live", "bench"):  # the synthetic scene's: numpy 2 imports them on first use
                import numpy.ma  # noqa: F401
                import numpy.random  # noqa: F401

            from ..sources import open as open_source  # noqa: F401 - files, cameras, the synthetic scene
            from ..sources import synthetic as synthetic_source  # noqa: F401

            if command == "bench":  # its benchmarks log to rerun from this thread: loaded now, as before
                from ..viz import recorder  # noqa: F401
        elif command == "calibrate":
            from ..tools import calibrate  # noqa: F401
        elif command == "markers":
            from ..tools import markers  # noqa: F401
        elif command == "map":
            from ..tools.map import command as map_command  # noqa: F401
        elif command == "study":
            from ..run import outputs  # noqa: F401 - the --out check's
            from ..tools.study import command as study  # noqa: F401
        elif command == "export":
            import mcap_ros2.writer  # noqa: F401

            from ..tools.export import bag, run  # noqa: F401
    except Exception:  # noqa: BLE001 - raised again, and reported, where the command imports it
        import logging

        logging.getLogger("ar_anchor").debug("preloading for %s failed", command, exc_info=True)


def _run_command(argv: Sequence[str] | None, signals: terminal.Signals) -> int:
    """Parse ``argv`` and run its command; errors become one line on stderr and an exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    terminal.quiet_libraries(args.verbose)
    _preload(args.command)
    try:
        signals.running()  # from now on a signal is a KeyboardInterrupt: the run closes its outputs
        try:
            if getattr(args, "connect", None):
                from ..viz.viewer import require_viewer

                require_viewer(args.connect, "--connect")
            if getattr(args, "serve", False):
                from .view import serve_run

                return serve_run(args)
            return int(args.func(args))
        finally:
            signals.finishing()
    except InputError as err:
        print(f"ar-anchor: error: {printable(err)}", file=sys.stderr)
        return EXIT_USAGE
    except ArAnchorError as err:
        print(f"ar-anchor: error: {printable(err)}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt as err:
        print(f"ar-anchor: interrupted; {terminal.interrupted_outputs(err)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as err:
        if _interrupted_within(err):  # a signal inside a library's code, which wrapped it (e.g. a RuntimeError)
            print(f"ar-anchor: interrupted; {terminal.interrupted_outputs(err)}", file=sys.stderr)
            return EXIT_INTERRUPTED
        # a bug: say so in one line, show the traceback only when asked
        import logging

        logging.getLogger("ar_anchor").debug("internal error", exc_info=True)
        print(
            f"ar-anchor: internal error: {type(err).__name__}: {printable(err)} (rerun with -vv for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE


def _interrupted_within(err: BaseException) -> bool:
    """Whether ``err`` was caused by a ``KeyboardInterrupt`` (Ctrl-C, SIGTERM) that code on the way wrapped in
    an error of its own (Python's class creation turns one into a ``RuntimeError``)."""
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command in ``argv`` (default ``sys.argv``); errors become one line on stderr and an exit code.

    Signals are handled first of all; stdout that cannot be written (a reader gone, a full device, an
    encoding without the character) is given up quietly, and the run keeps its own exit code."""
    with terminal.Signals() as signals, terminal.guarded_stdout(), terminal.warnings_to_log():
        _steady_malloc()
        _one_blas_thread()
        terminal.quiet_libraries_early()
        return _run_command(argv, signals)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
