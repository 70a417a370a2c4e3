"""Wire a frame source, a tracker and the outputs together for one run.

Outputs in ``out_dir``: ``poses.csv``, ``summary.json``, ``recording.rrd``. Whatever happens
(end of stream, an error, Ctrl-C) every output is closed so that it stays complete and readable;
``summary.json`` then says how the run ended.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import OutputError
from .outputs import PosesCsvWriter, RunSummary, write_json_atomic
from .sources.base import FrameSource
from .tracker import FrameResult, Tracker
from .viz import RerunRecorder

__all__ = ["RunOutputs", "run_session"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOutputs:
    out_dir: Path
    poses_csv: Path
    summary_json: Path
    recording_rrd: Path
    summary: dict[str, Any]


def run_session(
    source: FrameSource,
    tracker: Tracker,
    out_dir: str | Path,
    *,
    max_frames: int | None = None,
    spawn: bool = False,
    recording_name: str = "ar_anchor",
    progress: Callable[[int, int | None], Any] | None = None,
    extra_summary: dict[str, Any] | None = None,
) -> RunOutputs:
    """Track every frame of ``source`` (up to ``max_frames``) and write the outputs to ``out_dir``.

    ``progress(frames_done, total)`` is called after each frame (total may be None).
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"--out {out_dir}: cannot create the directory ({err.strerror})") from err
    poses_csv, summary_json, recording_rrd = out_dir / "poses.csv", out_dir / "summary.json", out_dir / "recording.rrd"
    total = source.frame_count
    if max_frames is not None:
        total = max_frames if total is None else min(total, max_frames)

    summary = RunSummary()
    status = "incomplete"
    data: dict[str, Any] = {}
    start = time.perf_counter()
    recorder = RerunRecorder(recording_rrd, camera=tracker.camera, settings=tracker.config.recording,
                             spawn=spawn, recording_name=recording_name)
    try:
        with PosesCsvWriter(poses_csv) as csv_writer:
            for frame in source:
                if max_frames is not None and summary.frames >= max_frames:
                    break
                result: FrameResult = tracker.process(frame)
                csv_writer.write(result)
                recorder.log_frame(frame, result)
                truth = None if frame.truth is None else {k: v for k, v in frame.truth.items() if tracker.reports(k)}
                summary.add(result, truth)
                if progress is not None:
                    progress(summary.frames, total)
        status = "completed"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    except Exception:
        status = "failed"
        raise
    finally:
        wall = time.perf_counter() - start
        try:
            recorder.close()
        finally:
            data = summary.as_dict(wall, status=status, **(extra_summary or {}))
            write_json_atomic(summary_json, data)
    return RunOutputs(out_dir, poses_csv, summary_json, recording_rrd, data)
