"""File outputs of a run: ``poses.csv`` (one row per frame per target) and ``summary.json``.

Both are written so that an interrupted run leaves them complete and readable: the CSV is
flushed after every frame, the summary is written to a temporary file and renamed.
"""

from __future__ import annotations

import array
import csv
import errno
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from ..errors import InputError, OutputError, printable
from ..geometry import Pose, pose_errors
from ..targets import TargetId, TrackState
from ..track.results import FrameResult

__all__ = [
    "POSES_CSV_HEADER",
    "DiskFullError",
    "PosesCsvWriter",
    "RawVideoWriter",
    "RunSummary",
    "SummaryFile",
    "WholeLinesFile",
    "check_not_a_file",
    "distance_and_tilt",
    "is_disk_full",
    "prepare_out_dir",
    "prepare_out_file_folder",
    "write_failure",
    "write_json_atomic",
]

WRONG_DEG = 10.0  # a rotation error above this is a flip: a wrong frame (as the benchmarks count it)
POSES_CSV_HEADER = (
    "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
    "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
).split(",")


def check_not_a_file(out: Path, option: str = "--out") -> None:
    """An :class:`InputError` when ``out``, or a folder it would be created in, is a file: it can never
    be a directory."""
    probe = out
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        what = "is" if probe == out else f"is inside {printable(probe)}, which is"
        raise InputError(f"{option}: {printable(out)} {what} a file, not a directory")


def prepare_out_file_folder(out: Path, option: str = "--out") -> None:
    """Create the folder the output file ``out`` goes in and check it is writable (:class:`OutputError`
    naming ``option`` otherwise). Whether ``out`` itself may be written is the caller's to say."""
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{option} {printable(out)}: cannot create its folder ({err.strerror})") from None
    if not os.access(out.parent, os.W_OK):
        raise OutputError(f"{option} {printable(out)}: folder {printable(out.parent)} is not writable")


def prepare_out_dir(out: str | os.PathLike[str], option: str = "--out") -> Path:
    """Create the output directory ``out``. One that can never be a directory (a file is in the way)
    is bad input (:class:`InputError`, exit 2); failing to create it otherwise is an :class:`OutputError`."""
    out = Path(out)
    check_not_a_file(out, option)
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


def is_disk_full(err: BaseException) -> bool:
    """Is ``err`` (or one it was raised from) a full disk or an exhausted quota (ENOSPC, EDQUOT)?"""
    seen: BaseException | None = err
    for _depth in range(8):
        if seen is None:
            return False
        if isinstance(seen, OSError) and seen.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(seen, DiskFullError) or "No space left on device" in str(seen):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


class DiskFullError(OutputError):
    """An output could not be written because the disk (or the quota) is full; ``path``: that file (None
    when the error did not say which: raised by the output thread's writer, say)."""

    def __init__(self, message: str, path: Path | None = None) -> None:  # (a default: it is unpickled with args only)
        super().__init__(message)
        self.path = path


def write_failure(path: Path, err: OSError, what: str = "cannot write") -> OutputError:
    """The error for ``path`` failing with ``err``: a :class:`DiskFullError` that says so when the disk is full."""
    if is_disk_full(err):
        return DiskFullError(f"{printable(path)}: {what}: the disk is full ({err.strerror or err})", path)
    return OutputError(f"{printable(path)}: {what} ({err.strerror or err})")


class WholeLinesFile:
    """A text file written in whole lines only: each :meth:`write` goes to the disk at once (no buffer), and a
    write the disk cuts short (full disk) is truncated away, so the file always ends on a complete line."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            self._file: IO[bytes] | None = open(self.path, "wb", buffering=0)  # noqa: SIM115
        except OSError as err:
            raise write_failure(self.path, err) from err
        self.size = 0  # bytes of whole lines written
        self.failure: OutputError | None = None

    def write(self, text: str) -> None:
        """Append ``text`` (whole lines), or raise the :class:`OutputError` that cut it (the lines before stay)."""
        if self.failure is not None:
            raise self.failure
        if self._file is None:
            raise OutputError(f"{printable(self.path)}: already closed")
        data = text.encode("utf-8")
        view = memoryview(data)
        try:
            while view:
                view = view[self._file.write(view) :]
        except OSError as err:
            self.failure = write_failure(self.path, err)
            self._truncate()
            raise self.failure from err
        self.size += len(data)

    def _truncate(self) -> None:
        """Cut the file back to its whole lines (frees the space a cut line took, even on a full disk)."""
        if self._file is not None:
            try:
                os.ftruncate(self._file.fileno(), self.size)
            except OSError:
                pass

    def close(self) -> None:
        """Close (idempotent); a file a write failed on is cut back to its whole lines first."""
        if self._file is not None:
            if self.failure is not None:
                self._truncate()
            self._file.close()
            self._file = None


class PosesCsvWriter:
    """Writes ``poses.csv`` exactly as DESIGN.md specifies; each frame's rows reach the file at once, whole
    (:class:`WholeLinesFile`: a full disk leaves the rows of the frames before, never half a row)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._file: WholeLinesFile | None = WholeLinesFile(self.path)
        self._buffer = io.StringIO()
        self._writer = csv.writer(self._buffer, lineterminator="\n")
        self._writer.writerow(POSES_CSV_HEADER)
        self._commit()
        self.rows = 0

    def _commit(self) -> None:
        assert self._file is not None
        text = self._buffer.getvalue()
        self._buffer.seek(0)
        self._buffer.truncate()
        self._file.write(text)

    def write(self, result: FrameResult) -> None:
        """One row per target of ``result`` (filtered and raw ``camera_from_target``), written at once."""
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
        self._commit()
        self.rows += len(result.targets)

    def close(self) -> None:
        """Close the file (it ends on the last whole row)."""
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
        self._csv_file: WholeLinesFile | None = WholeLinesFile(self.timestamps_path)
        self._csv_file.write("frame,timestamp_ns\n")
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
        self._csv_file.write(f"{int(index)},{int(timestamp_ns)}\n")
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._csv_file is not None:
            self._csv_file.close()
            self._csv_file = None


def write_json_atomic(path: str | os.PathLike[str], data: Mapping[str, Any]) -> None:
    """Write JSON to ``path`` via a temporary file and rename (never a half-written file, no temporary left)."""
    SummaryFile(path, reserve=0).write(data)


class SummaryFile:
    """``summary.json``, replaced atomically, with room for it set aside up front.

    :meth:`reserve` allocates ``<name>.tmp`` (``reserve`` bytes) while the disk has room; :meth:`write` writes
    the JSON into those blocks and renames it over ``summary.json``, so a disk that filled during the run
    cannot leave it empty or missing: either the new content or the previous one is there. Part of the
    reservation (``slack``) can be given back early (:meth:`release_slack`) for other files to finish in
    (a recording's footer, the last rows). The temporary file is never left behind after :meth:`write`.
    """

    def __init__(self, path: str | os.PathLike[str], *, reserve: int = 128 * 1024, slack: int = 0) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self._reserve = reserve
        self._slack = slack
        self.reserved = 0

    def reserve(self) -> None:
        """Allocate the temporary file's room now (a disk already full: :class:`DiskFullError`)."""
        size = self._reserve + self._slack
        if size <= 0:
            return
        try:
            fd = os.open(self.tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
            try:
                _allocate(fd, size)
            finally:
                os.close(fd)
        except OSError as err:
            self.tmp.unlink(missing_ok=True)
            raise write_failure(self.path, err, "cannot set aside room for it") from err
        self.reserved = size

    def release_slack(self) -> None:
        """Give back the slack (keep the room the summary itself needs)."""
        if self.reserved > self._reserve:
            try:
                os.truncate(self.tmp, self._reserve)
                self.reserved = self._reserve
            except OSError:
                pass

    def write(self, data: Mapping[str, Any]) -> None:
        """Write ``data`` as JSON into the reserved file (or a new one) and rename it over ``summary.json``."""
        text = (json.dumps(data, indent=2, allow_nan=False) + "\n").encode("utf-8")
        try:
            fd = os.open(self.tmp, os.O_WRONLY | os.O_CREAT | (0 if self.reserved else os.O_TRUNC), 0o666)
            try:
                view = memoryview(text)
                while view:
                    view = view[os.write(fd, view) :]
                os.ftruncate(fd, len(text))
            finally:
                os.close(fd)
            os.replace(self.tmp, self.path)
        except OSError as err:
            self.tmp.unlink(missing_ok=True)
            raise write_failure(self.path, err) from err
        finally:
            self.reserved = 0

    def discard(self) -> None:
        """Remove the reserved temporary file (the summary is not going to be written)."""
        if self.reserved:
            self.tmp.unlink(missing_ok=True)
            self.reserved = 0


def _allocate(fd: int, size: int) -> None:
    """Allocate ``size`` bytes of disk for ``fd`` (posix_fallocate, or zeros where it is not supported)."""
    try:
        os.posix_fallocate(fd, 0, size)
        return
    except (AttributeError, OSError) as err:
        if isinstance(err, OSError) and err.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            raise
    os.write(fd, bytes(size))


def _percentiles(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p95": None}
    arr = np.asarray(values)
    return {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95))}


@dataclass
class _TargetStats:
    measured: int = 0
    states: dict[str, int] = field(default_factory=lambda: {str(state): 0 for state in TrackState})
    causal_states: dict[str, int] | None = None  # offline replay: the live filter's states, for comparison
    in_view: int = 0
    measured_in_view: int = 0
    rotation_errors_deg: list[float] = field(default_factory=list)
    translation_errors_pct: list[float] = field(default_factory=list)
    distance_m: array.array = field(default_factory=lambda: array.array("d"))  # each measured frame's
    tilt_deg: array.array = field(default_factory=lambda: array.array("d"))
    last_state: str = ""  # the state of the last frame it was measured in
    member_frames: dict[str, int] = field(default_factory=dict)  # a marker: board -> frames drawn as its part


def distance_and_tilt(pose: Pose) -> tuple[float, float]:
    """How far the target is (metres, camera to the target's origin: ``||t||``, which is also the norm of the
    camera's centre in the target's frame) and how tilted it is to the camera (degrees: the angle between its z
    axis and the line of sight to it; 0 faces the camera, 90 is seen edge-on), from ``camera_from_target``."""
    translation = np.asarray(pose.tvec, np.float64)
    distance = float(np.linalg.norm(translation))
    if not distance > 0.0:
        return distance, math.nan
    normal = pose.rotation[:, 2]
    cosine = min(1.0, abs(float(normal @ translation)) / distance)
    return distance, math.degrees(math.acos(cosine))


def _where(stats: _TargetStats) -> dict[str, Any]:
    """summary.json's ``distance_m`` and ``tilt_deg`` of a target: the median over its measured frames and the
    last one (None when it was never measured)."""

    def pair(values: array.array) -> dict[str, float | None]:
        finite = [v for v in values if math.isfinite(v)]
        if not finite:
            return {"median": None, "last": None}
        return {"median": float(np.median(finite)), "last": finite[-1]}

    return {"distance_m": pair(stats.distance_m), "tilt_deg": pair(stats.tilt_deg), "last_state": stats.last_state}


class RunSummary:
    """Accumulates per-target statistics over a run; :meth:`as_dict` is ``summary.json``."""

    def __init__(self) -> None:
        self.frames = 0
        self.frames_with_markers = 0
        self.frames_with_pose = 0
        # markers seen but every one dropped: ids seen more than once in the frame (which is which is unknown)
        self.frames_with_only_duplicates = 0
        self.frames_with_duplicates = 0
        self.duplicated_ids: set[int] = set()
        self.targets: dict[str, _TargetStats] = {}
        self.has_truth = False
        self.latency_ms: dict[str, array.array] = {}  # stage -> ms per frame (8 bytes a value)

    def add(
        self, result: FrameResult, truth: Mapping[str, Pose] | None, stages: Mapping[str, float] | None = None
    ) -> None:
        """One tracked frame; ``stages``: the run loop's own per-frame times (ms) beside the tracker's."""
        self.frames += 1
        self.frames_with_markers += len(result.detections) > 0
        duplicated = getattr(result.detections, "duplicated", ())
        if len(duplicated):
            self.frames_with_duplicates += 1
            self.frames_with_only_duplicates += len(result.detections) == 0
            self.duplicated_ids.update(int(i) for i in duplicated)
        self.frames_with_pose += any(t.measured for t in result.targets.values())
        self.add_latency({key: [value] for key, value in {**result.latency_ms, **(stages or {})}.items()})
        if truth is not None:
            self.has_truth = True
            for name in truth:
                self.targets.setdefault(name, _TargetStats()).in_view += 1
        for name, target in (result.causal_targets or {}).items():
            stats = self.targets.setdefault(name, _TargetStats())
            if stats.causal_states is None:
                stats.causal_states = {str(state): 0 for state in TrackState}
            stats.causal_states[target.state] += 1
        members = result.board_members()
        for name, target in result.targets.items():
            stats = self.targets.setdefault(name, _TargetStats())
            stats.states[target.state] += 1
            if name in members:
                stats.member_frames[members[name]] = stats.member_frames.get(members[name], 0) + 1
            if not target.measured:
                continue
            stats.measured += 1
            distance, tilt = distance_and_tilt(target.pose)
            stats.distance_m.append(distance)
            stats.tilt_deg.append(tilt)
            stats.last_state = str(target.state)
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
                **_where(stats),
            }
            if stats.causal_states is not None:
                entry["causal_states"] = dict(stats.causal_states)
            if stats.member_frames:  # frames this marker was drawn as part of a board (FrameResult.board_members)
                entry["member_of"] = dict(stats.member_frames)
            if self.has_truth:
                entry["frames_in_view"] = stats.in_view
                entry["detection_rate_in_view"] = stats.measured_in_view / stats.in_view if stats.in_view else None
                entry["rotation_error_deg"] = _percentiles(stats.rotation_errors_deg)
                # frames whose output is a flip (rotation error > WRONG_DEG) among those with an output and truth
                entry["wrong_frames"] = sum(error > WRONG_DEG for error in stats.rotation_errors_deg)
                entry["frames_scored"] = len(stats.rotation_errors_deg)
                entry["translation_error_pct"] = _percentiles(stats.translation_errors_pct)
            targets[name] = entry
        return {
            "frames": self.frames,
            "frames_with_markers": self.frames_with_markers,
            "frames_with_pose": self.frames_with_pose,
            "frames_with_duplicated_ids": self.frames_with_duplicates,
            "frames_with_only_duplicated_ids": self.frames_with_only_duplicates,
            "duplicated_ids": sorted(self.duplicated_ids),
            "wall_time_s": wall_time_s,
            "fps": self.frames / wall_time_s if wall_time_s > 0 else None,
            "ground_truth": self.has_truth,
            "latency_ms": {k: _percentiles(v) for k, v in self.latency_ms.items()},
            "targets": targets,
            **extra,
        }
