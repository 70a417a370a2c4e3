"""`ar-anchor export` on hostile run folders (issue 34, the third ring): a real small run (a 2-frame demo, made
once per module) whose poses.csv or --out is then damaged: one line naming the file and row, exit 2, nothing of
the user's replaced, no internal error."""

from __future__ import annotations

import csv
import shutil
import tracemalloc
from pathlib import Path

import pytest

from ar_anchor.run.outputs import POSES_CSV_HEADER
from ar_anchor.tools.export.poses import MAX_LINE_CHARS
from tests.helpers import assert_clean_exit, error_lines, run_main


@pytest.fixture(scope="module")
def real_run(tmp_path_factory) -> Path:
    """A run folder `demo --frames 2` wrote (poses.csv with seven targets a frame, summary.json with its camera)."""
    out = tmp_path_factory.mktemp("real") / "run"
    result = run_main(["-q", "demo", "--frames", "2", "--out", str(out)])
    assert result.code == 0, result.describe()
    return out


@pytest.fixture
def run(real_run, tmp_path) -> Path:
    """A copy of the real run, free to damage."""
    copy = tmp_path / "run"
    shutil.copytree(real_run, copy)
    return copy


def _rows(run: Path) -> list[list[str]]:
    with (run / "poses.csv").open(newline="") as f:
        return list(csv.reader(f))


def _write_rows(run: Path, rows: list[list[str]]) -> None:
    with (run / "poses.csv").open("w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def _set(run: Path, row: int, column: str, value: str) -> None:
    rows = _rows(run)
    rows[row][POSES_CSV_HEADER.index(column)] = value
    _write_rows(run, rows)


def _one_error(result) -> str:
    """The run's one error line (exit 2, nothing else on stderr, no internal error)."""
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and result.stderr.strip() == lines[0], result.describe()
    return lines[0]


def _nothing_exported(run: Path) -> None:
    assert sorted(p.name for p in run.iterdir()) == ["poses.csv", "recording.rrd", "summary.json"]


def test_a_line_of_200m_commas_is_refused_after_the_line_limit_without_holding_it(run):
    # given a poses.csv with a line of 20 M commas (the 200 M took 1.87 GB before it was refused)
    with (run / "poses.csv").open("a") as f:
        f.write("," * 20_000_000 + "\n")
    lines = len(_rows(run)[:-1])
    # when exported (memory traced)
    tracemalloc.start()
    try:
        result = run_main(["-q", "export", str(run)])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # then one line naming the file and the line, and the memory is the limit's, not the line's
    message = _one_error(result)
    assert message == (
        f"ar-anchor: error: {run / 'poses.csv'}: line {lines + 1}: longer than {MAX_LINE_CHARS} characters: "
        "not a row of a poses.csv"
    )
    assert peak < 8_000_000, f"peak {peak / 1e6:.1f} MB"
    _nothing_exported(run)


@pytest.mark.parametrize(
    ("column", "value", "expected"),
    [
        (
            "rvec_x",
            "1e200",
            "line 2, column rvec_x: a rotation vector of 1e+200 rad is no rotation ar-anchor writes (at most pi; "
            "refused beyond 2 pi)",
        ),
        (
            "tvec_z",
            "1e300",
            "line 2, column tvec_x: a translation of 1e+300 m is no pose ar-anchor writes (refused beyond 1e+06 m)",
        ),
        (
            "timestamp_s",
            "1e30",
            "line 2, column timestamp_s: '1e30' s is beyond the last time a ROS 2 stamp holds (2147483647 s)",
        ),
        ("timestamp_s", "-1.0", "line 2, column timestamp_s: a negative time: '-1.0' s (a run's times start at 0)"),
    ],
    ids=["rvec-1e200", "tvec-1e300", "time-1e30", "time-negative"],
)
def test_values_no_run_writes_are_one_line_naming_the_file_line_and_column(run, column, value, expected):
    # given a real run's poses.csv with one value no run writes (in its first frame: every row of it)
    rows = _rows(run)
    for row in rows[1:]:
        if row[0] == rows[1][0]:
            row[POSES_CSV_HEADER.index(column)] = value
    _write_rows(run, rows)
    # when exported: one line naming the file, line and column, exit 2, nothing written
    assert _one_error(run_main(["-q", "export", str(run)])) == f"ar-anchor: error: {run / 'poses.csv'}: {expected}"
    _nothing_exported(run)


def test_time_that_goes_backwards_is_refused_at_the_row(run):
    rows = _rows(run)
    second = [i for i, row in enumerate(rows) if row[0] == "1"]
    for i in second:
        rows[i][1] = "0.000000000"
    rows[1 : second[0]] = [[*row[:1], "0.010000000", *row[2:]] for row in rows[1 : second[0]]]
    _write_rows(run, rows)
    assert _one_error(run_main(["-q", "export", str(run)])) == (
        f"ar-anchor: error: {run / 'poses.csv'}: line {second[0] + 1}, column timestamp_s: time goes backwards: "
        "frame 1 at 0.000000000 s is before frame 0 at 0.010000000 s"
    )
    _nothing_exported(run)


def test_the_same_target_twice_in_one_frame_is_refused_at_the_second_row(run):
    rows = _rows(run)
    rows.insert(3, list(rows[1]))
    _write_rows(run, rows)
    assert _one_error(run_main(["-q", "export", str(run)])) == (
        f"ar-anchor: error: {run / 'poses.csv'}: line 4, column target: {rows[1][2]} twice in frame 0 (line 2 "
        "too): one pose per target and frame"
    )
    _nothing_exported(run)


def test_two_targets_of_one_export_name_are_bad_input_naming_the_row(run):
    # given two boards whose names become the same file name and frame id (a space and an underscore)
    rows = _rows(run)
    rows[1][2] = "board:my desk"
    rows.insert(2, [*rows[1][:2], "board:my_desk", *rows[1][3:]])
    _write_rows(run, rows)
    assert _one_error(run_main(["-q", "export", str(run)])) == (
        f"ar-anchor: error: {run / 'poses.csv'}: line 3, column target: targets 'board:my desk' and "
        "'board:my_desk' would both be exported as 'board_my_desk': rename one of the boards"
    )
    _nothing_exported(run)


def test_a_utf8_byte_order_mark_is_read_as_nothing(run):
    # given the run's poses.csv saved by a spreadsheet as "CSV UTF-8" (a byte order mark first)
    text = (run / "poses.csv").read_text()
    (run / "poses.csv").write_text("\ufeff" + text)
    # when exported: it is read as the file without the mark
    result = run_main(["-q", "export", str(run), "--formats", "csv"])
    assert result.code == 0, result.describe()
    with (run / "poses_ext.csv").open(newline="") as f:
        exported = list(csv.DictReader(f))
    assert [r["frame"] for r in exported] == [r[0] for r in _rows(run)[1:]]
    assert list(exported[0])[0] == "frame"


# ------------------------------------------------------------------- never replace a file export did not write
def test_export_out_holding_the_users_files_is_refused_and_they_stay(run, tmp_path):
    # given an --out folder with the user's own run.mcap and poses_ext.csv (no export wrote them)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "run.mcap").write_bytes(b"my bag")
    (out / "poses_ext.csv").write_text("my table\n")
    # when exported into it: one line naming them, exit 2, both untouched, nothing else written
    assert _one_error(run_main(["-q", "export", str(run), "--out", str(out)])) == (
        f"ar-anchor: error: --out {out}: holds poses_ext.csv, run.mcap, which no ar-anchor export wrote; the "
        "export would overwrite them: move them or give another --out"
    )
    assert (out / "run.mcap").read_bytes() == b"my bag" and (out / "poses_ext.csv").read_text() == "my table\n"
    assert sorted(p.name for p in out.iterdir()) == ["poses_ext.csv", "run.mcap"]


def test_a_users_tum_file_of_an_exported_targets_name_refuses_the_whole_export(run, tmp_path):
    out = tmp_path / "mine"
    (out / "tum").mkdir(parents=True)
    (out / "tum" / "marker_0.txt").write_text("my trajectory\n")
    assert _one_error(run_main(["-q", "export", str(run), "--out", str(out)])) == (
        f"ar-anchor: error: --out {out}: holds tum/marker_0.txt, which no ar-anchor export wrote; the export would "
        "overwrite it: move it or give another --out"
    )
    # nothing moved into place (the check comes before the first file), no temporary left
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["tum", "tum/marker_0.txt"]
    assert (out / "tum" / "marker_0.txt").read_text() == "my trajectory\n"


def test_an_export_replaces_its_own_files_but_not_one_the_user_changed_since(run, tmp_path):
    out = tmp_path / "x"
    assert run_main(["-q", "export", str(run), "--out", str(out)]).code == 0
    assert run_main(["-q", "export", str(run), "--out", str(out)]).code == 0  # its own: replaced
    with (out / "run.mcap").open("ab") as f:
        f.write(b"the user's notes")
    edited = (out / "run.mcap").read_bytes()
    assert _one_error(run_main(["-q", "export", str(run), "--out", str(out)])).endswith(
        "holds run.mcap, which no ar-anchor export wrote; the export would overwrite it: move it or give another --out"
    )
    assert (out / "run.mcap").read_bytes() == edited
    # and without the mcap, the other formats are written
    assert run_main(["-q", "export", str(run), "--out", str(out), "--formats", "csv,tum"]).code == 0


def test_a_run_into_a_folder_holding_the_users_exports_keeps_them(tmp_path):
    # given a folder holding the user's run.mcap and poses_ext.csv (a run's start removed them as old exports)
    out = tmp_path / "o"
    out.mkdir()
    (out / "run.mcap").write_bytes(b"my bag")
    (out / "poses_ext.csv").write_text("my table\n")
    # when a run writes into it (no --export): they stay
    result = run_main(["-q", "demo", "--frames", "2", "--out", str(out)])
    assert result.code == 0, result.describe()
    assert (out / "run.mcap").read_bytes() == b"my bag" and (out / "poses_ext.csv").read_text() == "my table\n"
    # a run into a folder holding another run's exports (no run wrote the folder) keeps them too
    exported = tmp_path / "o2"
    assert run_main(["-q", "export", str(out), "--out", str(exported)]).code == 0
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(exported)]).code == 0
    assert {"run.mcap", "poses_ext.csv", "tum"} < {p.name for p in exported.iterdir()}
    # and a run into a run's folder removes the export of it (it belongs to the poses.csv the run replaces)
    run_dir = tmp_path / "r"
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(run_dir)]).code == 0
    assert run_main(["-q", "export", str(run_dir)]).code == 0
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(run_dir)]).code == 0
    assert sorted(p.name for p in run_dir.iterdir()) == ["poses.csv", "recording.rrd", "summary.json"]


def test_a_planted_export_manifest_never_removes_a_file_outside_the_folder(tmp_path):
    # given a run folder whose .ar-anchor-export.json lists, with their very sizes and times, a file beside the
    # folder ("../outside.txt") and one reached through a link (tum -> a folder elsewhere)
    import json
    import os

    run_dir = tmp_path / "r"
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(run_dir)]).code == 0
    outside = tmp_path / "outside.txt"
    outside.write_text("the user's")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "marker_0.txt").write_text("the user's too")
    (run_dir / "tum").symlink_to(elsewhere)

    def entry(path: Path) -> list[int]:
        st = os.stat(path)
        return [st.st_size, st.st_mtime_ns]

    files = {"../outside.txt": entry(outside), "tum/marker_0.txt": entry(elsewhere / "marker_0.txt")}
    (run_dir / ".ar-anchor-export.json").write_text(json.dumps({"files": files}))
    # when a new run starts in it (which removes the previous export's files): both stay
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(run_dir)]).code == 0
    assert outside.read_text() == "the user's" and (elsewhere / "marker_0.txt").read_text() == "the user's too"


@pytest.mark.parametrize(
    ("column", "value", "expected"),
    [
        # (was: internal error: ValueError: Exceeds the limit (4300 digits) for integer string conversion)
        ("frame", "9" * 5000, f"line 2, column frame: expected a frame index, got '{'9' * 40}...'"),
        ("target", "marker:" + "9" * 5000, "line 2, column target: a marker id has at most 18 digits, got one of 5000"),
        # (was: exit 1 naming the temporary folder's tum/board_xxx...txt: File name too long)
        (
            "target",
            "board:" + "x" * 3000,
            f"line 2, column target: target '{('board:' + 'x' * 3000)[:60]}'...: a name of 3006 characters is too "
            "long for its TUM file name (at most 200): rename the board",
        ),
    ],
    ids=["frame-5000-digits", "marker-5000-digits", "board-name-3000"],
)
def test_cells_too_long_for_their_meaning_are_one_line(run, column, value, expected):
    _set(run, 1, column, value)
    assert _one_error(run_main(["-q", "export", str(run)])) == f"ar-anchor: error: {run / 'poses.csv'}: {expected}"
    _nothing_exported(run)
