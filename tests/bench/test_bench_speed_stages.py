"""``bench speed --stages``: its plumbing on a tiny run: structure, finite stage times, accuracy, report files.

Timings are for the report only: nothing here asserts on speed.
"""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from ar_anchor.bench.speed import (
    ONE_THREAD_PIPELINES,
    PIPELINES,
    render_clip,
    speed_scene,
    write_stages_report,
)
from ar_anchor.bench.speed.measure import PLAIN_PIPELINES as PLAIN
from ar_anchor.camera import CameraModel

# 640x360 with the 720p clips' focal length: the 5 cm marker is 83 px wide, as at 720p. (At fx 500 it is
# 42 px, and the plain OpenCV loop's uncorrected corners give it a median rotation error near 3 deg.)
SMALL = (640, 360, 1000.0)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("speed")
    calls = []
    threads = cv2.getNumThreads()
    results = write_stages_report(
        out,
        progress=lambda i, total, name: calls.append((i, total, name)),
        command="test bench speed",
        frames=12,
        sizes=[SMALL],
        scenes=["one", "board"],
        extra=(),  # the 50-marker and real clips: tests/bench/test_bench_speed_clips.py
    )
    return out, results, calls, threads


def _finite_positive(stats: dict) -> bool:
    return all(math.isfinite(stats[k]) and stats[k] > 0 for k in ("median", "p95", "mean"))


@pytest.mark.slow
def test_structure_and_files(tiny):
    out, results, calls, threads = tiny
    assert (out / "speed_stages.md").is_file() and (out / "speed_stages.json").is_file()
    text = (out / "speed_stages.md").read_text()
    assert "test bench speed" in text and "360p one marker" in text and "360p 2x2 board" in text
    assert "setNumThreads(1)" in text and "End to end" in text
    saved = json.loads((out / "speed_stages.json").read_text())
    assert saved["meta"]["command"] == "test bench speed"
    assert [c["label"] for c in saved["clips"]] == ["360p one marker", "360p 2x2 board"]
    assert cv2.getNumThreads() == threads  # the one-thread pass restores the setting
    assert [c[0] for c in calls] == list(range(len(calls))) and all(c[1] == len(calls) for c in calls)
    assert {c["frames"] for c in results["clips"]} == {12}
    for clip in results["clips"]:
        assert set(clip["pipelines"]) == set(PIPELINES)
        assert set(clip["one_thread"]) == set(ONE_THREAD_PIPELINES)
        assert math.isfinite(clip["ratio_opencv_over_roi"]) and clip["ratio_opencv_over_roi"] > 0
        assert isinstance(clip["roi_vs_full"]["within"], bool)
        # the columns of issue 19 on the existing clips too
        assert set(clip["ratios"]) == {f"{t}/{p}" for t in ("tracker_full", "tracker_roi") for p in PLAIN}
        assert all(math.isfinite(r) and r > 0 for r in clip["ratios"].values())
        assert set(clip["peak_mb"]) == set(PIPELINES) and all(mb > 0 for mb in clip["peak_mb"].values())
        for pipe in clip["pipelines"].values():
            assert pipe["found_per_frame"]["min"] >= 1  # every marker in view in every frame of these clips
            assert math.isfinite(pipe["per_marker_ms"]["total_ms"]) and pipe["per_marker_ms"]["total_ms"] > 0
    assert "Per marker" in text and "opencv SUBPIX" in text and "Peak memory per pipeline" in text
    memory = results["memory"]
    assert memory["rss_peak_with_frames_mb"] > 0 and memory["rss_peak_end_to_end_mb"] > 0
    assert all(mb > 0 for mb in memory["tracemalloc_peak_mb"].values())


def test_stage_times_positive_and_finite(tiny):
    _, results, _, _ = tiny
    for clip in results["clips"]:
        for key, pipe in [*clip["pipelines"].items(), *clip["one_thread"].items()]:
            expected = {"detect_ms", "pose_ms"} | (set() if key.startswith("opencv") else {"filter_ms"})
            assert expected <= set(pipe["stages"]), key
            for stage in expected:
                assert pipe["stages"][stage]["n"] == 12
                assert _finite_positive(pipe["stages"][stage]), (clip["label"], key, stage)
            assert _finite_positive(pipe["total_ms"])
            assert math.isfinite(pipe["fps"]) and pipe["fps"] > 0
    e2e = results["end_to_end"]
    assert e2e["frames"] == 12
    for stage in ("decode_ms", "track_ms", "render_ms", "log_ms"):
        assert _finite_positive(e2e["stages"][stage]), stage
    assert _finite_positive(e2e["total_ms"]) and e2e["fps"] > 0


def test_accuracy_small_and_finite(tiny):
    _, results, _, _ = tiny
    one = next(c for c in results["clips"] if c["scene"] == "one")
    for key in PIPELINES:
        marker = one["pipelines"][key]["accuracy"]["marker"]
        assert marker["found_pct"] > 90, key
        assert marker["rot_median_deg"] < 2.0, key
        assert marker["trans_median_pct"] < 5.0, key
        assert math.isfinite(marker["rot_p95_deg"]) and math.isfinite(marker["trans_p95_pct"])
    board = next(c for c in results["clips"] if c["scene"] == "board")
    for key in ("tracker_full", "tracker_roi"):
        acc = board["pipelines"][key]["accuracy"]["board"]
        assert acc["found_pct"] > 90 and acc["rot_median_deg"] < 2.0, key
    assert board["roi_vs_full"]["target_kind"] == "board"
    e2e = results["end_to_end"]["accuracy"]["marker"]
    assert e2e["found"] > 0 and e2e["rot_median_deg"] < 2.0


def test_render_clip_noise_and_truth():
    camera = CameraModel.from_fov(1280, 720, 1000.0)  # the 720p clips' camera: all eight markers in view
    scene = speed_scene("eight", camera, 2)
    frames = render_clip(scene)
    clean = render_clip(dataclasses.replace(scene, noise_sigma=0.0))
    assert len(frames) == 2 and all(len(f.truth) == 8 for f in frames)
    residual = frames[1].image.astype(float) - clean[1].image.astype(float)
    assert abs(residual.std() - scene.noise_sigma) < 0.2 and abs(residual.mean()) < 0.05
    assert not np.array_equal(frames[0].image - clean[0].image, frames[1].image - clean[1].image)


def test_unknown_scene_rejected(tmp_path):
    with pytest.raises(ValueError, match="unknown speed scene"):
        write_stages_report(tmp_path, frames=2, sizes=[SMALL], scenes=["nine"])
