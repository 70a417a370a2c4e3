"""Speed benchmark: ``ar-anchor bench speed``.

Three pipelines are timed on the very same synthetic frames, rendered beforehand (rendering is never
timed) at 720p and 1080p with a moving camera:

``opencv``
    The plain loop a newcomer writes: ``cv2.aruco.ArucoDetector`` with OpenCV's default
    ``DetectorParameters`` on the grey image (the BGR -> grey conversion counts as detection), then
    ``cv2.solvePnP(..., SOLVEPNP_IPPE_SQUARE)`` per marker.
``tracker_full``
    :class:`~ar_anchor.track.tracker.Tracker` with ROI tracking off (full-frame detection every frame).
``tracker_roi``
    :class:`~ar_anchor.track.tracker.Tracker` with the default detector settings (ROI tracking on).

The pipelines take turns frame by frame (the order rotates every frame), so a background load that
comes and goes on a shared machine hits all of them alike. Every pipeline first runs a throw-away
instance over a few frames (warm-up); the measured instance then starts fresh at frame 0, so its
accuracy includes the filter's start. The default pass runs with OpenCV's own thread count; a second
pass repeats the loops with ``cv2.setNumThreads(1)`` (the one-core comparison).

Then one clip (1080p, one marker) goes through the whole chain a session runs, one stage after the
other: decode (the rendered frames encoded once to H.264 and read back by
:class:`~ar_anchor.sources.files.VideoFileSource`), track, overlay (the default cube on
``marker:*``) and rerun logging (default recording settings, to a temporary ``.rrd``).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import platform
import resource
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig, dictionary_id
from ..geometry import Pose, pose_errors
from ..sources.base import Frame
from ..sources.synthetic import PlacedBoard, PlacedMarker, SyntheticScene, SyntheticSource, Trajectory
from ..track.tracker import Tracker

__all__ = [
    "ONE_THREAD_PIPELINES",
    "PIPELINES",
    "SCENES",
    "SIZES",
    "render_clip",
    "run_speed_benchmark",
    "speed_config",
    "speed_markdown",
    "speed_scene",
    "write_speed_report",
]

SIZES: tuple[tuple[int, int, float], ...] = ((1280, 720, 1000.0), (1920, 1080, 1480.0))  # width, height, fx
SCENES: tuple[str, ...] = ("one", "eight", "board")
SCENE_LABELS = {"one": "one marker", "eight": "eight markers", "board": "2x2 board"}
PIPELINES: tuple[str, ...] = ("opencv", "tracker_full", "tracker_roi")
# the one-core comparison (cv2.setNumThreads(1)): the plain loop and the default tracker
ONE_THREAD_PIPELINES: tuple[str, ...] = ("opencv", "tracker_roi")
PIPELINE_LABELS = {"opencv": "opencv", "tracker_full": "tracker (full frame)", "tracker_roi": "tracker (ROI)"}
TRACKER_STAGES = ("detect_ms", "pose_ms", "filter_ms")
OPENCV_STAGES = ("detect_ms", "pose_ms")
E2E_STAGES = ("decode_ms", "track_ms", "render_ms", "log_ms")

MARKER_M = 0.05
NOISE = 2.0  # grey levels
BLUR = 0.6  # pixels
FPS = 30.0
PEAK_DEG_PER_S = 45.0  # the orbit's peak angular speed
WARMUP_FRAMES = 3
ROI_TOLERANCE = 0.10  # the ROI tracker's median errors may exceed the full-frame tracker's by this fraction ...
# ... plus this much: on these clean synthetic frames the trackers' median errors are a few thousandths of a
# degree and of a percent (a few micrometres), where 10 % is below what two runs on the same frames resolve
ROI_FLOOR = {"rot_median_deg": 0.001, "trans_median_pct": 0.001}
FLIP_DEG = 10.0
NOISE_SHIFT = 64  # pixels: the per-frame shift of the clip's noise field
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])  # board frame (y down, z into the wall) on the wall (y up, z out)


# ---------------------------------------------------------------------------- scenes


def speed_scene(kind: str, camera: CameraModel, frames: int, seed: int = 0) -> SyntheticScene:
    """One of the benchmark's clips: ``one`` marker, ``eight`` markers or a 2x2 ``board`` (all 5 cm
    markers), seen by a camera orbiting at 0.6-0.7 m (up to 45 deg/s), sensor noise 2, blur 0.6 px."""
    markers: tuple[PlacedMarker, ...] = ()
    boards: tuple[PlacedBoard, ...] = ()
    if kind == "one":
        markers = (PlacedMarker(0, MARKER_M, Pose.identity()),)
        near = 0.6  # 83 px wide at 720p (fx 1000), 123 px at 1080p (fx 1480)
    elif kind == "eight":
        # 4 x 2 on the wall, 16 cm apart: all in view at both sizes along the whole orbit
        centres = [np.array([-0.24 + 0.16 * (i % 4), 0.08 - 0.16 * (i // 4), 0.0]) for i in range(8)]
        markers = tuple(PlacedMarker(i, MARKER_M, Pose(np.zeros(3), centre)) for i, centre in enumerate(centres))
        near = 0.7  # 71 px at 720p, 106 px at 1080p
    elif kind == "board":
        board = BoardConfig(name="b", cols=2, rows=2, marker_length_m=MARKER_M, separation_m=0.01)
        width, height = board.size_m
        boards = (PlacedBoard(board, Pose.from_matrix(_FLIP_YZ, np.array([-width / 2, height / 2, 0.0]))),)
        near = 0.6
    else:
        raise ValueError(f"unknown speed scene {kind!r} (one of {', '.join(SCENES)})")
    seconds = frames / FPS
    azimuth = 35.0
    trajectory = Trajectory(
        kind="orbit",
        near_m=near,
        azimuth_deg=azimuth,
        elevation_deg=15.0,
        roll_deg=10.0,
        cycles=seconds * PEAK_DEG_PER_S / (2 * math.pi * azimuth),
    )
    return SyntheticScene(
        camera=camera,
        markers=markers,
        boards=boards,
        trajectory=trajectory,
        frames=frames,
        fps=FPS,
        seed=seed,
        noise_sigma=NOISE,
        blur_sigma=BLUR,
    )


def speed_config(base: TrackerConfig, scene: SyntheticScene, *, roi: bool) -> TrackerConfig:
    """``base`` set up for ``scene`` (dictionary, marker lengths, boards; filter on), ROI tracking on or off."""
    lengths = {m.marker_id: m.length_m for m in scene.markers}
    return dataclasses.replace(
        base,
        detector=dataclasses.replace(base.detector, dictionary=scene.dictionary, roi=roi),
        markers=dataclasses.replace(
            base.markers, length_m=MARKER_M, lengths_m=lengths, ids=tuple(sorted(lengths)) if lengths else ()
        ),
        boards=tuple(b.board for b in scene.boards),
        filter=dataclasses.replace(base.filter, enabled=True),
    )


def render_clip(
    scene: SyntheticScene, on_frame: Callable[[np.ndarray], None] | None = None, *, keep: bool = True
) -> list[Frame]:
    """All frames of ``scene`` with their ground truth, in memory.

    The sensor noise (Gaussian, ``scene.noise_sigma`` grey levels, rounded to whole levels) is added to
    the 8-bit render from one noise field drawn per clip, shifted by a random offset of up to
    :data:`NOISE_SHIFT` pixels each frame: the synthetic source's noise statistics at a small fraction of
    its cost (drawing 6 million Gaussian samples per 1080p frame would cost more than most pipelines
    measured here). ``on_frame`` sees every image (e.g. to encode the clip); ``keep=False`` returns no
    frames (a 1080p clip of 600 frames held in memory is 3.7 GB).
    """
    source = SyntheticSource(dataclasses.replace(scene, noise_sigma=0.0))
    width, height = scene.camera.size
    field = None
    if scene.noise_sigma > 0:
        rng = np.random.default_rng([scene.seed, 0x5EED])
        draws = rng.normal(0.0, scene.noise_sigma, size=(height + NOISE_SHIFT, 3 * (width + NOISE_SHIFT)))
        field = np.clip(np.rint(draws), -127, 127).astype(np.int8)
        del draws
    frames = []
    for index in range(scene.frames):
        camera_from_world = source.camera_from_world(index)
        image = source.render_view(camera_from_world)
        if field is not None:
            dy, dx = np.random.default_rng([scene.seed, index, 0x5EED]).integers(0, NOISE_SHIFT + 1, 2)
            noise = field[dy : dy + height, 3 * dx : 3 * (dx + width)]
            image = cv2.add(image.reshape(height, -1), noise, dtype=cv2.CV_8U).reshape(height, width, 3)
        if on_frame is not None:
            on_frame(image)
        timestamp_ns = int(round(index * 1e9 / scene.fps))
        if keep:
            frames.append(Frame(image, index, timestamp_ns, source.truth(camera_from_world)))
    return frames


# ---------------------------------------------------------------------------- pipelines


class _Loop(Protocol):
    def step(self, frame: Frame) -> tuple[dict[str, float], dict[str, Pose], dict[str, Pose]]: ...


class _OpenCVLoop:
    """The plain loop: full-frame ``detectMarkers`` with default parameters, ``solvePnP`` IPPE_SQUARE per marker."""

    def __init__(self, config: TrackerConfig, camera: CameraModel) -> None:
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(config.detector.dictionary))
        self.detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
        self.config = config
        self.k = np.asarray(camera.camera_matrix, dtype=np.float64)
        self.dist = camera.dist_or_none
        self._objects: dict[int, np.ndarray] = {}

    def _object(self, marker_id: int) -> np.ndarray:
        points = self._objects.get(marker_id)
        if points is None:
            h = self.config.marker_length(marker_id) / 2.0
            points = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]], np.float32)
            self._objects[marker_id] = points
        return points

    def step(self, frame: Frame) -> tuple[dict[str, float], dict[str, Pose], dict[str, Pose]]:
        t0 = time.perf_counter()
        grey = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self.detector.detectMarkers(grey)
        t1 = time.perf_counter()
        solved = []
        if ids is not None:
            for marker_id, marker_corners in zip(ids.reshape(-1).tolist(), corners):
                ok, rvec, tvec = cv2.solvePnP(
                    self._object(marker_id),
                    marker_corners.reshape(4, 2),
                    self.k,
                    self.dist,
                    flags=cv2.SOLVEPNP_IPPE_SQUARE,
                )
                if ok:
                    solved.append((marker_id, rvec, tvec))
        t2 = time.perf_counter()
        poses = {f"marker:{i}": Pose(rvec.reshape(3), tvec.reshape(3)) for i, rvec, tvec in solved}
        return {"detect_ms": (t1 - t0) * 1e3, "pose_ms": (t2 - t1) * 1e3}, poses, poses


class _TrackerLoop:
    def __init__(self, config: TrackerConfig, camera: CameraModel) -> None:
        self.tracker = Tracker(config, camera)

    def step(self, frame: Frame) -> tuple[dict[str, float], dict[str, Pose], dict[str, Pose]]:
        result = self.tracker.process(frame)
        outputs = {name: target.pose for name, target in result.targets.items()}
        raw = {name: target.raw for name, target in result.targets.items() if target.raw is not None}
        return dict(result.latency_ms), outputs, raw


@dataclass
class _Series:
    """One pipeline's per-frame records on one clip."""

    stages: dict[str, list[float]] = field(default_factory=dict)
    step_ms: list[float] = field(default_factory=list)  # the whole call, as seen from outside
    outputs: list[dict[str, Pose]] = field(default_factory=list)
    raw: list[dict[str, Pose]] = field(default_factory=list)


def _pipeline_factories(base: TrackerConfig, scene: SyntheticScene, keys: Sequence[str]) -> dict[str, Callable]:
    camera = scene.camera
    full = speed_config(base, scene, roi=False)
    roi = speed_config(base, scene, roi=True)
    makers: dict[str, Callable[[], _Loop]] = {
        "opencv": lambda: _OpenCVLoop(full, camera),
        "tracker_full": lambda: _TrackerLoop(full, camera),
        "tracker_roi": lambda: _TrackerLoop(roi, camera),
    }
    return {key: makers[key] for key in keys}


def _time_pass(frames: Sequence[Frame], factories: Mapping[str, Callable[[], _Loop]]) -> dict[str, _Series]:
    """Run every pipeline over ``frames``, taking turns frame by frame (rotating who goes first)."""
    for make in factories.values():  # warm-up on throw-away instances
        loop = make()
        for frame in frames[:WARMUP_FRAMES]:
            loop.step(frame)
    gc.collect()
    keys = list(factories)
    loops = {key: make() for key, make in factories.items()}
    series = {key: _Series() for key in keys}
    for index, frame in enumerate(frames):
        for offset in range(len(keys)):
            key = keys[(index + offset) % len(keys)]
            start = time.perf_counter()
            stages, outputs, raw = loops[key].step(frame)
            step_ms = (time.perf_counter() - start) * 1e3
            record = series[key]
            for stage, ms in stages.items():
                record.stages.setdefault(stage, []).append(ms)
            record.step_ms.append(step_ms)
            record.outputs.append(outputs)
            record.raw.append(raw)
    return series


# ---------------------------------------------------------------------------- statistics


def _stats(values: Sequence[float]) -> dict[str, float]:
    array = np.asarray(values, dtype=np.float64)
    if array.size == 0:
        return {"n": 0, "median": math.nan, "p95": math.nan, "mean": math.nan}
    return {
        "n": int(array.size),
        "median": float(np.median(array)),
        "p95": float(np.percentile(array, 95)),
        "mean": float(np.mean(array)),
    }


def _accuracy(outputs: Sequence[Mapping[str, Pose]], truths: Sequence[Mapping[str, Pose]], kind: str) -> dict:
    """Errors of every ``kind`` target (``marker`` / ``board``) in view, over all frames."""
    rot, trans = [], []
    in_view = 0
    for output, truth in zip(outputs, truths):
        for name, true_pose in truth.items():
            if not name.startswith(kind + ":"):
                continue
            in_view += 1
            pose = output.get(name)
            if pose is None:
                continue
            rotation, translation = pose_errors(pose, true_pose)
            rot.append(rotation)
            trans.append(translation)
    if in_view == 0:
        return {"in_view": 0}
    rot_a, trans_a = np.asarray(rot), np.asarray(trans)
    found = len(rot)
    return {
        "in_view": in_view,
        "found": found,
        "found_pct": 100.0 * found / in_view,
        "rot_median_deg": float(np.median(rot_a)) if found else math.nan,
        "rot_p95_deg": float(np.percentile(rot_a, 95)) if found else math.nan,
        "trans_median_pct": float(np.median(trans_a)) if found else math.nan,
        "trans_p95_pct": float(np.percentile(trans_a, 95)) if found else math.nan,
        "flipped_pct": 100.0 * float(np.mean(rot_a > FLIP_DEG)) if found else math.nan,
    }


def _timing(series: _Series, stages: Sequence[str]) -> dict[str, Any]:
    total = np.sum([series.stages.get(stage, [0.0] * len(series.step_ms)) for stage in stages], axis=0)
    total_stats = _stats(total)
    return {
        "stages": {stage: _stats(values) for stage, values in series.stages.items()},
        "total_stages": list(stages),
        "total_ms": total_stats,
        "fps": 1e3 / total_stats["mean"] if total_stats["mean"] > 0 else math.nan,
        "step_ms": _stats(series.step_ms),
    }


def _pipeline_result(key: str, series: _Series, truths: Sequence[Mapping[str, Pose]], threads: int) -> dict:
    stages = OPENCV_STAGES if key == "opencv" else TRACKER_STAGES
    out = {"label": PIPELINE_LABELS[key], "threads": threads, **_timing(series, stages)}
    out["accuracy"] = {kind: _accuracy(series.outputs, truths, kind) for kind in ("marker", "board")}
    out["accuracy_raw"] = {kind: _accuracy(series.raw, truths, kind) for kind in ("marker", "board")}
    return out


def _primary(scene_key: str) -> str:
    """The target kind a scene is about: its board, else its markers."""
    return "board" if scene_key == "board" else "marker"


def _roi_check(full: Mapping[str, Any], roi: Mapping[str, Any], kind: str) -> dict[str, Any]:
    a, b = full["accuracy"][kind], roi["accuracy"][kind]
    out: dict[str, Any] = {"target_kind": kind, "tolerance": ROI_TOLERANCE, "floor": dict(ROI_FLOOR)}
    within = strict = True
    for metric in ("rot_median_deg", "trans_median_pct"):
        full_value, roi_value = a.get(metric, math.nan), b.get(metric, math.nan)
        out[metric] = {"full": full_value, "roi": roi_value}
        finite = math.isfinite(full_value) and math.isfinite(roi_value)
        strict = strict and finite and roi_value <= full_value * (1 + ROI_TOLERANCE)
        within = within and finite and roi_value <= full_value * (1 + ROI_TOLERANCE) + ROI_FLOOR[metric]
    out["within"] = within  # 10 % plus the floor
    out["within_strict"] = strict  # 10 % alone
    return out


# ---------------------------------------------------------------------------- memory


def _maxrss_mb() -> float:
    """Peak resident set size of this process (since start, or since :func:`_reset_peak_rss`)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024  # bytes on macOS, KiB on Linux


def _rss_now_mb() -> float:
    """Current resident set size (Linux ``/proc/self/statm``; NaN elsewhere)."""
    try:
        with open("/proc/self/statm") as handle:
            pages = int(handle.read().split()[1])
    except (OSError, ValueError, IndexError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / (1024 * 1024)


def _release_freed_memory() -> None:
    """Hand freed heap memory back to the OS (glibc keeps big freed blocks, e.g. the clips' frames)."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_peak_rss() -> bool:
    """Reset the peak RSS (Linux >= 4.0: ``/proc/self/clear_refs`` 5 resets VmHWM and ``ru_maxrss``)."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
    except OSError:
        return False
    return True


def _tracemalloc_peak_mb(frames: Sequence[Frame], config: TrackerConfig, camera: CameraModel) -> float:
    """Peak of Python-side allocations (numpy arrays included, OpenCV's own buffers not) of a fresh tracker."""
    gc.collect()
    tracemalloc.start()
    try:
        tracker = Tracker(config, camera)
        for frame in frames:
            tracker.process(frame)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak / 1e6


# ---------------------------------------------------------------------------- end to end


def _end_to_end(
    video: Path, scene: SyntheticScene, truths: Sequence[Mapping[str, Pose]], base: TrackerConfig, tmp: Path
) -> dict[str, Any]:
    """decode -> track -> overlay -> rerun log, one frame after the other, with the ROI tracker."""
    from ..config import OverlayConfig, RecordingConfig
    from ..render.overlay import OverlayRenderer
    from ..sources.files import VideoFileSource
    from ..viz.recorder import RerunRecorder

    camera = scene.camera
    config = dataclasses.replace(
        speed_config(base, scene, roi=True),
        overlays=(OverlayConfig(target="marker:*", kind="cube"),),
        recording=RecordingConfig(),
    )
    tracker = Tracker(config, camera)
    renderer = OverlayRenderer(config, camera)
    rrd = tmp / "speed.rrd"
    recorder = RerunRecorder(rrd, camera=camera, settings=config.recording)
    recorder.overlay_models = renderer.models_for
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
    stats = {stage: _stats(values[keep]) for stage, values in times.items()}
    per_frame = np.sum([times[stage][keep] for stage in E2E_STAGES], axis=0)
    total = _stats(per_frame)
    return {
        "size": f"{camera.width}x{camera.height}",
        "scene": "one",
        "frames": decoded,
        "frames_excluded": keep.start or 0,
        "video_mb": video.stat().st_size / 1e6,
        "rrd_mb": rrd.stat().st_size / 1e6 if rrd.exists() else math.nan,
        "stages": stats,
        "tracker_detect_pose_filter_ms": _stats(tracker_ms[keep]),
        "total_ms": total,
        "fps": 1e3 / total["mean"] if total["mean"] > 0 else math.nan,
        "recorder_close_ms": close_ms,
        "accuracy": {kind: _accuracy(outputs, truths[:decoded], kind) for kind in ("marker", "board")},
    }


# ---------------------------------------------------------------------------- the run


def _machine() -> dict[str, Any]:
    processor = platform.processor()
    if not processor:
        try:
            with open("/proc/cpuinfo") as handle:
                names = (line.split(":", 1)[1].strip() for line in handle if line.startswith("model name"))
                processor = next(names, "")
        except OSError:
            processor = ""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "processor": processor or platform.machine(),
        "machine": platform.machine(),
        "system": f"{platform.system()} {platform.release()}",
        "cpu_count": os.cpu_count(),
        "usable_cpus": usable,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _clip_label(height: int, scene_key: str) -> str:
    return f"{height}p {SCENE_LABELS[scene_key]}"


def run_speed_benchmark(
    frames: int = 300,
    sizes: Sequence[tuple[int, int, float]] = SIZES,
    scenes: Sequence[str] = SCENES,
    *,
    config: TrackerConfig | None = None,
    one_thread: bool | str = True,
    end_to_end: bool = True,
    memory_frames: int = 30,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Time the three pipelines on every (size, scene) clip; return all numbers (see the module docstring).

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
    base = config or TrackerConfig()
    machine = _machine()
    threads = cv2.getNumThreads()
    rss_start = _maxrss_mb()
    largest = max(sizes, key=lambda s: s[0] * s[1])
    e2e_scene = "one" if "one" in scenes else scenes[0]
    steps = 2 * len(sizes) * len(scenes) + (1 if end_to_end else 0)
    step = 0

    def report(name: str) -> None:
        nonlocal step
        if progress is not None:
            progress(step, steps, name)
        step += 1

    clips: list[dict[str, Any]] = []
    memory: dict[str, Any] = {"rss_peak_at_start_mb": rss_start, "tracemalloc_peak_mb": {}}
    e2e_result: dict[str, Any] | None = None
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ar_anchor_speed_") as tmp_name:
        tmp = Path(tmp_name)
        video: Path | None = None
        e2e_truths: list[Mapping[str, Pose]] = []
        e2e_source_scene: SyntheticScene | None = None
        for width, height, focal in sizes:
            camera = CameraModel.from_fov(width, height, focal)
            for scene_key in scenes:
                label = _clip_label(height, scene_key)
                scene = speed_scene(scene_key, camera, frames)
                report(f"{label}: rendering")
                render_start = time.perf_counter()
                is_e2e = end_to_end and (width, height, focal) == tuple(largest) and scene_key == e2e_scene
                if is_e2e:
                    from ..render.video import AnnotatedVideoWriter

                    video = tmp / "clip.mp4"
                    with AnnotatedVideoWriter(video, fps=scene.fps) as writer:
                        clip_frames = render_clip(scene, writer.write)
                    e2e_truths = [dict(f.truth or {}) for f in clip_frames]
                    e2e_source_scene = scene
                else:
                    clip_frames = render_clip(scene)
                render_s = time.perf_counter() - render_start
                truths = [dict(f.truth or {}) for f in clip_frames]
                report(f"{label}: timing")
                series = _time_pass(clip_frames, _pipeline_factories(base, scene, PIPELINES))
                pipelines = {key: _pipeline_result(key, series[key], truths, threads) for key in PIPELINES}
                del series
                single: dict[str, Any] = {}
                if one_thread and (one_thread != "largest" or (width, height, focal) == tuple(largest)):
                    cv2.setNumThreads(1)
                    try:
                        series = _time_pass(clip_frames, _pipeline_factories(base, scene, ONE_THREAD_PIPELINES))
                    finally:
                        cv2.setNumThreads(threads)
                    single = {
                        key: {
                            "label": PIPELINE_LABELS[key],
                            "threads": 1,
                            **_timing(series[key], OPENCV_STAGES if key == "opencv" else TRACKER_STAGES),
                        }
                        for key in ONE_THREAD_PIPELINES
                    }
                    del series
                if memory_frames > 0 and (width, height, focal) == tuple(largest):
                    memory["tracemalloc_peak_mb"][label] = _tracemalloc_peak_mb(
                        clip_frames[:memory_frames], speed_config(base, scene, roi=True), camera
                    )
                clip = {
                    "label": label,
                    "size": f"{height}p",
                    "width": width,
                    "height": height,
                    "fx": focal,
                    "scene": scene_key,
                    "frames": frames,
                    "distance_m": scene.trajectory.near_m,
                    "marker_px": focal * MARKER_M / scene.trajectory.near_m,
                    "render_s": render_s,
                    "frame_store_mb": sum(f.image.nbytes for f in clip_frames) / 1e6,
                    "pipelines": pipelines,
                    "one_thread": single,
                    "ratio_opencv_over_roi": _ratio(pipelines["opencv"], pipelines["tracker_roi"]),
                    "roi_vs_full": _roi_check(pipelines["tracker_full"], pipelines["tracker_roi"], _primary(scene_key)),
                }
                if single:
                    clip["ratio_opencv_over_roi_one_thread"] = _ratio(single["opencv"], single["tracker_roi"])
                clips.append(clip)
                del clip_frames
                _release_freed_memory()
        memory["rss_peak_with_frames_mb"] = _maxrss_mb()
        memory["largest_frame_store_mb"] = max(c["frame_store_mb"] for c in clips)
        if end_to_end and video is not None and e2e_source_scene is not None:
            report(f"{_clip_label(largest[1], e2e_scene)}: end to end")
            _release_freed_memory()
            memory["peak_reset"] = _reset_peak_rss()
            memory["rss_before_end_to_end_mb"] = _rss_now_mb()
            e2e_result = _end_to_end(video, e2e_source_scene, e2e_truths, base, tmp)
            memory["rss_peak_end_to_end_mb"] = _maxrss_mb()
    wall = time.perf_counter() - start
    machine["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
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


def _ratio(opencv: Mapping[str, Any], roi: Mapping[str, Any]) -> float:
    a, b = opencv["total_ms"]["median"], roi["total_ms"]["median"]
    return a / b if b > 0 else math.nan


# ---------------------------------------------------------------------------- the report


def _f(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _g(value: Any, significant: int = 3) -> str:
    """Small errors with significant digits (0.000621, 0.0140, 0.833)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:#.{significant}g}".rstrip(".")


def speed_markdown(results: Mapping[str, Any], command: str) -> str:
    meta, clips, e2e, memory = results["meta"], results["clips"], results["end_to_end"], results["memory"]
    one_thread = any(c["one_thread"] for c in clips)
    load = meta.get("load_average_start")
    load_end = meta.get("load_average_end")
    lines = [
        "# Speed: plain OpenCV loop vs. the tracker (full frame and ROI)",
        "",
        f"Produced by `{command}` in {meta['wall_time_s']:.0f} s; {meta['frames_per_clip']} frames per clip, "
        f"the same frames for every pipeline.",
        "",
        "## Headline (default OpenCV threads: " + str(meta["opencv_threads"]) + ")",
        "",
        "Per-frame cost, median: opencv = grey conversion + `detectMarkers` + `solvePnP` per marker; tracker = "
        "detect + pose + filter (`FrameResult.latency_ms`). *speed-up* = opencv median / tracker (ROI) median "
        "(above 1: the tracker is faster). Errors: median over every target in view and every frame, of each "
        "pipeline's output pose (the tracker's filtered pose, opencv's solvePnP pose); boards for the board "
        "clip, markers otherwise. *ROI within 10 %*: the ROI tracker's median rotation and translation errors "
        f"are at most 110 % of the full-frame tracker's, plus {ROI_FLOOR['rot_median_deg']:g} deg / "
        f"{ROI_FLOOR['trans_median_pct']:g} % (a few micrometres: these clean frames give both trackers errors "
        "so small that 10 % of them is below what they resolve; the JSON also has the plain 10 % test).",
        "",
        "| clip | opencv | tracker full frame | tracker ROI | speed-up opencv / ROI | rot err med deg "
        "opencv / full / ROI | trans err med % opencv / full / ROI | ROI errors within 10 % of full frame |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for clip in clips:
        p = clip["pipelines"]
        kind = _primary(clip["scene"])
        check = clip["roi_vs_full"]

        def err(pipe: Mapping[str, Any], metric: str, kind: str = kind) -> Any:
            acc = pipe["accuracy"][kind] if pipe["accuracy"][kind].get("found") else pipe["accuracy"]["marker"]
            return acc.get(metric)

        rot = " / ".join(_g(err(p[key], "rot_median_deg")) for key in PIPELINES)
        trans = " / ".join(_g(err(p[key], "trans_median_pct")) for key in PIPELINES)
        verdict = "yes" if check["within"] else "no"
        verdict += (
            f" (ROI vs full: rot {_g(check['rot_median_deg']['roi'])} vs {_g(check['rot_median_deg']['full'])} "
            f"deg, trans {_g(check['trans_median_pct']['roi'])} vs {_g(check['trans_median_pct']['full'])} %"
            + ("" if check["within_strict"] == check["within"] else "; 10 % alone: no")
            + ")"
        )
        lines.append(
            f"| {clip['label']} | {_f(p['opencv']['total_ms']['median'])} ms "
            f"| {_f(p['tracker_full']['total_ms']['median'])} ms | {_f(p['tracker_roi']['total_ms']['median'])} ms "
            f"| {_f(clip['ratio_opencv_over_roi'])}x | {rot} | {trans} | {verdict} |"
        )
    if any(c["scene"] == "board" for c in clips):
        lines += [
            "",
            "Board clip: opencv has no board pose, so its errors there are its per-marker errors (the board's "
            "four markers, each on its own); the trackers' are the board pose's.",
        ]
    lines += [
        "",
        "## Stages (default threads)",
        "",
        "ms per frame, median / p95 / mean. *fps*: 1000 / mean of the total (that part of the pipeline alone).",
        "",
        "| clip | pipeline | detect | pose | filter | total median / p95 | fps |",
        "|---|---|---|---|---|---|---|",
    ]
    for clip in clips:
        for key in PIPELINES:
            pipe = clip["pipelines"][key]

            def trip(stage: str, pipe: Mapping[str, Any] = pipe) -> str:
                s = pipe["stages"].get(stage)
                return " / ".join(_f(s[k]) for k in ("median", "p95", "mean")) if s else "-"

            total = pipe["total_ms"]
            lines.append(
                f"| {clip['label']} | {pipe['label']} | {trip('detect_ms')} | {trip('pose_ms')} | {trip('filter_ms')} "
                f"| {_f(total['median'])} / {_f(total['p95'])} | {_f(pipe['fps'], 0)} |"
            )
    lines += [
        "",
        "## Accuracy against ground truth",
        "",
        "Over all frames (from frame 0: the tracker's filter start included) and every target in view. *found*: "
        "share of (frame, target in view) pairs with an output pose (the tracker also outputs predicted poses "
        "through short gaps). Markers: each marker's own pose (board members too); board: the board's pose.",
        "",
        "| clip | pipeline | markers found % | marker rot med / p95 deg | marker trans med / p95 % "
        "| board found % | board rot med / p95 deg | board trans med / p95 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for clip in clips:
        for key in PIPELINES:
            pipe = clip["pipelines"][key]
            m, b = pipe["accuracy"]["marker"], pipe["accuracy"]["board"]

            def pair(acc: Mapping[str, Any], a: str, b: str) -> str:
                return f"{_g(acc.get(a))} / {_g(acc.get(b))}" if acc.get("found") else "-"

            lines.append(
                f"| {clip['label']} | {pipe['label']} | {_f(m.get('found_pct'), 1)} "
                f"| {pair(m, 'rot_median_deg', 'rot_p95_deg')} | {pair(m, 'trans_median_pct', 'trans_p95_pct')} "
                f"| {_f(b.get('found_pct'), 1) if b.get('in_view') else '-'} "
                f"| {pair(b, 'rot_median_deg', 'rot_p95_deg')} | {pair(b, 'trans_median_pct', 'trans_p95_pct')} |"
            )
    if one_thread:
        lines += [
            "",
            "## One core: `cv2.setNumThreads(1)`",
            "",
            f"The plain loop and the default tracker (ROI) again, on the same frames, with OpenCV limited to one "
            f"thread (restored to {meta['opencv_threads']} afterwards). Total ms per frame, median / p95; fps = "
            "1000 / mean; *slow-down*: one-thread median / default-threads median."
            + ("" if all(c["one_thread"] for c in clips) else " Run at the largest size only."),
            "",
            "| clip | "
            + " | ".join(PIPELINE_LABELS[key] for key in ONE_THREAD_PIPELINES)
            + " | speed-up opencv / ROI | fps "
            + " / ".join(PIPELINE_LABELS[key] for key in ONE_THREAD_PIPELINES)
            + " | slow-down vs default threads "
            + " / ".join(PIPELINE_LABELS[key] for key in ONE_THREAD_PIPELINES)
            + " |",
            "|---|" + "---|" * (len(ONE_THREAD_PIPELINES) + 3),
        ]
        for clip in clips:
            single = clip["one_thread"]
            if not single:
                continue
            keys = [key for key in ONE_THREAD_PIPELINES if key in single]
            totals = " | ".join(
                f"{_f(single[key]['total_ms']['median'])} / {_f(single[key]['total_ms']['p95'])} ms" for key in keys
            )
            fps = " / ".join(_f(single[key]["fps"], 0) for key in keys)
            slow = " / ".join(
                _f(single[key]["total_ms"]["median"] / clip["pipelines"][key]["total_ms"]["median"])
                if clip["pipelines"][key]["total_ms"]["median"] > 0
                else "-"
                for key in keys
            )
            lines.append(
                f"| {clip['label']} | {totals} | {_f(clip.get('ratio_opencv_over_roi_one_thread'))}x | {fps} "
                f"| {slow}x |"
            )
    if e2e:
        lines += [
            "",
            f"## End to end: {e2e['size']} one marker, tracker (ROI), default threads",
            "",
            f"Each frame goes through decode -> track -> overlay -> log, one stage after the other. *decode*: "
            f"`VideoFileSource` reading the clip encoded once to H.264 ({_f(e2e['video_mb'], 1)} MB); *track*: "
            f"`Tracker.process`; *render*: `OverlayRenderer.annotate` (cube on `marker:*`); *log*: "
            f"`RerunRecorder.log_frame` (JPEG image and overlay, detections, 3D scene, metrics; default "
            f"recording settings) to a temporary .rrd ({_f(e2e['rrd_mb'], 1)} MB). The first "
            f"{e2e['frames_excluded']} of {e2e['frames']} frames are left out (first-frame costs).",
            "",
            "| stage | median ms | p95 ms | mean ms |",
            "|---|---|---|---|",
        ]
        names = {"decode_ms": "decode", "track_ms": "track", "render_ms": "render (overlay)", "log_ms": "log (rerun)"}
        for stage in E2E_STAGES:
            s = e2e["stages"][stage]
            lines.append(f"| {names[stage]} | {_f(s['median'])} | {_f(s['p95'])} | {_f(s['mean'])} |")
        t = e2e["total_ms"]
        lines += [
            f"| **sum per frame** | **{_f(t['median'])}** | **{_f(t['p95'])}** | **{_f(t['mean'])}** |",
            "",
            f"Sequential end-to-end throughput: **{_f(e2e['fps'], 1)} fps** (1000 / mean sum). Of *track*, "
            f"detect + pose + filter took {_f(e2e['tracker_detect_pose_filter_ms']['median'])} ms (median). "
            f"Closing the recording (flush) took {_f(e2e['recorder_close_ms'], 0)} ms once at the end. rerun "
            "encodes and writes in its own threads, so *log* is the caller's share only. Accuracy on the decoded "
            f"frames: rot {_g(e2e['accuracy']['marker'].get('rot_median_deg'))} deg, trans "
            f"{_g(e2e['accuracy']['marker'].get('trans_median_pct'))} % (median).",
        ]
    lines += ["", "## Memory", ""]
    lines.append(f"- peak RSS at the start of the run: {_f(memory['rss_peak_at_start_mb'], 0)} MB")
    lines.append(
        f"- peak RSS while rendering and timing (one clip's frames held in memory, up to "
        f"{_f(memory.get('largest_frame_store_mb'), 0)} MB): {_f(memory.get('rss_peak_with_frames_mb'), 0)} MB"
    )
    if "rss_peak_end_to_end_mb" in memory:
        since = (
            "peak since it was reset before the end-to-end run"
            if memory.get("peak_reset")
            else "peak since the process started (could not reset it)"
        )
        lines.append(
            f"- peak RSS of the end-to-end run (frames streamed, not held; {since}): "
            f"{_f(memory['rss_peak_end_to_end_mb'], 0)} MB (RSS when it started, the clips' frames freed: "
            f"{_f(memory.get('rss_before_end_to_end_mb'), 0)} MB)"
        )
    for label, mb in memory.get("tracemalloc_peak_mb", {}).items():
        lines.append(f"- tracemalloc peak of a fresh tracker (ROI) over the first frames of {label}: {_f(mb, 1)} MB")
    lines += [
        "",
        "## How measured",
        "",
        f"Machine: {meta['processor']} ({meta['machine']}, {meta['system']}), `os.cpu_count()` {meta['cpu_count']} "
        f"({meta['usable_cpus']} usable), Python {meta['python']}, NumPy {meta['numpy']}, OpenCV {meta['opencv']}, "
        f"`cv2.getNumThreads()` {meta['opencv_threads']}. Load average at start "
        f"{' / '.join(_f(x) for x in load) if load else '-'}, at the end "
        f"{' / '.join(_f(x) for x in load_end) if load_end else '-'} (other work on the machine slows every "
        "pipeline alike: they take turns frame by frame).",
        "",
        f"Clips: synthetic ({meta['frames_per_clip']} frames at 30 fps, rendered before any timing, kept in memory), "
        "5 cm DICT_4X4_50 markers on a cluttered wall, sensor noise "
        f"{_f(meta['noise'], 0)} grey levels (one Gaussian field per clip, shifted at random by up to "
        f"{NOISE_SHIFT} px each frame), blur {_f(meta['blur_px'], 1)} px; the camera orbits the markers "
        "(azimuth +-35 deg, elevation +-15 deg, roll +-10 deg, up to 45 deg/s) at a constant distance: "
        + "; ".join(
            f"{SCENE_LABELS[c['scene']]} {_f(c['distance_m'], 1)} m ({_f(c['marker_px'], 0)} px markers at {c['size']})"
            for c in clips
        )
        + ". The 2x2 board: 5 cm markers, 1 cm apart. 720p: fx 1000 px; 1080p: fx 1480 px; no lens distortion.",
        "",
        "Pipelines: *opencv* is `ArucoDetector(dictionary, DetectorParameters())` on the grey image (conversion "
        "counted in detect) and `solvePnP(SOLVEPNP_IPPE_SQUARE)` per detected marker (pose); no filter, no "
        "corner refinement. The *tracker* runs its configured pipeline (edge-fitted corners, both IPPE "
        "solutions, boards, flip-resolving filter) with ROI tracking off (*full frame*) or on (*ROI*, the "
        "default); its stage times are its own `latency_ms`. The three pipelines take turns on each frame (the "
        "one going first rotates), each on its own state; each first warms up on a throw-away instance over "
        f"{meta['warmup_frames']} frames. Time: `time.perf_counter`. The *default threads* numbers run with "
        f"OpenCV's own thread pool ({meta['opencv_threads']} threads); the *one core* numbers repeat the opencv "
        "and tracker (ROI) loops after `cv2.setNumThreads(1)` (only OpenCV's threads are limited, not NumPy's "
        "BLAS). Nothing else in the process runs during timing; the machine itself may be shared (load above).",
        "",
    ]
    return "\n".join(lines)


def write_speed_report(
    out_dir: Path,
    quick: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench speed",
    *,
    config: TrackerConfig | None = None,
    frames: int | None = None,
    sizes: Sequence[tuple[int, int, float]] = SIZES,
    scenes: Sequence[str] = SCENES,
    one_thread: bool | str | None = None,
    end_to_end: bool = True,
) -> dict[str, Any]:
    """Run the benchmark, write ``speed.md`` and ``speed.json`` to ``out_dir``, return the results.

    ``quick``: 90 frames per clip instead of 300, the one-core pass at the largest size only. ``frames``,
    ``sizes``, ``scenes``, ``one_thread``, ``end_to_end``: see :func:`run_speed_benchmark`.
    """
    frames = frames or (90 if quick else 300)
    results = run_speed_benchmark(
        frames,
        sizes,
        scenes,
        config=config,
        one_thread=("largest" if quick else True) if one_thread is None else one_thread,
        end_to_end=end_to_end,
        memory_frames=min(frames, 10 if quick else 30),
        progress=progress,
    )
    results["meta"]["command"] = command
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "speed.json").write_text(json.dumps(_jsonable(results), indent=2) + "\n")
    (out_dir / "speed.md").write_text(speed_markdown(results, command))
    return results


def _jsonable(value: Any) -> Any:
    """NaN and infinities as null (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value
