"""``configs/default.toml`` and ``configs/demo.toml``, written from the key declarations.

Each file is a config rendered by :func:`config_toml`: every table of :class:`TrackerConfig` in order,
every key as ``key = value`` with its doc as the comment beside it (long docs continue on comment
lines below, aligned). A key whose default is empty (``[markers] ids``, ``[markers.lengths_m]``) is
shown commented out with its declared example. The default config has no boards, so its
``[[boards]]`` are commented-out examples of each kind (:data:`EXAMPLE_BOARDS`), every key of each
kind with its doc; the overlays are the config's own, the first one followed by the keys no overlay
sets, commented out at their defaults.

Run ``python -m ar_anchor.config.document configs`` after changing a declaration (``--check``: only
say whether the files are current); a test fails while they are not.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import textwrap
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .board import BOARD_KEYS, BoardConfig, BoardKeys
from .keys import Key, default_of, table_keys
from .model import OverlayConfig, TrackerConfig, demo_config

__all__ = ["EXAMPLE_BOARDS", "config_toml", "default_toml", "demo_toml", "main"]

WIDTH = 120  # the repository's line length
COMMENT_AT = 34  # column of the comments beside the values

_ABOUT = """\
Every scalar key is optional (it takes the value shown); lists such as [[boards]] and
[markers.lengths_m] are what your file says (leave them out: none). Unknown keys are errors.
Lengths in metres. Written from the declarations in ar_anchor/config by
`python -m ar_anchor.config.document configs`: change those, not this file."""

DEFAULT_HEADER = f"""\
ar_anchor tracker configuration: the built-in defaults (replay and live without --config use exactly
these: lone markers of one size, no boards). `ar-anchor demo` uses configs/demo.toml.
{_ABOUT}"""

DEMO_HEADER = f"""\
ar_anchor's demo scene (`ar-anchor demo` and `live --device synthetic` use exactly this without --config):
the built-in defaults (configs/default.toml) plus marker 7 at 40 mm and the 2x2 `desk` board.
{_ABOUT}"""

# the default file's [[boards]] examples, one per kind (values as a file spells them)
EXAMPLE_BOARDS: tuple[dict[str, Any], ...] = (
    {"name": "desk", "kind": "grid", "cols": 2, "rows": 2, "marker_length_m": 0.04, "separation_m": 0.02,
     "first_id": 10},
    {"name": "charuco", "kind": "charuco", "squares_x": 5, "squares_y": 7, "square_length_m": 0.04,
     "marker_length_m": 0.02, "legacy": False, "first_id": 0},
    {"name": "cube", "kind": "custom", "layout": "cube_layout.toml"},
)  # fmt: skip


def default_toml() -> str:
    """The text of ``configs/default.toml``: :class:`TrackerConfig` ()."""
    return config_toml(TrackerConfig(), DEFAULT_HEADER)


def demo_toml() -> str:
    """The text of ``configs/demo.toml``: :func:`~ar_anchor.config.model.demo_config`."""
    return config_toml(demo_config(), DEMO_HEADER)


def config_toml(config: TrackerConfig, header: str) -> str:
    """``config`` as a commented TOML file that reads back equal to it (but for ``source``)."""
    lines = [f"# {line}" for line in header.splitlines()]
    for item, spec in table_keys(TrackerConfig):
        value = getattr(config, item.name)
        lines.append("")
        if spec.shape == "table":
            lines += _table(item.name, value, _summary(spec.doc or type(value).__doc__))
        elif spec.kind is BoardConfig:
            lines += _boards(value, spec.doc)
        else:
            lines += _overlays(value, spec.doc)
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- tables


def _table(name: str, table: Any, doc: str) -> list[str]:
    """``[name]``: its keys at the table's values; sub-tables (per-id values) last."""
    lines = _line(f"[{name}]", doc)
    subtables = []
    for item, spec in table_keys(type(table)):
        value = getattr(table, item.name)
        if spec.shape == "id_values":
            subtables.append((item.name, spec, value))
        elif _empty(value) and spec.example is not None:
            lines += _line(f"{item.name} = {_toml(spec.example)}", spec.doc, "# ")
        else:
            lines += _line(f"{item.name} = {_toml(value)}", spec.doc)
    for key_name, spec, values in subtables:
        header = f"[{name}.{key_name}]"
        prefix = "" if values else "# "
        lines += ["", *_line(header, spec.doc, prefix)]
        for marker_id, value in (values or spec.example).items():
            lines += _line(f"{marker_id} = {_toml(value)}", "", prefix)
    return lines


def _boards(boards: tuple[BoardConfig, ...], doc: str) -> list[str]:
    """The config's boards; none: a commented-out example of each kind. A key's doc is shown once."""
    lines = _paragraph(doc)
    documented: set[tuple[str, str]] = set()
    if boards:
        for index, board in enumerate(boards):
            lines += [*([""] if index else []), "[[boards]]", *_board(_board_values(board), "", documented)]
        return lines
    for index, example in enumerate(EXAMPLE_BOARDS):
        lines += [*(["#"] if index else []), "# [[boards]]", *_board(example, "# ", documented)]
    return lines


def _board(values: Mapping[str, Any], prefix: str, documented: set[tuple[str, str]]) -> list[str]:
    """One board's keys (common, then its kind's): those it sets, then the others commented out at an
    example (its own ids, the detector's dictionary, ...) or their default."""
    lines = []
    for cls in (BoardKeys, BOARD_KEYS[values["kind"]]):
        for item, spec in table_keys(cls):
            doc = "" if (item.name, spec.doc) in documented else spec.doc
            documented.add((item.name, spec.doc))
            if item.name in values:
                lines += _line(f"{item.name} = {_toml(values[item.name])}", doc, prefix)
            else:
                lines += _line(f"{item.name} = {_toml(_example_of(item, spec, values))}", doc, prefix + "# ")
    return lines


def _example_of(item: dataclasses.Field, spec: Key, values: Mapping[str, Any]) -> Any:
    """What to show for a key a board does not set."""
    first = values.get("first_id", 0)
    if item.name == "ids":
        count = values.get("cols", 0) * values.get("rows", 0) or values["squares_x"] * values["squares_y"] // 2
        return list(range(first, first + count))
    if item.name == "dictionary":
        return TrackerConfig().detector.dictionary
    if item.name == "markers":
        return [{"id": first, "corners": [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]}]
    return spec.example if spec.example is not None else default_of(item)


def _board_values(board: BoardConfig) -> dict[str, Any]:
    """What a ``[[boards]]`` table says for ``board`` (the inverse of the reader)."""
    values: dict[str, Any] = {"name": board.name, "kind": board.kind}
    if board.kind == "custom":
        if board.layout_source == "inline":
            return {
                **values,
                "markers": [{"id": i, "corners": [list(c) for c in corners]} for i, corners in board.layout],
            }
        return {**values, "layout": board.layout_source}
    if board.kind == "grid":
        values.update(cols=board.cols, rows=board.rows, separation_m=board.separation_m)
    else:
        values.update(squares_x=board.cols, squares_y=board.rows, square_length_m=board.square_length_m)
        values.update(legacy=board.legacy)
    values["marker_length_m"] = board.marker_length_m
    values.update({"ids": list(board.ids)} if board.ids else {"first_id": board.first_id})
    return values


def _overlays(overlays: tuple[OverlayConfig, ...], doc: str) -> list[str]:
    """Each overlay with the keys it sets; after the first, the keys none sets, commented out at their
    defaults. A key's doc is shown once."""
    lines = _paragraph(doc)
    keys = list(table_keys(OverlayConfig))
    documented: set[str] = set()
    for index, overlay in enumerate(overlays):
        lines += [*([""] if index else []), "[[overlays]]"]
        for item, spec in keys:
            if _sets(overlay, item.name):
                value = _toml(getattr(overlay, item.name))
                lines += _line(f"{item.name} = {value}", "" if item.name in documented else spec.doc)
                documented.add(item.name)
        if index == 0:
            for item, spec in keys:
                if not any(_sets(o, item.name) for o in overlays):
                    lines += _line(f"{item.name} = {_toml(default_of(item))}", spec.doc, "# ")
    return lines


def _sets(overlay: OverlayConfig, name: str) -> bool:
    """Does the file spell this key for this overlay (target and kind always, the rest when not default)?"""
    if name in ("target", "kind") or (name == "colour" and overlay.colour_set):
        return True
    return getattr(overlay, name) != getattr(OverlayConfig(), name)


# ---------------------------------------------------------------------------- lines and values


def _line(text: str, doc: str, prefix: str = "") -> list[str]:
    """``text`` with ``doc`` beside it at :data:`COMMENT_AT`, continued on aligned comment lines."""
    text = prefix + text
    if not doc:
        return [text]
    start = max(COMMENT_AT, len(text) + 1)
    room = WIDTH - start - 2
    if room < 30:  # a long value: the doc goes below it
        return [text, *(" " * COMMENT_AT + "# " + part for part in textwrap.wrap(doc, WIDTH - COMMENT_AT - 2))]
    first, *rest = textwrap.wrap(doc, room)
    rest = textwrap.wrap(" ".join(rest), WIDTH - COMMENT_AT - 2) if rest else []
    return [f"{text:<{start}}# {first}", *(" " * COMMENT_AT + "# " + part for part in rest)]


def _paragraph(doc: str) -> list[str]:
    return [f"# {line}" for line in textwrap.wrap(doc, WIDTH - 2)]


def _summary(doc: str | None) -> str:
    """A docstring's first sentence, reST markup removed."""
    first = (doc or "").strip().split("\n\n")[0].replace("\n", " ")
    first = re.sub(r":\w+:`~?([^`]*)`", r"\1", first).replace("``", "")
    return re.sub(r"\s+", " ", first).rstrip(".")


def _empty(value: Any) -> bool:
    return isinstance(value, (tuple, list, dict, Mapping)) and not value


def _toml(value: Any) -> str:
    """A TOML literal (inline arrays and tables) in the spelling a person would write."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if 0 < abs(value) < 1e-3:  # 1e-4, not 0.0001 (and not Python's 1e-05)
            mantissa, exponent = f"{value:e}".split("e")
            short = f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"
            if float(short) == value:
                return short
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{name} = {_toml(v)}" for name, v in value.items()) + "}"
    if isinstance(value, Iterable):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    raise TypeError(f"no TOML spelling for {type(value).__name__}")


# ---------------------------------------------------------------------------- command


FILES = {"default.toml": default_toml, "demo.toml": demo_toml}


def main(argv: list[str] | None = None) -> int:
    """Write ``default.toml`` and ``demo.toml`` into ``folder`` (``--check``: write nothing, 1 if one is stale)."""
    parser = argparse.ArgumentParser(
        prog="python -m ar_anchor.config.document",
        description="Write default.toml and demo.toml from the key declarations.",
    )
    parser.add_argument("folder", type=Path, help="where the files go (the repository's configs/)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file is not current")
    args = parser.parse_args(argv)
    stale = []
    for name, render in FILES.items():
        path, text = args.folder / name, render()
        if path.is_file() and path.read_text(encoding="utf-8") == text:
            continue
        stale.append(str(path))
        if not args.check:
            path.write_text(text, encoding="utf-8")
    verb = "not current" if args.check else "written"
    print(f"{verb}: {', '.join(stale)}" if stale else "all current")
    return 1 if stale and args.check else 0


if __name__ == "__main__":
    sys.exit(main())
