"""Packages that export their modules' names without importing those modules until a name is used.

A package's ``__init__`` that imports every module it re-exports makes any import of one of them (the
command line's options, say) pay for all of them (matplotlib, OpenCV, rerun): ``ar-anchor --help`` would
load them all. :func:`lazy_exports` gives the package a module ``__getattr__`` (PEP 562) instead, so that
``from package import name`` still works and imports only the module that defines ``name``. Standard
library only.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


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
