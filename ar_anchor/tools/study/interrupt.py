"""Ctrl-C and SIGTERM during a study: they end it within a second, and are never lost.

Python raises :class:`KeyboardInterrupt` wherever the main thread happens to be when the signal
arrives; inside a finalizer or a library's cleanup (matplotlib's, say) that exception is printed as
"ignored" and the run goes on. So within :func:`interruptible` a signal is also *recorded*, and the
studies' loops call :func:`check`, which raises again if one was. :func:`held` defers signals over the
few renames that put a study's files in place together, so they are either all final or all partial.
"""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["check", "held", "interruptible"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_received: list[int] = []  # the signals that arrived within interruptible() (process-wide, as signals are)


def _swap(handler: Callable[[int, Any], None]) -> dict[int, Any]:
    """Install ``handler`` for SIGINT and SIGTERM; the previous handlers ({} outside the main thread)."""
    previous: dict[int, Any] = {}
    try:
        for number in _SIGNALS:
            previous[number] = signal.signal(number, handler)
    except ValueError:  # not the main thread (embedded use): signals stay as they are
        _restore(previous)
        return {}
    return previous


def _restore(previous: dict[int, Any]) -> None:
    for number, handler in previous.items():
        signal.signal(number, handler)


def _raise(number: int, _frame: object) -> None:
    _received.append(number)
    raise KeyboardInterrupt(f"signal {number}")


def _record(number: int, _frame: object) -> None:
    _received.append(number)


@contextmanager
def interruptible() -> Iterator[None]:
    """Within: SIGINT and SIGTERM raise :class:`KeyboardInterrupt` and are recorded for :func:`check`."""
    _received.clear()
    previous = _swap(_raise)
    try:
        yield
    finally:
        _restore(previous)
        _received.clear()


def check() -> None:
    """Raise :class:`KeyboardInterrupt` if a signal arrived within :func:`interruptible`, even one whose
    exception a library swallowed."""
    if _received:
        raise KeyboardInterrupt(f"signal {_received[0]}")


@contextmanager
def held(*, raise_after: bool = True) -> Iterator[None]:
    """Within: SIGINT and SIGTERM are only recorded; on leaving, :func:`check` (unless not ``raise_after``).
    Keep what runs within short: a Ctrl-C waits for it."""
    previous = _swap(_record)
    try:
        yield
    finally:
        _restore(previous)
    if raise_after:
        check()
