"""The stability benchmark's metrics on hand-made series, and one tiny hand-held scenario end to end."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

import ar_anchor.bench.stability.report as stability_report
from ar_anchor.bench.stability import (
    DECISIVE_MARGIN_PX,
    DECISIVE_RATIO,
    Scenario,
    ScenarioRun,
    TargetSeries,
    acceptance,
    evaluate,
    is_decisive,
    longest_stretch,
    predicted_error_stats,
    run_scenario,
    stability_scenarios,
    write_stability_report,
    wrong_tracked,
)
from ar_anchor.camera import CameraModel
from ar_anchor.config import TrackerConfig
from ar_anchor.geometry import Pose
from ar_anchor.synthetic import Occluder


def turned(deg: float, z: float = 0.5) -> Pose:
    """A pose turned ``deg`` about y, ``z`` metres away."""
    return Pose(np.array([0.0, math.radians(deg), 0.0]), np.array([0.0, 0.0, z]))


def hyp(px: float) -> SimpleNamespace:
    return SimpleNamespace(reproj_px=px)


def test_decisive_needs_one_solution_or_a_clear_ratio_and_margin():
    assert is_decisive([hyp(0.4)])  # the other solution failed validation
    assert is_decisive([hyp(0.2), hyp(0.2 * DECISIVE_RATIO + 0.01)])  # 3x and 0.4 px worse
    assert not is_decisive([hyp(0.05), hyp(0.2)])  # 4x, but only 0.15 px: corner-bias level
    assert not is_decisive([hyp(1.0), hyp(1.0 + 2 * DECISIVE_MARGIN_PX)])  # 0.6 px, but only 1.6x
    assert not is_decisive([])
    assert not is_decisive([hyp(0.2), hyp(math.nan)])


def test_a_stretch_of_five_frames_far_from_decisive_raw_counts_five():
    # given 12 frames: the output agrees with the raw measurement except on frames 3-7 (a 40 deg flip)
    raw = [turned(20.0)] * 12
    output = [turned(20.0)] * 3 + [turned(-20.0)] * 5 + [turned(20.0)] * 4
    decisive = [True] * 12
    assert longest_stretch(output, raw, decisive) == 5
    # a single disagreeing frame elsewhere does not add to it
    output[10] = turned(-20.0)
    assert longest_stretch(output, raw, decisive) == 5
    # disagreement with a non-decisive measurement is not counted, and (strictly) ends the run
    decisive[5] = False
    assert longest_stretch(output, raw, decisive) == 2
    # the gap-tolerant run skips it: 4 decisive measurements in a row were disagreed with
    assert longest_stretch(output, raw, decisive, gaps_end=False) == 4
    # frames without output or measurement end the strict run too
    assert longest_stretch([None] * 12, raw, [True] * 12) == 0


def test_wrong_tracked_frames_are_counted_only_when_tracked():
    truth = [turned(10.0)] * 6
    output = [turned(10.0), turned(-10.0), turned(-10.0), turned(12.0), None, turned(-10.0)]
    state = ["tracked", "tracked", "ambiguous", "tracked", "", "predicted"]
    result = wrong_tracked(output, truth, state)
    assert result["wrong_tracked"] == 1  # frame 1: tracked and 20 deg off; 2 ambiguous, 5 predicted
    assert result["wrong_tracked_pct"] == pytest.approx(100.0 / 3)


def test_predicted_error_statistics():
    truth = [turned(0.0)] * 6
    output = [turned(1.0), turned(2.0), turned(3.0), turned(20.0), turned(50.0), None]
    state = ["predicted", "predicted", "predicted", "predicted", "tracked", "predicted"]
    stats = predicted_error_stats(output, truth, state)
    assert stats["predicted_frames"] == 4
    assert stats["predicted_median_deg"] == pytest.approx(2.5)
    assert stats["predicted_p95_deg"] == pytest.approx(np.percentile([1, 2, 3, 20], 95))
    assert predicted_error_stats(output, truth, ["tracked"] * 6)["predicted_median_deg"] is None


def series(truth, raw, output, state, decisive) -> TargetSeries:
    return TargetSeries(truth, raw, output, state, [math.nan] * len(truth), decisive)


def test_evaluate_pools_targets_finds_the_worst_and_applies_the_acceptance():
    # given a two-marker sheet: marker 0 followed perfectly, marker 1 held on the wrong branch for 4
    # frames against decisive measurements, and predicted well once
    n = 20
    truth = [turned(20.0)] * n
    good = series(truth, truth, truth, ["tracked"] * n, [True] * n)
    output = [turned(20.0)] * 5 + [turned(-20.0)] * 4 + [turned(20.0)] * (n - 10) + [turned(21.0)]
    state = ["tracked"] * 5 + ["ambiguous"] * 4 + ["tracked"] * (n - 10) + ["predicted"]
    raw = truth[:-1] + [None]
    bad = series(truth, raw, output, state, [True] * (n - 1) + [False])
    scenario = Scenario("hand-made", 0.05, 0.5, "handheld", sheet=2, frames=n)
    run = ScenarioRun(scenario, {"marker:0": good, "marker:1": bad}, track_ms=[1.0] * n)
    result = evaluate(run, TrackerConfig())
    # then the pooled rates count frames of both targets, the worst target is named
    assert result["raw"]["flipped_pct"] == 0.0
    assert result["tracker"]["wrong_frames"] == 4 and result["tracker"]["flipped_pct"] == pytest.approx(10.0)
    assert result["tracker"]["longest_stretch"] == 4
    assert result["tracker"]["wrong_tracked"] == 0  # the flipped frames were called ambiguous
    assert result["tracker"]["predicted_frames"] == 1
    assert result["worst"]["wrong_excess_points"] == {"target": "marker:1", "value": pytest.approx(20.0)}
    assert result["targets"]["marker:1"]["tracker"]["flipped_pct"] == pytest.approx(20.0)
    assert result["sheet"]["tracker"]["disagree_pct"] == pytest.approx(4 / 20 * 100)
    # and the acceptance fails on the wrong-frame excess and the stretch, naming the target
    verdict = result["acceptance"]
    assert not verdict["pass"]
    assert any("marker:1" in f and "wrong" in f for f in verdict["failed"])
    assert any("stretch 4" in f for f in verdict["failed"])
    # while the good target alone passes
    alone = evaluate(ScenarioRun(scenario, {"marker:0": good}, track_ms=[1.0] * n))
    assert alone["acceptance"] == {"pass": True, "failed": []}


def test_acceptance_thresholds():
    def result(**tracker):
        base = {"flipped_pct": 1.0, "wrong_tracked": 0, "twitches": 0, "longest_stretch": 3}
        return {"raw": {"flipped_pct": 0.9}, "tracker": {**base, **tracker}}

    assert acceptance(result())["pass"]  # 1.0 <= 0.9 + 0.2, stretch 3
    assert not acceptance(result(flipped_pct=1.2))["pass"]
    assert not acceptance(result(wrong_tracked=1))["pass"]
    assert not acceptance(result(twitches=1))["pass"]
    assert not acceptance(result(longest_stretch=4))["pass"]
    assert acceptance(result(predicted_median_deg=2.9, predicted_p95_deg=9.9))["pass"]
    assert not acceptance(result(predicted_median_deg=3.1, predicted_p95_deg=5.0))["pass"]
    assert not acceptance(result(predicted_median_deg=1.0, predicted_p95_deg=10.5))["pass"]


def test_scenario_config_tracks_exactly_the_scene_markers():
    scenario = Scenario("sheet", 0.04, 2.0, "handheld", sheet=6, min_perimeter_rate=0.015)
    config = scenario.tracker_config(TrackerConfig())
    assert config.boards == () and dict(config.markers.lengths_m) == {}
    assert config.markers.ids == (0, 1, 2, 3, 4, 5) and config.markers.length_m == 0.04
    assert config.filter.enabled and config.detector.min_perimeter_rate == 0.015
    assert Scenario("lone", 0.05, 1.0).tracker_config(TrackerConfig()).markers.ids == (0,)


def test_the_grid_keeps_the_calm_scenarios_and_adds_handheld_ones():
    full, quick = stability_scenarios(), stability_scenarios(quick=True)
    calm = full[:15]  # then the issue-32 scenes (tests/bench/test_bench_stability_scenes.py), then hand-held
    handheld = [s for s in full if s.motion == "handheld"]
    assert all(s.motion not in ("handheld", "stills", "cut") for s in calm)
    assert len(calm) == 15 and calm[0].name == "static 12cm 0.5m tilt30" and calm[0].frames == 150
    approach = [s for s in calm if s.motion == "approach"]  # issue 20: ambiguous far, decisive near
    assert [(s.far_m, s.distance_m, s.marker_m) for s in approach] == [(4.0, 0.5, 0.04)]
    assert any(s.motion == "approach" and s.frames == 90 for s in quick)
    assert len(handheld) >= 8
    names = " ".join(s.name for s in handheld)
    for needle in ("h264", "720p", "5fps", "60fps", "dup12", "200deg/s", "occlusion", "far 4cm", "distortion"):
        assert needle in names
    assert any(s.compression == "h264" and s.sheet == 6 and s.resolution == (640, 480) for s in handheld)
    assert any(s.content_fps == 12.0 and s.fps == 30.0 for s in handheld)
    assert len(quick) < len(full) and any(s.motion == "handheld" for s in quick)
    # every hand-held scenario has a clip of the same length in seconds whatever its fps
    for s in handheld:
        assert s.frames / s.fps == pytest.approx(5.0)


def test_a_tiny_handheld_scenario_end_to_end(tmp_path, monkeypatch):
    # given a 2-marker sheet, hand-held with blur, JPEG, a hand and duplicated frames: 24 frames at 320x240
    hand = (Occluder(8, 14, from_xy=(-0.3, 0.5), to_xy=(1.3, 0.5), size=0.6),)
    scenario = Scenario(
        "tiny", 0.05, 0.35, "handheld", far_m=0.45, tilt_deg=10, frames=24, sheet=2, sheet_cols=2,
        resolution=(320, 240), exposure_s=0.01, rolling_shutter_s=0.01, compression="jpeg", content_fps=15.0,
        occluders=hand, turn_peak_deg_s=60.0, turn_every_s=0.5, seed=3,
    )  # fmt: skip
    run = run_scenario(scenario, TrackerConfig(), CameraModel.default_synthetic())
    assert set(run.targets) == {"marker:0", "marker:1"}
    assert all(len(s.truth) == 24 for s in run.targets.values())
    assert sum(t is not None for t in run.targets["marker:0"].truth) >= 20
    result = evaluate(run)
    for key in ("raw", "tracker", "targets", "worst", "acceptance", "sheet"):
        assert key in result
    assert result["detected_pct"] > 40
    assert result["tracker"]["frames"] > 20
    json.dumps(result)  # JSON-ready
    # and the report writer runs it and shows the acceptance table with a pass column
    monkeypatch.setattr(stability_report, "stability_scenarios", lambda quick: [scenario])
    results = write_stability_report(tmp_path, quick=True, command="test bench stability")
    text = (tmp_path / "stability.md").read_text()
    assert "| pass |" in text and "tiny" in text and "longest stretch" in text
    assert "## Offline replay vs causal (" in text and "| interpolated % |" in text
    saved = json.loads((tmp_path / "stability.json").read_text())
    assert saved["meta"]["wall_time_s"] > 0 and len(results) == 1
    assert saved["meta"]["offline_scenarios"] == 1 and "offline_acceptance" in saved["results"][0]
    assert "interpolated_pct" in saved["results"][0]["offline"]
    assert saved["results"][0]["scenario"]["resolution"] == [320, 240]
