"""Property and fuzz tests of every file parser: tracker TOML, camera YAML (OpenCV and ROS
camera_info), board layout files (TOML and ArUco marker maps) and mesh files.

For every input the outcome is one of two: a typed error (:class:`ConfigError` /
:class:`CameraError`, both :class:`InputError`, exit code 2) with a one-line message naming the
file, or a result that passes validation (finite numbers, sizes and ids in range, and usable by
the next stage). Never another exception, a hang, or silent nonsense.

Budgets: see tests/helpers.py (CI: the counts below; ``HYPOTHESIS_PROFILE=long``: 20x).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import struct
import subprocess
import sys
import textwrap
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ar_anchor.boards import read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.config import (
    CORNER_REFINEMENTS,
    OVERLAY_KINDS,
    DetectorConfig,
    FilterConfig,
    PoseConfig,
    RecordingConfig,
    TrackerConfig,
    dictionary_names,
    dictionary_size,
    load_config,
    parse_config,
)
from ar_anchor.errors import CameraError, ConfigError, InputError
from ar_anchor.render.models import MAX_TRIANGLES, Model, load_mesh
from tests.helpers import fuzz_settings, outcome, time_limit

pytestmark = pytest.mark.slow  # fuzzing and end-to-end CLI runs: the full suite, not the fast tier

REPO = Path(__file__).resolve().parents[2]
DEFAULT_TOML = REPO / "configs" / "default.toml"
SYNTHETIC_YAML = REPO / "configs" / "camera_synthetic.yml"
PER_CALL_S = 20.0  # a parser taking longer than this on a file of a few kB is hung

# ============================================================================ value strategies

HUGE_INTS = st.sampled_from([2**63, -(2**63) - 1, 10**400, -(10**400)])
NUMBERS = st.one_of(
    st.floats(-1e3, 1e3),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-1000, 1000),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e300, -1.0, 1.0]),
    HUGE_INTS,
)
POSITIVE = st.one_of(st.floats(0.001, 0.3), NUMBERS)  # biased to valid lengths, so deep paths are reached
SMALL_INTS = st.one_of(st.integers(-3, 12), st.sampled_from([0, 1, 49, 50, 100, 101, 1000, 10_000]), HUGE_INTS)
# anything tomllib can return
TOML_LEAF = st.one_of(
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=10),
    st.datetimes(min_value=dt.datetime(1, 1, 1), max_value=dt.datetime(9999, 12, 31)),
    st.dates(),
    st.times(),
)
WILD = st.recursive(
    TOML_LEAF,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=8,
)


def sometimes_wild(strategy: st.SearchStrategy) -> st.SearchStrategy:
    return st.one_of(strategy, strategy, strategy, WILD)


def mostly(good: object, other: st.SearchStrategy) -> st.SearchStrategy:
    """``good`` three times in four, else ``other`` (keeps the share of inputs that get far enough high)."""
    return st.one_of(st.just(good), st.just(good), st.just(good), other)


def _value_for(default: object) -> st.SearchStrategy:
    if isinstance(default, bool):
        return sometimes_wild(st.booleans())
    if isinstance(default, int):
        return sometimes_wild(SMALL_INTS | st.floats(-10, 10))
    if isinstance(default, float):
        return sometimes_wild(st.one_of(st.floats(0.0, 2 * default + 1.0), NUMBERS))
    return WILD


def _table(cls: type, special: Mapping[str, st.SearchStrategy] | None = None) -> st.SearchStrategy:
    """A table of ``cls``'s keys (each optional) with plausible or wild values, sometimes an unknown key."""
    special = dict(special or {})
    keys = {
        f.name: special.pop(f.name) if f.name in special else _value_for(f.default) for f in dataclasses.fields(cls)
    }
    keys.update(special)
    table = st.fixed_dictionaries({}, optional=keys)
    with_typo = st.tuples(table, st.text(min_size=1, max_size=6), WILD).map(lambda t: {**t[0], t[1]: t[2]})
    return st.one_of(table, table, table, with_typo, WILD)


DICTIONARIES = dictionary_names()
DICTIONARY = sometimes_wild(st.sampled_from([*DICTIONARIES, "dict_4x4_50", "DICT_4X4_51", "", "DICT_"]))
QUAD = st.builds(
    lambda x, y, side, dz: [[x, y, 0.0], [x + side, y, 0.0], [x + side, y + side, dz], [x, y + side, dz]],
    st.floats(-1, 1),
    st.floats(-1, 1),
    st.floats(0.001, 0.2) | st.sampled_from([0.0, -0.05, 1e-7, 2000.0]),
    st.sampled_from([0.0, 0.0, 0.0, 0.01, float("nan")]),
)
CORNERS = st.one_of(QUAD, QUAD, st.lists(st.lists(NUMBERS, min_size=0, max_size=4), min_size=0, max_size=5), WILD)
LAYOUT_ENTRY = st.one_of(
    st.fixed_dictionaries({"id": sometimes_wild(st.integers(0, 60)), "corners": CORNERS}),
    st.fixed_dictionaries({"id": st.integers(0, 60)}, optional={"corners": CORNERS, "extra": WILD}),
    WILD,
)
LAYOUT_ENTRIES = st.lists(LAYOUT_ENTRY, max_size=4)

# layout files the configs may name (written by the `layout_dir` fixture), plus paths that do not exist
LAYOUT_FILES = {
    "good.toml": "[[markers]]\nid = 20\ncorners = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]\n"
    "[[markers]]\nid = 21\ncorners = [[0.1, 0, 0], [0.15, 0, 0], [0.15, 0.05, 0], [0.1, 0.05, 0]]\n",
    "cube.toml": "[[markers]]\nid = 30\ncorners = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]\n"
    "[[markers]]\nid = 31\ncorners = [[0, 0, 0.05], [0, 0, 0], [0, 0.05, 0], [0, 0.05, 0.05]]\n",
    "bad.toml": "[[markers]]\nid = 20\ncorners = [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]\n",
    "map.yml": "%YAML:1.0\n---\naruco_bc_nmarkers: 1\naruco_bc_mInfoType: 1\naruco_bc_markers:\n"
    "   - { id:40, corners:[ [ 0., 0., 0. ], [ 0.05, 0., 0. ], [ 0.05, 0.05, 0. ], [ 0., 0.05, 0. ] ] }\n",
    "pixels.yml": "%YAML:1.0\n---\naruco_bc_mInfoType: 0\naruco_bc_markers:\n"
    "   - { id:41, corners:[ [ 0., 0., 0. ], [ 50., 0., 0. ], [ 50., 50., 0. ], [ 0., 50., 0. ] ] }\n",
    "junk.toml": "\x00\x01 not toml [[[",
    "pin.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
}
LAYOUT_PATHS = st.sampled_from([*LAYOUT_FILES, "missing.toml", "../good.toml", "/nonexistent/x.toml", "", "."])

BOARD = st.fixed_dictionaries(
    {"name": sometimes_wild(st.sampled_from(["a", "b", "desk", "x-1", "a_b", "", "a b", "é"]))},
    optional={
        "kind": sometimes_wild(st.sampled_from(["grid", "charuco", "custom", "Grid", "aruco"])),
        "cols": sometimes_wild(st.integers(0, 5)),
        "rows": sometimes_wild(st.integers(0, 5)),
        "squares_x": sometimes_wild(st.integers(1, 6)),
        "squares_y": sometimes_wild(st.integers(1, 6)),
        "marker_length_m": POSITIVE,
        "square_length_m": POSITIVE,
        "separation_m": POSITIVE,
        "first_id": sometimes_wild(st.integers(-1, 55)),
        "ids": sometimes_wild(st.lists(st.integers(-1, 55), max_size=8)),
        "legacy": sometimes_wild(st.booleans()),
        "dictionary": DICTIONARY,
        "markers": sometimes_wild(LAYOUT_ENTRIES),
        "layout": sometimes_wild(LAYOUT_PATHS),
    },
)
OVERLAY = st.fixed_dictionaries(
    {},
    optional={
        "target": sometimes_wild(
            st.sampled_from(["*", "marker:*", "board:*", "marker:3", "board:a", "marker:x", "board:", "x"])
        ),
        "kind": sometimes_wild(st.sampled_from([*OVERLAY_KINDS, "sphere"])),
        "path": sometimes_wild(st.sampled_from(["builtin:pin", "builtin:cat", "", "pin.obj", "missing.obj"])),
        "size_m": POSITIVE,
        "scale": POSITIVE,
        "offset_m": sometimes_wild(st.lists(NUMBERS, max_size=4)),
        "rotation_deg": sometimes_wild(st.lists(NUMBERS, max_size=4)),
        "colour": sometimes_wild(st.lists(st.integers(-5, 300) | NUMBERS, max_size=4)),
        "opacity": POSITIVE,
    },
)
LENGTHS_M = st.dictionaries(
    st.sampled_from(["0", "7", "07", "49", "50", "-1", "x", "\u00b2", ""]) | st.integers(0, 60).map(str),
    POSITIVE,
    max_size=4,
)
CONFIG = st.fixed_dictionaries(
    {},
    optional={
        "detector": _table(
            DetectorConfig,
            {"dictionary": DICTIONARY, "corner_refinement": st.sampled_from([*CORNER_REFINEMENTS, "best"])},
        ),
        "markers": st.one_of(
            st.fixed_dictionaries(
                {},
                optional={
                    "length_m": POSITIVE,
                    "lengths_m": sometimes_wild(LENGTHS_M),
                    "ids": sometimes_wild(st.lists(st.integers(-1, 55), max_size=5)),
                },
            ),
            WILD,
        ),
        "boards": sometimes_wild(st.lists(BOARD, max_size=3)),
        "pose": _table(PoseConfig),
        "filter": _table(FilterConfig),
        "recording": _table(RecordingConfig),
        "overlays": sometimes_wild(st.lists(OVERLAY, max_size=3)),
        "source": WILD,
    },
)


@st.composite
def plausible_config(draw) -> dict:
    """Configs that mostly load (so the stages after parsing see many of them): every kind of board and
    overlay, mesh files present or missing."""
    boards = []
    next_id = draw(st.integers(0, 5))
    for index in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["grid", "charuco", "custom"]))
        board = {"name": f"b{index}", "kind": kind}
        if kind == "grid":
            cols, rows = draw(st.integers(1, 3)), draw(st.integers(1, 3))
            board.update(cols=cols, rows=rows, first_id=next_id, separation_m=draw(st.floats(0.0, 0.05)))
            board["marker_length_m"] = draw(st.floats(0.005, 0.2))
            next_id += cols * rows
        elif kind == "charuco":
            cols, rows = draw(st.integers(2, 5)), draw(st.integers(2, 5))
            square = draw(st.floats(0.01, 0.1))
            board.update(squares_x=cols, squares_y=rows, square_length_m=square, first_id=next_id)
            board.update(marker_length_m=square * draw(st.floats(0.3, 0.9)), legacy=draw(st.booleans()))
            next_id += (cols * rows) // 2
        else:
            quads = draw(
                st.lists(QUAD.filter(lambda q: all(math.isfinite(v) for p in q for v in p)), min_size=1, max_size=3)
            )
            board["markers"] = [{"id": next_id + i, "corners": quad} for i, quad in enumerate(quads)]
            next_id += len(quads)
        boards.append(board)
    overlays = draw(
        st.lists(
            st.fixed_dictionaries(
                {"target": st.sampled_from(["*", "marker:*", "board:*", "marker:3", "board:b0"])},
                optional={"size_m": st.floats(0.0, 0.2), "opacity": st.floats(0.0, 1.0)},
            ).flatmap(
                lambda o: st.sampled_from(
                    [
                        {**o, "kind": "cube"},
                        {**o, "kind": "axes"},
                        {**o, "kind": "mesh", "path": "builtin:pin"},
                        {**o, "kind": "mesh", "path": "pin.obj"},
                        {**o, "kind": "mesh", "path": "missing.obj"},
                    ]
                )
            ),
            max_size=3,
        )
    )
    data = {
        "detector": {"dictionary": "DICT_4X4_50"},
        "markers": {"length_m": draw(st.floats(0.005, 0.3))},
        "boards": boards,
        "overlays": overlays,
    }
    if next_id > 50:
        data["detector"]["dictionary"] = "DICT_4X4_250"
    return data


# ============================================================================ TOML writer


def toml_key(key: str) -> str:
    return json.dumps(key)


def toml_value(value: object) -> str:
    """A TOML literal for what tomllib would return (inline arrays and tables only)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (dt.datetime, dt.date, dt.time)):
        return value.isoformat()
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def toml_document(data: Mapping[str, object]) -> str:
    return "".join(f"{toml_key(k)} = {toml_value(v)}\n" for k, v in data.items())


# ============================================================================ validation of results


def assert_all_finite(value: object, where: str = "config") -> None:
    if dataclasses.is_dataclass(value):
        for f in dataclasses.fields(value):
            assert_all_finite(getattr(value, f.name), f"{where}.{f.name}")
    elif isinstance(value, float):
        assert math.isfinite(value), where
    elif isinstance(value, Mapping):
        for k, v in value.items():
            assert_all_finite(v, f"{where}[{k!r}]")
    elif isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            assert_all_finite(v, f"{where}[{i}]")


def assert_valid_config(config: TrackerConfig, source: str) -> None:
    """What a config that loaded promises to the rest of the tracker."""
    assert isinstance(config, TrackerConfig)
    assert config.source == source
    assert_all_finite(config)
    limit = dictionary_size(config.detector.dictionary)
    assert config.detector.corner_refinement in CORNER_REFINEMENTS
    assert config.markers.length_m > 0
    for marker_id, length in config.markers.lengths_m.items():
        assert isinstance(marker_id, int) and 0 <= marker_id < limit and length > 0
    assert all(0 <= i < limit for i in config.markers.ids)
    seen: set[int] = set()
    for board in config.boards:
        ids = board.marker_ids
        assert ids and len(set(ids)) == len(ids), board
        assert not seen & set(ids), "a marker id in two boards"
        assert all(isinstance(i, int) and 0 <= i < limit for i in ids)
        seen |= set(ids)
        corners = board.corners_in_board()
        assert set(corners) == set(ids)
        assert all(c.shape == (4, 3) and np.all(np.isfinite(c)) for c in corners.values())
        assert all(board.marker_length_of(i) > 0 for i in ids)
        assert all(math.isfinite(v) and v >= 0 for v in board.size_m)
        assert board.cv_board() is not None
    for overlay in config.overlays:
        assert overlay.kind in OVERLAY_KINDS
        assert 0.0 <= overlay.opacity <= 1.0 and overlay.scale > 0 and overlay.size_m >= 0
        assert all(isinstance(c, int) and 0 <= c <= 255 for c in overlay.colour)
        assert (overlay.kind == "mesh") == bool(overlay.path)


def assert_usable_config(config: TrackerConfig) -> None:
    """The next stages accept a valid config: overlays (mesh files are read here, a typed error when one
    is missing or bad) and the tracker on one frame."""
    from ar_anchor.render.overlay import OverlayRenderer
    from ar_anchor.sources.base import Frame
    from ar_anchor.track.tracker import Tracker

    camera = CameraModel.from_fov(320, 240, 300.0)
    try:
        OverlayRenderer(config, camera)
    except ConfigError as err:
        assert "mesh file" in str(err)
        return
    tracker = Tracker(config, camera)
    image = np.full((240, 320, 3), 200, np.uint8)
    result = tracker.process(Frame(image, 0, 0))
    assert result.index == 0


def assert_one_line_naming(err: Exception, path: Path | str) -> None:
    message = str(err)
    assert message and "\n" not in message, repr(message)
    assert str(path) in message, message
    assert isinstance(err, InputError)


@pytest.fixture(scope="module")
def layout_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cfg")
    for name, text in LAYOUT_FILES.items():
        (root / name).write_text(text, encoding="utf-8")
    return root


# ============================================================================ tracker TOML


@fuzz_settings(300)
@given(data=CONFIG)
def test_structured_config_is_config_error_or_valid(layout_dir, data):
    path = str(layout_dir / "fuzzed.toml")
    try:
        with time_limit(PER_CALL_S):
            config = parse_config(data, path)
    except ConfigError as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return
    outcome("valid")
    assert_valid_config(config, path)


@fuzz_settings(40)
@given(data=plausible_config())
def test_valid_config_is_usable_downstream(layout_dir, data):
    path = str(layout_dir / "fuzzed.toml")
    try:
        config = parse_config(data, path)
    except ConfigError as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return
    outcome("valid")
    assert_valid_config(config, path)
    assert_usable_config(config)


@fuzz_settings(120)
@given(data=CONFIG)
def test_config_file_round_trip_is_config_error_or_valid(layout_dir, data):
    # the same documents, written as TOML text and read by load_config (tomllib first)
    path = layout_dir / "written.toml"
    path.write_text(toml_document(data), encoding="utf-8")
    try:
        with time_limit(PER_CALL_S):
            config = load_config(path)
    except ConfigError as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return
    outcome("valid")
    assert_valid_config(config, str(path))


def _mutate_lines(text: str, edits: list[tuple[int, int, str]]) -> str:
    lines = text.splitlines()
    for op, at, token in edits:
        if not lines:
            lines = [token]
            continue
        i = at % len(lines)
        if op == 0:
            del lines[i]
        elif op == 1:
            lines.insert(i, lines[i])
        elif op == 2 and "=" in lines[i]:
            lines[i] = lines[i].split("=", 1)[0] + "= " + token
        else:
            lines.insert(i, token)
    return "\n".join(lines) + "\n"


TOKENS = st.one_of(
    st.builds(toml_value, TOML_LEAF),
    st.sampled_from(["", "[", "]", "[[boards]]", "[[overlays]]", "[markers]", "=", "x = ", "'", '"""', "nan"]),
)


@fuzz_settings(150)
@given(edits=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 10_000), TOKENS), min_size=1, max_size=6))
def test_mutated_default_toml_is_config_error_or_valid(tmp_path, edits):
    path = tmp_path / "mutated.toml"
    path.write_text(_mutate_lines(DEFAULT_TOML.read_text(encoding="utf-8"), edits), encoding="utf-8")
    try:
        config = load_config(path)
    except ConfigError as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return
    outcome("valid")
    assert_valid_config(config, str(path))


@fuzz_settings(100)
@given(data=st.binary(max_size=400) | st.binary(max_size=40).map(lambda b: DEFAULT_TOML.read_bytes()[:300] + b))
def test_random_bytes_config_is_config_error_or_valid(tmp_path, data):
    path = tmp_path / "bytes.toml"
    path.write_bytes(data)
    try:
        config = load_config(path)
    except ConfigError as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return
    outcome("valid")
    assert_valid_config(config, str(path))


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        pytest.param("[markers]\nlength_m = " + "9" * 400 + "\n", "length_m: must be finite", id="int-too-large-float"),
        pytest.param(
            "[[overlays]]\noffset_m = [" + "9" * 400 + ", 0, 0]\n", "offset_m: values must be", id="int-too-large-vec"
        ),
        pytest.param("[markers.lengths_m]\n7 = 0.04\n07 = 0.05\n", "marker 7 is listed twice", id="id-key-twice"),
        pytest.param('[detector]\n"\\n\\u001b[2J" = 1\n', r"unknown key\(s\): '\\n\\x1b\[2J'", id="key-with-newline"),
        pytest.param(
            '[[overlays]]\nkind = "mesh"\npath = "a\\nb.obj"\n', "path: must not contain line breaks", id="path-newline"
        ),
        pytest.param(
            '[[boards]]\nname = "a"\nkind = "custom"\nlayout = "x\\ry.toml"\n',
            "layout: must not contain line breaks",
            id="layout-path-newline",
        ),
        pytest.param(
            '[[boards]]\nname = "a"\nkind = "custom"\nmarkers = [{id = [], corners = []}]\n',
            "id must be an integer",
            id="inline-marker-list-id",
        ),
        pytest.param(  # found by the long run
            '[[boards]]\nname = "a"\nkind = "custom"\nmarkers = [{id = 0, corners = [[1' + "0" * 400 + "]]}]\n",
            "corners must be 4",
            id="inline-corner-int-too-large",
        ),
        pytest.param(
            '[detector]\ndictionary = """DICT\nX"""\n', r"unknown dictionary 'DICT\\nX'", id="multi-line-value"
        ),
        pytest.param("a = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply", id="deep-array"),
        pytest.param("a = " + "{b = " * 5000 + "1" + "}" * 5000 + "\n", "nested too deeply", id="deep-table"),
    ],
)
def test_config_found_by_fuzzing(tmp_path, text, expected):
    # inputs the fuzzing above found (each was an uncaught exception or a silent overwrite before)
    path = tmp_path / "found.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=expected) as info:
        load_config(path)
    assert_one_line_naming(info.value, path)


# ============================================================================ camera YAML

YAML_NUMBER = st.one_of(
    st.integers(-(10**6), 10**6).map(str),
    st.floats(-1e4, 1e4).map(repr),
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers().map(str),
    st.sampled_from([".nan", ".inf", "-.inf", "1e400", "-0", "0x10", "1_000", "1e-400"]),
)
YAML_SCALAR = st.one_of(
    YAML_NUMBER,
    YAML_NUMBER,
    st.sampled_from(['"abc"', "abc", "''", "~", "null", "true", "[]", "{}", '"500."', "[ 1, 2 ]"]),
)
GOOD_K = ["500.", "0.", "319.5", "0.", "500.", "239.5", "0.", "0.", "1."]
K_DATA = st.one_of(
    st.just(GOOD_K),
    st.just(GOOD_K),
    st.just(GOOD_K),
    st.lists(st.sampled_from(range(9)), max_size=3).flatmap(
        lambda spots: st.lists(YAML_SCALAR, min_size=len(spots), max_size=len(spots)).map(
            lambda values: [values[spots.index(i)] if i in spots else v for i, v in enumerate(GOOD_K)]
        )
    ),
    st.lists(YAML_SCALAR, max_size=16),
)
DIST_DATA = st.one_of(
    st.lists(st.floats(-0.5, 0.5).map(repr), min_size=5, max_size=5),
    st.lists(st.floats(-0.5, 0.5).map(repr), min_size=5, max_size=5),
    st.lists(st.floats(-0.5, 0.5).map(repr), min_size=8, max_size=8),
    st.lists(YAML_SCALAR, max_size=15),
)
DT = mostly("d", st.sampled_from(["f", "i", "u", "s", "c", "w", "2d", "3f", "x", '""']))


@st.composite
def matrix_yaml(draw, key: str, data: st.SearchStrategy, rows: int, ros: bool) -> str:
    values = draw(data)
    form = draw(mostly("ros" if ros else "opencv", st.sampled_from(["opencv", "ros", "list", "scalar", "missing"])))
    if form == "missing":
        return ""
    if form == "scalar":
        return f"{key}: {draw(YAML_SCALAR)}\n"
    if form == "list":
        return f"{key}: [ {', '.join(values)} ]\n"
    n_rows = draw(mostly(str(rows), YAML_SCALAR))
    n_cols = draw(mostly(str(max(1, len(values) // max(rows, 1))), YAML_SCALAR))
    indent = "  " if ros else "   "
    head = f"{key}:\n" if form == "ros" else f"{key}: !!opencv-matrix\n"
    lines = [f"{indent}rows: {n_rows}", f"{indent}cols: {n_cols}"]
    if form == "opencv":
        lines.append(f"{indent}dt: {draw(DT)}")
    lines.append(f"{indent}data: [ {', '.join(values)} ]")
    return head + "\n".join(lines) + "\n"


@st.composite
def camera_yaml(draw) -> str:
    ros = draw(st.booleans())
    parts = [
        f"image_width: {draw(mostly('640', YAML_SCALAR))}\n",
        f"image_height: {draw(mostly('480', YAML_SCALAR))}\n",
        draw(matrix_yaml("camera_matrix", K_DATA, 3, ros)),
        draw(matrix_yaml("distortion_coefficients", DIST_DATA, 1, ros)),
    ]
    if ros:
        model = draw(mostly("plumb_bob", st.sampled_from(["rational_polynomial", "equidistant", "", "3", None])))
        parts += ["camera_name: fuzz\n"] + ([f"distortion_model: {model}\n"] if model is not None else [])
        parts.append("rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n")
    parts += draw(
        st.lists(st.builds(lambda k, v: f"{k}: {v}\n", st.sampled_from(["note", "rms", "x"]), YAML_SCALAR), max_size=2)
    )
    parts = draw(st.permutations(parts))
    header = "" if ros and draw(st.booleans()) else draw(st.sampled_from(["%YAML:1.0\n---\n", "%YAML 1.2\n---\n"]))
    return header + "".join(parts)


def assert_valid_camera(camera: CameraModel) -> None:
    k = camera.camera_matrix
    assert k.shape == (3, 3) and np.all(np.isfinite(k))
    assert k[0, 0] > 0 and k[1, 1] > 0 and k[1, 0] == 0 and np.allclose(k[2], [0, 0, 1])
    assert camera.dist_coeffs.ndim == 1 and camera.dist_coeffs.size in (0, 4, 5, 8, 12, 14)
    assert np.all(np.isfinite(camera.dist_coeffs))
    assert isinstance(camera.width, int) and isinstance(camera.height, int)
    assert camera.width > 0 and camera.height > 0


def _typed_error_or_valid(load, path: Path, error: type[Exception], check):  # noqa: ANN001, ANN202
    """``load(path)`` within the time limit: a typed ``error`` naming ``path`` in one line (None), or a
    result ``check`` accepts (returned); the outcome counted either way."""
    try:
        with time_limit(PER_CALL_S):
            result = load(path)
    except error as err:
        assert_one_line_naming(err, path)
        outcome("typed error")
        return None
    outcome("valid")
    check(result)
    return result


def _load_camera(path: Path) -> CameraModel | None:
    return _typed_error_or_valid(CameraModel.from_yaml, path, CameraError, assert_valid_camera)


@fuzz_settings(300)
@given(text=camera_yaml())
def test_structured_camera_yaml_is_camera_error_or_valid(tmp_path, text):
    path = tmp_path / "camera.yml"
    path.write_text(text, encoding="utf-8")
    camera = _load_camera(path)
    if camera is not None and "ros" not in text:
        # what was read is what the file says (no key silently read as 0 or DBL_MAX)
        assert camera.width == 640 or "image_width: 640" not in text


def _mutate_bytes(data: bytes, edits: list[tuple[int, int, int]]) -> bytes:
    buffer = bytearray(data)
    for op, at, value in edits:
        if not buffer:
            break
        i = at % len(buffer)
        if op == 0:
            buffer[i] = value
        elif op == 1:
            del buffer[i]
        elif op == 2:
            buffer.insert(i, value)
        else:
            del buffer[i:]
    return bytes(buffer)


BYTE_EDITS = st.lists(st.tuples(st.integers(0, 3), st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=8)


@fuzz_settings(200)
@given(edits=BYTE_EDITS)
def test_mutated_camera_yaml_is_camera_error_or_valid(tmp_path, edits):
    path = tmp_path / "camera.yml"
    path.write_bytes(_mutate_bytes(SYNTHETIC_YAML.read_bytes(), edits))
    _load_camera(path)


@fuzz_settings(100)
@given(data=st.binary(max_size=300), suffix=st.sampled_from([".yml", ".yaml", ".xml", ".json", ".txt", ".yml.gz"]))
def test_random_bytes_camera_file_is_camera_error(tmp_path, data, suffix):
    path = tmp_path / f"camera{suffix}"
    path.write_bytes(data)
    assert _load_camera(path) is None or b"camera_matrix" in data


ROS_CAMERA_INFO = textwrap.dedent(
    """\
    image_width: 640
    image_height: 480
    camera_name: narrow_stereo
    camera_matrix:
      rows: 3
      cols: 3
      data: [502.5, 0.0, 318.25, 0.0, 501.0, 241.5, 0.0, 0.0, 1.0]
    distortion_model: {model}
    distortion_coefficients:
      rows: 1
      cols: {n}
      data: [{dist}]
    rectification_matrix:
      rows: 3
      cols: 3
      data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
    projection_matrix:
      rows: 3
      cols: 4
      data: [502.5, 0, 318.25, 0, 0, 501.0, 241.5, 0, 0, 0, 1, 0]
    """
)


@pytest.mark.parametrize("model, n", [("plumb_bob", 5), ("rational_polynomial", 8)])
def test_ros_camera_info_is_read(tmp_path, model, n):
    dist = [0.1, -0.2, 0.001, 0.002, 0.05, 0.01, 0.02, 0.03][:n]
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_CAMERA_INFO.format(model=model, n=n, dist=", ".join(map(str, dist))))
    camera = CameraModel.from_yaml(path)
    assert camera.size == (640, 480)
    np.testing.assert_array_equal(camera.camera_matrix, [[502.5, 0, 318.25], [0, 501.0, 241.5], [0, 0, 1]])
    np.testing.assert_array_equal(camera.dist_coeffs, dist)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        pytest.param(
            ROS_CAMERA_INFO.format(model="equidistant", n=4, dist="0.1, 0.01, 0.0, 0.0"),
            "distortion_model 'equidistant' is not supported",
            id="ros-fisheye",
        ),
        pytest.param(
            ROS_CAMERA_INFO.format(model="plumb_bob", n=5, dist="0, 0, 0, 0, 0").replace(
                "rows: 3\n  cols: 3\n  data: [502.5", "rows: -3\n  cols: -3\n  data: [502.5", 1
            ),
            "positive integer rows and cols",
            id="ros-negative-rows",
        ),
        pytest.param(
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
            "camera_matrix: [ 500., 0., abc, 0., 500., 239.5, 0., 0., 1. ]\n",
            "must hold numbers only",
            id="string-in-matrix-was-DBL_MAX",
        ),
        pytest.param(
            SYNTHETIC_YAML.read_bytes().replace(b"dt: d", b"dt: \xa5", 1),
            "not UTF-8 text",
            id="non-utf8-dt-was-UnicodeDecodeError",
        ),
    ],
)
def test_camera_found_by_fuzzing(tmp_path, text, expected):
    path = tmp_path / "cam.yml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(CameraError, match=expected) as info:
        CameraModel.from_yaml(path)
    assert_one_line_naming(info.value, path)


# Deep nesting crashed OpenCV's FileStorage parser with a segmentation fault (a C stack overflow):
# run in a child process, so that a regression is a failed test rather than a dead test run.
DEEP_FILES = {
    "flow.yml": "%YAML:1.0\n---\ncamera_matrix: " + "[" * 100_000 + "]" * 100_000 + "\n",
    "maps.yml": "%YAML:1.0\n---\ncamera_matrix: " + "{a: " * 60_000 + "1" + "}" * 60_000 + "\n",
    "dashes.yml": "%YAML:1.0\n---\na: " + "- " * 100_000 + "1\n",
    "indent.yml": "%YAML:1.0\n---\n" + "".join(" " * i + "-\n" for i in range(2_000)),
    "deep.json": '{"a": ' + "[" * 100_000 + "]" * 100_000 + "}",
    "deep.xml": '<?xml version="1.0"?>\n<opencv_storage>\n' + "<a>" * 100_000 + "1" + "</a>" * 100_000 + "\n",
    "map.yml": "%YAML:1.0\n---\naruco_bc_markers: " + "[" * 100_000 + "]" * 100_000 + "\n",
}


def test_deeply_nested_files_are_input_errors_not_segfaults(tmp_path):
    for name, text in DEEP_FILES.items():
        (tmp_path / name).write_text(text)
    script = textwrap.dedent(
        """
        import sys
        from pathlib import Path
        from ar_anchor.camera import CameraModel
        from ar_anchor.errors import InputError
        from ar_anchor.boards import read_layout
        for path in sorted(Path(sys.argv[1]).iterdir()):
            try:
                read_layout(path) if path.name == "map.yml" else CameraModel.from_yaml(path)
            except InputError as err:
                print("typed", path.name, err)
            else:
                print("loaded", path.name)
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, f"child died (exit {result.returncode}): {result.stderr[-2000:]}"
    lines = result.stdout.splitlines()
    assert len(lines) == len(DEEP_FILES), result.stdout
    assert all(line.startswith("typed ") and "levels deep" in line for line in lines), result.stdout


def test_matrix_without_cols_is_a_camera_error_not_heap_corruption(tmp_path):
    # OpenCV 5's FileNode.mat() copies `data` into a rows x cols matrix before checking that they agree: a
    # camera_matrix without `cols` (read as 0) overflowed the heap, and a later allocation aborted the
    # process ("malloc(): invalid size"). Read 500 times in a child, so that a regression fails this test.
    path = tmp_path / "cam.yml"
    path.write_text(SYNTHETIC_YAML.read_text().replace("cols: 3", "col: 3", 1))
    script = textwrap.dedent(
        f"""
        from ar_anchor.camera import CameraModel
        from ar_anchor.errors import CameraError
        for _ in range(500):
            try:
                CameraModel.from_yaml({str(path)!r})
            except CameraError as err:
                message = str(err)
        print(message)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, f"child died (exit {result.returncode}): {result.stderr[-1000:]}"
    assert "needs positive integer rows and cols" in result.stdout


# ============================================================================ layouts


def assert_valid_layout(layout) -> None:
    assert layout, "empty layout"
    ids = [marker_id for marker_id, _ in layout]
    assert len(set(ids)) == len(ids)
    for marker_id, corners in layout:
        assert isinstance(marker_id, int) and marker_id >= 0
        points = np.asarray(corners, np.float64)
        assert points.shape == (4, 3) and np.all(np.isfinite(points)) and np.abs(points).max() <= 1000
        edges = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
        assert edges.min() > 1e-6


def _load_layout(path: Path):  # noqa: ANN202
    return _typed_error_or_valid(read_layout, path, ConfigError, assert_valid_layout)


@fuzz_settings(150)
@given(entries=LAYOUT_ENTRIES, extra=st.dictionaries(st.text(max_size=5), WILD, max_size=2))
def test_toml_layout_is_config_error_or_valid(tmp_path, entries, extra):
    path = tmp_path / "layout.toml"
    path.write_text(toml_document({"markers": entries, **extra}), encoding="utf-8")
    _load_layout(path)


@st.composite
def marker_map_yaml(draw) -> str:
    lines = ["%YAML:1.0", "---", f"aruco_bc_nmarkers: {draw(YAML_SCALAR)}"]
    info = draw(mostly("1", st.one_of(YAML_SCALAR, st.none())))
    if info is not None:
        lines.append(f"aruco_bc_mInfoType: {info}")
    entries = []
    for index in range(draw(st.integers(0, 3))):
        ident = draw(mostly(str(index), st.one_of(st.integers(0, 60).map(str), YAML_SCALAR)))
        corners = draw(
            mostly(
                [["0.", "0.", "0."], ["0.05", "0.", "0."], ["0.05", "0.05", "0."], ["0.", "0.05", "0."]],
                st.one_of(
                    QUAD.map(lambda quad: [[repr(v) for v in p] for p in quad]),
                    st.lists(st.lists(YAML_SCALAR, max_size=4), max_size=5),
                ),
            )
        )
        text = ", ".join("[ " + ", ".join(p) + " ]" for p in corners)
        entries.append(f"   - {{ id:{ident}, corners:[ {text} ] }}")
    lines.append("aruco_bc_markers:" if entries else f"aruco_bc_markers: {draw(st.sampled_from(['[]', '1', 'x']))}")
    return "\n".join(lines + entries) + "\n"


@fuzz_settings(200)
@given(text=marker_map_yaml())
def test_aruco_marker_map_is_config_error_or_valid(tmp_path, text):
    path = tmp_path / "map.yml"
    path.write_text(text, encoding="utf-8")
    _load_layout(path)


@fuzz_settings(100)
@given(data=st.binary(max_size=300), head=st.sampled_from([b"", b"%YAML:1.0\n", b"aruco_bc_", b"[[markers]]\n"]))
def test_random_bytes_layout_is_config_error(tmp_path, data, head):
    path = tmp_path / "layout.bin"
    path.write_bytes(head + data)
    assert _load_layout(path) is None


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        pytest.param("aruco_bc_mInfoType: .nan\naruco_bc_markers: []\n", "mInfoType is nan", id="nan-info-type"),
        pytest.param("aruco_bc_mInfoType: abc\naruco_bc_markers: []\n", "not a number", id="string-info-type"),
        pytest.param(
            'aruco_bc_mInfoType: 1\naruco_bc_markers:\n  - { id: "x", corners: [[0,0,0],[1,0,0],[1,1,0],[0,1,0]] }\n',
            "id must be an integer",
            id="string-id-was-DBL_MAX",
        ),
        pytest.param(
            "aruco_bc_mInfoType: 1\naruco_bc_markers:\n  - { id: 3, corners: [[0,0,0],[1,0,0],[1,1,0],[0,1,z]] }\n",
            "must be \\[x, y, z\\] numbers",
            id="string-coordinate-was-DBL_MAX",
        ),
        pytest.param("-\n", "top level", id="list-document-was-cv2.error"),
        pytest.param("42\n", "not a readable OpenCV YAML", id="scalar-document"),
    ],
)
def test_marker_map_found_by_fuzzing(tmp_path, text, expected):  # list-document: found by the long run
    path = tmp_path / "map.yml"
    path.write_text("%YAML:1.0\n---\n" + text)
    with pytest.raises(ConfigError, match=expected) as info:
        read_layout(path)
    assert_one_line_naming(info.value, path)


# ============================================================================ meshes

MESH_NUMBER = st.one_of(
    st.floats(-10, 10).map(repr),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "1e308", "x", "", "0x1", "-0"]),
)
INDEX = st.one_of(st.integers(-5, 8).map(str), st.sampled_from(["0", "99999999999", "a", "1/1", "1//2", ""]))


@st.composite
def obj_text(draw) -> str:
    lines = []
    for _ in range(draw(st.integers(0, 6))):
        lines.append("v " + " ".join(draw(st.lists(MESH_NUMBER, min_size=2, max_size=4))))
    for _ in range(draw(st.integers(0, 5))):
        lines.append("f " + " ".join(draw(st.lists(INDEX, min_size=1, max_size=5))))
    lines += draw(
        st.lists(st.sampled_from(["vt 0 0", "vn 0 0 1", "o x", "g", "usemtl m", "mtllib ../../x.mtl", "#"]), max_size=3)
    )
    return "\n".join(draw(st.permutations(lines))) + "\n"


@st.composite
def ply_text(draw) -> str:
    n_vertices = draw(st.one_of(st.integers(0, 5), st.sampled_from([2_000_000_000, -1])))
    n_faces = draw(st.one_of(st.integers(0, 4), st.sampled_from([2_000_000_000, -1])))
    header = [
        "ply",
        draw(st.sampled_from(["format ascii 1.0", "format binary_little_endian 1.0", "format ascii 2.0"])),
        f"element vertex {n_vertices}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {n_faces}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [" ".join(draw(st.lists(MESH_NUMBER, min_size=3, max_size=3))) for _ in range(draw(st.integers(0, 5)))]
    body += ["3 " + " ".join(draw(st.lists(INDEX, min_size=3, max_size=3))) for _ in range(draw(st.integers(0, 4)))]
    return "\n".join(header + body) + "\n"


@st.composite
def off_text(draw) -> str:
    counts = " ".join(draw(st.lists(INDEX, min_size=3, max_size=3)))
    body = [" ".join(draw(st.lists(MESH_NUMBER, min_size=3, max_size=3))) for _ in range(draw(st.integers(0, 5)))]
    body += ["3 " + " ".join(draw(st.lists(INDEX, min_size=3, max_size=3))) for _ in range(draw(st.integers(0, 4)))]
    return "\n".join(["OFF", counts, *body]) + "\n"


@st.composite
def binary_stl(draw) -> bytes:
    triangles = draw(st.integers(0, 4))
    declared = draw(st.one_of(st.just(triangles), st.integers(0, 2**32 - 1)))
    body = b"".join(
        struct.pack("<12fH", *draw(st.lists(st.floats(width=32), min_size=12, max_size=12)), 0)
        for _ in range(triangles)
    )
    return b"\0" * 80 + struct.pack("<I", declared) + body


@st.composite
def gltf_text(draw) -> str:
    uri = draw(st.sampled_from(["data:application/octet-stream;base64,AAAA", "missing.bin", "../../etc/passwd", ""]))
    document = {
        "asset": {"version": draw(st.sampled_from(["2.0", "1.0", ""]))},
        "buffers": [{"uri": uri, "byteLength": draw(st.integers(-1, 64))}],
        "bufferViews": [{"buffer": draw(st.integers(-1, 2)), "byteLength": draw(st.integers(0, 64))}],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": draw(st.sampled_from([5126, 5125, 1])),
                "count": draw(st.integers(0, 2**31)),
                "type": draw(st.sampled_from(["VEC3", "SCALAR", "X"])),
            }
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": draw(st.integers(-1, 2))}, "indices": 0}]}],
    }
    return json.dumps(document)


def assert_valid_model(model: Model) -> None:
    assert model.vertices.ndim == 2 and model.vertices.shape[1] == 3 and np.all(np.isfinite(model.vertices))
    faces = model.faces
    assert faces.ndim == 2 and faces.shape[1] == 3 and 0 < len(faces) <= MAX_TRIANGLES
    assert faces.min() >= 0 and faces.max() < len(model.vertices)
    assert model.face_colours.shape == (len(faces), 3) and np.all(np.isfinite(model.face_colours))
    assert model.facets.shape == (len(faces),)


def _load_model(path: Path) -> Model | None:
    return _typed_error_or_valid(load_mesh, path, ConfigError, assert_valid_model)


MESH_FILES = st.one_of(
    st.tuples(st.just(".obj"), obj_text().map(str.encode)),
    st.tuples(st.just(".ply"), ply_text().map(str.encode)),
    st.tuples(st.just(".off"), off_text().map(str.encode)),
    st.tuples(st.just(".stl"), binary_stl()),
    st.tuples(st.just(".gltf"), gltf_text().map(str.encode)),
    st.tuples(
        st.sampled_from([".obj", ".ply", ".stl", ".glb", ".gltf", ".off", ".OBJ", ".fbx", ""]), st.binary(max_size=300)
    ),
)


@fuzz_settings(300)
@given(mesh=MESH_FILES)
def test_mesh_file_is_config_error_or_valid(tmp_path, mesh):
    suffix, data = mesh
    path = tmp_path / f"model{suffix}"
    path.write_bytes(data)
    _load_model(path)


@fuzz_settings(100)
@given(edits=BYTE_EDITS, suffix=st.sampled_from([".obj", ".ply", ".stl", ".glb", ".off"]))
def test_mutated_mesh_file_is_config_error_or_valid(tmp_path, mesh_originals, edits, suffix):
    path = tmp_path / f"mutated{suffix}"
    path.write_bytes(_mutate_bytes(mesh_originals[suffix], edits))
    _load_model(path)


@pytest.fixture(scope="module")
def mesh_originals(tmp_path_factory) -> dict[str, bytes]:
    import trimesh

    root = tmp_path_factory.mktemp("meshes")
    box = trimesh.creation.box()
    out = {}
    for suffix in (".obj", ".ply", ".stl", ".glb", ".off"):
        box.export(root / f"box{suffix}")
        out[suffix] = (root / f"box{suffix}").read_bytes()
    return out


def test_mesh_originals_load(tmp_path, mesh_originals):
    # the mutation test starts from files that do load
    for suffix, data in mesh_originals.items():
        path = tmp_path / f"box{suffix}"
        path.write_bytes(data)
        assert len(_load_model(path).faces) == 12
