"""``ar-anchor bench offline``: the offline replay against ``--causal`` (time, memory, chessboard.avi scores):
the report and verdicts on hand-made results, the RSS growth, and short real runs."""

from __future__ import annotations

import json

import pytest

from ar_anchor.bench.offline import offline_markdown, offline_verdicts, rss_growth, warmup_s
from ar_anchor.cli.main import main


def _score(flips: int, pair_frames: int, rotation: float) -> dict:
    return {
        "pair_frames": pair_frames,
        "flip_pct": 100 * flips / pair_frames,
        "rel_rot_rms_deg": rotation,
        "rel_trans_rms_mm": 0.6,
        "marker_frames": 2000,
        "flips": flips,
        "pairs": 40,
    }


def _run(mode: str, wall: float, growth: float, states: dict, causal_states: dict | None = None) -> dict:
    return {
        "mode": mode,
        "wall_s": wall,
        "frames": 18000,
        "memory": {"warmup_s": 60.0, "peak_mb": 400.0 + growth, "growth_mb": growth, "sustained_growth_mb": 5.0},
        "recording_mb": 1700.0,
        "offline": {"done": ["track", "decide", "write"], "frames": 18000, "spool_mb": 123.4}
        if mode == "offline"
        else None,
        "states": states,
        "causal_states": causal_states,
    }


def _results(offline_walls=(420.0, 430.0, 440.0), offline_growth=40.0, offline_rotation=0.24) -> dict:
    causal_states = {"tracked": 100000, "ambiguous": 5000, "lost": 20}
    offline_states = {"tracked": 104000, "ambiguous": 900, "interpolated": 120}
    causal = [_run("causal", wall, 20.0, causal_states) for wall in (300.0, 310.0, 320.0)]
    offline = [_run("offline", wall, offline_growth, offline_states, causal_states) for wall in offline_walls]
    long = {
        "frames": 18000,
        "minutes": 10.0,
        "size": "1280x720",
        "video_mb": 160.0,
        "encode_s": 900.0,
        "command": "ar-anchor replay demo_handheld_720p.mp4 --camera camera_720p.yml --config demo.toml",
        "runs": 3,
        "ratio_offline_over_causal": sorted(offline_walls)[1] / 310.0,
    }
    for mode, runs in (("causal", causal), ("offline", offline)):
        walls, growths = [r["wall_s"] for r in runs], [r["memory"]["growth_mb"] for r in runs]
        long[mode] = {"wall_s": walls, "wall_median_s": sorted(walls)[1], "growth_mb": growths,
                      "sustained_growth_mb": [r["memory"]["sustained_growth_mb"] for r in runs],
                      "growth_median_mb": growths[1], "growth_max_mb": max(growths), "runs": runs}  # fmt: skip
    board = {"command": "ar-anchor replay chessboard.avi --camera intrinsics.yml"}
    for mode, rotation in (("causal", 0.25), ("offline", offline_rotation)):
        board[mode] = {
            "wall_s": 5.0,
            "frames": 149,
            "states": {"tracked": 2036, "interpolated": 600 if mode == "offline" else 0},
            "causal_states": None,
            "offline": None,
            "scores": {"all rows": _score(3, 20000, rotation), "tracked only": _score(2, 14000, rotation)},
        }
    meta = {"processor": "cpu", "usable_cpus": 2, "python": "3.11", "opencv": "5.0", "opencv_threads": 2,
            "load_average_start": [1.0, 1.0, 1.0], "load_average_end": [2.0, 2.0, 2.0]}  # fmt: skip
    results = {"meta": meta, "notes": [], "long": long, "chessboard": board}
    results["verdicts"] = offline_verdicts(results)
    return results


def test_the_report_shows_ratio_memory_spool_states_and_scores_of_both_modes():
    results = _results()
    assert results["verdicts"] == {"time_ratio": True, "offline_growth": True, "chessboard": True}
    text = offline_markdown(results, "ar-anchor bench offline")
    assert "Produced by `ar-anchor bench offline`" in text
    assert "10 minutes at 1280x720, H.264" in text
    assert "| wall s per run | 300.0, 310.0, 320.0 | 420.0, 430.0, 440.0 |" in text
    assert "**Offline / causal wall time: 1.39x**" in text and "target <= 1.5x): **pass**" in text
    assert "**Offline RSS growth: 40.0 MB**" in text and "causal: 20.0 MB" in text
    assert "| spool MB (`summary.json`) | - | 123.4, 123.4, 123.4 |" in text
    assert "| sustained growth MB per run (10 s medians) | 5.0, 5.0, 5.0 | 5.0, 5.0, 5.0 |" in text
    assert "Sustained growth (10 s medians, the largest of the runs): offline 5.0 MB, causal 5.0 MB." in text
    assert "| recording MB (all parts) | 1700, 1700, 1700 | 1700, 1700, 1700 |" in text
    # the states: causal run, the offline run's live filter, the offline answer; zero-only states left out
    assert "| ambiguous | 5000 | 5000 | 900 |" in text
    assert "| interpolated | - | - | 120 |" in text and "| lost | 20 | 20 | - |" in text
    assert "| all rows | causal | 2000 | 20000 | 3 (0.01 %) | 0.250 | 0.60 |" in text
    assert "| tracked only | offline | 2000 | 14000 | 2 (0.01 %) | 0.240 | 0.60 |" in text
    assert "causal's (both row sets): **pass**." in text
    assert "## Machine" in text and "2 usable CPUs" in text


def test_verdicts_fail_on_a_slow_or_growing_offline_replay_and_a_worse_chessboard_score():
    results = _results(offline_walls=(470.0, 480.0, 490.0), offline_growth=100.0, offline_rotation=0.26)
    assert results["verdicts"] == {"time_ratio": False, "offline_growth": False, "chessboard": False}
    text = offline_markdown(results, "ar-anchor bench offline")
    assert "wall time: 1.55x** (median / median; target <= 1.5x): **FAIL**" in text
    assert "**Offline RSS growth: 100.0 MB** (the largest of its runs; target < 100 MB): **FAIL**" in text
    assert "causal's (both row sets): **FAIL**." in text


def test_without_the_long_replay_or_chessboard_the_report_says_what_was_skipped():
    results = _results()
    del results["long"]
    results["chessboard"] = {"skipped": "chessboard clip skipped: x not found"}
    results["notes"] = [results["chessboard"]["skipped"]]
    assert offline_verdicts(results) == {"time_ratio": None, "offline_growth": None, "chessboard": None}
    text = offline_markdown(results, "ar-anchor bench offline --minutes 0")
    assert "Note: chessboard clip skipped: x not found." in text
    assert "Long synthetic" not in text and "## chessboard.avi" not in text


def test_rss_growth_is_the_peak_after_the_warmup_minus_the_size_at_its_end():
    assert warmup_s(600.0) == 60.0 and warmup_s(20.0) == 5.0
    samples = [(0.5 * i, 100.0 + i) for i in range(10)] + [(t, 300.0) for t in (61.0, 62.0)] + [(63.0, 380.0)]
    memory = rss_growth(600.0, samples)  # warm-up 60 s: 300 MB after it, peak 380
    assert memory["rss_after_warmup_mb"] == 300.0 and memory["peak_after_warmup_mb"] == 380.0
    assert memory["growth_mb"] == pytest.approx(80.0) and memory["peak_mb"] == 380.0
    assert memory["final_mb"] == 380.0 and memory["samples"] == 13
    # a spike of a second or two is no sustained growth; a level that stays up is
    flat = [(60.0 + 0.5 * i, 300.0 + (400.0 if i in (40, 41) else 0.0)) for i in range(120)]
    assert rss_growth(600.0, flat)["growth_mb"] == 400.0 and rss_growth(600.0, flat)["sustained_growth_mb"] == 0.0
    step = [(60.0 + 0.5 * i, 300.0 + (120.0 if i >= 60 else 0.0)) for i in range(120)]
    assert rss_growth(600.0, step)["sustained_growth_mb"] == 120.0
    assert rss_growth(600.0, samples[:10])["growth_mb"] is None  # nothing after the warm-up


@pytest.mark.slow
def test_bench_offline_on_a_two_second_clip_writes_both_modes(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(tmp_path / "no-realdata"))
    out = tmp_path / "results"
    assert main(["-q", "bench", "offline", "--quick", "--minutes", "0.03", "--out", str(out)]) == 0
    results = json.loads((out / "offline.json").read_text())
    long = results["long"]
    assert long["frames"] == 54 and long["runs"] == 1
    causal, offline = long["causal"]["runs"][0], long["offline"]["runs"][0]
    assert causal["frames"] == offline["frames"] == 54
    assert causal["offline"] is None and causal["causal_states"] is None
    assert offline["offline"]["done"] == ["track", "decide", "write"] and offline["offline"]["spool_mb"] >= 0
    assert sum(offline["causal_states"].values()) == sum(offline["states"].values()) == sum(causal["states"].values())
    assert offline["causal_states"] == causal["states"]  # the live filter inside the offline run = --causal
    assert causal["memory"]["samples"] > 0 and long["ratio_offline_over_causal"] > 0
    assert causal["recording_mb"] > 0 and offline["recording_mb"] > 0
    assert "skipped" in results["chessboard"] and results["verdicts"]["chessboard"] is None
    text = (out / "offline.md").read_text()
    assert "ar-anchor bench offline --quick --minutes 0.03" in text
    assert "| | causal (`--causal`) | offline (default) |" in text and "Note: chessboard clip skipped" in text


@pytest.mark.realdata
@pytest.mark.slow
def test_bench_offline_scores_chessboard_video_in_both_modes(realdata, tmp_path, monkeypatch):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(realdata))
    out = tmp_path / "results"
    assert main(["-q", "bench", "offline", "--minutes", "0", "--out", str(out)]) == 0
    results = json.loads((out / "offline.json").read_text())
    assert "long" not in results
    board = results["chessboard"]
    for mode in ("causal", "offline"):
        assert board[mode]["frames"] == 149
        for rows in ("all rows", "tracked only"):
            assert board[mode]["scores"][rows]["pair_frames"] > 1000
    assert board["offline"]["offline"]["done"] == ["track", "decide", "write"]
    assert results["verdicts"]["chessboard"] is True
    assert "| tracked only | offline |" in (out / "offline.md").read_text()
