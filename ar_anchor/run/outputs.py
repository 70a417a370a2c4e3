"""File outputs of a run: ``poses.csv`` (one row per frame per target) and ``summary.json``.

Both are written so that an interrupted run leaves them complete and readable: the CSV is
flushed after every frame, the summary is written to a temporary file and renamed.
"""

from __future__ import annotations

import array
import csv
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from ..errors import InputError, OutputError
from ..geometry import Pose, pose_errors
from ..targets import TargetId, TrackState
from ..track.tracker import FrameResult

__all__ = [
    "POSES_CSV_HEADER",
    "PosesCsvWriter",
    "RawVideoWriter",
    "RunSummary",
    "prepare_out_dir",
    "write_json_atomic",
]

POSES_CSV_HEADER = (
    "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
    "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
).split(",")


def prepare_out_dir(out: str | os.PathLike[str], option: str = "--out") -> Path:
    """Create the output directory ``out``. One that can never be a directory (a file is in the way)
    is bad input (:class:`InputError`, exit 2); failing to create it otherwise is an :class:`OutputError`."""
    out = Path(out)
    probe = out
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        what = "is" if probe == out else f"is inside {probe}, which is"
        raise InputError(f"{option}: {out} {what} a file, not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{option}: cannot create directory {out} ({err.strerror or err})") from None
    return out


def _num(value: float | None) -> str:
    """CSV number: empty for None / NaN, shortest round-tripping repr otherwise."""
    if value is None or not math.isfinite(value):
        return ""
    return repr(float(value))


def _pose_cells(pose: Pose | None) -> list[str]:
    if pose is None:
        return [""] * 6
    return [_num(v) for v in (*pose.rvec, *pose.tvec)]


class PosesCsvWriter:
    """Writes ``poses.csv`` exactly as DESIGN.md specifies; flushed after each frame."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            self._file: IO[str] | None = open(self.path, "w", newline="", encoding="utf-8")  # noqa: SIM115
        except OSError as err:
            raise OutputError(f"{self.path}: cannot write ({err.strerror})") from err
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(POSES_CSV_HEADER)
        self.rows = 0

    def write(self, result: FrameResult) -> None:
        """One row per target of ``result`` (filtered and raw ``camera_from_target``), then flush."""
        if self._file is None:
            raise OutputError(f"{self.path}: already closed")
        timestamp = f"{result.timestamp_ns * 1e-9:.9f}"
        for name, target in result.targets.items():
            self._writer.writerow(
                [
                    str(result.index),
                    timestamp,
                    name,
                    target.state,
                    *_pose_cells(target.pose),
                    *_pose_cells(target.raw),
                    _num(target.reproj_px),
                    _num(target.ambiguity),
                ]
            )
            self.rows += 1
        try:
            self._file.flush()
        except OSError as err:
            raise OutputError(f"{self.path}: write failed ({err.strerror})") from err

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> PosesCsvWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RawVideoWriter:
    """Lossless recording of the frames the tracker processed, for frame-exact replay.

    Writes ``path`` (FFV1 in Matroska: lossless, so a replay sees the very same pixels) and
    ``<path>.timestamps.csv`` (``frame,timestamp_ns``: the original frame indices and capture
    times), which :class:`~ar_anchor.sources.files.VideoFileSource` picks up. Both are flushed
    per frame; a run that is interrupted leaves a playable file.
    """

    FOURCC = "FFV1"

    def __init__(self, path: str | os.PathLike[str], fps: float = 30.0) -> None:
        import cv2  # noqa: PLC0415 - only runs that record need the writer

        self._cv2 = cv2
        self.path = Path(path)
        self.fps = fps
        self.timestamps_path = self.path.with_name(self.path.name + ".timestamps.csv")
        self._writer = None
        self._size: tuple[int, int] | None = None
        try:
            self._csv_file: IO[str] | None = open(self.timestamps_path, "w", newline="", encoding="utf-8")  # noqa: SIM115
        except OSError as err:
            raise OutputError(f"{self.timestamps_path}: cannot write ({err.strerror})") from err
        self._csv = csv.writer(self._csv_file, lineterminator="\n")
        self._csv.writerow(["frame", "timestamp_ns"])
        self.frames = 0

    def write(self, image: np.ndarray, index: int, timestamp_ns: int) -> None:
        """Append ``image`` (the first one fixes the size) to the video, ``index, timestamp_ns`` to the CSV."""
        cv2 = self._cv2
        size = (image.shape[1], image.shape[0])
        if self._writer is None:
            self._writer = cv2.VideoWriter(
                str(self.path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*self.FOURCC), self.fps, size
            )
            if not self._writer.isOpened():
                raise OutputError(f"{self.path}: cannot open a lossless {self.FOURCC} video writer")
            self._size = size
        if size != self._size:
            raise OutputError(
                f"{self.path}: frame {index} is {size[0]}x{size[1]}, the recording is {self._size[0]}x{self._size[1]}"
            )
        self._writer.write(image)
        assert self._csv_file is not None
        self._csv.writerow([index, timestamp_ns])
        self._csv_file.flush()
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._csv_file is not None:
            self._csv_file.close()
            self._csv_file = None


def write_json_atomic(path: str | os.PathLike[str], data: Mapping[str, Any]) -> None:
    """Write JSON to ``path`` via a temporary file and rename (never a half-written file)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    except OSError as err:
        raise OutputError(f"{path}: cannot write ({err.strerror})") from err


def _percentiles(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p95": None}
    arr = np.asarray(values)
    return {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95))}


@dataclass
class _TargetStats:
    measured: int = 0
    states: dict[str, int] = field(default_factory=lambda: {str(state): 0 for state in TrackState})
    in_view: int = 0
    measured_in_view: int = 0
    rotation_errors_deg: list[float] = field(default_factory=list)
    translation_errors_pct: list[float] = field(default_factory=list)


class RunSummary:
    """Accumulates per-target statistics over a run; :meth:`as_dict` is ``summary.json``."""

    def __init__(self) -> None:
        self.frames = 0
        self.frames_with_markers = 0
        self.frames_with_pose = 0
        self.targets: dict[str, _TargetStats] = {}
        self.has_truth = False
        self.latency_ms: dict[str, array.array] = {}  # stage -> ms per frame (8 bytes a value)

    def add(
        self, result: FrameResult, truth: Mapping[str, Pose] | None, stages: Mapping[str, float] | None = None
    ) -> None:
        """One tracked frame; ``stages``: the run loop's own per-frame times (ms) beside the tracker's."""
        self.frames += 1
        self.frames_with_markers += len(result.detections) > 0
        self.frames_with_pose += any(t.measured for t in result.targets.values())
        self.add_latency({key: [value] for key, value in {**result.latency_ms, **(stages or {})}.items()})
        if truth is not None:
            self.has_truth = True
            for name in truth:
                self.targets.setdefault(name, _TargetStats()).in_view += 1
        for name, target in result.targets.items():
            stats = self.targets.setdefault(name, _TargetStats())
            stats.states[target.state] += 1
            if not target.measured:
                continue
            stats.measured += 1
            true_pose = truth.get(name) if truth is not None else None
            if true_pose is None:
                continue
            stats.measured_in_view += 1
            rotation, translation = pose_errors(target.pose, true_pose)
            stats.rotation_errors_deg.append(rotation)
            stats.translation_errors_pct.append(translation)

    def add_latency(self, latency_ms: Mapping[str, list[float]]) -> None:
        """Per-stage times (ms) measured elsewhere (e.g. the output thread's render and log times)."""
        for key, values in latency_ms.items():
            self.latency_ms.setdefault(key, array.array("d")).extend(values)

    def as_dict(self, wall_time_s: float, **extra: Any) -> dict[str, Any]:
        targets: dict[str, Any] = {}
        for name in TargetId.ordered(self.targets):
            stats = self.targets[name]
            entry: dict[str, Any] = {
                "frames_measured": stats.measured,
                "detection_rate": stats.measured / self.frames if self.frames else 0.0,
                "states": dict(stats.states),
            }
            if self.has_truth:
                entry["frames_in_view"] = stats.in_view
                entry["detection_rate_in_view"] = stats.measured_in_view / stats.in_view if stats.in_view else None
                entry["rotation_error_deg"] = _percentiles(stats.rotation_errors_deg)
                entry["translation_error_pct"] = _percentiles(stats.translation_errors_pct)
            targets[name] = entry
        return {
            "frames": self.frames,
            "frames_with_markers": self.frames_with_markers,
            "frames_with_pose": self.frames_with_pose,
            "wall_time_s": wall_time_s,
            "fps": self.frames / wall_time_s if wall_time_s > 0 else None,
            "ground_truth": self.has_truth,
            "latency_ms": {k: _percentiles(v) for k, v in self.latency_ms.items()},
            "targets": targets,
            **extra,
        }
