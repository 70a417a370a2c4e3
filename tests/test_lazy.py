"""ar_anchor.lazy: names exported on first use, and imports that a signal does not cut."""

from __future__ import annotations

import importlib
import signal
import sys
import textwrap

import pytest

from ar_anchor.lazy import import_held, lazy_exports

# a module that, like trimesh's optional imports, catches BaseException while it loads: a KeyboardInterrupt
# raised inside it would be swallowed
SWALLOWING = textwrap.dedent(
    """
    import os, signal, time
    try:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(200):  # the handler runs between these bytecodes
            time.sleep(0.001)
        SWALLOWED = False
    except BaseException:
        SWALLOWED = True
    """
)


@pytest.fixture
def swallowing_module(tmp_path, monkeypatch):
    (tmp_path / "swallowing_mod.py").write_text(SWALLOWING)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "swallowing_mod", raising=False)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield "swallowing_mod"
    signal.signal(signal.SIGINT, previous)
    sys.modules.pop("swallowing_mod", None)


def test_a_plain_import_swallows_the_signal(swallowing_module):
    # what import_held is for: without it the Ctrl-C is lost
    module = importlib.import_module(swallowing_module)
    assert module.SWALLOWED


def test_a_signal_during_a_held_import_is_raised_after_it(swallowing_module):
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        import_held(swallowing_module)
    module = sys.modules[swallowing_module]
    assert module.SWALLOWED is False  # the import ran whole
    assert signal.getsignal(signal.SIGINT) is handler  # the handler is back


def test_a_held_import_without_a_signal_is_an_import():
    handler = signal.getsignal(signal.SIGINT)
    assert import_held("json") is sys.modules["json"]
    assert signal.getsignal(signal.SIGINT) is handler


def test_lazy_exports_import_on_first_use(tmp_path, monkeypatch):
    package = tmp_path / "lazy_pkg"
    package.mkdir()
    (package / "__init__.py").write_text(
        "from ar_anchor.lazy import lazy_exports\n"
        "__getattr__, __dir__ = lazy_exports(__name__, {'.heavy': ['THING']}, globals())\n"
    )
    (package / "heavy.py").write_text("THING = 42\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import lazy_pkg

    try:
        assert "lazy_pkg.heavy" not in sys.modules
        assert "THING" in dir(lazy_pkg)
        from lazy_pkg import THING

        assert THING == 42 and "lazy_pkg.heavy" in sys.modules
        assert lazy_pkg.__dict__["THING"] == 42  # kept: the next use is a plain attribute
        with pytest.raises(AttributeError, match="no attribute 'other'"):
            lazy_pkg.other  # noqa: B018
    finally:
        for name in ("lazy_pkg", "lazy_pkg.heavy"):
            sys.modules.pop(name, None)


def test_lazy_exports_is_a_getattr_and_a_dir():
    namespace: dict[str, object] = {}
    getattr_, dir_ = lazy_exports("json", {".decoder": ["JSONDecodeError"]}, namespace)
    assert getattr_("JSONDecodeError").__name__ == "JSONDecodeError"
    assert dir_() == ["JSONDecodeError"]
    assert namespace == {"JSONDecodeError": getattr_("JSONDecodeError")}
