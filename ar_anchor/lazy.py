"""Packages that export their modules' names without importing those modules until a name is used.

A package's ``__init__`` that imports every module it re-exports makes any import of one of them (the
command line's options, say) pay for all of them (matplotlib, OpenCV, rerun): ``ar-anchor --help`` would
load them all. :func:`lazy_exports` gives the package a module ``__getattr__`` (PEP 562) instead, so that
``from package import name`` still works and imports only the module that defines ``name``.

A library imported where it is first needed is imported while a command runs, when Ctrl-C and SIGTERM
raise ``KeyboardInterrupt`` (:mod:`ar_anchor.cli.terminal`). :func:`import_held` imports one whole: a
signal that arrives meanwhile is delivered once the import is complete, never inside it (where an
``except BaseException`` of the library's would swallow it). Standard library only.
"""

from __future__ import annotations

import importlib
import signal
import threading
from collections.abc import Callable, Iterable, Mapping
from types import ModuleType
from typing import Any

__all__ = ["import_held", "lazy_exports"]


def lazy_exports(
    package: str, exports: Mapping[str, Iterable[str]], namespace: dict[str, Any]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for the package ``package`` (its ``__name__``) whose module globals are
    ``namespace``: ``exports`` maps each module, relative to the package (``".command"``), to the names it
    defines that the package exports. A name is imported on first use and kept in ``namespace``."""
    where = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *where})

    return __getattr__, __dir__


def import_held(name: str) -> ModuleType:
    """Import the module ``name`` with SIGINT and SIGTERM held until the import is complete; a signal that
    arrived meanwhile then goes to the handler that was in place (the first one of them, once).

    For a library whose imports catch ``BaseException`` (trimesh's optional ones do): a ``KeyboardInterrupt``
    raised inside it was swallowed, and an interrupted run went on and ended with exit 0. Off the main thread
    (where Python runs no signal handler) and for signals without a Python handler, a plain import."""
    if threading.current_thread() is not threading.main_thread():
        return importlib.import_module(name)
    held: list[int] = []
    previous: dict[int, Any] = {}

    def hold(signum: int, _frame: object) -> None:
        held.append(signum)

    for signum in (signal.SIGINT, signal.SIGTERM):
        if callable(signal.getsignal(signum)):
            previous[signum] = signal.signal(signum, hold)
    try:
        return importlib.import_module(name)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        if held:
            previous[held[0]](held[0], None)
