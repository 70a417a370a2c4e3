"""The speed benchmark's run: every (size, scene) clip rendered, timed and scored, then the end-to-end
chain and the memory figures."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from ...camera import CameraModel
from ...config import TrackerConfig
from ...geometry import Pose
from ...sources.base import Frame
from ...synthetic import SyntheticScene
from ..report import load_average, machine_info
from .end_to_end import run_end_to_end
from .measure import (
    ONE_THREAD_PIPELINES,
    PIPELINES,
    WARMUP_FRAMES,
    pipeline_factories,
    pipeline_result,
    pipeline_timing,
    primary_kind,
    ratio_opencv_over_roi,
    roi_check,
    time_pass,
)
from .memory import maxrss_mb, release_freed_memory, reset_peak_rss, rss_now_mb, tracemalloc_peak_mb
from .scenes import BLUR, MARKER_M, NOISE, SCENES, SIZES, clip_label, render_clip, speed_config, speed_scene

__all__ = ["run_speed_benchmark"]

Size = tuple[int, int, float]  # width, height, fx


def run_speed_benchmark(
    frames: int = 300,
    sizes: Sequence[Size] = SIZES,
    scenes: Sequence[str] = SCENES,
    *,
    config: TrackerConfig | None = None,
    one_thread: bool | str = True,
    end_to_end: bool = True,
    memory_frames: int = 30,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Time the three pipelines on every (size, scene) clip; return all numbers (see :mod:`ar_anchor.bench.speed`).

    ``sizes``: (width, height, fx) per clip size. ``scenes``: any of :data:`SCENES`. ``one_thread``: repeat
    the opencv and tracker (ROI) loops with ``cv2.setNumThreads(1)`` (``"largest"``: at the largest size
    only). ``end_to_end``: the decode -> track -> overlay -> log chain on the largest size's one-marker clip
    (else its first scene). ``memory_frames``: frames of the tracemalloc pass (largest size; 0: none).
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    for key in scenes:
        if key not in SCENES:
            raise ValueError(f"unknown speed scene {key!r} (one of {', '.join(SCENES)})")
    machine = machine_info()
    plan = _Plan(
        base=config or TrackerConfig(),
        frames=frames,
        largest=tuple(max(sizes, key=lambda s: s[0] * s[1])),
        e2e_scene=("one" if "one" in scenes else scenes[0]) if end_to_end else None,
        one_thread=one_thread,
        memory_frames=memory_frames,
        threads=cv2.getNumThreads(),
        steps=_Steps(2 * len(sizes) * len(scenes) + (1 if end_to_end else 0), progress),
    )
    memory: dict[str, Any] = {"rss_peak_at_start_mb": maxrss_mb(), "tracemalloc_peak_mb": {}}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ar_anchor_speed_") as tmp_name:
        tmp = Path(tmp_name)
        clips: list[dict[str, Any]] = []
        e2e_input: _EndToEndInput | None = None
        for size in sizes:
            for scene_key in scenes:
                clip, e2e_clip = _measure_clip(plan, tuple(size), scene_key, tmp, memory)
                clips.append(clip)
                e2e_input = e2e_clip or e2e_input
        memory["rss_peak_with_frames_mb"] = maxrss_mb()
        memory["largest_frame_store_mb"] = max(c["frame_store_mb"] for c in clips)
        e2e_result = _end_to_end(plan, e2e_input, tmp, memory) if e2e_input is not None else None
    wall = time.perf_counter() - start
    machine["load_average_end"] = load_average()
    return {
        "meta": {
            "frames_per_clip": frames,
            "sizes": [list(s) for s in sizes],
            "scenes": list(scenes),
            "warmup_frames": WARMUP_FRAMES,
            "noise": NOISE,
            "blur_px": BLUR,
            "wall_time_s": wall,
            **machine,
        },
        "clips": clips,
        "end_to_end": e2e_result,
        "memory": memory,
    }


class _Steps:
    """Progress reports, numbered from 0 of a known total."""

    def __init__(self, total: int, progress: Callable[[int, int, str], None] | None) -> None:
        self.total, self.progress, self.done = total, progress, 0

    def report(self, name: str) -> None:
        if self.progress is not None:
            self.progress(self.done, self.total, name)
        self.done += 1


@dataclass(frozen=True)
class _Plan:
    """What every clip of one run shares."""

    base: TrackerConfig
    frames: int
    largest: Size  # the largest clip size: the one-core pass ("largest"), tracemalloc and end to end run there
    e2e_scene: str | None  # the scene of the end-to-end run (None: no end-to-end run)
    one_thread: bool | str
    memory_frames: int
    threads: int  # OpenCV's own thread count
    steps: _Steps


@dataclass(frozen=True)
class _EndToEndInput:
    """The clip kept for the end-to-end run: its label, encoded to ``video``, its scene and its truth."""

    label: str
    video: Path
    scene: SyntheticScene
    truths: list[Mapping[str, Pose]]


def _measure_clip(
    plan: _Plan, size: Size, scene_key: str, tmp: Path, memory: dict[str, Any]
) -> tuple[dict[str, Any], _EndToEndInput | None]:
    """Render one clip, time the pipelines on it (and the one-core pass, and tracemalloc at the largest
    size); the clip's record, and the end-to-end input when this is its clip."""
    width, height, focal = size
    camera = CameraModel.from_fov(width, height, focal)
    label = clip_label(height, scene_key)
    scene = speed_scene(scene_key, camera, plan.frames)
    at_largest = size == plan.largest
    video = tmp / "clip.mp4" if at_largest and scene_key == plan.e2e_scene else None
    plan.steps.report(f"{label}: rendering")
    render_start = time.perf_counter()
    clip_frames = _render(scene, video)
    render_s = time.perf_counter() - render_start
    truths = [dict(f.truth or {}) for f in clip_frames]
    plan.steps.report(f"{label}: timing")
    series = time_pass(clip_frames, pipeline_factories(plan.base, scene, PIPELINES))
    pipelines = {key: pipeline_result(key, series[key], truths, plan.threads) for key in PIPELINES}
    del series
    single: dict[str, Any] = {}
    if plan.one_thread and (plan.one_thread != "largest" or at_largest):
        single = _one_thread_pass(plan, scene, clip_frames)
    if plan.memory_frames > 0 and at_largest:
        memory["tracemalloc_peak_mb"][label] = tracemalloc_peak_mb(
            clip_frames[: plan.memory_frames], speed_config(plan.base, scene, roi=True), camera
        )
    clip = {
        "label": label,
        "size": f"{height}p",
        "width": width,
        "height": height,
        "fx": focal,
        "scene": scene_key,
        "frames": plan.frames,
        "distance_m": scene.trajectory.near_m,
        "marker_px": focal * MARKER_M / scene.trajectory.near_m,
        "render_s": render_s,
        "frame_store_mb": sum(f.image.nbytes for f in clip_frames) / 1e6,
        "pipelines": pipelines,
        "one_thread": single,
        "ratio_opencv_over_roi": ratio_opencv_over_roi(pipelines["opencv"], pipelines["tracker_roi"]),
        "roi_vs_full": roi_check(pipelines["tracker_full"], pipelines["tracker_roi"], primary_kind(scene_key)),
    }
    if single:
        clip["ratio_opencv_over_roi_one_thread"] = ratio_opencv_over_roi(single["opencv"], single["tracker_roi"])
    del clip_frames
    release_freed_memory()
    return clip, (_EndToEndInput(label, video, scene, truths) if video is not None else None)


def _render(scene: SyntheticScene, video: Path | None) -> list[Frame]:
    """The clip's frames in memory; with ``video``, also encoded to that file as they are rendered."""
    if video is None:
        return render_clip(scene)
    from ...render.video import AnnotatedVideoWriter

    with AnnotatedVideoWriter(video, fps=scene.fps) as writer:
        return render_clip(scene, writer.write)


def _one_thread_pass(plan: _Plan, scene: SyntheticScene, clip_frames: Sequence[Frame]) -> dict[str, Any]:
    """The one-core comparison: the :data:`ONE_THREAD_PIPELINES` again with ``cv2.setNumThreads(1)``."""
    cv2.setNumThreads(1)
    try:
        series = time_pass(clip_frames, pipeline_factories(plan.base, scene, ONE_THREAD_PIPELINES))
    finally:
        cv2.setNumThreads(plan.threads)
    return {key: pipeline_timing(key, series[key], 1) for key in ONE_THREAD_PIPELINES}


def _end_to_end(plan: _Plan, e2e: _EndToEndInput, tmp: Path, memory: dict[str, Any]) -> dict[str, Any]:
    """The end-to-end run, with the peak RSS reset before it (the clips' frames freed)."""
    plan.steps.report(f"{e2e.label}: end to end")
    release_freed_memory()
    memory["peak_reset"] = reset_peak_rss()
    memory["rss_before_end_to_end_mb"] = rss_now_mb()
    result = run_end_to_end(e2e.video, e2e.scene, e2e.truths, plan.base, tmp)
    memory["rss_peak_end_to_end_mb"] = maxrss_mb()
    return result
