"""The outputs that draw and log each tracked frame: the rerun recording, the overlay, ``--video-out`` and
``--images-out`` (:class:`OutputWorker`), opened from a description that crosses a process boundary
(:class:`OutputSpec`).

The worker runs behind the tracker, in a process of its own (:mod:`.output_process`, the default) or in a
thread (:class:`~.threads.OutputStage`): the same code either way. It opens its outputs, draws and logs one
frame at a time, and closes them in a written-down order (the annotated video, the annotated images' list,
the recording), every step taken even when one before it failed; what they wrote is counted
(:class:`WorkerCounts`), for ``summary.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ..camera import CameraModel
from ..config import RecordingConfig
from ..errors import OutputError
from ..render.overlay import OverlayRenderer
from ..render.video import AnnotatedVideoWriter
from ..sources.base import Frame
from ..track.results import FrameResult
from .options import RunOptions
from .stills import AnnotatedStillsWriter, StillsPlan

if TYPE_CHECKING:  # (rerun: imported when the worker opens, in its own thread or process)
    from ..viz.recorder import RerunRecorder

__all__ = ["OutputSpec", "OutputWorker", "WorkerCounts", "close_in_order"]


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


@dataclass(frozen=True)
class OutputSpec:
    """What the worker opens: the recording (``rrd_path``, its settings and viewer options), the annotated
    video and images, the overlay renderer (None: nothing drawn), and the source's video (referenced by the
    recording instead of JPEG frames when rerun decodes it). Picklable: it is the child process's start."""

    rrd_path: Path | None  # None: no recording (--no-recording)
    camera: CameraModel
    recording: RecordingConfig
    renderer: OverlayRenderer | None
    overlays: bool = True
    spawn: bool = False
    connect: str | None = None
    recording_name: str = "ar_anchor"
    camera_name: str | None = None
    recording_id: str | None = None
    video_out: Path | None = None
    record_fps: float = 30.0
    images_out: StillsPlan | None = None
    video_path: str | None = None
    frame_count: int | None = None

    @classmethod
    def of(
        cls,
        rrd_path: Path,
        options: RunOptions,
        camera: CameraModel,
        recording: RecordingConfig,
        renderer: OverlayRenderer | None,
        video_path: str | None,
        frame_count: int | None,
    ) -> OutputSpec:
        """The spec of a run with ``options``."""
        return cls(
            rrd_path if options.recording else None,
            camera,
            recording,
            renderer,
            overlays=options.overlays,
            spawn=options.spawn,
            connect=options.connect,
            recording_name=options.recording_name,
            camera_name=options.camera_name,
            recording_id=options.recording_id,
            video_out=options.video_out,
            record_fps=options.record_fps,
            images_out=options.images_out,
            video_path=None if video_path is None else str(video_path),
            frame_count=frame_count,
        )

    def needs_pixels(self, index: int, image_logging: str) -> bool:
        """Does the worker read frame ``index``'s image? For ``--video-out``, an annotated still, or the
        recording's JPEG (not when the recording references the source video: ``image_logging``)."""
        if self.video_out is not None:
            return True
        if self.images_out is not None and index in self.images_out.names:
            return True
        every = self.recording.image_every
        return self.rrd_path is not None and image_logging == "jpeg" and bool(every) and index % every == 0


@dataclass
class WorkerCounts:
    """What the worker's outputs hold once closed: frames in the annotated video, annotated images written,
    the recording's files (names), and how the recording holds the images (``none``, ``jpeg``, ``video_asset``)."""

    video_frames: int = 0
    stills_written: int = 0
    recording_parts: list[str] = field(default_factory=list)
    image_logging: str = "none"


class OutputWorker:
    """Opens the outputs of ``spec`` (the recording first, then the annotated video and images); then
    :meth:`work` for each frame and :meth:`close` once. A failure to open leaves what did open for
    :meth:`close`."""

    def __init__(self, spec: OutputSpec) -> None:
        self.spec = spec
        self.counts = WorkerCounts()
        self._recorder: RerunRecorder | None = None
        self._video: AnnotatedVideoWriter | None = None
        self._stills: AnnotatedStillsWriter | None = None

    def open(self) -> None:
        """Open the recording (it holds the overlay models unless ``--no-overlay``), the annotated video and
        the annotated images' folder, in this order."""
        from ..viz.recorder import RerunRecorder  # rerun: 0.3-0.5 s, in the worker's own time

        spec = self.spec
        if spec.rrd_path is not None:
            self._open_recording(spec, RerunRecorder)
        if spec.video_out is not None:
            self._video = AnnotatedVideoWriter(spec.video_out, fps=spec.record_fps)
        if spec.images_out is not None:
            self._stills = AnnotatedStillsWriter(spec.images_out)

    def _open_recording(self, spec: OutputSpec, recorder: type[RerunRecorder]) -> None:
        renderer = spec.renderer
        self._recorder = recorder(
            spec.rrd_path,
            camera=spec.camera,
            settings=spec.recording,
            spawn=spec.spawn,
            connect=spec.connect,
            recording_name=spec.recording_name,
            camera_name=spec.camera_name,
            recording_id=spec.recording_id,
            overlay_models=renderer.models_for if renderer is not None and spec.overlays else None,
        )
        self.counts.image_logging = "jpeg"
        if spec.video_path is not None and self._recorder.use_video(spec.video_path, spec.frame_count):
            self.counts.image_logging = "video_asset"

    def work(self, frame: Frame, result: FrameResult, stages: dict[str, float]) -> dict[str, float]:
        """The overlay, ``--video-out``, the annotated still and the rerun log of one frame; the times it
        took (``render_ms``, ``log_ms``). The overlay is rasterised only for ``--video-out``, a still and
        ``[recording] overlay_images`` (not with ``--no-overlay``): the viewer draws the recording's own
        from its 3D models."""
        recorder = self._recorder
        renderer = self.spec.renderer
        t0 = time.perf_counter()
        annotated = None
        overlay_image = recorder is not None and self.spec.overlays and recorder.wants_overlay_image(frame)
        still = self._stills is not None and self._stills.wants(frame.index)
        if renderer is not None and (self._video is not None or overlay_image or still):
            annotated = renderer.annotate(frame.image, result)
        t1 = time.perf_counter()
        if self._video is not None:
            self._video.write(annotated)
        if still and annotated is not None:
            self._stills.write(frame.index, annotated)  # type: ignore[union-attr]
        if recorder is not None:
            recorder.log_frame(frame, result, annotated if overlay_image else None, stages=stages)
        t2 = time.perf_counter()
        measured = {"render_ms": (t1 - t0) * 1e3, "log_ms": (t2 - t1) * 1e3}
        if recorder is not None:
            recorder.log_latency(measured)
        return measured

    def close(self, timeout_s: float | None = None) -> WorkerCounts:
        """Close the annotated video, the annotated images' list and the recording, in this order, each
        even when one before it failed (the last failure is raised, the earlier ones its context), and
        count what they hold. ``timeout_s`` bounds the recording's flush (default: its settings')."""
        close_in_order([self._close_video, self._close_stills, lambda: self._close_recording(timeout_s)])
        return self.counts

    def _close_video(self) -> None:
        if self._video is not None:
            video, self._video = self._video, None
            self.counts.video_frames = video.frames
            try:
                video.close()
            except OutputError as err:
                err.path = getattr(err, "path", None) or Path(video.path)  # type: ignore[attr-defined]
                raise

    def _close_stills(self) -> None:
        if self._stills is not None:
            stills, self._stills = self._stills, None
            self.counts.stills_written = stills.written
            stills.close()

    def _close_recording(self, timeout_s: float | None) -> None:
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            self.counts.recording_parts = [part.name for part in recorder.parts]
            try:
                recorder.close(timeout_s)
            except OutputError as err:
                err.path = getattr(err, "path", None) or (  # type: ignore[attr-defined]
                    recorder.parts[-1] if recorder.parts else None
                )
                raise

    def describe(self) -> list[str]:
        """The files this worker writes into (their names), for an error saying what is incomplete."""
        names = [self.spec.rrd_path.name] if self.spec.rrd_path is not None else []
        if self.spec.video_out is not None:
            names.append(str(self.spec.video_out))
        if self.spec.images_out is not None:
            names.append(f"{self.spec.images_out.folder}/")
        return names
