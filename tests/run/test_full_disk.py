"""A full disk loses nothing already written: ``poses.csv`` ends on a whole row, ``summary.json`` is the new
one or the previous one (never empty or missing, no temporary left), the recording is complete or named
incomplete, and the one error line names the first file the disk refused and says the disk is full.

Covered twice: by fault injection (a file object that raises ENOSPC after N bytes; runs everywhere) and on
a really full disk (a 2 MiB tmpfs, where this machine lets the tests mount one; skipped otherwise)."""

from __future__ import annotations

import csv
import errno
import io
import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from ar_anchor.config import demo_config
from ar_anchor.run import outputs as outputs_module
from ar_anchor.run.outputs import DiskFullError, PosesCsvWriter, SummaryFile
from ar_anchor.run.paths import LOCK_NAME
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.track.tracker import Tracker
from tests.helpers import assert_clean_exit, error_lines, run_main
from tests.run.test_pipeline import small_scene

HEADER_FIELDS = 18


class _FullDisk(io.FileIO):
    """A file on a disk with ``budget`` bytes left: the write that crosses it is cut short, the next raises."""

    budget = 0

    def write(self, data) -> int:
        left = type(self).budget
        if left <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written = super().write(bytes(data)[:left])
        type(self).budget -= written
        return written


def _full_disk_after(monkeypatch, budget: int, name: str = "poses.csv") -> None:
    """Files named ``name`` opened by the outputs module see a disk with ``budget`` bytes left."""
    real_open = open
    _FullDisk.budget = budget

    def fake_open(path, mode="r", *args, **kwargs):
        if Path(path).name == name and "w" in mode:
            return _FullDisk(path, "w")
        return real_open(path, mode, *args, **kwargs)

    monkeypatch.setattr(outputs_module, "open", fake_open, raising=False)


def _rows(path: Path) -> list[list[str]]:
    text = path.read_text(encoding="utf-8")
    assert text.endswith("\n"), f"{path} ends on a cut row: {text[-80:]!r}"
    rows = list(csv.reader(io.StringIO(text)))
    assert all(len(row) == HEADER_FIELDS for row in rows), [row for row in rows if len(row) != HEADER_FIELDS]
    return rows


# ------------------------------------------------------------------------------------ fault injection
def test_a_row_cut_by_a_full_disk_is_truncated_away(tmp_path, monkeypatch):
    scene = small_scene()
    tracker = Tracker(demo_config(), scene.camera)
    results = [tracker.process(frame) for frame in scene_frames(scene, 4)]
    _full_disk_after(monkeypatch, 400)  # the header and part of the first rows
    writer = PosesCsvWriter(tmp_path / "poses.csv")
    with pytest.raises(DiskFullError, match=r"poses\.csv: cannot write: the disk is full"):
        for result in results:
            writer.write(result)
    with pytest.raises(DiskFullError):  # and it stays failed: no row after a gap
        writer.write(results[-1])
    writer.close()
    rows = _rows(tmp_path / "poses.csv")
    assert rows[0][0] == "frame"


def scene_frames(scene, count: int):
    """The first ``count`` frames of ``scene``."""
    with SyntheticSource(scene) as source:
        for index, frame in enumerate(source):
            if index >= count:
                return
            yield frame


def test_a_run_on_a_full_disk_names_poses_csv_and_leaves_valid_outputs(tmp_path, monkeypatch):
    out = tmp_path / "o"
    _full_disk_after(monkeypatch, 3000)
    result = run_main(["-q", "demo", "--frames", "12", "--out", str(out)])
    assert_clean_exit(result)
    assert result.code == 1, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and "poses.csv" in lines[0] and "the disk is full" in lines[0], result.describe()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["incomplete"][0] == "poses.csv"
    frames = {row[0] for row in _rows(out / "poses.csv")[1:]}
    assert len(frames) == summary["frames"] > 0
    assert not (out / "summary.json.tmp").exists() and not (out / LOCK_NAME).exists()


def test_the_summary_keeps_its_previous_content_when_it_cannot_be_written(tmp_path, monkeypatch):
    path = tmp_path / "summary.json"
    path.write_text('{"previous": true}\n')
    summary = SummaryFile(path, reserve=0)

    def no_room(fd, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputs_module.os, "write", no_room)
    with pytest.raises(DiskFullError, match=r"summary\.json: cannot write: the disk is full"):
        summary.write({"frames": 1})
    monkeypatch.undo()
    assert path.read_text() == '{"previous": true}\n'
    assert not (tmp_path / "summary.json.tmp").exists()


def test_the_summary_is_written_into_the_room_set_aside_for_it(tmp_path):
    path = tmp_path / "summary.json"
    summary = SummaryFile(path, reserve=64 * 1024, slack=64 * 1024)
    summary.reserve()
    assert (tmp_path / "summary.json.tmp").stat().st_size == 128 * 1024
    summary.release_slack()
    assert (tmp_path / "summary.json.tmp").stat().st_size == 64 * 1024
    summary.write({"frames": 3})
    assert json.loads(path.read_text()) == {"frames": 3}
    assert not (tmp_path / "summary.json.tmp").exists()


# ------------------------------------------------------------------------------------ a really full disk
@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (root and a container that allows mounting), else skip."""
    mount = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode(errors='replace').strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True, check=False)


@pytest.mark.slow
def test_a_run_that_fills_a_real_disk_loses_nothing_written(small_disk):
    out = small_disk / "run"
    (small_disk / "summary-before").write_text("")
    done = subprocess.run(
        [sys.executable, "-m", "ar_anchor", "-q", "demo", "--frames", "120", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    lines = error_lines(done.stderr)
    assert len(lines) == 1 and "the disk is full" in lines[0], done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed"
    first = summary["incomplete"][0]
    assert f"/{first}:" in lines[0], (first, lines[0])  # the message names the first file refused
    assert "recording.rrd" in lines[0] or "recording.rrd" not in summary["incomplete"]  # named when incomplete
    frames = {row[0] for row in _rows(out / "poses.csv")[1:]}
    assert len(frames) >= summary["frames"] > 0
    assert not (out / "summary.json.tmp").exists() and not (out / LOCK_NAME).exists()


def test_a_full_disk_that_names_no_file_is_still_reported_and_summarised(tmp_path):
    # given a run's outputs, and a full-disk error from a writer that does not say which file it was
    # (seen once under load in CI: the run ended with an internal error instead of the disk-full line)
    from ar_anchor.errors import OutputError
    from ar_anchor.run.options import RunOptions
    from ar_anchor.run.outputs import DiskFullError
    from ar_anchor.run.run_outputs import RunOutputs

    outputs = RunOutputs(tmp_path, RunOptions())
    outputs._first(OutputError("cannot write: No space left on device"))
    assert "No space left on device" in str(outputs._failure_message())  # reported as it is, no crash
    # when the next failure names its file (the recording's close, after its flush failed)
    outputs._first(OutputError("recording.rrd: No space left on device"), tmp_path / "recording.rrd")
    outputs._first(OutputError("No space left on device"), tmp_path / "poses.csv")  # and another file
    # then the run's failure names that file, and the summary lists what is incomplete, the first file first
    assert outputs._first_failure.path == tmp_path / "recording.rrd"
    with pytest.raises(DiskFullError, match="recording.rrd.*also incomplete: poses.csv"):
        outputs.write_summary("failed", 1.0, {})
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["incomplete"] == ["recording.rrd", "poses.csv"]


# ------------------------------------------------------------------------------------ the offline spool (issue 34)
def test_a_full_disk_under_the_offline_spool_names_the_spool_not_the_recording(tmp_path, monkeypatch):
    """An offline replay keeps its first pass's frames in an unnamed temporary file in --out: a disk that
    fills under it was blamed on recording.rrd (which had barely begun)."""
    import cv2

    from ar_anchor.run.loop import SPOOL_NAME
    from ar_anchor.track.spool import SpoolStore

    scene = small_scene(frames=6)
    shots = tmp_path / "shots"
    shots.mkdir()
    for frame in SyntheticSource(scene):
        assert cv2.imwrite(str(shots / f"f_{frame.index}.png"), frame.image)
    camera = tmp_path / "cam.yml"
    scene.camera.to_yaml(camera)
    real_append = SpoolStore.append

    def append(self, item):
        if len(self) >= 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_append(self, item)

    monkeypatch.setattr(SpoolStore, "append", append)
    out = tmp_path / "out"
    result = run_main(["-q", "replay", str(shots), "--sequence", "--camera", str(camera), "--out", str(out)])
    assert_clean_exit(result)
    assert result.code == 1, result.describe()
    (line,) = error_lines(result.stderr)
    assert line.startswith(
        f"ar-anchor: error: {out}/: the offline replay's spool (an unnamed temporary file there, "
    ), line
    assert "for 3 frames) cannot grow: the disk is full" in line and "replay --causal" in line
    assert "recording.rrd: incomplete" not in line
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["incomplete"][0] == SPOOL_NAME
    assert not (out / "summary.json.tmp").exists() and not (out / LOCK_NAME).exists()
