"""Config keys are declared once: the shipped TOML files, the reader and the errors all follow the declarations.

``configs/default.toml`` and ``configs/demo.toml`` are written by ``python -m ar_anchor.config.document
configs``; the tests here check them both ways: equal to what the writer makes now, and (read on their
own, not through the writer) holding every declared key with its default and its doc, and nothing else.
"""

from __future__ import annotations

import dataclasses
import re
import sys
import typing
from pathlib import Path

import pytest

from ar_anchor.config import ConfigValueError, TrackerConfig, demo_config, load_config, parse_config
from ar_anchor.config.board import BOARD_KEYS, BoardConfig, BoardKeys
from ar_anchor.config.document import EXAMPLE_BOARDS, config_toml, default_toml, demo_toml, main
from ar_anchor.config.keys import default_of, table_keys
from ar_anchor.config.model import OverlayConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
DEFAULT_TOML = REPO / "configs" / "default.toml"
DEMO_TOML = REPO / "configs" / "demo.toml"
REGENERATE = "stale: run `python -m ar_anchor.config.document configs`"

SCALAR_TABLES = [(item.name, spec.kind) for item, spec in table_keys(TrackerConfig) if spec.shape == "table"]
KEY_CLASSES = [cls for _, cls in SCALAR_TABLES] + [OverlayConfig, BoardKeys, *BOARD_KEYS.values()]
ASSIGNMENT = re.compile(r"^(?P<comment>(?:# )*)(?P<key>[A-Za-z0-9_]+) = (?P<value>.*?)(?:\s+# (?P<doc>.*))?$")
CONTINUATION = re.compile(r"^ {34}# (?P<doc>.*)$")


def assignments(text: str) -> dict[str, list[dict[str, str]]]:
    """Every ``key = value  # doc`` line of a written file (commented out or not) under its table header,
    with the doc's continuation lines joined; read without the writer's help."""
    found: dict[str, list[dict[str, str]]] = {}
    table = "top level"
    lines = text.splitlines()
    for index, line in enumerate(lines):
        header = re.match(r"^(?:# )?(\[\[?[a-z_.]+\]\]?)", line)
        if header:
            table = header.group(1)
            continue
        match = ASSIGNMENT.match(line)
        if not match:
            continue
        entry = match.groupdict()
        entry["doc"] = entry["doc"] or ""
        for following in lines[index + 1 :]:
            more = CONTINUATION.match(following)
            if not more:
                break
            entry["doc"] = f"{entry['doc']} {more['doc']}".strip()
        found.setdefault(table, []).append(entry)
    return found


# ============================================================================ the files are the declarations


def test_committed_config_files_are_written_from_the_declarations():
    assert DEFAULT_TOML.read_text(encoding="utf-8") == default_toml(), REGENERATE
    assert DEMO_TOML.read_text(encoding="utf-8") == demo_toml(), REGENERATE


def test_the_files_read_back_as_the_configs_they_were_written_from():
    assert dataclasses.replace(load_config(DEFAULT_TOML), source="x") == dataclasses.replace(
        TrackerConfig(), source="x"
    )
    assert dataclasses.replace(load_config(DEMO_TOML), source="x") == dataclasses.replace(demo_config(), source="x")


@pytest.mark.parametrize(("table", "cls"), SCALAR_TABLES)
def test_default_toml_has_every_key_of_a_table_with_its_default_and_doc_and_nothing_else(table, cls):
    # given the shipped default file, read line by line (not through the writer)
    written = {entry["key"]: entry for entry in assignments(DEFAULT_TOML.read_text(encoding="utf-8"))[f"[{table}]"]}
    data = tomllib.loads(DEFAULT_TOML.read_text(encoding="utf-8"))[table]
    declared = {item.name: (item, spec) for item, spec in table_keys(cls) if spec.shape != "id_values"}
    # then the table holds exactly the declared keys ...
    assert set(written) == set(declared)
    for name, (item, spec) in declared.items():
        default = default_of(item)
        entry = written[name]
        # ... each with its doc beside it ...
        assert " ".join(spec.doc.split()) == entry["doc"], name
        if default in ((), {}):
            # ... an empty list shown commented out with its example ...
            assert entry["comment"] == "# " and name not in data, name
            assert tomllib.loads(f"x = {entry['value']}")["x"] == spec.example
        else:
            # ... and every other key at its default
            assert entry["comment"] == "", name
            value = data[name]
            assert (tuple(value) if isinstance(value, list) else value) == default, name
            assert type(value) is spec.kind or isinstance(value, list), name


def test_per_id_sizes_are_shown_as_an_example_in_default_toml_and_set_in_demo_toml():
    default = DEFAULT_TOML.read_text(encoding="utf-8")
    assert "\n# [markers.lengths_m]" in default and "\n# 7 = 0.04\n" in default
    demo = DEMO_TOML.read_text(encoding="utf-8")
    assert "\n[markers.lengths_m]" in demo and "\n7 = 0.04\n" in demo


def test_every_overlay_key_is_in_default_toml_once_with_its_doc():
    entries = assignments(DEFAULT_TOML.read_text(encoding="utf-8"))["[[overlays]]"]
    documented = {entry["key"]: entry["doc"] for entry in entries if entry["doc"]}
    keys = {item.name: spec for item, spec in table_keys(OverlayConfig)}
    assert {entry["key"] for entry in entries} == set(keys)
    assert documented == {name: " ".join(spec.doc.split()) for name, spec in keys.items()}


# ============================================================================ board examples


def example_blocks(text: str) -> list[str]:
    """The default file's commented-out ``[[boards]]`` examples, each uncommented once."""
    blocks: list[list[str]] = []
    for line in text.splitlines():
        if line == "# [[boards]]":
            blocks.append([])
        elif blocks and blocks[-1] is not None and (line.startswith("# ") or line.startswith(" " * 34 + "#")):
            blocks[-1].append(line[2:] if line.startswith("# ") else line)
        elif blocks:
            blocks.append(None)  # the block ended
    return ["[[boards]]\n" + "\n".join(block) + "\n" for block in blocks if block is not None]


def test_default_toml_shows_one_example_board_of_each_kind_with_every_key_and_doc():
    text = DEFAULT_TOML.read_text(encoding="utf-8")
    blocks = example_blocks(text)
    assert [tomllib.loads(block)["boards"][0]["kind"] for block in blocks] == list(BOARD_KEYS)
    documented = {(entry["key"], entry["doc"]) for entry in assignments(text)["[[boards]]"] if entry["doc"]}
    for block, kind in zip(blocks, BOARD_KEYS):
        shown = {entry["key"] for entry in assignments(block)["[[boards]]"]}
        declared = {item.name: spec for cls in (BoardKeys, BOARD_KEYS[kind]) for item, spec in table_keys(cls)}
        assert shown == set(declared), kind
        for name, spec in declared.items():
            assert (name, " ".join(spec.doc.split())) in documented, name


def test_the_example_boards_load(tmp_path):
    # given the three examples, uncommented, each in a file beside the layout the custom one names
    layout = "[[markers]]\nid = 3\ncorners = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]\n"
    (tmp_path / "cube_layout.toml").write_text(layout)
    boards = []
    for index, block in enumerate(example_blocks(DEFAULT_TOML.read_text(encoding="utf-8"))):
        path = tmp_path / f"example{index}.toml"
        path.write_text(block)
        boards += load_config(path).boards
    # then they are the documented examples
    assert [(b.name, b.kind, len(b.marker_ids)) for b in boards] == [
        ("desk", "grid", 4),
        ("charuco", "charuco", 17),
        ("cube", "custom", 1),
    ]
    assert [b.name for b in boards] == [example["name"] for example in EXAMPLE_BOARDS]


# ============================================================================ the reader follows the declarations

WRONG_TYPE = {
    bool: ("1", "true or false"),
    int: ("'1'", "an integer"),
    float: ("'1'", "a number"),
    str: ("1", "a string"),
}


@pytest.mark.parametrize(
    ("table", "name", "kind"),
    [
        pytest.param(table, item.name, spec.kind, id=f"{table}.{item.name}")
        for table, cls in SCALAR_TABLES
        for item, spec in table_keys(cls)
        if spec.shape == "value"
    ],
)
def test_every_scalar_key_is_read_as_its_declared_type(tmp_path, table, name, kind):
    path = tmp_path / "typed.toml"
    text, expected = WRONG_TYPE[kind]
    path.write_text(f"[{table}]\n{name} = {text}\n")
    with pytest.raises(
        ConfigValueError, match=re.escape(f"{path}: [{table}] {name}: must be {expected}, got ")
    ) as info:
        load_config(path)
    assert (info.value.table, info.value.key) == (f"[{table}]", name)


@pytest.mark.parametrize("cls", KEY_CLASSES, ids=lambda cls: cls.__name__)
def test_declarations_are_consistent(cls):
    hints = typing.get_type_hints(cls)
    for item, spec in table_keys(cls):
        # every key says what it is for
        assert spec.doc.strip(), item.name
        # a scalar's declared kind is its annotation; a vector's, its items'
        if spec.shape == "value":
            assert hints[item.name] is spec.kind, item.name
        if spec.shape == "vector":
            assert set(typing.get_args(hints[item.name])) == {spec.kind}, item.name
        # defaults meet their own checks (a marker id against the default dictionary's 50)
        default = default_of(item)
        if spec.check is not None and default is not dataclasses.MISSING and spec.shape == "value":
            assert spec.check.problem(default, 50) is None, item.name


def test_grid_board_defaults_are_its_keys_defaults():
    board, keys = BoardConfig(name="x"), BOARD_KEYS["grid"]
    for item, _ in table_keys(keys):
        assert getattr(board, item.name) == default_of(item), item.name


def test_a_config_of_every_board_kind_and_overlay_key_round_trips_through_the_writer(tmp_path):
    # given a config with boards of every kind and an overlay that sets every key
    data = {
        "detector": {"dictionary": "DICT_5X5_100", "roi": False},
        "markers": {"length_m": 0.07, "ids": [1, 2], "lengths_m": {"2": 0.03}},
        "boards": [
            {"name": "g", "kind": "grid", "cols": 3, "rows": 1, "ids": [20, 22, 21]},
            {"name": "c", "kind": "charuco", "squares_x": 3, "squares_y": 4, "square_length_m": 0.05,
             "marker_length_m": 0.03, "legacy": True, "first_id": 40},
            {"name": "cu", "kind": "custom",
             "markers": [{"id": 60, "corners": [[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0.5]]}]},
        ],
        "filter": {"enabled": False, "still_translation_m_sqrt_s": 2.5e-6},
        "overlays": [
            {"target": "board:g", "kind": "mesh", "path": "builtin:pin", "size_m": 0.1, "scale": 2.0,
             "offset_m": [0, 0, 0.01], "rotation_deg": [90, 0, 0], "colour": [1, 2, 3], "opacity": 0.5},
            {"target": "marker:1", "kind": "axes"},
        ],
    }  # fmt: skip
    config = parse_config(data, "x.toml")
    # when written and read back
    path = tmp_path / "round.toml"
    path.write_text(config_toml(config, "round trip"))
    # then it is the same config
    assert dataclasses.replace(load_config(path), source="x.toml") == config


def test_document_command_checks_and_writes(tmp_path, capsys):
    assert main([str(REPO / "configs"), "--check"]) == 0
    assert main([str(tmp_path), "--check"]) == 1
    assert not list(tmp_path.iterdir())
    assert main([str(tmp_path)]) == 0
    assert (tmp_path / "default.toml").read_text(encoding="utf-8") == default_toml()
    assert main([str(tmp_path), "--check"]) == 0
    assert "not current" in capsys.readouterr().out
