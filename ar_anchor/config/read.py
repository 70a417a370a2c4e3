"""Reading a TOML document into a :class:`~ar_anchor.config.model.TrackerConfig`.

One generic reader, :func:`read_keys`, reads any table into the keys its dataclass declares (type,
shape and check from each field's :class:`~ar_anchor.config.keys.Key`); what is left over in a
table is an unknown key, refused with a hint. The special cases are the ones that relate keys or
tables to each other:

- the dictionary (``[detector]``) bounds every marker id, so it is read first;
- ``[[boards]]``: the kind decides the other keys; ids must fit the dictionary, not overlap other
  boards', and agree with ``[markers.lengths_m]``; a custom layout comes from a file or inline;
- ``[[overlays]]``: the model path is relative to the config file and only for meshes; absent: the
  defaults (a cube on every lone marker, the pin on every board).

Every error is a :class:`~ar_anchor.config.keys.ConfigValueError` whose message is one line naming
the file, table and key (``configs/x.toml: [markers] length_m: must be > 0, got -1``).
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..boards import layout_from_mapping, read_layout
from ..camera.files import input_file_problem
from ..errors import ConfigError, printable
from .board import BOARD_KEYS, BoardConfig, BoardKeys, CharucoBoardKeys, CustomBoardKeys
from .dictionaries import canonical_dictionary, dictionary_size
from .keys import ConfigValueError, Key, declared, default_of, table_keys
from .model import OverlayConfig, TrackerConfig, implausible_length_hint

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = ["load_config", "parse_config", "read_keys"]

log = logging.getLogger(__name__)


class Table:
    """One TOML table being read: keys are taken out of it; what is left at :meth:`done` is unknown."""

    def __init__(self, data: Any, where: str, path: str) -> None:
        if not isinstance(data, dict):
            problem = f"must be a table, got {type(data).__name__}"
            raise ConfigValueError(f"{path}: {where} {problem}", problem=problem, table=where, value=data)
        self.data = dict(data)
        self.where = where
        self.path = path

    def fail(self, key: str, problem: str, value: Any = None) -> ConfigValueError:
        message = f"{self.path}: {self.where} {_shown_key(key)}: {problem}"
        return ConfigValueError(message, problem=problem, key=key, table=self.where, value=value)

    def read(self, cls: type, name: str, limit: int = 0) -> Any:
        """Key ``name`` of dataclass ``cls``: read and checked, or its default when absent."""
        item, spec = declared(cls, name)
        if name in self.data:
            return _READERS[spec.shape](self, name, spec, limit)
        if spec.required:
            raise self.fail(name, spec.required)
        return default_of(item)

    def done(self, known: Iterable[str], elsewhere: Mapping[str, str] | None = None) -> None:
        """Refuse what is left: unknown keys, with a hint (a near spelling, or where the key belongs)."""
        if not self.data:
            return
        unknown = sorted(map(_shown_key, self.data))
        known = list(known)
        hints = []
        for name in unknown:
            if elsewhere and name in elsewhere:
                hints.append(f"{name} is {elsewhere[name]}")
            else:
                hints += [f"did you mean {close}?" for close in difflib.get_close_matches(name, known, n=1)]
        hint = "; ".join(hints) if hints else f"known: {', '.join(known)}"
        problem = f"unknown key(s): {', '.join(unknown)} ({hint})"
        raise ConfigValueError(
            f"{self.path}: {self.where}: {problem}", problem=problem, key=unknown[0], table=self.where
        )


def read_keys(table: Table, cls: type, limit: int = 0) -> dict[str, Any]:
    """The keys of dataclass ``cls`` that ``table`` holds, each read and checked as declared (sub-tables
    last, as a file writes them; ``limit``: the dictionary's marker count, for marker ids). A missing
    required key is an error; the other missing keys are left out (the dataclass has their defaults).
    Keys of shapes that need more than the table (arrays of tables, inline layouts) are the caller's."""
    values = {}
    for item, spec in sorted(table_keys(cls), key=lambda pair: pair[1].shape == "id_values"):
        if spec.shape not in _READERS:
            continue
        if item.name in table.data:
            values[item.name] = _READERS[spec.shape](table, item.name, spec, limit)
        elif spec.required:
            raise table.fail(item.name, spec.required)
    return values


def read_table(root: Table, name: str, limit: int = 0) -> Any:
    """``[name]`` of ``root`` as the dataclass :class:`TrackerConfig` declares for it (absent: all defaults)."""
    cls = declared(TrackerConfig, name)[1].kind
    table = Table(root.data.pop(name, {}), f"[{name}]", root.path)
    values = read_keys(table, cls, limit)
    table.done(_names(cls))
    return cls(**values)


# ---------------------------------------------------------------------------- one key, by shape


def _read_value(table: Table, name: str, spec: Key, limit: int) -> Any:
    value = table.data.pop(name)
    kind = spec.kind
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            value = float(value)
        except OverflowError:  # TOML integers are not bounded in tomllib
            raise table.fail(name, "must be finite, got an integer too large for a number", value) from None
    if kind is int and isinstance(value, bool) or not isinstance(value, kind):
        raise table.fail(name, f"must be {_kind_name(kind)}, got {value!r}", value)
    if kind is float and not math.isfinite(value):
        raise table.fail(name, f"must be finite, got {value!r}", value)
    return _checked(table, name, spec, value, limit)


def _read_ids(table: Table, name: str, _spec: Key, limit: int) -> tuple[int, ...]:
    value = table.data.pop(name)
    if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise table.fail(name, f"must be a list of integer marker ids, got {value!r}", value)
    bad = [v for v in value if not 0 <= v < limit]
    if bad:
        raise table.fail(name, f"ids {bad} are outside the dictionary (0..{limit - 1})", value)
    if len(set(value)) != len(value):
        raise table.fail(name, f"ids must be unique, got {value!r}", value)
    return tuple(value)


def _read_vector(table: Table, name: str, spec: Key, limit: int) -> tuple[Any, ...]:
    value = table.data.pop(name)
    numbers = isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not numbers or len(value) != spec.size:
        raise table.fail(name, f"must be a list of {spec.size} numbers, got {value!r}", value)
    _checked(table, name, spec, value, limit)  # range first: no float() of a huge integer
    return tuple(spec.kind(float(v)) for v in value)


def _read_id_values(table: Table, name: str, spec: Key, limit: int) -> dict[int, Any]:
    """A sub-table keyed by marker id (``[markers.lengths_m]``: ``7 = 0.04``)."""
    ids = Table(table.data.pop(name), f"{table.where[:-1]}.{name}]", table.path)
    values: dict[int, Any] = {}
    for raw in list(ids.data):
        if not (raw.isascii() and raw.isdigit()) or not 0 <= int(raw) < limit:
            raise ids.fail(raw, f"keys must be marker ids 0..{limit - 1}", raw)
        if int(raw) in values:  # "7" and "07"
            raise ids.fail(raw, f"marker {int(raw)} is listed twice", raw)
        values[int(raw)] = _read_value(ids, raw, spec, limit)
    return values


_READERS = {"value": _read_value, "ids": _read_ids, "vector": _read_vector, "id_values": _read_id_values}


def _checked(table: Table, name: str, spec: Key, value: Any, limit: int) -> Any:
    problem = spec.check.problem(value, limit) if spec.check is not None else None
    if problem:
        raise table.fail(name, problem if spec.check.shows_value else f"{problem}, got {value!r}", value)
    return value


def _names(*classes: type) -> list[str]:
    return [item.name for cls in classes for item, _ in table_keys(cls)]


def _shown_key(key: object) -> str:
    """A key as the message shows it: quoted when it holds line breaks or control characters (a TOML
    key may), so that the message stays one line and prints nothing but text."""
    text = str(key)
    return text if text.isprintable() else repr(text)


def _kind_name(kind: type) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false"}.get(kind, kind.__name__)


def _base_folder(path: str) -> Path:
    """Where relative file names in the config start (absolute: they are read later, maybe from
    another working directory)."""
    return Path(path).parent.absolute() if path and not path.startswith("<") else Path.cwd()


# ---------------------------------------------------------------------------- the document


def parse_config(data: Mapping[str, Any], path: str = "<config>") -> TrackerConfig:
    """Validate a parsed TOML document into a :class:`TrackerConfig` (``path``: named in errors)."""
    root = Table(data, "top level", path)
    detector = read_table(root, "detector")
    detector = dataclasses.replace(detector, dictionary=canonical_dictionary(detector.dictionary))  # as written
    limit = dictionary_size(detector.dictionary)
    markers = read_table(root, "markers", limit)
    boards = _read_boards(root, detector.dictionary, limit, markers.lengths_m)
    pose = read_table(root, "pose")
    filter_config = read_table(root, "filter")
    groups = read_table(root, "groups")
    recording = read_table(root, "recording")
    overlays = _read_overlays(root)
    root.done(_names(TrackerConfig))
    _warn_implausible_lengths(markers, boards, path)
    return TrackerConfig(
        detector=detector,
        markers=markers,
        boards=boards,
        pose=pose,
        filter=filter_config,
        groups=groups,
        recording=recording,
        overlays=overlays,
        source=path,
    )


def _warn_implausible_lengths(markers: Any, boards: tuple[BoardConfig, ...], path: str) -> None:
    """Warn (once per key) about marker sides over a metre: most likely millimetres."""
    lengths = [("[markers] length_m =", markers.length_m)]
    lengths += [(f"[markers.lengths_m] {marker_id} =", length) for marker_id, length in markers.lengths_m.items()]
    for board in boards:
        if board.kind != "custom":
            lengths.append((f"[[boards]] '{board.name}' marker_length_m =", board.marker_length_m))
        elif implausible_length_hint(side := max(map(board.marker_length_of, board.marker_ids), default=0.0), ""):
            log.warning(
                "%s: [[boards]] '%s': its layout's markers are %g m wide: did you give millimetres? (a layout's "
                "corners are in metres)",
                printable(path),
                board.name,
                side,
            )
    for name, length in lengths:
        hint = implausible_length_hint(length, name)
        if hint is not None:
            log.warning("%s: %s", printable(path), hint)


def _array_of_tables(root: Table, name: str) -> list[Any]:
    raw = root.data.pop(name, [])
    if not isinstance(raw, list):
        problem = f"must be an array of tables ([[{name}]])"
        raise ConfigValueError(f"{root.path}: {name} {problem}", problem=problem, key=name, value=raw)
    return raw


def _read_boards(root: Table, dictionary: str, limit: int, lengths_m: Mapping[int, float]) -> tuple[BoardConfig, ...]:
    """``[[boards]]``: each read by :func:`read_board`, then checked against the others and against
    ``[markers.lengths_m]``."""
    boards: list[BoardConfig] = []
    owner: dict[int, str] = {}  # marker id -> board name
    for index, raw in enumerate(_array_of_tables(root, "boards")):
        table = Table(raw, f"[[boards]] #{index + 1}", root.path)
        board = read_board(table, dictionary, limit)
        if any(b.name == board.name for b in boards):
            raise table.fail("name", "duplicate board name", board.name)
        for marker_id in board.marker_ids:
            if marker_id in owner:
                raise table.fail("ids", f"marker id {marker_id} is already used by board '{owner[marker_id]}'")
            owner[marker_id] = board.name
            if marker_id in lengths_m and abs(lengths_m[marker_id] - board.marker_length_of(marker_id)) > 1e-9:
                raise table.fail(
                    "marker_length_m",
                    f"marker {marker_id} also has [markers.lengths_m] "
                    f"{lengths_m[marker_id]:g}; a board marker's size is the board's",
                )
        boards.append(board)
    return tuple(boards)


def read_board(table: Table, dictionary: str, limit: int) -> BoardConfig:
    """One ``[[boards]]`` table: the common keys, then its kind's (keys of other kinds are unknown)."""
    name = table.read(BoardKeys, "name")
    table.where = f"[[boards]] '{name}'"
    kind = table.read(BoardKeys, "kind")
    if kind == "custom":
        board = _custom_board(table, name, dictionary, limit)
    else:
        board = _board_of_cells(table, name, kind, dictionary, limit)
    elsewhere = {
        key_name: f"a {other} board's key"
        for other, keys in BOARD_KEYS.items()
        if other != kind
        for key_name in _names(keys)
        if key_name not in _names(BOARD_KEYS[kind])
    }
    table.done(_names(BoardKeys, BOARD_KEYS[kind]), elsewhere)
    return board


def _board_of_cells(table: Table, name: str, kind: str, dictionary: str, limit: int) -> BoardConfig:
    """A grid or ChArUco board: a grid's keys are BoardConfig's; a ChArUco board's squares are its cells."""
    values = read_keys(table, BOARD_KEYS[kind], limit)
    if kind == "charuco":
        values = _charuco_as_board(table, values, dictionary)
    board = BoardConfig(name=name, kind=kind, dictionary=dictionary, **values)
    if kind == "grid":
        count, formula = board.cols * board.rows, "cols*rows"
    else:
        count, formula = (board.cols * board.rows) // 2, "squares_x*squares_y//2"
    if board.ids and len(board.ids) != count:
        raise table.fail("ids", f"needs {formula} = {count} ids, got {len(board.ids)}", board.ids)
    if not board.ids and board.first_id + count > limit:
        last = board.first_id + count - 1
        raise table.fail("first_id", f"ids {board.first_id}..{last} exceed the dictionary's {limit} markers")
    return board


def _same_dictionary(name: str, dictionary: str) -> bool:
    """Do ``name`` (any spelling) and ``dictionary`` name the same dictionary? (An unknown name does not.)"""
    try:
        return canonical_dictionary(name) == canonical_dictionary(dictionary)
    except ConfigValueError:
        return False


# a ChArUco board's keys that BoardConfig names otherwise (the chessboard's squares are the board's cells)
_CHARUCO_AS_BOARD = {"squares_x": "cols", "squares_y": "rows"}


def _charuco_as_board(table: Table, values: dict[str, Any], dictionary: str) -> dict[str, Any]:
    """A ChArUco table's keys (``values``: those it holds), checked against each other and against the
    detector's ``dictionary``, as BoardConfig's keys (all but the dictionary; a missing one: its default)."""
    keys = CharucoBoardKeys(**values)
    if keys.marker_length_m >= keys.square_length_m:
        raise table.fail(
            "marker_length_m",
            f"must be smaller than square_length_m ({keys.square_length_m:g}), got {keys.marker_length_m!r}",
            keys.marker_length_m,
        )
    if "dictionary" in values and not _same_dictionary(keys.dictionary, dictionary):
        problem = f"must be the detector's dictionary ({dictionary}), got {keys.dictionary!r}"
        raise table.fail("dictionary", problem, keys.dictionary)
    every = dataclasses.asdict(keys)
    return {_CHARUCO_AS_BOARD.get(field, field): value for field, value in every.items() if field != "dictionary"}


def _custom_board(table: Table, name: str, dictionary: str, limit: int) -> BoardConfig:
    """A custom layout: from a file (``layout``, relative to the config file) or inline (``markers``)."""
    has_file, has_inline = "layout" in table.data, "markers" in table.data
    if has_file == has_inline:
        raise table.fail("layout", 'a custom board needs either layout = "<file>" or inline [[boards.markers]]')
    if has_file:
        layout_path = _base_folder(table.path) / table.read(CustomBoardKeys, "layout")
        problem = input_file_problem(layout_path)
        if problem is not None:
            raise table.fail("layout", f"layout file {printable(layout_path)}: {problem}")
        try:
            layout = read_layout(layout_path)
        except ConfigError as err:
            raise table.fail("layout", str(err)) from None
        source = str(layout_path)
    else:
        try:
            layout = layout_from_mapping({"markers": table.data.pop("markers")}, "inline markers")
        except ConfigError as err:
            raise table.fail("markers", str(err)) from None
        source = "inline"
    bad = [marker_id for marker_id, _ in layout if marker_id >= limit]
    if bad:
        key = "markers" if source == "inline" else "layout"
        raise table.fail(key, f"marker ids {bad} are outside the dictionary (0..{limit - 1})")
    return BoardConfig(name=name, kind="custom", dictionary=dictionary, layout=layout, layout_source=source)


def _read_overlays(root: Table) -> tuple[OverlayConfig, ...]:
    """``[[overlays]]``; absent: the defaults (a cube on every lone marker, the pin on every board)."""
    if "overlays" not in root.data:
        return default_of(declared(TrackerConfig, "overlays")[0])
    base = _base_folder(root.path)
    overlays = []
    for index, raw in enumerate(_array_of_tables(root, "overlays")):
        table = Table(raw, f"[[overlays]] #{index + 1}", root.path)
        colour_set = "colour" in table.data
        values = read_keys(table, OverlayConfig)
        values["path"] = _overlay_model(table, values.get("kind", "cube"), values.get("path", ""), base)
        table.done(_names(OverlayConfig))
        overlays.append(OverlayConfig(**values, colour_set=colour_set))
    return tuple(overlays)


def _overlay_model(table: Table, kind: str, mesh_path: str, base: Path) -> str:
    """An overlay's model: only for meshes, which need one; a file is made absolute from ``base``."""
    if kind == "mesh" and not mesh_path:
        raise table.fail("path", 'a mesh overlay needs a model file (or "builtin:pin")')
    if kind != "mesh" and mesh_path:
        raise table.fail("path", f"only mesh overlays take a model file (this one is {kind!r})", mesh_path)
    if mesh_path and not mesh_path.startswith("builtin:"):
        return str(base / mesh_path)
    if mesh_path and mesh_path not in ("builtin:pin",):
        raise table.fail("path", f"unknown built-in model {mesh_path!r} (builtin:pin)", mesh_path)
    return mesh_path


def load_config(path: str | os.PathLike[str] | None = None, *, demo: bool = False) -> TrackerConfig:
    """Read a tracker TOML file (None: the built-in defaults, identical to ``configs/default.toml``: no
    boards, no per-id sizes; with ``demo``: :func:`~ar_anchor.config.model.demo_config`, identical to
    ``configs/demo.toml``)."""
    if path is None:
        from .model import demo_config

        return demo_config() if demo else TrackerConfig()
    path = Path(path)
    problem = input_file_problem(path)
    if problem is not None:
        raise ConfigError(f"config file {printable(path)}: {problem}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise ConfigError(f"config file {path}: not UTF-8 text ({err.reason})") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path}: invalid TOML: {err}") from None
    except RecursionError:  # tomllib recurses per nesting level of arrays and inline tables
        raise ConfigError(f"config file {path}: invalid TOML: nested too deeply") from None
    except OSError as err:
        raise ConfigError(f"config file {path}: cannot read ({err.strerror})") from None
    return parse_config(data, str(path))
