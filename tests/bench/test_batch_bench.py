"""``ar-anchor bench batch``'s report: the table and the verdict from a results dict (the run itself is the
benchmark: bench/results/batch.md)."""

from __future__ import annotations

import json

from ar_anchor.bench.batch import batch_markdown
from ar_anchor.bench.report import machine_info


def _results(batch_s: float) -> dict:
    variants = {
        "sequential": {"wall_s": 100.0},
        "batch": {"wall_s": batch_s, "speedup": 100.0 / batch_s, "same_poses": 12},
        "batch --ray": {"wall_s": 60.0, "speedup": 100.0 / 60.0, "same_poses": 11},
    }
    return {
        "meta": machine_info(),
        "notes": [],
        "jobs": 2,
        "clips": {"clips": 12, "frames": 300, "size": "640x480", "video_mb": 9.0, "render_s": 80.0},
        "variants": variants,
        "verdict": 100.0 / batch_s >= 1.7,
    }


def test_the_report_says_the_speedup_and_whether_the_target_is_met():
    # given results where batch is 2x the loop
    text = batch_markdown(_results(50.0), "ar-anchor bench batch")
    # then
    assert "| batch | 50.0 | 72.0 | 2.00 | 12 of 12 |" in text
    assert "| batch --ray | 60.0 | 60.0 | 1.67 | 11 of 12 |" in text
    assert "**batch over the loop: 2.00x** (target >= 1.7x): **pass**" in text


def test_a_missed_target_is_reported_as_a_fail():
    results = _results(80.0)
    json.dumps(results)  # (what batch.json holds is plain JSON)
    assert "(target >= 1.7x): **FAIL**" in batch_markdown(results, "ar-anchor bench batch")
