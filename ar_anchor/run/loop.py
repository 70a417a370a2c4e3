"""Wire a frame source, a tracker and the outputs together for one run (:func:`run_session`).

Outputs in ``out_dir``: ``poses.csv``, ``summary.json``, ``recording.rrd`` and, when asked,
``raw.mkv`` + ``raw.mkv.timestamps.csv`` (the processed frames, lossless) and an annotated video.
Whatever happens (end of stream, an error, Ctrl-C, SIGTERM) every output is closed so that it stays
complete and readable (:class:`~.run_outputs.RunOutputs` says in which order); ``summary.json`` then
says how the run ended (``status``).

An offline replay (:class:`OfflineReplay`, ``replay`` without ``--causal``) tracks in three passes: the
frames are tracked as ``live`` would and their results kept in a temporary file (not in memory), the
flip filter runs backwards over them (:mod:`ar_anchor.track.offline`), and the source is decoded again
while the outputs are written from the offline answer (the live filter's beside it in the recording).
Nothing is written before the last pass: an offline replay interrupted earlier leaves empty outputs.

A run, step by step: check the options that could fail before any output exists (overlay models,
``--video-out``), create ``out_dir``; then, with Ctrl-C and SIGTERM held off while a frame's outputs
are written (:class:`~.interrupts.InterruptGuard`): open the outputs, track every frame (:func:`_track`), probe
the other dictionaries when a short run found no marker (:meth:`~.hints.RunHints.end_of_stream`), stop
reading ahead, close the outputs; last, write ``summary.json``. A second Ctrl-C while the outputs close
ends the process at once (exit 130): ``summary.json`` written, the outputs still closing named.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable, Generator, Iterable, Iterator
from contextlib import AbstractContextManager, closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..camera.files import opencv_path_problem
from ..errors import ArAnchorError, InputError, OutputError, printable
from ..render.overlay import OverlayRenderer
from ..render.video import SUPPORTED_EXTENSIONS
from ..sources.base import Frame, FrameSource, SourceInfo
from ..sources.files import IMAGE_EXTENSIONS
from ..track.ahead import detected_ahead
from ..track.offline import decide, offline_results
from ..track.results import DetectedFrame, FrameResult
from ..track.spool import SpoolStore
from ..track.tracker import Tracker
from .hints import RunHints
from .interrupts import InterruptGuard
from .options import RunOptions
from .outputs import DiskFullError, is_disk_full, prepare_out_dir
from .run_outputs import RunOutputs
from .threads import Prefetcher

__all__ = ["OfflineReplay", "RunResult", "run_session"]

Progress = Callable[[int, int | None, FrameResult], Any]


@dataclass(frozen=True)
class OfflineReplay:
    """A replay decided with the whole recording (see the module doc): ``reopen()`` opens the same source
    again (its frames are decoded a second time for the outputs); ``progress(name)`` gives a progress
    callback ``(done, total)`` for the passes after the first (``decide``, ``write``), with an optional
    ``close()``."""

    reopen: Callable[[], AbstractContextManager[FrameSource]]
    progress: Callable[[str], Callable[[int, int], Any]] | None = None


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
    offline: OfflineReplay | None = None,
) -> RunResult:
    """Track every frame of ``source`` (up to ``options.max_frames``) and write the outputs to ``out_dir``.

    ``progress(frames_done, total, result)`` is called after each frame (total may be None);
    ``summary_extras()`` is merged into ``summary.json`` when the run ends, however it ends.
    ``offline``: decide every frame with the whole recording (a replay; see the module doc).
    """
    options = options or RunOptions()
    renderer = _overlay_renderer(tracker, options)  # before any output exists: a bad model is a clean input error
    outputs = RunOutputs(prepare_out_dir(out_dir), options)
    hints = RunHints(tracker.config)  # the wrong dictionary, a length in millimetres: said once, as it shows
    info = source.info
    status = "incomplete"
    passes: dict[str, Any] = {}  # an offline replay's passes, for summary.json
    start = time.perf_counter()
    try:
        abandon = lambda: _abandon(outputs, options, time.perf_counter() - start, summary_extras)  # noqa: E731
        with InterruptGuard(abandon, outputs.out_dir) as guard, _quick_gil_handover():
            feed = _FrameFeed(source, info, options, guard)
            try:
                outputs.open(tracker.camera, tracker.config.recording, info, renderer)
                if offline is None:
                    _track(feed, tracker, options, progress, hints, _writer(outputs, guard))
                else:
                    _track_offline(feed, tracker, outputs, guard, options, progress, hints, offline, passes)
                hints.end_of_stream()  # (a short run's dictionary probe: seconds, so while a signal is an interrupt)
            finally:
                guard.hold()  # the closing is not interrupted: a signal now waits until the guard exits
                feed.close()  # the decoding thread first: nothing reads the source any more
                outputs.close()
        status = "completed"
    except KeyboardInterrupt as err:
        status = "interrupted"
        err.out_dir = outputs.out_dir  # type: ignore[attr-defined]  # where the outputs are, for the last line
        if offline is not None and "writing" not in passes:
            done = passes.get("done") or ["none"]
            err.note = (  # type: ignore[attr-defined]
                f"the offline replay was interrupted before writing (passes done: {', '.join(done)}): the outputs in "
                f"{printable(outputs.out_dir)}/ are complete but hold no frames (replay --causal writes each frame "
                "as it goes)"
            )
        raise
    except BaseException:
        status = "failed"
        raise
    finally:
        extras = summary_extras() if summary_extras is not None else {}
        extras = {**hints.finish(probe=False), **extras}  # (probed above, inside the guard)
        if offline is not None:
            extras["offline"] = passes
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
    incomplete = [outputs.recording_rrd.name] if options.recording else []
    if options.video_out is not None:
        incomplete.append(str(options.video_out))
    if outputs.raw_video is not None:
        incomplete.append(outputs.raw_video.name)
    extras = summary_extras() if summary_extras is not None else {}
    outputs.write_summary("interrupted", wall_time_s, {**extras, "closing_cut_short": incomplete})
    return incomplete


def _overlay_renderer(tracker: Tracker, options: RunOptions) -> OverlayRenderer | None:
    """The overlay renderer (its models read from their files now), None when nothing draws overlays;
    and ``--video-out`` checked, so that neither fails once outputs exist (``--images-out``: by the command)."""
    drawn = options.overlays or options.video_out or options.images_out
    renderer = OverlayRenderer(tracker.config, tracker.camera) if drawn else None
    check_video_out(options.video_out)
    return renderer


def check_video_out(video_out: Path | None) -> None:
    """``--video-out``'s extension and path, checked before anything is written (:class:`InputError`)."""
    if video_out is not None and video_out.suffix.lower() not in SUPPORTED_EXTENSIONS:
        still = " (annotated images of an image folder: replay --images-out DIR)"
        raise InputError(
            f"--video-out {video_out}: unsupported extension (use {', '.join(SUPPORTED_EXTENSIONS)})"
            + (still if video_out.suffix.lower() in IMAGE_EXTENSIONS else "")
        )
    if video_out is not None and (problem := opencv_path_problem(video_out)):
        raise InputError(f"--video-out {os.fsencode(video_out)!r}: {problem}")


@contextmanager
def _quick_gil_handover() -> Iterator[None]:
    """The run's threads share the GIL (the tracker, the detection one frame ahead, the output thread): each
    hands it over every 1 ms instead of 5, so that a thread coming back from OpenCV (which works without it)
    waits less for one running Python. Measured: live, median capture-to-pose 10-15 % lower; a causal replay
    of chessboard.avi looped to 1043 frames, 36 -> 44 fps (default outputs, a busy machine, 3 runs each)."""
    previous = sys.getswitchinterval()
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
        self.live = info.live
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
    options: RunOptions,
    progress: Progress | None,
    hints: RunHints,
    keep: Callable[[Frame, FrameResult, dict[str, Any] | None, dict[str, float]], int],
) -> None:
    """Track each frame of ``feed`` and ``keep(frame, result, truth, stages)`` it (written to the outputs,
    or spooled for an offline replay), which returns how many frames are kept so far."""
    # files and renders: each frame's detection overlaps the frame before's pose and filter (see track/ahead.py)
    frames: Generator[tuple[Frame, float | None, DetectedFrame | None], None, None]
    frames = ((f, d, None) for f, d in feed) if feed.live else detected_ahead(tracker, feed)
    with closing(frames):  # (an early end waits for the detection under way)
        for frame, decode_ms, detected in frames:
            result, stages, truth = _tracked(tracker, frame, decode_ms, detected)
            kept = keep(frame, result, truth, stages)
            hints.after_frame(frame, result)
            if progress is not None:
                progress(kept, feed.total, result)
            if options.max_frames is not None and kept >= options.max_frames:
                break  # before taking another frame from the source (files: one more may be under detection)


def _writer(outputs: RunOutputs, guard: InterruptGuard) -> Callable[..., int]:
    """``keep`` for :func:`_track`: each frame's outputs written whole (never cut by a signal)."""

    def write(frame: Frame, result: FrameResult, truth: dict[str, Any] | None, stages: dict[str, float]) -> int:
        with guard.critical():
            outputs.write(frame, result, truth, stages)
        return outputs.summary.frames

    return write


def _tracked(
    tracker: Tracker, frame: Frame, decode_ms: float | None, detected: DetectedFrame | None = None
) -> tuple[FrameResult, dict[str, float], dict[str, Any] | None]:
    """One frame tracked (``detected``: its detection, done ahead): its result, the loop's own stage times
    (ms: decode, and from the frame's arrival the wait and capture-to-pose), and the truth of the targets
    the tracker reports (None: no truth)."""
    began_ns = time.monotonic_ns()
    result = tracker.process(frame) if detected is None else tracker.track(detected)
    tracked_ns = time.monotonic_ns()
    stages = {} if decode_ms is None else {"decode_ms": decode_ms}
    if frame.arrived_ns is not None:
        stages["wait_ms"] = (began_ns - frame.arrived_ns) * 1e-6
        stages["capture_to_pose_ms"] = (tracked_ns - frame.arrived_ns) * 1e-6
    truth = None if frame.truth is None else {k: v for k, v in frame.truth.items() if tracker.reports(k)}
    return result, stages, truth


def _track_offline(
    feed: _FrameFeed,
    tracker: Tracker,
    outputs: RunOutputs,
    guard: InterruptGuard,
    options: RunOptions,
    progress: Progress | None,
    hints: RunHints,
    offline: OfflineReplay,
    passes: dict[str, Any],
) -> None:
    """An offline replay's three passes (see the module doc); ``passes`` says how far they got."""
    with SpoolStore(outputs.out_dir) as spool:
        passes["done"] = []

        def keep(_frame: Frame, result: FrameResult, truth: dict[str, Any] | None, stages: dict[str, float]) -> int:
            if not spool:
                outputs.wait_open()  # opened while the first frame was tracked; a failure is said now, not at the end
            outputs.poll()  # (and what the output process failed to open, once it says so)
            try:
                spool.append((result, truth, stages))
            except OSError as err:  # (a full disk: the spool's, not the recording's, which has barely begun)
                raise outputs.failed(_spool_failure(outputs.out_dir, spool, err)) from None
            return len(spool)

        _track(feed, tracker, options, progress, hints, keep)
        feed.close()
        _close_progress(progress)
        passes.update(done=["track"], frames=len(spool), spool_mb=round(spool.size_bytes / 1e6, 1))
        records = _Records(spool)
        bar = offline.progress("decide") if offline.progress is not None else None
        plan = decide(records.results, tracker.config, bar)
        _close_progress(bar)
        passes["done"].append("decide")
        bar = offline.progress("write") if offline.progress is not None else None
        passes["writing"] = True
        with _said_once(), offline.reopen() as again:
            written = _write_offline(
                again, records, offline_results(records.results, plan), outputs, guard, options, bar
            )
        _close_progress(bar)
        if written < len(records):
            raise ArAnchorError(
                f"the source gave {written} frames when decoded again, {len(records)} the first time: "
                "outputs cover those frames only"
            )
        passes["done"].append("write")
        del passes["writing"]


SPOOL_NAME = "offline spool (temporary)"  # the spool in summary.json's ``incomplete``: it has no name of its own


def _spool_failure(out_dir: Path, spool: SpoolStore[Any], err: OSError) -> OutputError:
    """The error for the offline replay's spool (an unnamed temporary file in ``out_dir``) failing to grow."""
    what = (
        f"{printable(out_dir)}/: the offline replay's spool (an unnamed temporary file there, "
        f"{spool.size_bytes / 1e6:.1f} MB for {len(spool)} frames) cannot grow"
    )
    if is_disk_full(err):
        return DiskFullError(
            f"{what}: the disk is full ({err.strerror or err}); replay --causal writes as it goes, with no spool",
            out_dir / SPOOL_NAME,
        )
    return OutputError(f"{what} ({err.strerror or err})")


def _write_offline(
    source: FrameSource,
    records: _Records,
    results: Iterator[FrameResult],
    outputs: RunOutputs,
    guard: InterruptGuard,
    options: RunOptions,
    progress: Callable[[int, int], Any] | None,
) -> int:
    """The offline replay's last pass: ``source`` decoded again, each frame written with its offline
    result; the number of frames written."""
    feed = _FrameFeed(source, source.info, options, guard)
    written = 0
    try:
        for frame, _ in feed:
            if written >= len(records):
                break
            causal, truth, stages = records[written]
            if (frame.index, frame.timestamp_ns) != (causal.index, causal.timestamp_ns):
                raise ArAnchorError(
                    f"the source gave frame {frame.index} at {frame.timestamp_ns} ns when decoded again, frame "
                    f"{causal.index} at {causal.timestamp_ns} ns the first time: outputs cover the frames before"
                )
            result = next(results)
            with guard.critical():
                outputs.write(frame, result, truth, stages)
            written += 1
            if progress is not None:
                progress(written, len(records))
    finally:
        feed.close()
    return written


@contextmanager
def _said_once() -> Iterator[None]:
    """The source decoded a second time (an offline replay's write pass) says nothing below an error: its
    warnings (a damaged image, a file's quirks) were said in the first pass."""
    sources = logging.getLogger("ar_anchor.sources")
    level = sources.level
    sources.setLevel(logging.ERROR)
    try:
        yield
    finally:
        sources.setLevel(level)


def _close_progress(progress: object) -> None:
    close = getattr(progress, "close", None)
    if close is not None:
        close()


class _Records:
    """The first pass's spooled (result, truth, stages) by position, the last one read kept (the output
    pass reads each twice: for the offline result and for its truth); :attr:`results` the results alone."""

    def __init__(self, spool: SpoolStore[tuple[FrameResult, Any, dict[str, float]]]) -> None:
        self._spool = spool
        self._last: tuple[int, tuple[FrameResult, Any, dict[str, float]]] | None = None
        self.results = _ResultsView(self)

    def __len__(self) -> int:
        return len(self._spool)

    def __getitem__(self, position: int) -> tuple[FrameResult, Any, dict[str, float]]:
        if self._last is None or self._last[0] != position:
            self._last = (position, self._spool[position])
        return self._last[1]


class _ResultsView:
    """The results of :class:`_Records`, by position (a :class:`~ar_anchor.track.offline.FrameStore`)."""

    def __init__(self, records: _Records) -> None:
        self._records = records

    def __len__(self) -> int:
        return len(self._records)

    def __getitem__(self, position: int) -> FrameResult:
        return self._records[position][0]
