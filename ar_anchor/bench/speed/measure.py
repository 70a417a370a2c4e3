"""The three pipelines timed on the same frames, taking turns, and their statistics: stage times,
accuracy against truth, and the ROI tracker's errors against the full-frame tracker's."""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from ...camera import CameraModel
from ...config import TrackerConfig, dictionary_id
from ...geometry import Pose, pose_errors
from ...sources.base import Frame
from ...synthetic import SyntheticScene
from ...targets import TargetId
from ...track.tracker import Tracker
from ..report import FLIP_DEG
from .scenes import speed_config

__all__ = [
    "ONE_THREAD_PIPELINES",
    "OPENCV_STAGES",
    "PIPELINES",
    "PIPELINE_LABELS",
    "PLAIN_PIPELINES",
    "ROI_FLOOR",
    "ROI_TOLERANCE",
    "TRACKER_PIPELINES",
    "TRACKER_STAGES",
    "WARMUP_FRAMES",
    "accuracy",
    "found_stats",
    "loop_factories",
    "per_marker_ms",
    "pipeline_factories",
    "pipeline_result",
    "pipeline_timing",
    "primary_kind",
    "ratio_opencv_over_roi",
    "ratios_tracker_over_plain",
    "roi_check",
    "summary_stats",
    "time_pass",
]

PIPELINES: tuple[str, ...] = ("opencv", "opencv_subpix", "tracker_full", "tracker_roi")
PLAIN_PIPELINES: tuple[str, ...] = ("opencv", "opencv_subpix")
TRACKER_PIPELINES: tuple[str, ...] = ("tracker_full", "tracker_roi")
# the one-core comparison (cv2.setNumThreads(1)): the plain loop and the default tracker
ONE_THREAD_PIPELINES: tuple[str, ...] = ("opencv", "tracker_roi")
PIPELINE_LABELS = {
    "opencv": "opencv",
    "opencv_subpix": "opencv SUBPIX",
    "tracker_full": "tracker (full frame)",
    "tracker_roi": "tracker (ROI)",
}
TRACKER_STAGES = ("detect_ms", "pose_ms", "filter_ms")
OPENCV_STAGES = ("detect_ms", "pose_ms")
WARMUP_FRAMES = 3
ROI_TOLERANCE = 0.10  # the ROI tracker's median errors may exceed the full-frame tracker's by this fraction ...
# ... plus this much: on these clean synthetic frames the trackers' median errors are a few thousandths of a
# degree and of a percent (a few micrometres), where 10 % is below what two runs on the same frames resolve
ROI_FLOOR = {"rot_median_deg": 0.001, "trans_median_pct": 0.001}


Step = tuple[dict[str, float], dict[str, Pose], dict[str, Pose], int]  # stage ms, outputs, raw, markers found


class _Loop(Protocol):
    def step(self, frame: Frame) -> Step: ...


class _OpenCVLoop:
    """The plain loop: full-frame ``detectMarkers`` with OpenCV's default ``DetectorParameters`` (``subpix``:
    with ``cornerRefinementMethod = CORNER_REFINE_SUBPIX``), ``solvePnPGeneric`` IPPE_SQUARE per marker
    (its first, lower-error solution)."""

    def __init__(self, config: TrackerConfig, camera: CameraModel, *, subpix: bool = False) -> None:
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(config.detector.dictionary))
        parameters = cv2.aruco.DetectorParameters()
        if subpix:
            parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self.detector = cv2.aruco.ArucoDetector(dictionary, parameters)
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

    def step(self, frame: Frame) -> Step:
        t0 = time.perf_counter()
        grey = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY) if frame.image.ndim == 3 else frame.image
        corners, ids, _ = self.detector.detectMarkers(grey)
        t1 = time.perf_counter()
        solved = []
        found = 0 if ids is None else len(ids)
        if ids is not None:
            for marker_id, marker_corners in zip(ids.reshape(-1).tolist(), corners):
                count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                    self._object(marker_id),
                    marker_corners.reshape(4, 2),
                    self.k,
                    self.dist,
                    flags=cv2.SOLVEPNP_IPPE_SQUARE,
                )
                if count:
                    solved.append((marker_id, rvecs[0], tvecs[0]))
        t2 = time.perf_counter()
        poses = {TargetId.marker(i): Pose(rvec.reshape(3), tvec.reshape(3)) for i, rvec, tvec in solved}
        return {"detect_ms": (t1 - t0) * 1e3, "pose_ms": (t2 - t1) * 1e3}, poses, poses, found


class _TrackerLoop:
    def __init__(self, config: TrackerConfig, camera: CameraModel) -> None:
        self.tracker = Tracker(config, camera)

    def step(self, frame: Frame) -> Step:
        result = self.tracker.process(frame)
        outputs = {name: target.pose for name, target in result.targets.items()}
        raw = {name: target.raw for name, target in result.targets.items() if target.raw is not None}
        return dict(result.latency_ms), outputs, raw, len(result.detections)


@dataclass
class _Series:
    """One pipeline's per-frame records on one clip."""

    stages: dict[str, list[float]] = field(default_factory=dict)
    step_ms: list[float] = field(default_factory=list)  # the whole call, as seen from outside
    outputs: list[dict[str, Pose]] = field(default_factory=list)
    raw: list[dict[str, Pose]] = field(default_factory=list)
    found: list[int] = field(default_factory=list)  # markers detected per frame


def pipeline_factories(base: TrackerConfig, scene: SyntheticScene, keys: Sequence[str]) -> dict[str, Callable]:
    """A maker of a fresh loop per pipeline key (``keys`` of :data:`PIPELINES`), set up for ``scene``."""
    full = speed_config(base, scene, roi=False)
    return loop_factories(full, speed_config(base, scene, roi=True), scene.camera, keys)


def loop_factories(
    full: TrackerConfig, roi: TrackerConfig, camera: CameraModel, keys: Sequence[str]
) -> dict[str, Callable]:
    """A maker of a fresh loop per pipeline key: the trackers with ``full`` (ROI off) and ``roi`` (ROI on),
    the plain loops with ``full``'s dictionary and marker lengths."""
    makers: dict[str, Callable[[], _Loop]] = {
        "opencv": lambda: _OpenCVLoop(full, camera),
        "opencv_subpix": lambda: _OpenCVLoop(full, camera, subpix=True),
        "tracker_full": lambda: _TrackerLoop(full, camera),
        "tracker_roi": lambda: _TrackerLoop(roi, camera),
    }
    return {key: makers[key] for key in keys}


def time_pass(frames: Sequence[Frame], factories: Mapping[str, Callable[[], _Loop]]) -> dict[str, _Series]:
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
            stages, outputs, raw, found = loops[key].step(frame)
            step_ms = (time.perf_counter() - start) * 1e3
            record = series[key]
            for stage in stages.keys() | record.stages.keys():
                # a stage a frame skipped (the tracker's repeated frames: detection only) took 0 ms there
                record.stages.setdefault(stage, [0.0] * len(record.step_ms)).append(stages.get(stage, 0.0))
            record.step_ms.append(step_ms)
            record.outputs.append(outputs)
            record.raw.append(raw)
            record.found.append(found)
    return series


# ---------------------------------------------------------------------------- statistics


def summary_stats(values: Sequence[float]) -> dict[str, float]:
    """Count, median, p95 and mean (NaN without values)."""
    array = np.asarray(values, dtype=np.float64)
    if array.size == 0:
        return {"n": 0, "median": math.nan, "p95": math.nan, "mean": math.nan}
    return {
        "n": int(array.size),
        "median": float(np.median(array)),
        "p95": float(np.percentile(array, 95)),
        "mean": float(np.mean(array)),
    }


def accuracy(outputs: Sequence[Mapping[str, Pose]], truths: Sequence[Mapping[str, Pose]], kind: str) -> dict:
    """Errors of every ``kind`` target (``marker`` / ``board``) in view, over all frames."""
    rot, trans = [], []
    in_view = 0
    for output, truth in zip(outputs, truths):
        for name, true_pose in truth.items():
            if TargetId.parse(name).kind != kind:
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


def found_stats(found: Sequence[int]) -> dict[str, float]:
    """Markers found per frame: mean, median, min and max (NaN without frames)."""
    array = np.asarray(found, dtype=np.float64)
    if array.size == 0:
        return {"mean": math.nan, "median": math.nan, "min": math.nan, "max": math.nan}
    return {
        "mean": float(array.mean()),
        "median": float(np.median(array)),
        "min": float(array.min()),
        "max": float(array.max()),
    }


def per_marker_ms(values: Sequence[float], found: Sequence[int]) -> float:
    """ms per marker: the median over frames with at least one marker of (that frame's ms / its markers found)."""
    per = [ms / n for ms, n in zip(values, found) if n > 0]
    return float(np.median(per)) if per else math.nan


def _timing(series: _Series, stages: Sequence[str]) -> dict[str, Any]:
    total = np.sum([series.stages.get(stage, [0.0] * len(series.step_ms)) for stage in stages], axis=0)
    total_stats = summary_stats(total)
    per_marker = {stage: per_marker_ms(values, series.found) for stage, values in series.stages.items()}
    per_marker["total_ms"] = per_marker_ms(total.tolist(), series.found)
    return {
        "stages": {stage: summary_stats(values) for stage, values in series.stages.items()},
        "total_stages": list(stages),
        "total_ms": total_stats,
        "per_marker_ms": per_marker,
        "found_per_frame": found_stats(series.found),
        "fps": 1e3 / total_stats["mean"] if total_stats["mean"] > 0 else math.nan,
        "step_ms": summary_stats(series.step_ms),
    }


def pipeline_timing(key: str, series: _Series, threads: int) -> dict[str, Any]:
    """One pipeline's stage and total times (its stages: :data:`OPENCV_STAGES` or :data:`TRACKER_STAGES`),
    per marker found, markers found per frame and frames per second, with its label and OpenCV's thread
    count during the pass."""
    stages = OPENCV_STAGES if key in PLAIN_PIPELINES else TRACKER_STAGES
    return {"label": PIPELINE_LABELS[key], "threads": threads, **_timing(series, stages)}


def pipeline_result(key: str, series: _Series, truths: Sequence[Mapping[str, Pose]], threads: int) -> dict:
    """:func:`pipeline_timing` and the accuracy of the pipeline's output and raw poses."""
    out = pipeline_timing(key, series, threads)
    out["accuracy"] = {kind: accuracy(series.outputs, truths, kind) for kind in ("marker", "board")}
    out["accuracy_raw"] = {kind: accuracy(series.raw, truths, kind) for kind in ("marker", "board")}
    return out


def primary_kind(scene_key: str) -> str:
    """The target kind a scene is about: its board, else its markers."""
    return "board" if scene_key == "board" else "marker"


def roi_check(full: Mapping[str, Any], roi: Mapping[str, Any], kind: str) -> dict[str, Any]:
    """Are the ROI tracker's median errors on ``kind`` targets within ``ROI_TOLERANCE`` (plus ``ROI_FLOOR``)
    of the full-frame tracker's?"""
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


def ratios_tracker_over_plain(pipelines: Mapping[str, Mapping[str, Any]]) -> dict[str, float]:
    """Median total time of each tracker over each plain loop (``"tracker_roi/opencv_subpix"``: above 1, the
    tracker is slower), for the pipelines present."""
    out = {}
    for tracker in TRACKER_PIPELINES:
        for plain in PLAIN_PIPELINES:
            if tracker in pipelines and plain in pipelines:
                a, b = pipelines[tracker]["total_ms"]["median"], pipelines[plain]["total_ms"]["median"]
                out[f"{tracker}/{plain}"] = a / b if b > 0 else math.nan
    return out


def ratio_opencv_over_roi(opencv: Mapping[str, Any], roi: Mapping[str, Any]) -> float:
    """The speed-up: opencv's median total time over the ROI tracker's (NaN when the latter is 0)."""
    a, b = opencv["total_ms"]["median"], roi["total_ms"]["median"]
    return a / b if b > 0 else math.nan
