"""Everything one run writes, owned by one object that opens it and closes it in a written-down order.

:class:`RunOutputs` owns ``poses.csv``, the statistics for ``summary.json`` and ``raw.mkv`` (``--record``),
written in the tracker's process, and the worker that draws and logs each tracked frame behind the tracker:
the rerun recording (not with ``--no-recording``), the annotated video (``--video-out``) and images
(``--images-out``), in a process of its own (:class:`~.output_process.OutputProcess`; or a thread of this
process, ``RunOptions(output_process=False)``: :class:`~.threads.OutputThread`).

:meth:`RunOutputs.close` closes them in this order, each step taken even when one before it failed
(the last failure is raised, with the earlier ones as its context, as nested ``finally`` blocks would):

1. the worker: it finishes the frames already queued, so that the recording and the annotated video end
   on the same frame as ``poses.csv``; then it closes the annotated video (its encoder flushed, the
   container finalised), the annotated images' list and the recording (flushed, bounded so that a viewer
   that went away does not hang the end), in that order (:meth:`.output_worker.OutputWorker.close`);
2. ``raw.mkv`` and its timestamps;
3. ``poses.csv`` (flushed after every frame already).

:meth:`RunOutputs.write_summary` then writes ``summary.json``, whatever happened before: how the run
ended, and how many frames reached the video and the recording, which only the closed outputs know.
An output that fails to open leaves those opened before it to :meth:`~RunOutputs.close`; the summary
is still written. A worker process that died (killed, crashed) leaves the tracking going: its outputs
are named incomplete (``summary.json``'s ``incomplete``, and the one error the run ends with, exit 1).

A full disk: the outputs are made so that it loses nothing already written. The output directory is locked
for the run (:class:`~.paths.OutDirLock`) and ``summary.json`` is written at once (status ``running``), with
room for the final one set aside (:class:`~.outputs.SummaryFile`) and some slack given back at the first
file the disk refuses, for the others to finish in (the recording's footer). ``poses.csv`` keeps whole rows.
The error raised is the first file that could not be written (:class:`~.outputs.DiskFullError`), with the
files left incomplete; ``summary.json`` lists them (``incomplete``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..camera import CameraModel
from ..config import RecordingConfig
from ..errors import OutputError
from ..geometry import Pose
from ..render.overlay import OverlayRenderer
from ..sources.base import Frame, SourceInfo
from ..track.results import FrameResult
from .options import RunOptions
from .output_process import OutputProcess
from .output_worker import OutputSpec, OutputWorker, WorkerCounts, close_in_order
from .outputs import DiskFullError, PosesCsvWriter, RawVideoWriter, RunSummary, SummaryFile, is_disk_full
from .paths import OutDirLock
from .threads import OutputThread

__all__ = ["RunOutputs", "close_in_order"]

log = logging.getLogger(__name__)

_SUMMARY_ROOM = 128 * 1024  # bytes set aside for summary.json (a run of hundreds of targets fits)
_SLACK = 384 * 1024  # and given back at the first full-disk error, for the other files to finish


def _worker(spec: OutputSpec, options: RunOptions) -> OutputProcess | OutputThread:
    """The worker for ``spec``: in a process of its own (``output_process``), or, where no such process can be
    started (no interpreter to run, a platform without inherited file descriptors), in a thread of this one."""
    if options.output_process:
        try:
            return OutputProcess(spec, depth=options.output_queue)
        except OSError as err:
            log.warning("the outputs run in a thread of the tracker's process: no process of their own (%s)", err)
    return OutputThread(spec, depth=options.output_queue)


class RunOutputs:
    """The outputs of one run into ``out_dir`` (see the module doc for the order they close in).

    Use: :meth:`open`, :meth:`write` each tracked frame, :meth:`close`, :meth:`write_summary`.
    """

    def __init__(self, out_dir: Path, options: RunOptions) -> None:
        self.out_dir = out_dir
        self.poses_csv = out_dir / "poses.csv"
        self.summary_json = out_dir / "summary.json"
        self.recording_rrd = out_dir / "recording.rrd"
        self.raw_video = out_dir / "raw.mkv" if options.record_raw else None
        self.summary = RunSummary()
        self.image_logging = "none"  # how the recording holds the images: none, jpeg or video_asset
        self._options = options
        self._first_failure: DiskFullError | None = None  # the first file a full disk refused
        self._incomplete: list[str] = []  # files a full disk left incomplete
        self._lock = OutDirLock(out_dir)
        self._lock.acquire()
        self._summary_file = SummaryFile(self.summary_json, reserve=_SUMMARY_ROOM, slack=_SLACK)
        try:  # a summary at once (an interrupted run's directory never shows the previous run's), and room
            self._summary_file.write(self.summary.as_dict(0.0, status="running", **options.extra_summary))
            self._summary_file.reserve()
        except BaseException:
            self._lock.release()
            raise
        self._live = False
        self._csv: PosesCsvWriter | None = None
        self._raw: RawVideoWriter | None = None
        self._stage: OutputProcess | OutputThread | None = None  # the recording, --video-out, --images-out
        self._stage_open = False
        self._opening: threading.Thread | None = None  # opens the outputs (see open)
        self._open_error: BaseException | None = None  # what failed to open them, not raised yet
        # what the closed outputs report in summary.json
        self._counts = WorkerCounts()
        self._lost: list[str] = []  # the worker's outputs, when its process died: incomplete

    # ------------------------------------------------------------------ opening
    def open(
        self,
        camera: CameraModel,
        recording: RecordingConfig,
        info: SourceInfo,
        renderer: OverlayRenderer | None,
    ) -> None:
        """Start the worker (it opens the recording, the annotated video and images), open ``poses.csv`` and
        ``raw.mkv``. ``renderer`` draws the overlays
        (None: none drawn); ``info``: the source's, for the worker's policy (live: never make the tracker
        wait) and the recording's video reference. The recording holds the overlay models (the viewer
        projects them onto the frame) unless ``--no-overlay``.

        They are opened in a thread of its own, while the tracker takes on the first frame. :meth:`write`
        waits until that thread is done (:meth:`wait_open`), and raises what failed to open ``poses.csv`` or
        ``raw.mkv`` or to start the worker (nothing written yet: ``poses.csv`` gets no row); :meth:`close`
        waits too. The worker's process opens its own outputs meanwhile (its imports and the recording take
        0.5-1 s, which do not hold up the first poses: the frames wait in its pipe); what fails there is
        raised at the first frame after it is known (:meth:`poll`), at the latest by :meth:`close`."""
        self._live = info.live
        self._opening = threading.Thread(
            target=self._open_in_thread, args=(camera, recording, info, renderer), name="open-outputs"
        )
        self._opening.start()

    def _open_in_thread(
        self, camera: CameraModel, recording: RecordingConfig, info: SourceInfo, renderer: OverlayRenderer | None
    ) -> None:
        try:
            self._open(camera, recording, info, renderer)
        except BaseException as err:  # noqa: BLE001 - raised in the caller's thread by wait_open
            self._open_error = err

    def wait_open(self) -> None:
        """Wait until :meth:`open`'s thread is done; raise (once) what failed to open the outputs (an offline
        replay, which writes nothing until its last pass, calls it after its first frame)."""
        if self._opening is not None:
            self._opening.join()
            self._opening = None
        if self._open_error is not None:
            err, self._open_error = self._open_error, None
            raise err

    def poll(self) -> None:
        """Raise what the worker failed at, once known (its outputs failing to open, an error while writing):
        for an offline replay's first pass, which hands the worker nothing."""
        if self._stage is not None and self._stage_open:
            try:
                self._stage.poll()
            except OutputError as err:
                raise self._first(err) from None

    def _open(
        self, camera: CameraModel, recording: RecordingConfig, info: SourceInfo, renderer: OverlayRenderer | None
    ) -> None:
        options = self._options
        if options.recording or options.video_out is not None or options.images_out is not None:
            spec = OutputSpec.of(
                self.recording_rrd, options, camera, recording, renderer, info.video_path, info.frame_count
            )
            self._stage = _worker(spec, options)
            self._stage_open = True
        self._csv = PosesCsvWriter(self.poses_csv)
        if self.raw_video is not None:
            self._raw = RawVideoWriter(self.raw_video, fps=options.record_fps)

    # ------------------------------------------------------------------ per frame
    def write(
        self, frame: Frame, result: FrameResult, truth: Mapping[str, Pose] | None, stages: dict[str, float]
    ) -> None:
        """One tracked frame: ``raw.mkv`` and ``poses.csv`` now (in the tracker's thread), its statistics,
        and its overlay, annotated video frame and rerun log queued for the output thread. Live, a frame
        the output thread has no room for is not drawn or logged (the tracker never waits for it),
        unless ``--video-out`` asks for a video of every tracked frame."""
        self.wait_open()
        assert self._csv is not None, "open() the outputs first"
        try:
            if self._raw is not None:
                self._raw.write(frame.image, frame.index, frame.timestamp_ns)
            self._csv.write(result)
            self.summary.add(result, truth, stages)
            if self._stage is not None:
                every_frame = self._options.video_out is not None or self._options.images_out is not None
                self._stage.submit(frame, result, stages, block=not self._live or every_frame)
        except OutputError as err:
            raise self._first(err) from None

    def failed(self, err: OutputError, path: Path | None = None) -> OutputError:
        """What to raise for ``err``, a failure to write beside the outputs (the offline replay's spool): the
        first full-disk failure of the run, so that it is the one named (see :meth:`_first`)."""
        return self._first(err, path)

    def _first(self, err: OutputError, path: Path | None = None) -> OutputError:
        """What to raise for ``err``: the first full-disk failure of the run once there was one (recorded now
        if ``err`` is it; ``path``: the file it is about, when ``err`` does not say), else ``err``."""
        if is_disk_full(err):
            if self._first_failure is None:
                where = getattr(err, "path", None) or path
                self._first_failure = err if isinstance(err, DiskFullError) else DiskFullError(str(err), where)
                self._summary_file.release_slack()  # room for the other files to finish in
            elif err is not self._first_failure:
                where = getattr(err, "path", None) or path
                if where is not None and self._first_failure.path is None:
                    # the first failure named no file (the output thread's writer): the first one that does
                    # is the one to name (under load the recording's flush fails before its close says so)
                    self._first_failure = err if isinstance(err, DiskFullError) else DiskFullError(str(err), where)
                elif where is not None and where.name not in self._incomplete:
                    self._incomplete.append(where.name)
        return self._first_failure or err

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Close every output that is open, in the module doc's order; idempotent."""
        try:
            close_in_order(
                [
                    self.wait_open,  # what failed to open is raised, and what did open is closed
                    self._close_worker,
                    self._close_raw_video,
                    self._close_poses_csv,
                ]
            )
        except OutputError as err:
            raise self._first(err) from None
        if self._first_failure is not None:
            raise self._first_failure

    def _failure_message(self) -> DiskFullError:
        """The first full-disk failure, naming the files it left incomplete."""
        first = self._first_failure
        assert first is not None
        others = [name for name in self._incomplete if first.path is None or name != first.path.name]
        if not others:
            return first
        return DiskFullError(f"{first}; also incomplete: {', '.join(others)}", first.path)

    def _close_worker(self) -> None:
        """The worker finishes the frames queued, then closes the annotated video, the annotated images'
        list and the recording, in that order (:meth:`.output_worker.OutputWorker.close`)."""
        if self._stage is not None and self._stage_open:
            self._stage_open = False  # kept: its counts go into the summary
            try:
                self._counts = self._stage.close()
            except OutputError:
                if self._stage.gone is not None:
                    self._lost = OutputWorker(self._stage.spec).describe()
                raise

    def _close_raw_video(self) -> None:
        if self._raw is not None:
            raw, self._raw = self._raw, None
            raw.close()

    def _close_poses_csv(self) -> None:
        if self._csv is not None:
            csv, self._csv = self._csv, None
            csv.close()

    def write_summary(self, status: str, wall_time_s: float, extras: Mapping[str, Any]) -> dict[str, Any]:
        """Write ``summary.json`` (after :meth:`close`) and return it: the statistics, ``status`` (how the
        run ended), the options' ``extra_summary``, what the outputs counted, then ``extras``."""
        options = self._options
        counts = dict(options.extra_summary)
        if not options.recording:
            counts["recording"] = False  # (--no-recording: said, so that view can say why there is none)
        video_frames = self._counts.video_frames
        if options.video_out is not None and video_frames:  # (opened at its first frame: none, no file)
            counts["video_out"] = {"path": str(options.video_out), "frames": video_frames}
        if options.images_out is not None:
            counts["images_out"] = {"folder": str(options.images_out.folder), "images": self._counts.stills_written}
        if len(self._counts.recording_parts) > 1:
            counts["recording_parts"] = self._counts.recording_parts  # open together: rerun recording*.rrd
        if self._stage is not None:
            self.summary.add_latency(self._stage.latency_ms)
            counts["frames_logged"] = self._stage.done
            if self._stage.skipped:
                counts["frames_not_logged"] = self._stage.skipped
            if self._stage.skipped and not self._lost:  # (a dead output process: its own error says so)
                log.warning(
                    "%d frame(s) tracked but not logged or drawn: the outputs could not keep up (live mode "
                    "never makes the tracker wait); they are in poses.csv",
                    self._stage.skipped,
                )
        if self._first_failure is not None:
            first = self._first_failure.path
            counts["incomplete"] = [first.name if first is not None else "an output", *self._incomplete]
        elif self._lost:
            counts["incomplete"] = self._lost
        counts.update(extras)
        if self._stage is not None and self._stage.image_logging is not None:
            self.image_logging = self._stage.image_logging
        data = self.summary.as_dict(wall_time_s, status=status, image_logging=self.image_logging, **counts)
        try:
            self._summary_file.write(data)
        except OutputError as err:
            raise self._first(err, self.summary_json) from None
        finally:
            self._lock.release()
        if self._first_failure is not None:
            raise self._failure_message()
        return data
