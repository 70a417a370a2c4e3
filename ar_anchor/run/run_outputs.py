"""Everything one run writes, owned by one object that opens it and closes it in a written-down order.

:class:`RunOutputs` owns ``poses.csv``, the statistics for ``summary.json``, ``raw.mkv`` (``--record``),
the annotated video (``--video-out``) and images (``--images-out``), the rerun recording, and the output
thread that draws and logs each tracked frame behind the tracker (:class:`~.threads.OutputStage`).

:meth:`RunOutputs.close` closes them in this order, each step taken even when one before it failed
(the last failure is raised, with the earlier ones as its context, as nested ``finally`` blocks would):

1. the output thread: it finishes the frames already queued, so that the recording and the annotated
   video end on the same frame as ``poses.csv``; it writes into both, so it stops first;
2. the annotated video: its encoder flushed, the container finalised (playable even if that fails);
3. the annotated images' list (each image was written whole as it came);
4. ``raw.mkv`` and its timestamps;
5. ``poses.csv`` (flushed after every frame already);
6. the recording: flushed (bounded, so a viewer that went away does not hang the end) and closed.

:meth:`RunOutputs.write_summary` then writes ``summary.json``, whatever happened before: how the run
ended, and how many frames reached the video and the recording, which only the closed outputs know.
An output that fails to open leaves those opened before it to :meth:`~RunOutputs.close`; the summary
is still written.

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
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..camera import CameraModel
from ..config import RecordingConfig
from ..errors import OutputError
from ..geometry import Pose
from ..render.overlay import OverlayRenderer
from ..render.video import AnnotatedVideoWriter
from ..sources.base import Frame, SourceInfo
from ..track.results import FrameResult
from .options import RunOptions
from .outputs import DiskFullError, PosesCsvWriter, RawVideoWriter, RunSummary, SummaryFile, is_disk_full
from .paths import OutDirLock
from .stills import AnnotatedStillsWriter
from .threads import OutputStage

if TYPE_CHECKING:  # imported by the thread that opens the outputs (rerun: 0.3-0.5 s), see RunOutputs.open
    from ..viz.recorder import RerunRecorder

__all__ = ["RunOutputs", "close_in_order"]

log = logging.getLogger(__name__)

_SUMMARY_ROOM = 128 * 1024  # bytes set aside for summary.json (a run of hundreds of targets fits)
_SLACK = 384 * 1024  # and given back at the first full-disk error, for the other files to finish


def close_in_order(steps: Sequence[Callable[[], object]]) -> None:
    """Call every step in turn, even after one raised; then raise the last failure, the earlier ones
    chained as its context (what nested ``try/finally`` blocks, or an ``ExitStack``, would raise)."""
    failure: BaseException | None = None
    for step in steps:
        try:
            step()
        except BaseException as err:  # noqa: BLE001 - raised below, once every step ran
            if failure is not None and err is not failure:
                err.__context__ = failure
            failure = err
    if failure is not None:
        raise failure


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
        self._renderer: OverlayRenderer | None = None
        self._recorder: RerunRecorder | None = None
        self._csv: PosesCsvWriter | None = None
        self._raw: RawVideoWriter | None = None
        self._video: AnnotatedVideoWriter | None = None
        self._stills: AnnotatedStillsWriter | None = None
        self._stage: OutputStage | None = None
        self._stage_open = False
        self._opening: threading.Thread | None = None  # opens the outputs (see open)
        self._open_error: BaseException | None = None  # what failed to open them, not raised yet
        # what the closed outputs report in summary.json
        self._video_frames = 0
        self._stills_written = 0
        self._recording_parts: list[str] = []

    # ------------------------------------------------------------------ opening
    def open(
        self,
        camera: CameraModel,
        recording: RecordingConfig,
        info: SourceInfo,
        renderer: OverlayRenderer | None,
    ) -> None:
        """Open the recording, ``poses.csv``, ``raw.mkv``, the annotated video and the output thread, in
        this order. ``renderer`` draws the overlays (None: none drawn); ``info``: the source's, for the
        output thread's policy (live: never make the tracker wait) and the recording's video reference.
        The recording holds the overlay models (the viewer projects them onto the frame) unless ``--no-overlay``.

        They are opened in a thread of its own, while the tracker takes on the first frame: importing rerun
        and opening the recording take 0.3-0.5 s, which once came before the first frame was tracked.
        :meth:`write` waits until they are open (:meth:`wait_open`), and raises what failed to open them,
        as this method did (nothing written yet: ``poses.csv`` gets no row); :meth:`close` waits too. No
        signal is raised in that thread: rerun is never imported halfway."""
        self._live = info.live
        self._renderer = renderer
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

    def _open(
        self, camera: CameraModel, recording: RecordingConfig, info: SourceInfo, renderer: OverlayRenderer | None
    ) -> None:
        from ..viz.recorder import RerunRecorder  # rerun: see open

        options = self._options
        self._recorder = RerunRecorder(
            self.recording_rrd,
            camera=camera,
            settings=recording,
            spawn=options.spawn,
            connect=options.connect,
            recording_name=options.recording_name,
            camera_name=options.camera_name,
            recording_id=options.recording_id,
            overlay_models=renderer.models_for if renderer is not None and options.overlays else None,
        )
        self.image_logging = "jpeg"
        if info.video_path is not None and self._recorder.use_video(info.video_path, info.frame_count):
            self.image_logging = "video_asset"
        self._csv = PosesCsvWriter(self.poses_csv)
        if self.raw_video is not None:
            self._raw = RawVideoWriter(self.raw_video, fps=options.record_fps)
        if options.video_out is not None:
            self._video = AnnotatedVideoWriter(options.video_out, fps=options.record_fps)
        if options.images_out is not None:
            self._stills = AnnotatedStillsWriter(options.images_out)
        self._stage = OutputStage(self._draw_and_log, depth=options.output_queue)
        self._stage_open = True

    # ------------------------------------------------------------------ per frame
    def write(
        self, frame: Frame, result: FrameResult, truth: Mapping[str, Pose] | None, stages: dict[str, float]
    ) -> None:
        """One tracked frame: ``raw.mkv`` and ``poses.csv`` now (in the tracker's thread), its statistics,
        and its overlay, annotated video frame and rerun log queued for the output thread. Live, a frame
        the output thread has no room for is not drawn or logged (the tracker never waits for it),
        unless ``--video-out`` asks for a video of every tracked frame."""
        self.wait_open()
        assert self._csv is not None and self._stage is not None, "open() the outputs first"
        try:
            if self._raw is not None:
                self._raw.write(frame.image, frame.index, frame.timestamp_ns)
            self._csv.write(result)
            self.summary.add(result, truth, stages)
            every_frame = self._video is not None or self._stills is not None
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

    def _draw_and_log(self, frame: Frame, result: FrameResult, stages: dict[str, float]) -> dict[str, float]:
        """The overlay, ``--video-out`` and the rerun log of one frame (in the output thread). The overlay is
        rasterised only for ``--video-out`` and ``[recording] overlay_images`` (not with ``--no-overlay``):
        the viewer draws the recording's own from its 3D models."""
        recorder = self._recorder
        assert recorder is not None
        t0 = time.perf_counter()
        annotated = None
        overlay_image = self._options.overlays and recorder.wants_overlay_image(frame)
        still = self._stills is not None and self._stills.wants(frame.index)
        if self._renderer is not None and (self._video is not None or overlay_image or still):
            annotated = self._renderer.annotate(frame.image, result)
        t1 = time.perf_counter()
        if self._video is not None:
            self._video.write(annotated)
        if still and annotated is not None:
            self._stills.write(frame.index, annotated)  # type: ignore[union-attr]
        recorder.log_frame(frame, result, annotated if overlay_image else None, stages=stages)
        t2 = time.perf_counter()
        measured = {"render_ms": (t1 - t0) * 1e3, "log_ms": (t2 - t1) * 1e3}
        recorder.log_latency(measured)
        return measured

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Close every output that is open, in the module doc's order; idempotent."""
        try:
            close_in_order(
                [
                    self.wait_open,  # what failed to open is raised, and what did open is closed
                    self._stop_output_thread,
                    self._close_annotated_video,
                    self._close_stills,
                    self._close_raw_video,
                    self._close_poses_csv,
                    self._close_recording,
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

    def _stop_output_thread(self) -> None:
        if self._stage is not None and self._stage_open:
            self._stage_open = False  # kept: its counts go into the summary
            self._stage.close()

    def _close_annotated_video(self) -> None:
        if self._video is not None:
            video, self._video = self._video, None
            self._video_frames = video.frames
            try:
                video.close()
            except OutputError as err:
                raise self._first(err, Path(video.path)) from None

    def _close_stills(self) -> None:
        if self._stills is not None:
            stills, self._stills = self._stills, None
            self._stills_written = stills.written
            stills.close()

    def _close_raw_video(self) -> None:
        if self._raw is not None:
            raw, self._raw = self._raw, None
            raw.close()

    def _close_poses_csv(self) -> None:
        if self._csv is not None:
            csv, self._csv = self._csv, None
            csv.close()

    def _close_recording(self) -> None:
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            self._recording_parts = [part.name for part in recorder.parts]
            try:
                recorder.close()
            except OutputError as err:
                raise self._first(err, recorder.parts[-1] if recorder.parts else None) from None

    def write_summary(self, status: str, wall_time_s: float, extras: Mapping[str, Any]) -> dict[str, Any]:
        """Write ``summary.json`` (after :meth:`close`) and return it: the statistics, ``status`` (how the
        run ended), the options' ``extra_summary``, what the outputs counted, then ``extras``."""
        options = self._options
        counts = dict(options.extra_summary)
        if options.video_out is not None and self._video_frames:  # (opened at its first frame: none, no file)
            counts["video_out"] = {"path": str(options.video_out), "frames": self._video_frames}
        if options.images_out is not None:
            counts["images_out"] = {"folder": str(options.images_out.folder), "images": self._stills_written}
        if len(self._recording_parts) > 1:
            counts["recording_parts"] = self._recording_parts  # open together: rerun recording*.rrd
        if self._stage is not None:
            self.summary.add_latency(self._stage.latency_ms)
            counts["frames_logged"] = self._stage.done
            if self._stage.skipped:
                counts["frames_not_logged"] = self._stage.skipped
                log.warning(
                    "%d frame(s) tracked but not logged or drawn: the outputs could not keep up (live mode "
                    "never makes the tracker wait); they are in poses.csv",
                    self._stage.skipped,
                )
        if self._first_failure is not None:
            first = self._first_failure.path
            counts["incomplete"] = [first.name if first is not None else "an output", *self._incomplete]
        counts.update(extras)
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
