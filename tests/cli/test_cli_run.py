"""End-to-end runs of the CLI that end abnormally: outputs must stay complete and readable."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # fuzzing and end-to-end CLI runs: the full suite, not the fast tier

RERUN = Path(sys.executable).with_name("rerun")


def verify_rrd(path: Path) -> None:
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    result = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def test_sigterm_mid_run_leaves_complete_outputs(tmp_path):
    # given a long demo run
    out = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "ar_anchor", "-q", "demo", "--frames", "2000", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    # when it is terminated once some frames are written
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        poses = out / "poses.csv"
        if poses.exists() and poses.read_text().count("\n") > 20:
            break
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    _stdout, stderr = process.communicate(timeout=60)
    # then it exits 130 with one message, and every output is complete
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    rows = list(csv.DictReader((out / "poses.csv").open()))
    assert rows and int(rows[-1]["frame"]) == summary["frames"] - 1
    verify_rrd(out / "recording.rrd")


def test_spawn_without_a_display_records_to_file_and_says_why(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = subprocess.run(
        [sys.executable, "-m", "ar_anchor", "-q", "demo", "--frames", "3", "--spawn", "--out", str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "no display" in result.stderr
    verify_rrd(tmp_path / "run" / "recording.rrd")
