"""The whole chain a session runs, one stage after the other, on one encoded clip: decode
(:class:`~ar_anchor.sources.files.VideoFileSource`), track, overlay (the default cube on ``marker:*``)
and rerun logging (default recording settings, to a temporary ``.rrd``)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ...config import TrackerConfig
from ...geometry import Pose
from ...synthetic import SyntheticScene
from ...track.tracker import Tracker
from .measure import TRACKER_STAGES, WARMUP_FRAMES, accuracy, summary_stats
from .scenes import speed_config

__all__ = ["E2E_STAGES", "run_end_to_end"]

E2E_STAGES = ("decode_ms", "track_ms", "render_ms", "log_ms")


def run_end_to_end(
    video: Path, scene: SyntheticScene, truths: Sequence[Mapping[str, Pose]], base: TrackerConfig, tmp: Path
) -> dict[str, Any]:
    """decode -> track -> overlay -> rerun log, one frame after the other, with the ROI tracker."""
    from ...config import OverlayConfig, RecordingConfig
    from ...render.overlay import OverlayRenderer
    from ...sources.files import VideoFileSource
    from ...viz.recorder import RerunRecorder

    camera = scene.camera
    config = dataclasses.replace(
        speed_config(base, scene, roi=True),
        overlays=(OverlayConfig(target="marker:*", kind="cube"),),
        recording=RecordingConfig(),
    )
    tracker = Tracker(config, camera)
    renderer = OverlayRenderer(config, camera)
    rrd = tmp / "speed.rrd"
    recorder = RerunRecorder(rrd, camera=camera, settings=config.recording, overlay_models=renderer.models_for)
    times: dict[str, list[float]] = {stage: [] for stage in E2E_STAGES}
    tracker_ms: list[float] = []
    outputs: list[dict[str, Pose]] = []
    source = VideoFileSource(video)
    try:
        frames = iter(source)
        while True:
            t0 = time.perf_counter()
            frame = next(frames, None)
            t1 = time.perf_counter()
            if frame is None:
                break
            result = tracker.process(frame)
            t2 = time.perf_counter()
            annotated = renderer.annotate(frame.image, result)
            t3 = time.perf_counter()
            recorder.log_frame(frame, result, annotated)
            t4 = time.perf_counter()
            for stage, ms in zip(E2E_STAGES, np.diff([t0, t1, t2, t3, t4]) * 1e3):
                times[stage].append(float(ms))
            tracker_ms.append(sum(result.latency_ms.get(stage, 0.0) for stage in TRACKER_STAGES))
            outputs.append({name: target.pose for name, target in result.targets.items()})
    finally:
        source.close()
        start = time.perf_counter()
        recorder.close()
        close_ms = (time.perf_counter() - start) * 1e3
    decoded = len(outputs)
    keep = slice(WARMUP_FRAMES if decoded > 2 * WARMUP_FRAMES else 0, None)
    stats = {stage: summary_stats(values[keep]) for stage, values in times.items()}
    per_frame = np.sum([times[stage][keep] for stage in E2E_STAGES], axis=0)
    total = summary_stats(per_frame)
    return {
        "size": f"{camera.width}x{camera.height}",
        "scene": "one",
        "frames": decoded,
        "frames_excluded": keep.start or 0,
        "video_mb": video.stat().st_size / 1e6,
        "rrd_mb": rrd.stat().st_size / 1e6 if rrd.exists() else math.nan,
        "stages": stats,
        "tracker_detect_pose_filter_ms": summary_stats(tracker_ms[keep]),
        "total_ms": total,
        "fps": 1e3 / total["mean"] if total["mean"] > 0 else math.nan,
        "recorder_close_ms": close_ms,
        "accuracy": {kind: accuracy(outputs, truths[:decoded], kind) for kind in ("marker", "board")},
    }
