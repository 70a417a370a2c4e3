"""Everything rerun: the only module that calls ``rerun``.

Entity tree
-----------
``camera/image``                  the frame (JPEG), with ``markers`` outlines + ids and ``corners``
``world``                         the anchor target's frame (the first target that gets a pose)
``world/camera``                  ``world_from_camera`` (so the camera centre is ``C = -R^T t``) + ``Pinhole``
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

Timelines: ``frame`` (sequence) and ``time`` (seconds since the stream's start).
Rerun places pixel *corners* at integers, OpenCV pixel *centres*: 2D positions are shifted by
half a pixel here so overlays sit exactly on the image.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..camera import CameraModel
from ..config import RecordingConfig
from ..errors import OutputError
from ..geometry import Pose, angle_between_deg, marker_corners_in_marker
from ..sources.base import Frame
from ..targets import TargetId, TrackState
from ..track.tracker import FrameResult, TargetResult

__all__ = ["RerunRecorder", "default_blueprint"]

log = logging.getLogger(__name__)

_STATE_COLOURS = {
    TrackState.TRACKED: (40, 220, 80),
    TrackState.AMBIGUOUS: (250, 190, 30),
    TrackState.PREDICTED: (120, 120, 255),
}
_FAILED_COLOUR = (255, 60, 60)
_TRAJECTORY_POINTS = 1000  # the camera's trajectory line keeps the last this many centres
_SINK_CHECK_S = 2.0  # how often the sinks are flushed to find out whether they still write


def entity_name(target: str) -> str:
    """``marker:3`` -> ``marker_3`` (a single entity path part)."""
    return TargetId.parse(target).path_part


def default_blueprint() -> rrb.Blueprint:
    """Image, 3D scene and plots side by side.

    The 3D eye starts in front of the anchor (a marker frame: y up, z toward the viewer), a
    decimetre grid gives scale; the ambiguity plot shows 1..5 (values near 1 are the ambiguous
    ones; the data itself is not clipped).
    """
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Tabs(
                    rrb.Spatial2DView(origin="camera/image", name="Camera"),
                    rrb.Spatial2DView(origin="camera/overlay", name="AR overlay"),
                ),
                rrb.Spatial3DView(
                    origin="world",
                    name="3D scene",
                    line_grid=rrb.LineGrid3D(visible=True, spacing=0.1),
                    eye_controls=rrb.EyeControls3D(
                        kind=rrb.Eye3DKind.Orbital,
                        position=(0.9, 0.7, 1.8),
                        look_target=(0.0, 0.0, 0.4),
                        eye_up=(0, 1, 0),
                    ),
                ),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="metrics/reproj_px", name="Reprojection error (px)"),
                    rrb.TimeSeriesView(
                        origin="metrics/ambiguity", name="IPPE ambiguity ratio", axis_y=rrb.ScalarAxis(range=(1.0, 5.0))
                    ),
                    rrb.TimeSeriesView(origin="metrics/flip_evidence_px", name="Flip evidence (px, + = branch 0)"),
                    rrb.TimeSeriesView(origin="metrics/rotation_error_deg", name="Rotation error vs truth (deg)"),
                    rrb.TimeSeriesView(origin="metrics/inliers", name="Board inliers (corners)"),
                    rrb.TimeSeriesView(origin="metrics/latency", name="Latency (ms)"),
                ),
                column_shares=[3, 3, 2],
            ),
            rrb.TextLogView(origin="events", name="Tracker events"),
            row_shares=[5, 1],
        ),
        collapse_panels=True,
    )


VIEWER_PORT = 9876  # rerun's default gRPC port


def _listening(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.2)
        return probe.connect_ex((host, port)) == 0


def spawn_local_viewer(what: str = "--spawn") -> str | None:
    """Start a rerun viewer that listens on 127.0.0.1 only, and return its gRPC URL; None (with a
    warning) when there is no display or no viewer. A viewer already listening there is reused.

    ``rr.spawn`` is not used: the viewer it starts listens on every network interface (0.0.0.0), and
    rerun 0.41 offers no bind address for it. The viewer outlives the run (its own session).
    """
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        log.warning("%s: no display (DISPLAY / WAYLAND_DISPLAY unset), so no rerun viewer; recording only", what)
        return None
    url = f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"
    if _listening("127.0.0.1", VIEWER_PORT):
        return url
    beside = Path(sys.executable).with_name("rerun")
    executable = str(beside) if beside.exists() else shutil.which("rerun")
    if executable is None:
        log.warning("%s: no rerun viewer found (pip install rerun-sdk); recording to file only", what)
        return None
    command = [executable, "--bind", "127.0.0.1", "--port", str(VIEWER_PORT), "--expect-data-soon"]
    try:
        subprocess.Popen(  # noqa: S603 - a fixed command line, no shell
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
    except OSError as err:
        log.warning("%s: could not start the rerun viewer (%s); recording to file only", what, err.strerror or err)
        return None
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        if _listening("127.0.0.1", VIEWER_PORT):
            return url
        time.sleep(0.1)
    log.warning("%s: the rerun viewer did not start listening; recording to file only", what)
    return None


class RerunRecorder:
    """Logs frames and tracker results to an ``.rrd`` file and/or a spawned viewer."""

    def __init__(
        self,
        rrd_path: str | os.PathLike[str] | None,
        *,
        camera: CameraModel,
        settings: RecordingConfig | None = None,
        spawn: bool = False,
        connect: str | None = None,
        recording_name: str = "ar_anchor",
    ) -> None:
        self.settings = settings or RecordingConfig()
        self.camera = camera
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        self._viewer: rr.GrpcSink | None = None
        self._viewer_url: str | None = None
        if connect is not None:
            self._viewer, self._viewer_url = rr.GrpcSink(connect), connect
        elif spawn and (url := spawn_local_viewer()) is not None:
            self._viewer, self._viewer_url = rr.GrpcSink(url), url
        self.rec = rr.RecordingStream("ar_anchor")
        self.parts: list[Path] = []  # the recording's files, in order (see part_minutes)
        self._part_started = time.monotonic()
        if self.rrd_path is not None:
            try:
                self.rrd_path.touch()
            except OSError as err:
                raise OutputError(f"{self.rrd_path}: cannot write ({err.strerror})") from err
            self.parts.append(self.rrd_path)
        self._set_sinks()
        self._recording_name = recording_name
        self.rec.send_recording_name(recording_name)
        self.anchor: str | None = None
        self._static_targets: set[str] = set()
        self._video_frame_ns: np.ndarray | None = None
        self._video_asset: rr.AssetVideo | None = None
        self._states: dict[str, str] = {}
        self._trajectory: list[np.ndarray] = []
        self._last_check = time.monotonic()
        # target -> its overlay models in the target frame (set by the session when it draws overlays)
        self.overlay_models: Callable[[TargetResult], list[Any]] | None = None
        self._log_static_camera(camera)

    def _set_sinks(self) -> None:
        sinks: list[rr.FileSink | rr.GrpcSink] = [rr.FileSink(str(self.parts[-1]))] if self.parts else []
        if self._viewer is not None:
            sinks.append(self._viewer)
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=default_blueprint())

    def _next_part(self) -> None:
        """Close the current file and go on in ``recording.partN.rrd``: the same recording (open the parts
        together: ``rerun recording*.rrd``), each file complete, with the static scene logged again so a
        part also opens alone. Bounds the file writer's memory on long runs (see ``part_minutes``)."""
        assert self.rrd_path is not None
        self._flush(timeout_s=30.0)
        path = self.rrd_path.with_name(f"{self.rrd_path.stem}.part{len(self.parts) + 1}{self.rrd_path.suffix}")
        try:
            path.touch()
        except OSError as err:
            raise OutputError(f"{path}: cannot write ({err.strerror})") from err
        self.parts.append(path)
        self._set_sinks()
        self._part_started = time.monotonic()
        self.rec.send_recording_name(self._recording_name)
        self._log_static_camera(self.camera)
        self._static_targets.clear()  # each target's static shape (the anchor's too) goes into the new part when seen
        if self._video_asset is not None:
            self.rec.log("camera/image", self._video_asset, static=True)

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
        self.rec.log("camera/image", asset, static=True)
        self._video_asset = asset
        self._video_frame_ns = frame_ns
        return True

    # ------------------------------------------------------------------ static
    def _log_static_camera(self, camera: CameraModel) -> None:
        self.rec.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=np.asarray(camera.camera_matrix),
                resolution=[camera.width, camera.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.1,
            ),
            static=True,
        )

    def _log_static_target(self, name: str, target: TargetResult, is_anchor: bool) -> None:
        """The target as a 3D object: its marker squares (one for a marker, all of a board's)."""
        path = "world" if is_anchor else f"world/targets/{entity_name(name)}"
        length_m = target.length_m
        self.rec.log(
            f"{path}/outline",
            rr.LineStrips3D(_closed_squares(target), colors=[(230, 230, 230)], radii=[length_m / 60]),
            static=True,
        )
        self.rec.log(f"{path}/axes", rr.TransformAxes3D(axis_length=length_m * 0.75), static=True)
        self.rec.log(f"{path}/label", rr.Points3D([[0, 0, 0]], labels=[name], radii=[length_m / 40]), static=True)
        if self.overlay_models is not None:
            for index, placed in enumerate(self.overlay_models(target)):
                self.rec.log(f"{path}/overlay/{index}", _mesh3d(placed.model), static=True)

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
        rec = self.rec
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("time", duration=frame.timestamp_ns * 1e-9)
        scale = self.settings.image_scale
        if self._video_frame_ns is not None:
            scale = 1.0  # the referenced video is the full-resolution original
            if frame.index < self._video_frame_ns.size:
                rec.log("camera/image", rr.VideoFrameReference(nanoseconds=int(self._video_frame_ns[frame.index])))
        elif self.wants_image(frame):
            self._log_jpeg("camera/image", frame.image)
        if overlay is not None and self.wants_image(frame):
            self._log_jpeg("camera/overlay", overlay)
        self._log_detections(result, scale)
        self._log_world(result, frame.truth)
        self.log_latency({**result.latency_ms, **(stages or {})})
        now = time.monotonic()
        if now - self._last_check >= _SINK_CHECK_S:
            self._last_check = now
            self._flush(timeout_s=10.0)  # a sink that died (disk full) fails the run now, not at its end

    def _flush(self, timeout_s: float) -> None:
        """Flush the sinks; a file sink that could not write (disk full, file too large) is an OutputError."""
        try:
            self.rec.flush(timeout_sec=timeout_s)
        except RuntimeError as err:
            where = [str(self.parts[-1])] if self.parts else []
            if self._viewer_url is not None:
                where.append(f"the viewer at {self._viewer_url}")
            raise OutputError(
                f"{' and '.join(where) or 'recording'}: cannot write the recording ({err}: disk full, or the "
                "viewer gone?); the file holds the frames logged before"
            ) from None

    def log_latency(self, stages: Mapping[str, float]) -> None:
        """Per-stage times (ms) of the current frame, as ``metrics/latency/<stage>``."""
        for stage, ms in stages.items():
            self.rec.log(f"metrics/latency/{stage.removesuffix('_ms')}", rr.Scalars(ms))

    def _log_jpeg(self, path: str, image: np.ndarray) -> None:
        """``image`` at the recording's ``image_scale`` and JPEG quality, under ``path``."""
        scale = self.settings.image_scale
        if scale != 1.0:
            size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.settings.jpeg_quality])
        if ok:
            self.rec.log(path, rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))

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
        self.rec.log("camera/image/markers", rr.LineStrips2D(strips, colors=colours, labels=labels, radii=[1.0]))
        corners = result.detections.corners.reshape(-1, 2)
        self.rec.log("camera/image/corners", rr.Points2D(to_rerun(corners), radii=[1.5], colors=[(255, 0, 255)]))
        for name, target in result.targets.items():
            if not name.is_board:
                continue
            path = f"camera/image/boards/{entity_name(name)}"
            inliers = (
                target.corners_in_image.reshape(-1, 2) if target.corners_in_image is not None else np.zeros((0, 2))
            )
            outliers = (
                target.outlier_points_in_image if target.outlier_points_in_image is not None else np.zeros((0, 2))
            )
            self.rec.log(f"{path}/inliers", rr.Points2D(to_rerun(inliers), radii=[2.5], colors=[(60, 220, 90)]))
            self.rec.log(f"{path}/outliers", rr.Points2D(to_rerun(outliers), radii=[3.5], colors=[(255, 40, 40)]))

    def _choose_anchor(self, result: FrameResult) -> None:
        """The first target seen (boards first) anchors the 3D view, for the whole run; its static shape
        is logged once per recording part."""
        if self.anchor is None and result.targets:
            self.anchor = TargetId.ordered(result.targets)[0]
            log.info("rerun 3D view anchored on %s", self.anchor)
        if self.anchor is None or self.anchor in self._static_targets or self.anchor not in result.targets:
            return
        up = rr.ViewCoordinates.RIGHT_HAND_Y_DOWN if self.anchor.is_board else rr.ViewCoordinates.RIGHT_HAND_Y_UP
        self.rec.log("world", up, static=True)
        self._log_static_target(self.anchor, result.targets[self.anchor], is_anchor=True)
        self._static_targets.add(self.anchor)

    def _log_world(self, result: FrameResult, truth: Mapping[str, Pose] | None) -> None:
        rec = self.rec
        self._choose_anchor(result)
        for name, target in result.targets.items():
            part = entity_name(name)
            if math.isfinite(target.reproj_px):
                rec.log(f"metrics/reproj_px/{part}", rr.Scalars(target.reproj_px))
            if math.isfinite(target.ambiguity):
                rec.log(f"metrics/ambiguity/{part}", rr.Scalars(target.ambiguity))
            if name.is_board and target.measured:
                rec.log(f"metrics/inliers/{part}", rr.Scalars(float(target.inliers)))
            if math.isfinite(target.evidence_px):
                rec.log(f"metrics/flip_evidence_px/{part}", rr.Scalars(target.evidence_px))
            previous_state = self._states.get(name)
            if previous_state != target.state:
                self._states[name] = target.state
                rec.log("events", rr.TextLog(f"{name}: state {previous_state or '-'} -> {target.state}", level="INFO"))
            for event in target.events:
                level = "WARN" if event.kind in ("switch", "uncommit") else "INFO"
                rec.log("events", rr.TextLog(f"{name}: {event.kind}: {event.message}", level=level))
            if truth is not None and name in truth:
                error = angle_between_deg(target.pose.rotation, truth[name].rotation)
                rec.log(f"metrics/rotation_error_deg/{part}", rr.Scalars(error))
        if self.anchor is None:
            return
        anchor = result.targets.get(self.anchor)
        if truth is not None and self.anchor in truth:
            rec.log(
                "world/truth_camera",
                rr.Points3D(
                    [truth[self.anchor].camera_centre()],
                    colors=[(255, 255, 255)],
                    radii=[0.005],
                    labels=["true camera"],
                ),
            )
        if anchor is None:
            return
        world_from_camera = anchor.pose.inverse()  # its translation is the camera centre C = -R^T t
        rec.log("world/camera", rr.Transform3D(translation=world_from_camera.tvec, mat3x3=world_from_camera.rotation))
        self._trajectory.append(world_from_camera.tvec.copy())
        del self._trajectory[:-_TRAJECTORY_POINTS]
        if len(self._trajectory) >= 2:
            rec.log(
                "world/camera_trajectory",
                rr.LineStrips3D([np.asarray(self._trajectory)], colors=[(255, 210, 60)], radii=[anchor.length_m / 80]),
            )
        for name, target in result.targets.items():
            if name == self.anchor:
                continue
            if name not in self._static_targets:
                self._log_static_target(name, target, is_anchor=False)
                self._static_targets.add(name)
            world_from_target = world_from_camera.compose(target.pose)
            rec.log(
                f"world/targets/{entity_name(name)}",
                rr.Transform3D(translation=world_from_target.tvec, mat3x3=world_from_target.rotation),
            )
        self._log_hypotheses(result, world_from_camera)

    def _log_hypotheses(self, result: FrameResult, world_from_camera: Pose) -> None:
        """Both IPPE branches of every marker, faint, so the flip the filter resolves can be seen."""
        for name, target in result.targets.items():
            for branch, pose in enumerate(target.branch_poses):
                path = f"world/hypotheses/{entity_name(name)}/branch_{branch}"
                if pose is None:
                    self.rec.log(path, rr.Clear(recursive=False))
                    continue
                world_from_branch = world_from_camera.compose(pose)
                squares = [world_from_branch.apply(square) for square in _closed_squares(target)]
                normal = world_from_branch.apply(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, target.length_m]]))
                colour = (90, 200, 255, 90) if branch == 0 else (255, 140, 60, 90)
                self.rec.log(path, rr.LineStrips3D([*squares, normal], colors=[colour], radii=[target.length_m / 120]))

    def log_message(self, text: str, level: str = "INFO") -> None:
        self.rec.log("log", rr.TextLog(text, level=level))

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush everything to the sinks and close the file (the .rrd is complete afterwards).

        The flush is bounded: a viewer that went away must not hang the end of a run.
        """
        try:
            self._flush(timeout_s)
        finally:
            self.rec.disconnect()


def _mesh3d(model: Any) -> rr.Mesh3D:
    """A :class:`~ar_anchor.render.models.Model` as flat-shaded ``rr.Mesh3D`` (vertices repeated per face, so
    each face keeps its own colour and normal)."""
    corners = model.vertices[model.faces]  # (F, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    count = len(model.faces)
    return rr.Mesh3D(
        vertex_positions=corners.reshape(-1, 3).astype(np.float32),
        triangle_indices=np.arange(3 * count, dtype=np.uint32).reshape(-1, 3),
        vertex_normals=np.repeat(normals, 3, axis=0).astype(np.float32),
        vertex_colors=np.repeat(np.clip(model.face_colours, 0, 255).astype(np.uint8), 3, axis=0),
    )


def _closed_squares(target: TargetResult) -> list[np.ndarray]:
    """The target's marker squares as closed 3D line strips in its own frame."""
    quads = target.outline_in_target
    if quads is None:
        quads = marker_corners_in_marker(target.length_m)[None]
    return [np.vstack([quad, quad[:1]]) for quad in np.asarray(quads, np.float64).reshape(-1, 4, 3)]
