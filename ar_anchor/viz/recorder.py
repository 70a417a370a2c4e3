"""The tracker run's recording: every frame's image, detections, 3D scene, metrics and events.

Entity tree
-----------
``camera/image``                  the frame (JPEG or a reference into the source video), with ``markers``
                                  outlines + ids and ``corners``
``camera/overlay``                the annotated image (when overlays are drawn)
``world``                         the anchor target's frame (the first target that gets a pose)
``world/camera``                  ``world_from_camera`` (so the camera centre is ``C = -R^T t``) + ``Pinhole``
``world/camera_trajectory``       the camera centre's recent path
``world/targets/<target>``        ``world_from_target`` of every other target, drawn as its marker squares + axes
``camera/image/boards/<board>/inliers|outliers``  the corners a board's pose used / rejected
``metrics/inliers/<board>``       corners a board's pose was solved from
``world/truth_camera``            the true camera centre (synthetic sources)
``metrics/reproj_px/<target>``    RMS reprojection error of the output pose
``metrics/ambiguity/<target>``    IPPE error ratio (worse / better; near 1 = ambiguous)
``metrics/rotation_error_deg/<target>``  against ground truth, when known
``metrics/latency/<stage>``       per-stage time, milliseconds
``metrics/flip_evidence_px/<target>``  the filter's flip evidence (signed: + favours branch 0)
``world/hypotheses/<target>/branch_<k>``  this frame's solution on each filter branch, faint
``events``                        state changes, commits, switches, re-acquisitions, resets (TextLog)

A target that is gone (no longer in a frame's results) is cleared once, on that frame, from every
entity above that is its own; it is drawn again when it comes back. The anchor's shape is the
``world`` frame itself and stays.

Timelines: ``frame`` (sequence) and ``time`` (seconds since the stream's start).
Rerun places pixel *corners* at integers, OpenCV pixel *centres*: 2D positions are shifted by
half a pixel (see :mod:`.sinks`) so overlays sit exactly on the image.
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
from ..track.tracker import FrameResult, TargetResult
from .blueprints import run_blueprint
from .parts import closed_squares, entity_name, mesh3d
from .sinks import Recording

__all__ = ["RerunRecorder"]

log = logging.getLogger(__name__)

_STATE_COLOURS = {
    TrackState.TRACKED: (40, 220, 80),
    TrackState.AMBIGUOUS: (250, 190, 30),
    TrackState.PREDICTED: (120, 120, 255),
}
_FAILED_COLOUR = (255, 60, 60)
_TRAJECTORY_POINTS = 1000  # the camera's trajectory line keeps the last this many centres
_SINK_CHECK_S = 2.0  # how often the sinks are flushed to find out whether they still write


class RerunRecorder:
    """Logs frames and tracker results to an ``.rrd`` file and/or a viewer (spawned, or ``connect``: its URL).

    ``overlay_models``: a target -> its overlay models in the target frame, drawn in the 3D scene
    (given when the run draws overlays).
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
    ) -> None:
        self.settings = settings or RecordingConfig()
        self.camera = camera
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        self.overlay_models = overlay_models
        self.recording = Recording(
            "ar_anchor", path=rrd_path, spawn=spawn, connect=connect, blueprint=run_blueprint(), name=recording_name
        )
        self._part_started = time.monotonic()
        self.anchor: TargetId | None = None
        self._shapes_logged: set[TargetId] = set()  # targets whose shape is in the current part and not cleared
        self._drawn: dict[TargetId, set[str]] = {}  # a target -> its entities logged since it was last cleared
        self._video_frame_ns: np.ndarray | None = None
        self._video_asset: rr.AssetVideo | None = None
        self._states: dict[TargetId, TrackState] = {}
        self._trajectory: list[np.ndarray] = []
        self._last_check = time.monotonic()
        self._log_static_camera(camera)

    @property
    def parts(self) -> list[Path]:
        """The recording's files, in order (see ``part_minutes``)."""
        return self.recording.files

    def _next_part(self) -> None:
        """Close the current file and go on in ``recording.partN.rrd``: the same recording (open the parts
        together: ``rerun recording*.rrd``), each file complete, with the static scene logged again so a
        part also opens alone. Bounds the file writer's memory on long runs (see ``part_minutes``)."""
        assert self.rrd_path is not None
        path = self.rrd_path.with_name(f"{self.rrd_path.stem}.part{len(self.parts) + 1}{self.rrd_path.suffix}")
        self.recording.next_file(path)
        self._part_started = time.monotonic()
        self._log_static_camera(self.camera)
        self._shapes_logged.clear()  # each target's shape (the anchor's too) goes into the new part when seen
        if self._video_asset is not None:
            self.recording.log("camera/image", self._video_asset, static=True)

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
        self.recording.log("camera/image", asset, static=True)
        self._video_asset = asset
        self._video_frame_ns = frame_ns
        return True

    # ------------------------------------------------------------------ shapes
    def _log_static_camera(self, camera: CameraModel) -> None:
        self.recording.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=np.asarray(camera.camera_matrix),
                resolution=[camera.width, camera.height],
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
        length_m = target.length_m
        log_ = self.recording.log
        log_(
            f"{path}/outline",
            rr.LineStrips3D(closed_squares(target), colors=[(230, 230, 230)], radii=[length_m / 60]),
            static=is_anchor,
        )
        log_(f"{path}/axes", rr.TransformAxes3D(axis_length=length_m * 0.75), static=is_anchor)
        log_(f"{path}/label", rr.Points3D([[0, 0, 0]], labels=[name], radii=[length_m / 40]), static=is_anchor)
        if self.overlay_models is not None:
            for index, placed in enumerate(self.overlay_models(target)):
                log_(f"{path}/overlay/{index}", mesh3d(placed.model), static=is_anchor)
        self._shapes_logged.add(name)

    def _own(self, name: TargetId, entity: str) -> str:
        """``entity`` belongs to target ``name`` (it is cleared when the target is gone)."""
        self._drawn.setdefault(name, set()).add(entity)
        return entity

    def _clear_gone(self, result: FrameResult) -> None:
        """Clear, once, the entities of every target drawn before that is not in this frame's results."""
        for name in [name for name in self._drawn if name not in result.targets]:
            for entity in sorted(self._drawn.pop(name)):
                self.recording.clear(entity, recursive=True)
            if name != self.anchor:
                self._shapes_logged.discard(name)  # drawn again when it comes back

    # ------------------------------------------------------------------ per frame
    def wants_image(self, frame: Frame) -> bool:
        """Is an image logged for this frame (so an overlay image is worth drawing)?"""
        every = self.settings.image_every
        return bool(every) and frame.index % every == 0

    def log_frame(
        self,
        frame: Frame,
        result: FrameResult,
        overlay: np.ndarray | None = None,
        stages: Mapping[str, float] | None = None,
    ) -> None:
        """Log one frame: the image (or its video reference), detections, the 3D scene, metrics, and
        ``overlay`` (the annotated image, when given) under ``camera/overlay``. ``stages``: the run
        loop's per-frame times (ms) beside the tracker's own, all under ``metrics/latency/``."""
        part_s = 60.0 * self.settings.part_minutes
        if self.parts and part_s > 0 and time.monotonic() - self._part_started >= part_s:
            self._next_part()
        recording = self.recording
        recording.time("frame", sequence=frame.index)
        recording.time("time", seconds=frame.timestamp_ns * 1e-9)
        scale = self.settings.image_scale
        if self._video_frame_ns is not None:
            scale = 1.0  # the referenced video is the full-resolution original
            if frame.index < self._video_frame_ns.size:
                ns = int(self._video_frame_ns[frame.index])
                recording.log("camera/image", rr.VideoFrameReference(nanoseconds=ns))
        elif self.wants_image(frame):
            self._log_jpeg("camera/image", frame.image)
        if overlay is not None and self.wants_image(frame):
            self._log_jpeg("camera/overlay", overlay)
        self._clear_gone(result)
        self._log_detections(result, scale)
        self._log_world(result, frame.truth)
        self.log_latency({**result.latency_ms, **(stages or {})})
        now = time.monotonic()
        if now - self._last_check >= _SINK_CHECK_S:
            self._last_check = now
            recording.flush(timeout_s=10.0)  # a sink that died (disk full) fails the run now, not at its end

    def log_latency(self, stages: Mapping[str, float]) -> None:
        """Per-stage times (ms) of the current frame, as ``metrics/latency/<stage>``."""
        for stage, ms in stages.items():
            self.recording.scalar(f"metrics/latency/{stage.removesuffix('_ms')}", ms)

    def _log_jpeg(self, path: str, image: np.ndarray) -> None:
        """``image`` at the recording's ``image_scale`` and JPEG quality, under ``path``."""
        self.recording.jpeg(path, image, quality=self.settings.jpeg_quality, scale=self.settings.image_scale)

    def _log_detections(self, result: FrameResult, scale: float) -> None:
        def to_rerun(pixels: np.ndarray) -> np.ndarray:
            return (np.asarray(pixels, np.float64) + 0.5) * scale

        strips, colours, labels = [], [], []
        failed = {f.marker_id for f in result.failures}
        for marker_id, corners in zip(result.detections.ids.tolist(), result.detections.corners):
            target = result.targets.get(TargetId.marker(marker_id))
            colour = (
                _STATE_COLOURS[target.state] if target else (_FAILED_COLOUR if marker_id in failed else (160, 160, 160))
            )
            strips.append(to_rerun(np.vstack([corners, corners[:1]])))
            colours.append(colour)
            labels.append(str(marker_id))
        self.recording.log("camera/image/markers", rr.LineStrips2D(strips, colors=colours, labels=labels, radii=[1.0]))
        corners = np.asarray(result.detections.corners.reshape(-1, 2), np.float64)
        self.recording.image_points("camera/image/corners", corners, radius=1.5, colours=[(255, 0, 255)], scale=scale)
        for name, target in result.targets.items():
            if not name.is_board:
                continue
            path = self._own(name, f"camera/image/boards/{entity_name(name)}")
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
                self.recording.image_points(f"{path}/{entity}", points, radius=radius, colours=[colour], scale=scale)

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
        """Each target's metrics, state changes and filter events."""
        scalar = self.recording.scalar
        for name, target in result.targets.items():
            part = entity_name(name)
            if math.isfinite(target.reproj_px):
                scalar(self._own(name, f"metrics/reproj_px/{part}"), target.reproj_px)
            if math.isfinite(target.ambiguity):
                scalar(self._own(name, f"metrics/ambiguity/{part}"), target.ambiguity)
            if name.is_board and target.measured:
                scalar(self._own(name, f"metrics/inliers/{part}"), float(target.inliers))
            if math.isfinite(target.evidence_px):
                scalar(self._own(name, f"metrics/flip_evidence_px/{part}"), target.evidence_px)
            previous_state = self._states.get(name)
            if previous_state != target.state:
                self._states[name] = target.state
                self.recording.text("events", f"{name}: state {previous_state or '-'} -> {target.state}")
            for event in target.events:
                warn = event.kind in ("switch", "uncommit")
                self.recording.text("events", f"{name}: {event.kind}: {event.message}", warn=warn)
            if truth is not None and name in truth:
                error = angle_between_deg(target.pose.rotation, truth[name].rotation)
                scalar(self._own(name, f"metrics/rotation_error_deg/{part}"), error)

    def _log_world(self, result: FrameResult, truth: Mapping[str, Pose] | None) -> None:
        self._choose_anchor(result)
        self._log_metrics(result, truth)
        if self.anchor is None:
            return
        anchor = result.targets.get(self.anchor)
        if truth is not None and self.anchor in truth:
            self.recording.points3d(
                "world/truth_camera",
                np.asarray([truth[self.anchor].camera_centre()]),
                radius=0.005,
                colours=[(255, 255, 255)],
                labels=["true camera"],
            )
        if anchor is None:
            return
        world_from_camera = anchor.pose.inverse()  # its translation is the camera centre C = -R^T t
        self.recording.log(
            "world/camera", rr.Transform3D(translation=world_from_camera.tvec, mat3x3=world_from_camera.rotation)
        )
        self._trajectory.append(world_from_camera.tvec.copy())
        del self._trajectory[:-_TRAJECTORY_POINTS]
        if len(self._trajectory) >= 2:
            self.recording.log(
                "world/camera_trajectory",
                rr.LineStrips3D([np.asarray(self._trajectory)], colors=[(255, 210, 60)], radii=[anchor.length_m / 80]),
            )
        for name, target in result.targets.items():
            if name == self.anchor:
                continue
            if name not in self._shapes_logged:
                self._log_shape(name, target, is_anchor=False)
            world_from_target = world_from_camera.compose(target.pose)
            self.recording.log(
                self._own(name, f"world/targets/{entity_name(name)}"),
                rr.Transform3D(translation=world_from_target.tvec, mat3x3=world_from_target.rotation),
            )
        self._log_hypotheses(result, world_from_camera)

    def _log_hypotheses(self, result: FrameResult, world_from_camera: Pose) -> None:
        """Both IPPE branches of every marker, faint, so the flip the filter resolves can be seen."""
        for name, target in result.targets.items():
            if not target.branch_poses:
                continue
            root = self._own(name, f"world/hypotheses/{entity_name(name)}")
            for branch, pose in enumerate(target.branch_poses):
                path = f"{root}/branch_{branch}"
                if pose is None:
                    self.recording.clear(path)
                    continue
                world_from_branch = world_from_camera.compose(pose)
                squares = [world_from_branch.apply(square) for square in closed_squares(target)]
                normal = world_from_branch.apply(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, target.length_m]]))
                colour = (90, 200, 255, 90) if branch == 0 else (255, 140, 60, 90)
                strips = rr.LineStrips3D([*squares, normal], colors=[colour], radii=[target.length_m / 120])
                self.recording.log(path, strips)

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush everything to the sinks and close the file (the .rrd is complete afterwards).

        The flush is bounded: a viewer that went away must not hang the end of a run.
        """
        self.recording.close(timeout_s=timeout_s)
