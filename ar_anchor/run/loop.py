"""Wire a frame source, a tracker and the outputs together for one run (:func:`run_session`).

Outputs in ``out_dir``: ``poses.csv``, ``summary.json``, ``recording.rrd`` and, when asked,
``raw.mkv`` + ``raw.mkv.timestamps.csv`` (the processed frames, lossless) and an annotated video.
Whatever happens (end of stream, an error, Ctrl-C, SIGTERM) every output is closed so that it stays
complete and readable (:class:`~.run_outputs.RunOutputs` says in which order); ``summary.json`` then
says how the run ended (``status``).

A run, step by step: check the options that could fail before any output exists (overlay models,
``--video-out``), create ``out_dir``; then, with Ctrl-C and SIGTERM held off while a frame's outputs
are written (:class:`~.interrupts.InterruptGuard`): open the outputs, track every frame (:func:`_track`), stop
reading ahead, close the outputs; last, write ``summary.json``. A second Ctrl-C while the outputs close
ends the process at once (exit 130): ``summary.json`` written, the outputs still closing named.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..camera import opencv_path_problem
from ..errors import InputError
from ..render.overlay import OverlayRenderer
from ..render.video import SUPPORTED_EXTENSIONS
from ..sources.base import Frame, FrameSource, SourceInfo
from ..track.tracker import FrameResult, Tracker
from .hints import RunHints
from .interrupts import InterruptGuard
from .options import RunOptions
from .outputs import prepare_out_dir
from .run_outputs import RunOutputs
from .threads import Prefetcher

__all__ = ["RunResult", "run_session"]

Progress = Callable[[int, int | None, FrameResult], Any]


@dataclass(frozen=True)
class RunResult:
    """Where a finished run's outputs are, and its ``summary.json`` as a dict."""

    out_dir: Path
    poses_csv: Path
    summary_json: Path
    recording_rrd: Path
    raw_video: Path | None
    summary: dict[str, Any]


def run_session(
    source: FrameSource,
    tracker: Tracker,
    out_dir: str | Path,
    options: RunOptions | None = None,
    *,
    progress: Progress | None = None,
    summary_extras: Callable[[], dict[str, Any]] | None = None,
) -> RunResult:
    """Track every frame of ``source`` (up to ``options.max_frames``) and write the outputs to ``out_dir``.

    ``progress(frames_done, total, result)`` is called after each frame (total may be None);
    ``summary_extras()`` is merged into ``summary.json`` when the run ends, however it ends.
    """
    options = options or RunOptions()
    renderer = _overlay_renderer(tracker, options)  # before any output exists: a bad model is a clean input error
    outputs = RunOutputs(prepare_out_dir(out_dir), options)
    hints = RunHints(tracker.config)  # the wrong dictionary, a length in millimetres: said once, as it shows
    info = source.info
    status = "incomplete"
    start = time.perf_counter()
    try:
        abandon = lambda: _abandon(outputs, options, time.perf_counter() - start, summary_extras)  # noqa: E731
        with InterruptGuard(abandon, outputs.out_dir) as guard, _quick_gil_handover(info.live):
            feed = _FrameFeed(source, info, options, guard)
            try:
                outputs.open(tracker.camera, tracker.config.recording, info, renderer)
                _track(feed, tracker, outputs, guard, options, progress, hints)
            finally:
                guard.hold()  # the closing is not interrupted: a signal now waits until the guard exits
                feed.close()  # the decoding thread first: nothing reads the source any more
                outputs.close()
        status = "completed"
    except KeyboardInterrupt as err:
        status = "interrupted"
        err.out_dir = outputs.out_dir  # type: ignore[attr-defined]  # where the outputs are, for the last line
        raise
    except BaseException:
        status = "failed"
        raise
    finally:
        extras = summary_extras() if summary_extras is not None else {}
        extras = {**hints.finish(probe=status == "completed"), **extras}
        summary = outputs.write_summary(status, time.perf_counter() - start, extras)
    return RunResult(
        outputs.out_dir, outputs.poses_csv, outputs.summary_json, outputs.recording_rrd, outputs.raw_video, summary
    )


def _abandon(
    outputs: RunOutputs,
    options: RunOptions,
    wall_time_s: float,
    summary_extras: Callable[[], dict[str, Any]] | None,
) -> list[str]:
    """A second Ctrl-C cut the closing short: ``summary.json`` is written now (status ``interrupted``,
    naming what may be incomplete). ``poses.csv`` is flushed after every frame, so it is complete; the
    outputs still closing may not be: their names."""
    incomplete = [outputs.recording_rrd.name]
    if options.video_out is not None:
        incomplete.append(str(options.video_out))
    if outputs.raw_video is not None:
        incomplete.append(outputs.raw_video.name)
    extras = summary_extras() if summary_extras is not None else {}
    outputs.write_summary("interrupted", wall_time_s, {**extras, "closing_cut_short": incomplete})
    return incomplete


def _overlay_renderer(tracker: Tracker, options: RunOptions) -> OverlayRenderer | None:
    """The overlay renderer (its models read from their files now), None when nothing draws overlays;
    and ``--video-out`` checked, so that neither fails once outputs exist."""
    renderer = OverlayRenderer(tracker.config, tracker.camera) if options.overlays or options.video_out else None
    video_out = options.video_out
    if video_out is not None and video_out.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise InputError(f"--video-out {video_out}: unsupported extension (use {', '.join(SUPPORTED_EXTENSIONS)})")
    if video_out is not None and (problem := opencv_path_problem(video_out)):
        raise InputError(f"--video-out {os.fsencode(video_out)!r}: {problem}")
    return renderer


@contextmanager
def _quick_gil_handover(live: bool) -> Iterator[None]:
    """Live, the tracker shares the GIL with the output thread: hand it over every 1 ms instead of 5, so
    that a frame's pose waits less for the logger (measured: median capture-to-pose 10-15 % lower)."""
    previous = sys.getswitchinterval()
    if live:
        sys.setswitchinterval(min(previous, 0.001))
    try:
        yield
    finally:
        sys.setswitchinterval(previous)


class _FrameFeed:
    """The frames to track, each with its decode time (ms): read ahead in a thread (files, synthetic
    renders), or, live, taken as the device hands them over (no read-ahead, no decode time)."""

    def __init__(self, source: FrameSource, info: SourceInfo, options: RunOptions, guard: InterruptGuard) -> None:
        self.total = info.frame_count
        if options.max_frames is not None:
            self.total = options.max_frames if self.total is None else min(self.total, options.max_frames)
        self._prefetcher: Prefetcher | None = None
        self._frames: Iterable[tuple[Frame, float | None]]
        if options.max_frames == 0:
            self._frames = ()
        elif info.live:
            self._frames = ((frame, None) for frame in source)
        else:
            self._prefetcher = Prefetcher(source, depth=options.decode_queue, held=guard.critical)
            self._frames = self._prefetcher

    def __iter__(self) -> Iterator[tuple[Frame, float | None]]:
        return iter(self._frames)

    def close(self) -> None:
        """Stop reading ahead and wait for the decoding thread (so the source can be closed afterwards)."""
        if self._prefetcher is not None:
            self._prefetcher.close()


def _track(
    feed: _FrameFeed,
    tracker: Tracker,
    outputs: RunOutputs,
    guard: InterruptGuard,
    options: RunOptions,
    progress: Progress | None,
    hints: RunHints,
) -> None:
    """Track each frame of ``feed`` and hand it to ``outputs``; a frame's outputs are written whole."""
    for frame, decode_ms in feed:
        began_ns = time.monotonic_ns()
        result = tracker.process(frame)
        tracked_ns = time.monotonic_ns()
        stages = {} if decode_ms is None else {"decode_ms": decode_ms}
        if frame.arrived_ns is not None:
            stages["wait_ms"] = (began_ns - frame.arrived_ns) * 1e-6
            stages["capture_to_pose_ms"] = (tracked_ns - frame.arrived_ns) * 1e-6
        truth = None if frame.truth is None else {k: v for k, v in frame.truth.items() if tracker.reports(k)}
        with guard.critical():
            outputs.write(frame, result, truth, stages)
        hints.after_frame(frame, result)
        if progress is not None:
            progress(outputs.summary.frames, feed.total, result)
        if options.max_frames is not None and outputs.summary.frames >= options.max_frames:
            break  # before taking another frame from the source
