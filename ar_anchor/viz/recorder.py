"""The tracker run's recording: every frame's image, detections, 3D scene, metrics and events.

Entity tree
-----------
``world``                         the anchor target's frame (the first target that gets a pose): its marker
                                  squares (``outline``), ``axes`` and ``overlay/<n>`` meshes
``world/camera``                  ``world_from_camera`` (so the camera centre is ``C = -R^T t``) + ``Pinhole``
``world/camera/image``            the frame (JPEG or a reference into the source video), with ``markers``
                                  outlines + ids, ``corners`` and ``boards/<board>/inliers|outliers`` (the
                                  corners a board's pose used / rejected), all in the frame's own pixels
``world/camera_trajectory``       the camera centre's recent path
``world/targets/<target>``        ``world_from_target`` of every other target, drawn as its marker squares,
                                  axes and ``overlay/<n>`` meshes
``world/labels``                  every target's name at its centre (the 3D view's; not in the AR overlay)
``world/hypotheses``              this frame's solution on each filter branch of every target, faint
``world/truth_camera``            the true camera centre (synthetic sources)
``world/causal``                  offline replay: the live (causal) filter's pose of every target, as thin axes
``camera/overlay``                the annotated image, only with ``[recording] overlay_images``
``metrics/reproj_px/<target>``    RMS reprojection error of the output pose
``metrics/ambiguity/<target>``    IPPE error ratio (worse / better; near 1 = ambiguous)
``metrics/inliers/<target>``      corners a board's pose was solved from
``metrics/flip_evidence_px/<target>``  the filter's flip evidence (signed: + favours branch 0)
``metrics/rotation_error_deg/<target>``  against ground truth, when known
``metrics/offline_vs_causal_deg/<target>``  offline replay: angle between its pose and the live filter's
``metrics/latency/<stage>``       per-stage time, milliseconds
``events``                        state changes, commits, switches, re-acquisitions, resets (TextLog)

The AR overlay is drawn by the viewer: the image is a child of the camera's ``Pinhole``, and the run's
blueprint shows it in a 2D view whose origin is that pinhole and whose contents include the 3D world, so
the viewer projects the targets' meshes, squares and axes onto the frame (:mod:`.blueprints`). Nothing
is rasterised for it: drawing the overlay into an image (:mod:`ar_anchor.render.overlay`) is left to
``--video-out`` and ``overlay_images``. The viewer's pinhole has no lens distortion: the projected overlay
is drawn where an undistorted camera would see it, off by up to the lens's distortion at the image's
edges (logged once in ``events``), while the image and its 2D detections stay in the camera's own
(distorted) pixels. While the anchor is out of view the camera is held where it was last seen and the
other targets are placed from it, so the projection onto the frame stays right (their ``world`` places are
then relative to that held camera).

The ``metrics/*`` series are sent every ``metrics_every`` frames, one call per series holding every frame's
value (:mod:`.series`: a live viewer sees them up to that many frames late). So is what is logged each frame
above when no viewer watches (a file alone): the poses of ``world/camera`` and ``world/targets/<target>``, the
image's ``markers``, ``corners`` and board points, ``world/camera_trajectory``, ``labels``, ``hypotheses``,
``truth_camera`` and ``causal``, one call per entity; with a viewer they go each frame, so that its AR overlay
stays on the frame's image. The images, events, target shapes and clears go when they happen.

A target that is gone (no longer in a frame's results) is cleared once, on that frame, from every
entity above that is its own; it is drawn again when it comes back. The anchor's shape is the
``world`` frame itself and stays.

Several cameras, one recording: a recorder given a ``camera_name`` (``--name``) puts the whole tree above
under ``cameras/<name>/`` (``cameras/left/world/camera``, ``cameras/left/metrics/...``,
``cameras/left/events``), so that processes streaming into one recording (the same ``recording_id``,
``--recording-id``) never write the same entity. Each camera's ``world`` is its own anchor's frame, and
every ``cameras/<name>/world`` sits at the recording's origin: in a 3D view of ``cameras`` the worlds
coincide, which is right when the cameras anchor on the same target (the same marker or board, first seen)
and meaningless otherwise; each camera's own views (``cameras/<name>/world``, its pinhole) are right
either way. The layout: without a name, :func:`.blueprints.run_blueprint` as above; a named camera alone
(no ``recording_id``), the same layout under its prefix; a named camera sharing a recording sends none,
since the viewer keeps one blueprint per application and each process's own would replace the
others' (the viewer's automatic layout shows every camera's views).

Timelines: ``frame`` (sequence) and ``time`` (seconds since the stream's start).
Rerun places pixel *corners* at integers, OpenCV pixel *centres*: 2D positions are shifted by
half a pixel (see :mod:`.sinks`), and so is the pinhole's principal point, so overlays sit exactly on
the image.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from ..camera import CameraModel
from ..config import RecordingConfig
from ..geometry import Pose, angle_between_deg
from ..sources.base import Frame
from ..targets import TargetId, TrackState
from ..track.results import FrameResult, TargetResult
from .blueprints import Framing, run_blueprint
from .parts import (
    Drawings,
    Place,
    Shapes,
    Trail,
    branch_strips,
    camera_in_world,
    causal_axes,
    entity_name,
    mesh3d,
    placed,
)
from .pinhole import _distortion_note, image_from_camera
from .series import SeriesBuffer
from .sinks import Recording

__all__ = ["IMAGE", "OVERLAY_IMAGE", "RerunRecorder"]

log = logging.getLogger(__name__)

_STATE_COLOURS = {
    TrackState.TRACKED: (40, 220, 80),
    TrackState.AMBIGUOUS: (250, 190, 30),
    TrackState.PREDICTED: (120, 120, 255),
    TrackState.INTERPOLATED: (90, 200, 230),
}
_FAILED_COLOUR = (255, 60, 60)
_MEMBER_RADIUS = 0.5  # the outline of a marker drawn as part of its board (FrameResult.board_members)
_METRICS = ("reproj_px", "ambiguity", "inliers", "flip_evidence_px", "rotation_error_deg")  # per target
_SHAPES_KEPT = 256  # the targets' outlines and axes kept built (a learned group's outline changes)
_TRAJECTORY_POINTS = 1000  # the camera's trajectory line keeps the last this many centres
_NO_AXES = Recording.prebuilt(rr.TransformAxes3D(axis_length=0.0))  # a gone target's axes (_clear_gone)
_SINK_CHECK_S = 2.0  # how often the sinks are flushed to find out whether they still write
IMAGE = "world/camera/image"  # the frame, under the camera's pinhole (where the viewer projects the 3D scene)
OVERLAY_IMAGE = "camera/overlay"  # the annotated image (``overlay_images``), outside the projected world


class RerunRecorder:
    """Logs frames and tracker results to an ``.rrd`` file and/or a viewer (spawned, or ``connect``: its URL).

    ``overlay_models``: a target -> its overlay models in the target frame, drawn in the 3D scene
    (given when the run draws overlays). ``camera_name``: the camera's own subtree (``cameras/<name>/``) and
    ``recording_id``: the recording it shares with other processes (see the module doc: no layout is sent
    when both are given).
    """

    def __init__(
        self,
        rrd_path: str | os.PathLike[str] | None,
        *,
        camera: CameraModel,
        settings: RecordingConfig | None = None,
        spawn: bool = False,
        connect: str | None = None,
        recording_name: str = "ar_anchor",
        overlay_models: Callable[[TargetResult], list[Any]] | None = None,
        camera_name: str | None = None,
        recording_id: str | None = None,
    ) -> None:
        self.settings = settings or RecordingConfig()
        self.camera = camera
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        self.overlay_models = overlay_models
        self.root = f"cameras/{camera_name}" if camera_name else None
        self._sends_layout = not (camera_name and recording_id)  # a shared recording's layout is not one camera's
        blueprint = self._layout() if self._sends_layout else None
        self.recording = Recording(
            "ar_anchor",
            path=rrd_path,
            spawn=spawn,
            connect=connect,
            blueprint=blueprint,
            name=recording_name,
            recording_id=recording_id,
            root=self.root,
        )
        # a viewer watching live gets each frame's scene at once (its AR overlay on the frame's image)
        at_once = self.recording.viewer_url is not None
        self.series = SeriesBuffer(self.recording, self.settings.metrics_every, at_once=at_once)
        self._part_started = time.monotonic()
        self._part_media_ns: int | None = None  # the first frame's timestamp in the current file
        self.anchor: TargetId | None = None
        self._shapes_logged: set[TargetId] = set()  # targets whose shape is in the current part and not cleared
        self._drawn: dict[TargetId, set[str]] = {}  # a target -> its entities logged since it was last cleared
        self._meshes: dict[TargetId, list[rr.Mesh3D]] = {}  # a target -> its overlay models as meshes
        self._drawings = Drawings(_SHAPES_KEPT)  # each target's outline and axes
        self._video_frame_ns: np.ndarray | None = None  # a referenced source video's frame times
        self._video_part: str | None = None  # the part that holds that video (the first)
        self._states: dict[TargetId, TrackState] = {}
        self._series_of: dict[TargetId, tuple[str, ...]] = {}  # a target -> its metrics' series (_metric_series)
        self._trajectory = Trail(_TRAJECTORY_POINTS)  # the camera centre's last places
        self._shapes = Shapes(_SHAPES_KEPT)  # each target's branch shape (world/hypotheses)
        self._labelled = False  # world/labels holds something (cleared when no target is left)
        self._world_from_camera: Place | None = None  # the camera where the anchor last placed it
        self._hypotheses_drawn = False
        self._framed = False  # the 3D view's eye framed on the targets (once, at the first frame placing them)
        self._causal_drawn = False
        distortion = _distortion_note(camera)
        self._part_notes = [distortion] if distortion is not None else []  # events of each part's first frame
        self._notes_due = bool(self._part_notes)
        self._last_check = time.monotonic()
        self._log_static_camera(camera)

    def _layout(self, framing: Framing | None = None) -> Any:
        """The run's layout (its 3D eye at ``framing``), under :attr:`root`."""
        return run_blueprint(overlay_image=self.settings.overlay_images, framing=framing, root=self.root)

    @property
    def parts(self) -> list[Path]:
        """The recording's files, in order (see ``part_minutes``)."""
        return self.recording.files

    def _part_due(self, timestamp_ns: int, part_s: float) -> bool:
        """Is it time for the next file: ``part_s`` of wall time in this one, or of the frames' own time (a
        replay writes faster than real time: by wall time alone its parts, and the writer's memory, would
        grow with its speed; measured: the offline replay's write pass, at 130 fps, held 2.3x the frames)?"""
        if time.monotonic() - self._part_started >= part_s:
            return True
        return self._part_media_ns is not None and timestamp_ns - self._part_media_ns >= part_s * 1e9

    def _next_part(self) -> None:
        """Close the current file and go on in ``recording.partN.rrd``: the same recording (open the parts
        together: ``rerun recording*.rrd``), each file complete, with the static scene logged again so a
        part also opens alone. Bounds the file writer's memory on long runs (see ``part_minutes``).

        A referenced source video (:meth:`use_video`) is in the first part only, and each later part says
        so in its events: logged again in each part, it costs its whole size in every file, and rerun's
        writer holds it twice while it encodes it (measured on a 10-minute replay of a 159 MB video: a
        spike of 100-300 MB at every part)."""
        assert self.rrd_path is not None
        path = self.rrd_path.with_name(f"{self.rrd_path.stem}.part{len(self.parts) + 1}{self.rrd_path.suffix}")
        self.series.flush()  # what is kept so far (metrics, scene) belongs to the file that ends
        self.recording.next_file(path)
        self._part_started = time.monotonic()
        self._part_media_ns = None
        self._log_static_camera(self.camera)
        self._shapes_logged.clear()  # each target's shape (the anchor's too) goes into the new part when seen
        if self._video_part is not None and len(self.parts) == 2:
            self._part_notes.append(
                f"the camera images are the source video, logged once in {self._video_part}: open this part "
                f"with it (rerun {self.rrd_path.stem}*.rrd) to see them"
            )
        self._notes_due = bool(self._part_notes)

    def use_video(self, path: str | os.PathLike[str], expected_frames: int | None = None) -> bool:
        """Reference the source video itself (``AssetVideo`` + ``VideoFrameReference``) instead of
        logging a JPEG per frame. Only MP4 with a codec rerun decodes (H.264, H.265, AV1, VP9)
        qualifies; returns False (JPEG logging stays) otherwise."""
        path = Path(path)
        if path.suffix.lower() not in (".mp4", ".m4v", ".mov"):
            return False
        try:
            asset = rr.AssetVideo(path=path)
            frame_ns = np.asarray(asset.read_frame_timestamps_nanos(), dtype=np.int64)
        except Exception as err:  # unsupported codec or container: rerun says which
            log.info("%s: not referenced as a video in the recording (%s); logging JPEG frames", path, err)
            return False
        if frame_ns.size == 0 or (expected_frames is not None and frame_ns.size != expected_frames):
            log.info("%s: rerun sees %d frames, OpenCV %s; logging JPEG frames", path, frame_ns.size, expected_frames)
            return False
        self.recording.log(IMAGE, asset, static=True)
        self._video_part = self.parts[-1].name if self.parts else "the recording"
        self._video_frame_ns = frame_ns
        self._log_static_camera(self.camera)  # the pinhole of the full-resolution video
        return True

    # ------------------------------------------------------------------ shapes
    def _log_static_camera(self, camera: CameraModel) -> None:
        """The camera's ``Pinhole``, in the pixels of the image logged under it: scaled by ``image_scale``
        (not for a referenced video, which is the original) and with the principal point half a pixel
        further (rerun's pixel corners at integers) so that what the viewer projects sits on the image."""
        scale = 1.0 if self._video_frame_ns is not None else self.settings.image_scale
        self.recording.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=image_from_camera(camera, scale),
                resolution=[camera.width * scale, camera.height * scale],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.1,
            ),
            static=True,
        )

    def _log_shape(self, name: TargetId, target: TargetResult, is_anchor: bool) -> None:
        """The target as a 3D object: its marker squares (one for a marker, all of a board's), axes, label
        and overlay models. The anchor's is static (it is the world frame); any other target's is logged
        on the timeline, so that clearing the target when it is gone removes it."""
        path = "world" if is_anchor else self._own(name, f"world/targets/{entity_name(name)}")
        outline, axes = self._drawings(target)  # (built once per shape: targets come and go, each drawn anew)
        log_ = self.recording.log
        log_(f"{path}/outline", outline, static=is_anchor)
        log_(f"{path}/axes", axes, static=is_anchor)
        if self.overlay_models is not None:
            if name not in self._meshes:  # built once per target: it comes back with the same models
                self._meshes[name] = [mesh3d(overlay.model) for overlay in self.overlay_models(target)]
            for index, mesh in enumerate(self._meshes[name]):
                log_(f"{path}/overlay/{index}", mesh, static=is_anchor)
        self._shapes_logged.add(name)

    def _own(self, name: TargetId, entity: str) -> str:
        """``entity`` belongs to target ``name`` (it is cleared when the target is gone)."""
        self._drawn.setdefault(name, set()).add(entity)
        return entity

    def _clear(self, entity: str) -> None:
        """Clear ``entity`` (logged through :attr:`series`) from this frame on."""
        self.series.clearing([entity])
        self.recording.clear(entity)

    def _clear_gone(self, result: FrameResult) -> None:
        """Clear, once, the entities of every target drawn before that is not in this frame's results."""
        for name in [name for name in self._drawn if name not in result.targets]:
            entities = sorted(self._drawn.pop(name))
            self.series.clearing(entities, recursive=True)  # (its values kept at the clear's time go out first)
            for entity in entities:
                self.recording.clear(entity, recursive=True)
                if entity == f"world/targets/{entity_name(name)}":
                    # a cleared TransformAxes3D is drawn at the viewer's default length, from the world origin
                    # (long lines across the AR overlay): zero-length axes draw nothing until it comes back
                    self.recording.log(f"{entity}/axes", _NO_AXES)
            if name != self.anchor:
                self._shapes_logged.discard(name)  # drawn again when it comes back

    # ------------------------------------------------------------------ per frame
    def wants_image(self, frame: Frame) -> bool:
        """Is an image logged for this frame?"""
        every = self.settings.image_every
        return bool(every) and frame.index % every == 0

    def wants_overlay_image(self, frame: Frame) -> bool:
        """Is an annotated image logged for this frame (``overlay_images``), so worth drawing?"""
        return self.settings.overlay_images and self.wants_image(frame)

    def log_frame(
        self,
        frame: Frame,
        result: FrameResult,
        overlay: np.ndarray | None = None,
        stages: Mapping[str, float] | None = None,
    ) -> None:
        """Log one frame: the image (or its video reference), detections, the 3D scene, metrics, and
        ``overlay`` (the annotated image, when given and ``overlay_images`` is set) under ``camera/overlay``.
        ``stages``: the run loop's per-frame times (ms) beside the tracker's own, all under
        ``metrics/latency/``."""
        part_s = 60.0 * self.settings.part_minutes
        if self.parts and part_s > 0 and self._part_due(frame.timestamp_ns, part_s):
            self._next_part()
        if self._part_media_ns is None:
            self._part_media_ns = frame.timestamp_ns
        recording = self.recording
        recording.time("frame", sequence=frame.index)
        recording.time("time", seconds=frame.timestamp_ns * 1e-9)
        self.series.at(frame.index, frame.timestamp_ns * 1e-9)
        if self._notes_due:
            self._notes_due = False
            for note in self._part_notes:
                recording.text("events", note)
        scale = self.settings.image_scale
        if self._video_frame_ns is not None:
            scale = 1.0  # the referenced video is the full-resolution original
            if frame.index < self._video_frame_ns.size:
                ns = int(self._video_frame_ns[frame.index])
                recording.log(IMAGE, rr.VideoFrameReference(nanoseconds=ns))
        elif self.wants_image(frame):
            self._log_jpeg(IMAGE, frame.image)
        if overlay is not None and self.wants_overlay_image(frame):
            self._log_jpeg(OVERLAY_IMAGE, overlay)
        self._clear_gone(result)
        self._log_detections(result, scale)
        self._log_world(result, frame.truth)
        self.log_latency({**result.latency_ms, **(stages or {})})
        now = time.monotonic()
        if now - self._last_check >= _SINK_CHECK_S:
            self._last_check = now
            # a sink that died (disk full) or a viewer that stopped reading fails the run now, not at its end
            recording.flush(timeout_s=self.settings.flush_timeout_s)

    def log_latency(self, stages: Mapping[str, float]) -> None:
        """Per-stage times (ms) of the current frame, as ``metrics/latency/<stage>`` (sent in batches)."""
        for stage, ms in stages.items():
            self.series.add(f"metrics/latency/{stage.removesuffix('_ms')}", ms)

    def _log_jpeg(self, path: str, image: np.ndarray) -> None:
        """``image`` at the recording's ``image_scale`` and JPEG quality, under ``path``."""
        self.recording.jpeg(path, image, quality=self.settings.jpeg_quality, scale=self.settings.image_scale)

    def _log_detections(self, result: FrameResult, scale: float) -> None:
        """The detected markers' outlines (coloured by their target's state) and ids, their corners, and
        each board's inlier and outlier corners, on the image (its pixels: distorted, at ``scale``). A marker
        drawn as part of a board (:meth:`FrameResult.board_members`) is outlined thinly in the board's state
        colour, without an id: the board is the target there."""
        colours, labels, radii = [], [], []
        failed = {f.marker_id for f in result.failures}
        members = result.board_members()
        targets = result.targets
        for marker_id in result.detections.ids.tolist():
            name = f"marker:{marker_id}"  # (TargetId.marker's string, which finds its target's entries)
            board = members.get(name)
            if board is not None:  # part of a board: thin, in the board's colour, no label of its own
                colours.append(_STATE_COLOURS[targets[board].state])
                labels.append("")
                radii.append(_MEMBER_RADIUS)
                continue
            target = targets.get(name)
            colour = (
                _STATE_COLOURS[target.state] if target else (_FAILED_COLOUR if marker_id in failed else (160, 160, 160))
            )
            colours.append(colour)
            labels.append(str(marker_id))
            radii.append(1.0)
        quads = np.asarray(result.detections.corners, np.float64).reshape(-1, 4, 2)
        strips = (np.concatenate([quads, quads[:, :1]], axis=1) + 0.5) * scale  # (N, 5, 2), one array
        markers = Recording.cells("LineStrips2D", strips=strips, colors=colours, labels=labels, radii=radii)
        self.series.log(f"{IMAGE}/markers", markers)
        corners = np.asarray(result.detections.corners.reshape(-1, 2), np.float64)
        self.series.log(f"{IMAGE}/corners", self.recording.image_points_data(corners, 1.5, [(255, 0, 255)], scale))
        for name, target in result.targets.items():
            if not name.is_board:
                continue
            path = self._own(name, f"{IMAGE}/boards/{entity_name(name)}")
            inliers = (
                target.corners_in_image.reshape(-1, 2) if target.corners_in_image is not None else np.zeros((0, 2))
            )
            outliers = (
                target.outlier_points_in_image if target.outlier_points_in_image is not None else np.zeros((0, 2))
            )
            for entity, points, radius, colour in (
                ("inliers", inliers, 2.5, (60, 220, 90)),
                ("outliers", outliers, 3.5, (255, 40, 40)),
            ):
                points = np.asarray(points, np.float64)
                self.series.log(f"{path}/{entity}", self.recording.image_points_data(points, radius, [colour], scale))

    def _choose_anchor(self, result: FrameResult) -> None:
        """The first target seen (boards first) anchors the 3D view, for the whole run; its static shape
        is logged once per recording part."""
        if self.anchor is None and result.targets:
            self.anchor = TargetId.ordered(result.targets)[0]
            log.info("rerun 3D view anchored on %s", self.anchor)
        if self.anchor is None or self.anchor in self._shapes_logged or self.anchor not in result.targets:
            return
        up = rr.ViewCoordinates.RIGHT_HAND_Y_DOWN if self.anchor.is_board else rr.ViewCoordinates.RIGHT_HAND_Y_UP
        self.recording.log("world", up, static=True)
        self._log_shape(self.anchor, result.targets[self.anchor], is_anchor=True)

    def _log_metrics(self, result: FrameResult, truth: Mapping[str, Pose] | None) -> None:
        """Each target's metrics (sent in batches), state changes and filter events."""
        scalar = self.series.add
        for name, target in result.targets.items():
            *series, rotation_error = self._metric_series(name)
            inliers = float(target.inliers) if name.is_board and target.measured else math.nan
            owned = None
            for entity, value in zip(series, (target.reproj_px, target.ambiguity, inliers, target.evidence_px)):
                if math.isfinite(value):  # (the target's own: cleared when it is gone)
                    if owned is None:
                        owned = self._drawn.setdefault(name, set())
                    owned.add(entity)
                    scalar(entity, value)
            previous_state = self._states.get(name)
            if previous_state != target.state:
                self._states[name] = target.state
                self.recording.text("events", f"{name}: state {previous_state or '-'} -> {target.state}")
            for event in target.events:
                warn = event.kind in ("switch", "uncommit")
                self.recording.text("events", f"{name}: {event.kind}: {event.message}", warn=warn)
            if truth is not None and name in truth:
                error = angle_between_deg(target.pose.rotation, truth[name].rotation)
                scalar(self._own(name, rotation_error), error)

    def _metric_series(self, name: TargetId) -> tuple[str, ...]:
        """The target's ``metrics/<metric>/<target>`` series (:data:`_METRICS`), named once per target."""
        series = self._series_of.get(name)
        if series is None:
            part = entity_name(name)
            series = self._series_of[name] = tuple(f"metrics/{metric}/{part}" for metric in _METRICS)
        return series

    def _log_world(self, result: FrameResult, truth: Mapping[str, Pose] | None) -> None:
        """The camera (placed by the anchor; held where it was last seen while the anchor is out of view),
        every other target placed from it, and the filter's hypotheses."""
        self._choose_anchor(result)
        self._log_metrics(result, truth)
        if self.anchor is None:
            return
        anchor = result.targets.get(self.anchor)
        if truth is not None and self.anchor in truth:
            centre = np.asarray([truth[self.anchor].camera_centre()])
            self.series.log(
                "world/truth_camera", rr.Points3D(centre, radii=0.005, colors=[(255, 255, 255)], labels=["true camera"])
            )
        if anchor is not None:
            self._log_camera(camera_in_world(anchor.pose), anchor.length_m)
        world_from_camera = self._world_from_camera
        if world_from_camera is None:
            return
        others = [target for name, target in result.targets.items() if name != self.anchor]
        rotations, translations = placed(world_from_camera, [target.pose for target in others])  # world_from_target
        labels: list[tuple[str, np.ndarray, float]] = []  # every target's name at its centre, in the world
        index = 0
        for name, target in result.targets.items():
            if name == self.anchor:
                labels.append((name, np.zeros(3), target.length_m))
                continue
            if name not in self._shapes_logged or any(e.kind == "group" for e in target.events):
                self._log_shape(name, target, is_anchor=False)  # (a learned group's members changed: drawn anew)
            entity = self._own(name, f"world/targets/{entity_name(name)}")
            self.series.transform(entity, translations[index], rotations[index])  # sent in batches
            labels.append((name, translations[index], target.length_m))
            index += 1
        self._log_labels(labels)
        if labels and not self._framed:
            self._frame_targets(labels, world_from_camera)
        self._log_hypotheses(result, world_from_camera)
        self._log_causal(result, world_from_camera)

    def _frame_targets(self, labels: list[tuple[str, np.ndarray, float]], world_from_camera: Place) -> None:
        """The layout again, its 3D eye framed on the targets placed now (``labels``), from the camera's side."""
        self._framed = True
        if not self._sends_layout:
            return
        framing = Framing.on(
            np.array([position for _, position, _ in labels]),
            np.array([length for _, _, length in labels]),
            world_from_camera[1],
        )
        self.recording.send_blueprint(self._layout(framing))

    def _log_labels(self, labels: list[tuple[str, np.ndarray, float]]) -> None:
        """Every target's name at its centre, one ``Points3D`` for all (``world/labels``, logged whole each
        frame): the 3D view's labels, left out of the AR overlay view, where the frame's 2D outlines carry
        the ids already."""
        if not labels:
            if self._labelled:
                self._clear("world/labels")
                self._labelled = False
            return
        self.series.log(
            "world/labels",
            Recording.cells(
                "Points3D",
                positions=np.array([position for _, position, _ in labels]),
                labels=[name for name, _, _ in labels],
                radii=np.array([length / 40 for _, _, length in labels]),
            ),
        )
        self._labelled = True

    def _log_camera(self, world_from_camera: Place, length_m: float) -> None:
        """``world/camera``'s pose (its translation is the camera centre C = -R^T t) and its trajectory."""
        self._world_from_camera = world_from_camera
        rotation, translation = world_from_camera
        self.series.transform("world/camera", translation, rotation)  # in batches
        self._trajectory.append(translation)
        if len(self._trajectory) >= 2:
            path = self._trajectory.points()[None]  # (one strip)
            line = Recording.cells("LineStrips3D", strips=path, colors=[(255, 210, 60)], radii=[length_m / 80])
            self.series.log("world/camera_trajectory", line)

    def _log_hypotheses(self, result: FrameResult, world_from_camera: Place) -> None:
        """Both IPPE branches of every target, faint, so the flip the filter resolves can be seen: all
        targets' in one ``LineStrips3D`` (per branch its marker squares and its normal), logged whole each
        frame, so a branch or target that is gone is gone from it."""
        drawn = branch_strips(list(result.targets.values()), world_from_camera, self._shapes)
        if drawn is not None:
            strips, colours, radii = drawn
            lines = Recording.cells("LineStrips3D", strips=strips, colors=colours, radii=radii)
            self.series.log("world/hypotheses", lines)
            self._hypotheses_drawn = True
        elif self._hypotheses_drawn:
            self._clear("world/hypotheses")
            self._hypotheses_drawn = False

    def _log_causal(self, result: FrameResult, world_from_camera: Place) -> None:
        """Offline replay: the live (causal) filter's pose of every target beside the offline one, as thin
        axes (``world/causal``, all targets in one ``Arrows3D``), and the angle between the two poses."""
        causal = result.causal_targets
        if causal is None:
            return
        for name, target in causal.items():
            offline = result.targets.get(name)
            if offline is not None:
                self.series.add(
                    self._own(name, f"metrics/offline_vs_causal_deg/{entity_name(name)}"),
                    angle_between_deg(offline.pose.rotation, target.pose.rotation),
                )
        if causal:
            origins, vectors, colours = causal_axes(list(causal.values()), world_from_camera)
            arrows = rr.Arrows3D(origins=origins, vectors=vectors, colors=colours)
            self.series.log("world/causal", arrows)
            self._causal_drawn = True
        elif self._causal_drawn:
            self._clear("world/causal")
            self._causal_drawn = False

    def close(self, timeout_s: float | None = None) -> None:
        """Send the metrics and poses kept, flush everything to the sinks and close the file (the .rrd is complete
        afterwards).

        The flush is bounded (``timeout_s``, default ``[recording] flush_timeout_s``): a viewer that went
        away must not hang the end of a run.
        """
        try:
            self.series.flush()
        finally:
            self.recording.close(timeout_s=self.settings.flush_timeout_s if timeout_s is None else timeout_s)
