"""The package's layers hold: every import inside ``ar_anchor`` goes down (or sideways within one
package), and rerun is imported only by ``viz/``.

Layers, bottom to top (docs/architecture.md)::

    errors, geometry, lazy, targets, units  <  camera  <  boards  <  config  <  synthetic  <  sources  <  track
      <  render, viz  <  run  <  tools, bench  <  cli

Peers (render and viz, tools and bench) do not import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.helpers import parsed_module

PACKAGE = Path(__file__).resolve().parents[1] / "ar_anchor"

LAYER = {
    "errors": 0,
    "geometry": 0,
    "lazy": 0,
    "targets": 0,
    "units": 0,
    "camera": 1,
    "boards": 2,
    "config": 3,
    "synthetic": 4,
    "sources": 5,
    "track": 6,
    "render": 7,
    "viz": 7,
    "run": 8,
    "tools": 9,
    "bench": 9,
    "cli": 10,
}


def _unit(module: str) -> str:
    """``ar_anchor.track.pose`` -> ``track`` (the top-level module or package it belongs to)."""
    return module.split(".")[1] if module.count(".") >= 1 else ""


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) for every ``ar_anchor`` import in ``path``, lazy ones included."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    package = parts if parts[-1] == "__init__" else parts[:-1]
    package = [p for p in package if p != "__init__"]
    found = []
    for node in ast.walk(parsed_module(path)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
                names = [f"{module}.{a.name}" for a in node.names] if node.module is None else [module]
            else:
                names = [node.module or ""]
            found += [(node.lineno, n) for n in names if n.startswith("ar_anchor.")]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("ar_anchor.")]
    return found


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__main__.py")


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down(path):
    here = _unit("ar_anchor." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
    if here in ("", "__init__"):
        return  # the top-level face re-exports lazily, by name
    assert here in LAYER, f"{path}: top-level module or package {here!r} has no layer: add it to LAYER and the docs"
    for line, module in _imports(path):
        there = _unit(module)
        if there == here or there in ("", "__init__") or there.startswith("__"):
            continue
        assert there in LAYER, f"{path}:{line}: imports {module}, whose layer is unknown"
        assert LAYER[there] < LAYER[here], (
            f"{path}:{line}: {here} (layer {LAYER[here]}) imports {module} (layer {LAYER[there]})"
        )


def test_rerun_is_imported_only_by_viz():
    offenders = []
    for path in _modules():
        for node in ast.walk(parsed_module(path)):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom) and not node.level
                else []
            )
            if any(n == "rerun" or n.startswith("rerun.") for n in names):
                offenders.append(str(path.relative_to(PACKAGE)))
    assert offenders and all(o.startswith("viz/") for o in offenders), offenders


def test_every_module_says_what_lives_there():
    missing = [str(p.relative_to(PACKAGE)) for p in _modules() if not ast.get_docstring(parsed_module(p))]
    assert not missing, f"modules without a docstring: {missing}"


def _is_overload(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(
        (isinstance(d, ast.Name) and d.id == "overload") or (isinstance(d, ast.Attribute) and d.attr == "overload")
        for d in node.decorator_list
    )


def test_every_public_name_says_what_it_does():
    """Public top-level functions and classes, and public methods of more than 3 statements, have docstrings."""
    functions = (ast.FunctionDef, ast.AsyncFunctionDef)
    missing = []
    for path in sorted(PACKAGE.rglob("*.py")):
        where = path.relative_to(PACKAGE)
        for node in parsed_module(path).body:
            if not isinstance(node, (*functions, ast.ClassDef)) or node.name.startswith("_"):
                continue
            if not (isinstance(node, functions) and _is_overload(node)) and not ast.get_docstring(node):
                missing.append(f"{where}:{node.lineno}:{node.name}")
            if isinstance(node, ast.ClassDef):
                missing += [
                    f"{where}:{m.lineno}:{node.name}.{m.name}"
                    for m in node.body
                    if isinstance(m, functions)
                    and not m.name.startswith("_")
                    and not _is_overload(m)
                    and len(m.body) > 3
                    and not ast.get_docstring(m)
                ]
    assert not missing, f"public names without a docstring: {missing}"
