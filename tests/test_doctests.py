"""The examples in the package's docstrings run and print what they say (``python -m doctest`` style)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import ar_anchor

MODULES = sorted(
    m.name for m in pkgutil.walk_packages(ar_anchor.__path__, "ar_anchor.") if not m.name.endswith("__main__")
)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, report=True)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed (printed above)"


def test_there_are_examples():
    attempted = sum(
        doctest.testmod(importlib.import_module(n), optionflags=doctest.ELLIPSIS, report=False).attempted
        for n in ("ar_anchor.targets", "ar_anchor.track.tracker", "ar_anchor.tools.map.model")
    )
    assert attempted >= 8
