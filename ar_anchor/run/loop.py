"""Wire a frame source, a tracker and the outputs together for one run.

Outputs in ``out_dir``: ``poses.csv``, ``summary.json``, ``recording.rrd`` and, when asked,
``raw.mkv`` + ``raw.mkv.timestamps.csv`` (the processed frames, lossless). Whatever happens (end
of stream, an error, Ctrl-C, SIGTERM) every output is closed so that it stays complete and
readable; ``summary.json`` then says how the run ended (``status``).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..camera import opencv_path_problem
from ..errors import InputError
from ..render.overlay import OverlayRenderer
from ..render.video import SUPPORTED_EXTENSIONS, AnnotatedVideoWriter
from ..sources.base import Frame, FrameSource
from ..track.tracker import FrameResult, Tracker
from ..viz.recorder import RerunRecorder
from .outputs import PosesCsvWriter, RawVideoWriter, RunSummary, prepare_out_dir, write_json_atomic
from .threads import OutputStage, Prefetcher

__all__ = ["RunOptions", "RunOutputs", "run_session"]

log = logging.getLogger(__name__)


class _InterruptGuard:
    """Turns SIGINT/SIGTERM into KeyboardInterrupt, but never in the middle of writing one frame's
    outputs: a signal that arrives there is held until the frame is complete, so ``poses.csv``,
    the recording and ``summary.json`` always agree on the last frame. Main thread only; elsewhere
    it does nothing."""

    def __init__(self) -> None:
        self._previous: dict[int, Any] = {}
        self._critical = False
        self._pending: int | None = None

    def __enter__(self) -> _InterruptGuard:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        if self._pending is not None and exc_type is None:
            signum, self._pending = self._pending, None
            raise KeyboardInterrupt(f"signal {signum}")

    def hold(self) -> None:
        """From now on (closing the outputs), hold signals until the guard exits: a late Ctrl-C must not
        cut the flush of a recording or the last frames of a video."""
        self._critical = True

    def _handle(self, signum: int, _frame: object) -> None:
        if self._critical:
            self._pending = signum
            return
        raise KeyboardInterrupt(f"signal {signum}")

    @contextmanager
    def critical(self) -> Iterator[None]:
        self._critical = True
        try:
            yield
        finally:
            self._critical = False
        if self._pending is not None:
            signum, self._pending = self._pending, None
            raise KeyboardInterrupt(f"signal {signum}")


@dataclass(frozen=True)
class RunOptions:
    """How a run logs and records, beyond the tracker itself."""

    max_frames: int | None = None
    spawn: bool = False
    connect: str | None = None  # a running rerun viewer's gRPC URL
    recording_name: str = "ar_anchor"
    record_raw: bool = False  # also write raw.mkv (lossless) + timestamps
    record_fps: float = 30.0
    video_asset: Path | None = None  # reference this MP4 in the recording instead of JPEG frames
    video_out: Path | None = None  # write the annotated (overlay) video here
    overlays: bool = True  # draw the config's overlays (rerun's camera/overlay and --video-out)
    decode_queue: int = 4  # frames decoded ahead of the tracker (file and synthetic sources)
    output_queue: int = 8  # tracked frames waiting for their overlay, video and rerun log
    extra_summary: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunOutputs:
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
    progress: Callable[[int, int | None, FrameResult], Any] | None = None,
    summary_extras: Callable[[], dict[str, Any]] | None = None,
) -> RunOutputs:
    """Track every frame of ``source`` (up to ``options.max_frames``) and write the outputs to ``out_dir``.

    ``progress(frames_done, total, result)`` is called after each frame (total may be None);
    ``summary_extras()`` is merged into ``summary.json`` when the run ends, however it ends.
    """
    options = options or RunOptions()
    # models (mesh files) are read before any output exists: a bad model is a clean input error
    renderer = OverlayRenderer(tracker.config, tracker.camera) if options.overlays or options.video_out else None
    if options.video_out is not None and options.video_out.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise InputError(
            f"--video-out {options.video_out}: unsupported extension (use {', '.join(SUPPORTED_EXTENSIONS)})"
        )
    if options.video_out is not None and (problem := opencv_path_problem(options.video_out)):
        raise InputError(f"--video-out {os.fsencode(options.video_out)!r}: {problem}")
    out_dir = prepare_out_dir(out_dir)
    poses_csv, summary_json, recording_rrd = out_dir / "poses.csv", out_dir / "summary.json", out_dir / "recording.rrd"
    raw_video = out_dir / "raw.mkv" if options.record_raw else None
    total = source.frame_count
    if options.max_frames is not None:
        total = options.max_frames if total is None else min(total, options.max_frames)

    summary = RunSummary()
    extra_counts: dict[str, Any] = {}
    status = "incomplete"
    data: dict[str, Any] = {}
    image_logging = "none"
    live = bool(getattr(source, "live", False))
    outputs_stage: OutputStage | None = None
    switch_interval = sys.getswitchinterval()
    if live:
        # the tracker shares the GIL with the output thread: hand it over every 1 ms instead of 5, so that
        # a frame's pose waits less for the logger (measured: median capture-to-pose 10-15 % lower)
        sys.setswitchinterval(min(switch_interval, 0.001))
    start = time.perf_counter()
    try:
        with ExitStack() as stack:
            guard = stack.enter_context(_InterruptGuard())  # exited last: after every output is closed
            recorder = RerunRecorder(
                recording_rrd,
                camera=tracker.camera,
                settings=tracker.config.recording,
                spawn=options.spawn,
                connect=options.connect,
                recording_name=options.recording_name,
            )
            stack.callback(recorder.close)
            stack.callback(lambda: extra_counts.update(recording_parts=[p.name for p in recorder.parts]))
            if renderer is not None:
                recorder.overlay_models = renderer.models_for
            image_logging = "jpeg"
            if options.video_asset is not None and recorder.use_video(options.video_asset, source.frame_count):
                image_logging = "video_asset"
            csv_writer = stack.enter_context(PosesCsvWriter(poses_csv))
            raw_writer = None
            if raw_video is not None:
                raw_writer = RawVideoWriter(raw_video, fps=options.record_fps)
                stack.callback(raw_writer.close)
            video_writer = None
            if options.video_out is not None:
                video_writer = AnnotatedVideoWriter(options.video_out, fps=options.record_fps)
                stack.callback(video_writer.close)
                stack.callback(lambda: extra_counts.update(video_frames=video_writer.frames))

            def output(frame: Frame, result: FrameResult, stages: dict[str, float]) -> dict[str, float]:
                """Overlay, --video-out and the rerun log of one frame (in the output thread)."""
                t0 = time.perf_counter()
                annotated = None
                if renderer is not None and (video_writer is not None or recorder.wants_image(frame)):
                    annotated = renderer.annotate(frame.image, result)
                t1 = time.perf_counter()
                if video_writer is not None:
                    video_writer.write(annotated)
                recorder.log_frame(frame, result, annotated, stages=stages)
                t2 = time.perf_counter()
                measured = {"render_ms": (t1 - t0) * 1e3, "log_ms": (t2 - t1) * 1e3}
                recorder.log_latency(measured)
                return measured

            # closed first (callbacks run last-in first-out): the queued frames reach the recorder and the
            # video before those close
            outputs_stage = OutputStage(output, depth=options.output_queue)
            stack.callback(outputs_stage.close)
            frames: Iterable[tuple[Frame, float | None]]
            if live or options.max_frames == 0:
                frames = ((frame, None) for frame in (source if options.max_frames != 0 else ()))
            else:
                prefetcher = Prefetcher(source, depth=options.decode_queue)
                stack.callback(prefetcher.close)
                frames = prefetcher
            stack.callback(guard.hold)  # runs first when the block ends: the closing is not interrupted
            for frame, decode_ms in frames:
                began_ns = time.monotonic_ns()
                result = tracker.process(frame)
                tracked_ns = time.monotonic_ns()
                stages = {} if decode_ms is None else {"decode_ms": decode_ms}
                if frame.arrived_ns is not None:
                    stages["wait_ms"] = (began_ns - frame.arrived_ns) * 1e-6
                    stages["capture_to_pose_ms"] = (tracked_ns - frame.arrived_ns) * 1e-6
                truth = None if frame.truth is None else {k: v for k, v in frame.truth.items() if tracker.reports(k)}
                with guard.critical():
                    if raw_writer is not None:
                        raw_writer.write(frame.image, frame.index, frame.timestamp_ns)
                    csv_writer.write(result)
                    summary.add(result, truth, stages)
                    # live: the tracker never waits for the rerun log (a frame it cannot take is not logged),
                    # unless --video-out asks for a video of every tracked frame
                    outputs_stage.submit(frame, result, stages, block=not live or video_writer is not None)
                if progress is not None:
                    progress(summary.frames, total, result)
                if options.max_frames is not None and summary.frames >= options.max_frames:
                    break  # before taking another frame from the source
        status = "completed"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    except BaseException:
        status = "failed"
        raise
    finally:
        sys.setswitchinterval(switch_interval)
        wall = time.perf_counter() - start
        extras = dict(options.extra_summary)
        if options.video_out is not None:
            extras["video_out"] = {"path": str(options.video_out), "frames": extra_counts.get("video_frames", 0)}
        if len(extra_counts.get("recording_parts", ())) > 1:
            extras["recording_parts"] = extra_counts["recording_parts"]  # open together: rerun recording*.rrd
        if outputs_stage is not None:
            summary.add_latency(outputs_stage.latency_ms)
            extras["frames_logged"] = outputs_stage.done
            if outputs_stage.skipped:
                extras["frames_not_logged"] = outputs_stage.skipped
                log.warning(
                    "%d frame(s) tracked but not logged or drawn: the outputs could not keep up (live mode "
                    "never makes the tracker wait); they are in poses.csv",
                    outputs_stage.skipped,
                )
        if summary_extras is not None:
            extras.update(summary_extras())
        data = summary.as_dict(wall, status=status, image_logging=image_logging, **extras)
        write_json_atomic(summary_json, data)
    return RunOutputs(out_dir, poses_csv, summary_json, recording_rrd, raw_video, data)
