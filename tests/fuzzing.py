"""Shared helpers of the fuzz / fault-injection suite (tests/test_fuzz_*.py, test_media_faults.py).

Example budgets: every property test declares its CI budget with :func:`fuzz_settings`; under
``HYPOTHESIS_PROFILE=long`` the budget is multiplied by ``FUZZ_SCALE`` (default 20), which is the
documented longer run (docs/robustness.md).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import signal
from collections.abc import Sequence
from dataclasses import dataclass

from hypothesis import settings

PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
SCALE = int(os.environ.get("FUZZ_SCALE", "20")) if PROFILE == "long" else 1

# Exit codes of ar_anchor.cli.main (docs/robustness.md)
EXIT_CODES = {0, 1, 2, 130}


def examples(ci_budget: int) -> int:
    """The example count of a property test: its CI budget, scaled up under the long profile."""
    return ci_budget * SCALE


def fuzz_settings(ci_budget: int, **kwargs) -> settings:
    return settings(max_examples=examples(ci_budget), deadline=None, **kwargs)


@dataclass(frozen=True)
class CliResult:
    code: int
    stdout: str
    stderr: str
    system_exit: bool  # argparse ended the call with SystemExit (usage error, --help, --version)

    def describe(self) -> str:
        return f"exit {self.code} (SystemExit: {self.system_exit})\nstdout: {self.stdout!r}\nstderr: {self.stderr!r}"


def run_main(argv: Sequence[str]) -> CliResult:
    """``ar_anchor.cli.main.main(argv)`` in-process, stdout/stderr captured, SystemExit turned into its code.

    main() changes process-wide state (the "ar_anchor" logger's handler, the SIGTERM handler);
    both are restored so that other tests see what they saw before.
    """
    from ar_anchor.cli.main import main

    logger = logging.getLogger("ar_anchor")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    saved_sigterm = signal.getsignal(signal.SIGTERM)
    out, err = io.StringIO(), io.StringIO()
    system_exit = False
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(argv))
            except SystemExit as exc:
                system_exit = True
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    finally:
        logger.handlers[:] = saved[0]
        logger.setLevel(saved[1])
        logger.propagate = saved[2]
        signal.signal(signal.SIGTERM, saved_sigterm)
    return CliResult(code, out.getvalue(), err.getvalue(), system_exit)


def assert_clean_exit(result: CliResult, allowed: set[int] = EXIT_CODES) -> None:
    """An exit code of the documented set, and nothing that betrays a bug on the user's screen."""
    assert isinstance(result.code, int) and result.code in allowed, result.describe()
    for text in (result.stdout, result.stderr):
        assert "Traceback" not in text, result.describe()
        assert "internal error" not in text, result.describe()  # main()'s catch-all for unexpected exceptions


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("ar-anchor: error:")]


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class Hang(BaseException):
    """Raised by :func:`time_limit` (a BaseException, so that no ``except Exception`` can swallow it)."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Fail a call that takes longer than ``seconds`` (main thread; Python-level code only)."""

    def expired(_signum: int, _frame: object) -> None:
        raise Hang(f"took longer than {seconds} s: a hang?")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(text: str) -> None:
    """Count an outcome in Hypothesis' statistics (``--hypothesis-show-statistics``); no-op outside @given."""
    from hypothesis import event
    from hypothesis.errors import InvalidArgument

    try:
        event(f"outcome: {text}")
    except InvalidArgument:
        pass
