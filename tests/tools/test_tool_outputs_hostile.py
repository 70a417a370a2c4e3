"""``calibrate`` and ``markers`` under the rule every writing command follows (issue 34): a file the command did not
write is never replaced, one run per output folder (the lock replay takes), each refusal one line naming the
option."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import ar_anchor.tools.calibrate.command as calibrate_command
from ar_anchor.run.paths import LOCK_NAME
from tests.helpers import assert_clean_exit, error_lines, run_main
from tests.tools.test_calibrate import BOARD_ARGS

MARKERS = ["markers", "--dictionary", "DICT_4X4_50", "--ids", "0-1", "--size-mm", "40"]
SHEET = "DICT_4X4_50_ids0-1_40mm"


def _one_error(result, code: int = 2) -> str:
    assert_clean_exit(result)
    assert result.code == code, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and result.stderr.strip() == lines[0], result.describe()
    return lines[0]


@pytest.fixture
def held(tmp_path):
    """Make a folder busy: its lock held by another live process (a run of any command)."""
    sleepers = []

    def hold(folder: Path) -> int:
        folder.mkdir(parents=True, exist_ok=True)
        sleeper = subprocess.Popen(["sleep", "30"])
        sleepers.append(sleeper)
        (folder / LOCK_NAME).write_text(f"{sleeper.pid} {os.uname().nodename}\n")
        return sleeper.pid

    yield hold
    for sleeper in sleepers:
        sleeper.kill()
        sleeper.wait()


# ---------------------------------------------------------------------------------------------- markers
def test_markers_never_replace_a_file_of_the_users_named_like_the_sheet(tmp_path):
    out = tmp_path / "sheets"
    out.mkdir()
    (out / f"{SHEET}.toml").write_text("# my edited snippet\n")
    line = _one_error(run_main(["-q", *MARKERS, "--out", str(out)]))
    assert line == (
        f"ar-anchor: error: --out {out}: holds {SHEET}.toml, which ar-anchor markers did not write; the sheet would "
        "overwrite it: move it or give another --out"
    )
    assert (out / f"{SHEET}.toml").read_text() == "# my edited snippet\n"
    assert sorted(p.name for p in out.iterdir()) == [f"{SHEET}.toml"]


def test_markers_replace_their_own_sheet_and_a_file_with_the_same_bytes(tmp_path):
    out = tmp_path / "sheets"
    assert run_main(["-q", *MARKERS, "--out", str(out)]).code == 0
    first = (out / f"{SHEET}.pdf").read_bytes()
    assert run_main(["-q", *MARKERS, "--out", str(out)]).code == 0  # its own (listed): replaced
    # a copy of the same sheet made elsewhere (not listed, the same bytes): replacing it loses nothing
    other = tmp_path / "copy"
    other.mkdir()
    for name in (f"{SHEET}.pdf", f"{SHEET}.toml"):
        (other / name).write_bytes((out / name).read_bytes())
    assert run_main(["-q", *MARKERS, "--out", str(other)]).code == 0
    assert (other / f"{SHEET}.pdf").read_bytes() == first
    assert not (out / LOCK_NAME).exists()


def test_markers_on_a_busy_folder_are_refused(tmp_path, held):
    out = tmp_path / "sheets"
    pid = held(out)
    line = _one_error(run_main(["-q", *MARKERS, "--out", str(out)]))
    assert line.startswith(f"ar-anchor: error: --out {out}: another run (pid {pid} on ")
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


# ---------------------------------------------------------------------------------------------- calibrate
@pytest.fixture
def report(six_view_report):
    """A calibration of 6 rendered views (computed once: tests/tools/conftest.py; the command's own calibration is
    replaced by it)."""
    return six_view_report


@pytest.fixture
def calibrate(report, monkeypatch, tmp_path):
    """``ar-anchor calibrate SHOTS ...`` with the calibration itself replaced by :func:`report` (fast)."""
    shots = tmp_path / "shots"
    shots.mkdir()
    monkeypatch.setattr(calibrate_command, "calibrate_source", lambda *args, **kwargs: report)
    return lambda *extra: run_main(["-q", "calibrate", str(shots), *BOARD_ARGS, *extra])


def test_calibrate_never_replaces_a_recording_it_did_not_write(tmp_path, calibrate):
    # given the user's camera.rrd where the recording goes by default (beside --out camera.yml)
    mine = tmp_path / "camera.rrd"
    mine.write_bytes(b"RRF2 my own recording")
    line = _one_error(calibrate("--out", str(tmp_path / "camera.yml")))
    assert line == (
        f"ar-anchor: error: --out {tmp_path / 'camera.yml'}: would overwrite {mine} (the recording), which "
        "ar-anchor calibrate did not write: move that file or give --rrd elsewhere"
    )
    # and named with --rrd
    line = _one_error(calibrate("--out", str(tmp_path / "camera.yml"), "--rrd", str(mine)))
    assert line == (
        f"ar-anchor: error: --rrd {mine}: would overwrite {mine} (the recording), which ar-anchor calibrate did not "
        "write: move that file or give another --rrd"
    )
    assert mine.read_bytes() == b"RRF2 my own recording" and not (tmp_path / "camera.yml").exists()


def test_calibrate_replaces_its_own_recording(tmp_path, calibrate):
    out = tmp_path / "calib" / "camera.yml"
    assert calibrate("--out", str(out)).code == 0
    assert (out.parent / "camera.rrd").is_file()
    result = calibrate("--out", str(out))
    assert result.code == 0, result.describe()
    assert sorted(p.name for p in out.parent.iterdir()) == ["camera.rrd", "camera.yml"]


def test_calibrate_on_a_busy_folder_is_refused_and_holds_the_lock_while_it_runs(tmp_path, calibrate, held, report):
    out = tmp_path / "calib" / "camera.yml"
    pid = held(out.parent)
    line = _one_error(calibrate("--out", str(out)))
    assert line.startswith(f"ar-anchor: error: --out {out.parent}: another run (pid {pid} on ")
    assert sorted(p.name for p in out.parent.iterdir()) == [LOCK_NAME]
    # --rrd in another folder: that folder is locked too, for the whole calibration
    (out.parent / LOCK_NAME).unlink()
    rrd = tmp_path / "rec" / "cal.rrd"
    seen = []

    def calibrating(*args, **kwargs):
        seen.append(((out.parent / LOCK_NAME).exists(), (rrd.parent / LOCK_NAME).exists()))
        return report

    calibrate_command.calibrate_source = calibrating  # (monkeypatched by the fixture: restored after the test)
    assert calibrate("--out", str(out), "--rrd", str(rrd)).code == 0
    assert seen == [(True, True)] and not (rrd.parent / LOCK_NAME).exists() and rrd.is_file()
