"""The last line of a run lists every file it wrote: each part of a split recording, the exports, the video."""

from __future__ import annotations

import json
import subprocess

from ar_anchor.cli.report import outputs_line
from tests.helpers import cli, describe

PARTS_TOML = "[recording]\npart_minutes = 0.01\n"  # a new part every 0.6 s of frame (or wall) time: 60 frames, 4+


def test_a_split_run_with_exports_lists_every_file_in_its_last_line(tmp_path):
    # given a demo run whose recording is split in parts, exported, with an annotated video
    (tmp_path / "parts.toml").write_text(PARTS_TOML)
    argv = ["demo", "--frames", "60", "--config", "parts.toml", "--out", "run", "--export", "--video-out", "ar.avi"]
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, describe(result)
    # then its last line names each file it wrote, the parts in order
    last = result.stdout.strip().splitlines()[-1]
    parts = json.loads((tmp_path / "run" / "summary.json").read_text())["recording_parts"]
    on_disk = {path.name for path in (tmp_path / "run").glob("recording*.rrd")}
    assert len(parts) >= 3 and set(parts) == on_disk, (parts, on_disk)
    listed = last.split("(", 1)[1]
    assert listed.startswith(f"poses.csv, summary.json, {', '.join(parts)}, poses_ext.csv"), last
    assert "run.mcap" in last and "tum/ (2 files)" in last, last
    assert last.endswith("annotated video: ar.avi (60 frames)"), last
    # and nothing after it repeats or contradicts it (the exports' line comes before)
    assert not any(line.startswith("exports:") for line in result.stdout.splitlines()), result.stdout


def test_a_run_in_one_file_lists_recording_rrd_and_the_raw_videos_timestamps(tmp_path):
    # given a run's folder with one recording and a raw video (--record)
    names = ["poses.csv", "summary.json", "recording.rrd", "raw.mkv", "raw.mkv.timestamps.csv"]
    for name in names:
        (tmp_path / name).write_text("x")
    # then the line lists them all, the timestamps too, in that order
    assert outputs_line(tmp_path, {}) == f"outputs: {tmp_path}/ ({', '.join(names)})"
    # and a summary's parts replace recording.rrd alone; a listed part that is missing is not claimed
    (tmp_path / "recording.part2.rrd").write_text("x")
    summary = {"recording_parts": ["recording.rrd", "recording.part2.rrd", "recording.part3.rrd"]}
    assert "recording.rrd, recording.part2.rrd, raw.mkv" in outputs_line(tmp_path, summary)
