"""``ar-anchor bench profile``: the tracker's CPU per stage and its costliest functions on a real video."""

from __future__ import annotations

import json

import pytest

from ar_anchor.cli.main import main


@pytest.mark.realdata
@pytest.mark.slow
def test_bench_profile_on_the_first_frames_of_chessboard_video(realdata, tmp_path, monkeypatch):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(realdata))
    out = tmp_path / "results"
    assert main(["-q", "bench", "profile", "--frames", "12", "--out", str(out)]) == 0
    text = (out / "profile.md").read_text()
    assert "ar-anchor bench profile --frames 12" in text and "12 frames of `chessboard.avi`" in text
    results = json.loads((out / "profile.json").read_text())
    assert results["frames"] == 12 and results["markers_per_frame"] > 10
    stages = results["stage_cpu_ms"]
    assert set(stages) == {"detect", "pose", "filter", "total"}
    assert all(stage["mean"] > 0 for stage in stages.values())
    assert stages["total"]["mean"] == pytest.approx(
        sum(stages[s]["mean"] for s in ("detect", "pose", "filter")), rel=0.05
    )
    # the table names the tracker's own functions and OpenCV's detection, costliest first
    rows = results["functions"]
    names = [row["function"] for row in rows]
    assert "process" in names and any("detectMarkers" in name for name in names)
    assert [row["ms_per_frame"] for row in rows] == sorted((row["ms_per_frame"] for row in rows), reverse=True)
    assert not any(row["where"].startswith("bench/") for row in rows)


def test_bench_profile_without_its_video_is_a_clear_exit_2(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["-q", "bench", "profile", "--video", str(tmp_path / "none.avi"), "--out", str(out)]) == 2
    assert "--video" in capsys.readouterr().err
    assert not out.exists()
