"""``ar-anchor bench speed --stages``: every (size, scene) clip rendered, timed in-process and scored, then the
end-to-end chain and the memory figures."""

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
    loop_factories,
    pipeline_result,
    pipeline_timing,
    primary_kind,
    ratio_opencv_over_roi,
    ratios_tracker_over_plain,
    roi_check,
    time_pass,
)
from .memory import loop_peak_mb, maxrss_mb, release_freed_memory, reset_peak_rss, rss_now_mb
from .real_clip import CHESSBOARD, RealClip, load_chessboard
from .scenes import (
    BLUR,
    EXTRA_CLIPS,
    FIFTY,
    FIFTY_SIZE,
    MARKER_M,
    NOISE,
    SCENES,
    SIZES,
    clip_label,
    render_clip,
    speed_config,
    speed_scene,
)

__all__ = ["run_stages_benchmark"]

Size = tuple[int, int, float]  # width, height, fx


def run_stages_benchmark(
    frames: int = 300,
    sizes: Sequence[Size] = SIZES,
    scenes: Sequence[str] = SCENES,
    *,
    extra: Sequence[str] = EXTRA_CLIPS,
    config: TrackerConfig | None = None,
    one_thread: bool | str = True,
    end_to_end: bool = True,
    memory_frames: int = 30,
    realdata: Path | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Time the pipelines on every (size, scene) clip and the ``extra`` clips; return all numbers (see
    :mod:`ar_anchor.bench.speed`).

    ``sizes``: (width, height, fx) per clip size. ``scenes``: any of :data:`SCENES`. ``extra``: any of
    :data:`EXTRA_CLIPS` (``50markers`` at 720p; ``chessboard``, the real video, at most ``frames`` of it,
    from ``realdata`` (default ``$AR_ANCHOR_REALDATA`` or ../shared/realdata), skipped with a note in
    ``results["notes"]`` when absent). ``one_thread``: repeat the opencv and tracker (ROI) loops with
    ``cv2.setNumThreads(1)`` (``"largest"``: at the largest size only). ``end_to_end``: the decode -> track
    -> overlay -> log chain on the largest size's one-marker clip (else its first scene; none without
    scenes). ``memory_frames``: frames of each pipeline's tracemalloc pass on every clip (0: none).
    """
    _check_choices(frames, scenes, extra)
    machine = machine_info()
    base = config or TrackerConfig()
    real: RealClip | str | None = None
    if CHESSBOARD in extra:  # decoded first: the note, and the step count, depend on it
        real = load_chessboard(base, frames, realdata)
    notes = [real] if isinstance(real, str) else []
    grid = [(tuple(size), key) for size in sizes for key in scenes]
    fifty = FIFTY in extra
    plan = _Plan(
        base=base,
        frames=frames,
        largest=tuple(max(sizes, key=lambda s: s[0] * s[1])) if sizes else FIFTY_SIZE,
        e2e_scene=("one" if "one" in scenes else scenes[0]) if end_to_end and scenes and sizes else None,
        one_thread=one_thread,
        memory_frames=memory_frames,
        threads=cv2.getNumThreads(),
        steps=_Steps(
            2 * (len(grid) + fifty) + isinstance(real, RealClip) + (1 if end_to_end and grid else 0), progress
        ),
    )
    memory: dict[str, Any] = {"rss_peak_at_start_mb": maxrss_mb(), "tracemalloc_peak_mb": {}}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ar_anchor_speed_") as tmp_name:
        tmp = Path(tmp_name)
        clips: list[dict[str, Any]] = []
        e2e_input: _EndToEndInput | None = None
        for size, scene_key in grid + ([(FIFTY_SIZE, FIFTY)] if fifty else []):
            clip, e2e_clip = _synthetic_clip(plan, size, scene_key, tmp, memory)
            clips.append(clip)
            e2e_input = e2e_clip or e2e_input
        if isinstance(real, RealClip):
            clips.append(_real_clip(plan, real, memory))
            del real
            release_freed_memory()
        memory["rss_peak_with_frames_mb"] = maxrss_mb()
        memory["largest_frame_store_mb"] = max((c["frame_store_mb"] for c in clips), default=0.0)
        e2e_result = _end_to_end(plan, e2e_input, tmp, memory) if e2e_input is not None else None
    wall = time.perf_counter() - start
    machine["load_average_end"] = load_average()
    return {
        "meta": _meta(frames, sizes, scenes, extra, memory_frames, wall, machine),
        "notes": notes,
        "clips": clips,
        "end_to_end": e2e_result,
        "memory": memory,
    }


def _meta(
    frames: int,
    sizes: Sequence[Size],
    scenes: Sequence[str],
    extra: Sequence[str],
    memory_frames: int,
    wall: float,
    machine: dict[str, Any],
) -> dict[str, Any]:
    """The results' ``meta``: what was asked for, the render settings, the wall time and the machine."""
    return {
        "frames_per_clip": frames,
        "sizes": [list(s) for s in sizes],
        "scenes": list(scenes),
        "extra_clips": list(extra),
        "warmup_frames": WARMUP_FRAMES,
        "memory_frames": memory_frames,
        "noise": NOISE,
        "blur_px": BLUR,
        "wall_time_s": wall,
        **machine,
    }


def _check_choices(frames: int, scenes: Sequence[str], extra: Sequence[str]) -> None:
    """:class:`ValueError` for a frame count below one or an unknown scene or clip name."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    for key in scenes:
        if key not in SCENES:
            raise ValueError(f"unknown speed scene {key!r} (one of {', '.join(SCENES)})")
    for key in extra:
        if key not in EXTRA_CLIPS:
            raise ValueError(f"unknown speed clip {key!r} (one of {', '.join(EXTRA_CLIPS)})")


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


@dataclass(frozen=True)
class _ClipInput:
    """One clip ready to time: its frames in memory (with truth, or empty truths for real video), the
    camera, the tracker configs (ROI off and on) and its fixed fields in the report."""

    label: str
    scene_key: str
    frames: list[Frame]
    truths: list[Mapping[str, Pose]]
    camera: CameraModel
    full: TrackerConfig
    roi: TrackerConfig
    has_truth: bool
    record: dict[str, Any]  # fields of the clip's record known before timing


def _synthetic_clip(
    plan: _Plan, size: Size, scene_key: str, tmp: Path, memory: dict[str, Any]
) -> tuple[dict[str, Any], _EndToEndInput | None]:
    """Render one synthetic clip and time it; its record, and the end-to-end input when this is its clip."""
    width, height, focal = size
    camera = CameraModel.from_fov(width, height, focal)
    label = clip_label(height, scene_key)
    scene = speed_scene(scene_key, camera, plan.frames)
    video = tmp / "clip.mp4" if size == plan.largest and scene_key == plan.e2e_scene else None
    plan.steps.report(f"{label}: rendering")
    render_start = time.perf_counter()
    clip_frames = _render(scene, video)
    render_s = time.perf_counter() - render_start
    truths = [dict(f.truth or {}) for f in clip_frames]
    length_m = scene.markers[0].length_m if scene.markers else MARKER_M
    record = {
        "size": f"{height}p",
        "width": width,
        "height": height,
        "fx": focal,
        "source": "synthetic",
        "distance_m": scene.trajectory.near_m,
        "far_m": scene.trajectory.far_m if scene.trajectory.kind == "handheld" else scene.trajectory.near_m,
        "marker_m": length_m,
        "marker_px": focal * length_m / scene.trajectory.near_m,
        "markers_in_scene": len(scene.markers) + sum(len(b.board.marker_ids) for b in scene.boards),
        "render_s": render_s,
    }
    clip_input = _ClipInput(
        label,
        scene_key,
        clip_frames,
        truths,
        camera,
        speed_config(plan.base, scene, roi=False),
        speed_config(plan.base, scene, roi=True),
        True,
        record,
    )
    del clip_frames
    clip = _measure_clip(plan, clip_input, memory)
    return clip, (_EndToEndInput(label, video, scene, truths) if video is not None else None)


def _real_clip(plan: _Plan, real: RealClip, memory: dict[str, Any]) -> dict[str, Any]:
    """Time the pipelines on the decoded real video (no truth)."""
    width, height = real.camera.size
    record = {
        "size": f"{height}p",
        "width": width,
        "height": height,
        "fx": float(real.camera.camera_matrix[0, 0]),
        "source": "real",
        "video": real.video.name,
        "marker_m": real.full.markers.length_m,
        "dictionary": real.full.detector.dictionary,
    }
    frames = list(real.frames)
    clip_input = _ClipInput(
        f"{height}p {real.video.name}",
        CHESSBOARD,
        frames,
        [{} for _ in frames],
        real.camera,
        real.full,
        real.roi,
        False,
        record,
    )
    return _measure_clip(plan, clip_input, memory)


def _measure_clip(plan: _Plan, clip: _ClipInput, memory: dict[str, Any]) -> dict[str, Any]:
    """Time the pipelines on one clip's frames (and the one-core pass, and each pipeline's tracemalloc
    peak); the clip's record."""
    plan.steps.report(f"{clip.label}: timing")
    factories = loop_factories(clip.full, clip.roi, clip.camera, PIPELINES)
    series = time_pass(clip.frames, factories)
    pipelines = {key: pipeline_result(key, series[key], clip.truths, plan.threads) for key in PIPELINES}
    del series
    at_largest = (clip.record["width"], clip.record["height"], clip.record["fx"]) == plan.largest
    single: dict[str, Any] = {}
    if plan.one_thread and (plan.one_thread != "largest" or at_largest):
        single = _one_thread_pass(plan, clip)
    peaks: dict[str, float] = {}
    if plan.memory_frames > 0:
        peaks = {key: loop_peak_mb(make, clip.frames[: plan.memory_frames]) for key, make in factories.items()}
        memory["tracemalloc_peak_mb"][clip.label] = peaks["tracker_roi"]
    out = {
        "label": clip.label,
        "scene": clip.scene_key,
        "frames": len(clip.frames),
        **clip.record,
        "has_truth": clip.has_truth,
        "frame_store_mb": sum(f.image.nbytes for f in clip.frames) / 1e6,
        "pipelines": pipelines,
        "one_thread": single,
        "peak_mb": peaks,
        "ratio_opencv_over_roi": ratio_opencv_over_roi(pipelines["opencv"], pipelines["tracker_roi"]),
        "ratios": ratios_tracker_over_plain(pipelines),
        "roi_vs_full": roi_check(pipelines["tracker_full"], pipelines["tracker_roi"], primary_kind(clip.scene_key)),
    }
    if single:
        out["ratio_opencv_over_roi_one_thread"] = ratio_opencv_over_roi(single["opencv"], single["tracker_roi"])
    clip.frames.clear()
    release_freed_memory()
    return out


def _render(scene: SyntheticScene, video: Path | None) -> list[Frame]:
    """The clip's frames in memory; with ``video``, also encoded to that file as they are rendered."""
    if video is None:
        return render_clip(scene)
    from ...render.video import AnnotatedVideoWriter

    with AnnotatedVideoWriter(video, fps=scene.fps) as writer:
        return render_clip(scene, writer.write)


def _one_thread_pass(plan: _Plan, clip: _ClipInput) -> dict[str, Any]:
    """The one-core comparison: the :data:`ONE_THREAD_PIPELINES` again with ``cv2.setNumThreads(1)``."""
    cv2.setNumThreads(1)
    try:
        series = time_pass(clip.frames, loop_factories(clip.full, clip.roi, clip.camera, ONE_THREAD_PIPELINES))
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
