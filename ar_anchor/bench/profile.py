"""``ar-anchor bench profile``: where the tracker's time goes, frame by frame, on a real video (default
chessboard.avi: 18 markers, 640x480).

Two passes over the same decoded frames, OpenCV on one thread (so that a stage's CPU time is its cost,
whatever else the machine runs):

1. **Stages**: the CPU time of detect, pose and filter per frame (``time.process_time`` around
   :meth:`Tracker.process`'s stages, read from its ``latency_ms`` split), median and mean.
2. **Functions**: ``cProfile`` over the whole pass: the tracker's own functions and the OpenCV calls,
   by cumulative time per frame and calls per frame. cProfile slows pure-Python code more than OpenCV
   calls, so these times are inflated where Python dominates; compare them with each other.
"""

from __future__ import annotations

import cProfile
import pstats
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import TrackerConfig
from ..sources.base import Frame
from .real.inputs import RealInputs
from .report import machine_info, write_json

__all__ = ["ProfileResult", "profile_tracker", "write_profile_report"]

_TOP = 30  # rows of the function table


@dataclass
class ProfileResult:
    """One profile: stage CPU per frame (ms) and the cProfile rows."""

    video: str
    frames: int
    markers_per_frame: float
    stage_cpu_ms: dict[str, dict[str, float]] = field(default_factory=dict)
    functions: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0


def _decoded(video: Path, limit: int | None) -> list[np.ndarray]:
    from ..sources import open_source

    images = []
    with open_source(video, live=False) as source:
        for frame in source:
            images.append(frame.image)
            if limit is not None and len(images) >= limit:
                break
    return images


def _run(tracker_factory, images: Sequence[np.ndarray], fps: float) -> tuple[list[dict[str, float]], int]:
    tracker = tracker_factory()
    stages, markers = [], 0
    for index, image in enumerate(images):
        started = time.process_time()
        result = tracker.process(Frame(image, index, int(index * 1e9 / fps)))
        cpu = (time.process_time() - started) * 1e3
        wall = sum(result.latency_ms.get(k, 0.0) for k in ("detect_ms", "pose_ms", "filter_ms")) or cpu
        # split the frame's CPU time over the stages as their wall times split (one thread: the same)
        stages.append({k: cpu * result.latency_ms.get(f"{k}_ms", 0.0) / wall for k in ("detect", "pose", "filter")})
        markers += len(result.detections)
    return stages, markers


_OPENCV_CALLS = (
    "detectMarkers",
    "refineDetectedMarkers",
    "solvePnP",
    "projectPoints",
    "Rodrigues",
    "cvtColor",
    "remap",
    "undistortPoints",
    "Laplacian",
    "pyrDown",
    "absdiff",
    "resize",
)


def _function_rows(stats: pstats.Stats, frames: int) -> list[dict[str, Any]]:
    """The tracker's functions and OpenCV's calls, costliest first (cumulative time per frame)."""
    rows = []
    for (filename, line, name), (_calls, primitive, _total, cumulative, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        parts = Path(filename).parts
        own = "ar_anchor" in parts and "bench" not in parts  # (not this module's own loop)
        opencv = filename == "~" and any(call in name for call in _OPENCV_CALLS) and "numpy" not in name
        if not (own or opencv):
            continue
        where = Path(filename).as_posix().split("ar_anchor/")[-1] + f":{line}" if own else "OpenCV"
        rows.append(
            {
                "function": name,
                "where": where,
                "ms_per_frame": 1e3 * cumulative / frames,
                "calls_per_frame": primitive / frames,
            }
        )
    rows.sort(key=lambda row: -row["ms_per_frame"])
    return rows[:_TOP]


def profile_tracker(
    inputs: RealInputs, config: TrackerConfig, *, frames: int | None = None, fps: float = 30.0
) -> ProfileResult:
    """Profile :class:`~ar_anchor.track.tracker.Tracker` on ``inputs.video`` (see the module doc)."""
    from ..track.tracker import Tracker

    images = _decoded(inputs.video, frames)
    if not images:
        raise ValueError(f"{inputs.video}: no frames")
    height, width = images[0].shape[:2]
    camera = CameraModel.from_yaml(inputs.camera).scaled_to(width, height)
    config = config.with_overrides(dictionary=inputs.dictionary, marker_length_m=inputs.marker_length_m)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    started = time.perf_counter()
    try:
        stages, markers = _run(lambda: Tracker(config, camera), images, fps)
        profiler = cProfile.Profile()
        profiler.enable()
        _run(lambda: Tracker(config, camera), images, fps)
        profiler.disable()
    finally:
        cv2.setNumThreads(threads)
    result = ProfileResult(str(inputs.video), len(images), markers / len(images), wall_s=time.perf_counter() - started)
    for stage in ("detect", "pose", "filter"):
        values = np.array([s[stage] for s in stages])
        result.stage_cpu_ms[stage] = {"median": float(np.median(values)), "mean": float(values.mean())}
    totals = np.array([sum(s.values()) for s in stages])
    result.stage_cpu_ms["total"] = {"median": float(np.median(totals)), "mean": float(totals.mean())}
    result.functions = _function_rows(pstats.Stats(profiler), len(images))
    return result


def write_profile_report(result: ProfileResult, out_dir: Path, command: str) -> Path:
    """``profile.md`` and ``profile.json`` in ``out_dir``; returns the markdown's path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Where the tracker's time goes",
        "",
        f"Produced by `{command}` in {result.wall_s:.0f} s: {result.frames} frames of `{Path(result.video).name}`, "
        f"{result.markers_per_frame:.1f} markers per frame on average, OpenCV on one thread.",
        "",
        "## CPU time per frame, by stage (ms)",
        "",
        "| stage | median | mean |",
        "|---|---|---|",
    ]
    for stage, values in result.stage_cpu_ms.items():
        lines.append(f"| {stage} | {values['median']:.2f} | {values['mean']:.2f} |")
    lines += [
        "",
        f"## The {_TOP} costliest functions (cProfile, cumulative, per frame)",
        "",
        "A function's time includes the functions it calls. cProfile inflates Python-heavy rows more than "
        "OpenCV calls: compare rows with each other, not with the stage times above.",
        "",
        "| function | where | ms / frame | calls / frame |",
        "|---|---|---|---|",
    ]
    for row in result.functions:
        lines.append(
            f"| `{row['function']}` | {row['where']} | {row['ms_per_frame']:.2f} | {row['calls_per_frame']:.1f} |"
        )
    path = out_dir / "profile.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    write_json(out_dir / "profile.json", {"machine": machine_info(), "command": command, **result.__dict__})
    return path
