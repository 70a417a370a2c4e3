"""``ar_anchor.viz``: sinks and files of a recording, the run recorder's entities (gone targets cleared), the viewer."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb

from ar_anchor.camera import CameraModel
from ar_anchor.config import RecordingConfig
from ar_anchor.errors import OutputError
from ar_anchor.geometry import Pose
from ar_anchor.render.models import cube_model
from ar_anchor.render.video import AnnotatedVideoWriter
from ar_anchor.sources.base import Frame
from ar_anchor.targets import TargetId, TrackState
from ar_anchor.track.detection import MarkerDetections
from ar_anchor.track.tracker import FrameResult, TargetResult
from ar_anchor.viz import viewer
from ar_anchor.viz.blueprints import calibrate_blueprint, run_blueprint, study_blueprint
from ar_anchor.viz.pinhole import image_from_camera
from ar_anchor.viz.recorder import IMAGE, OVERLAY_IMAGE, RerunRecorder
from ar_anchor.viz.sinks import Recording
from tests.helpers import distorted_camera

RERUN = Path(sys.executable).with_name("rerun")


def rrd_chunks(*paths: Path) -> set[str]:
    """``/entity - data columns: [...]`` of every chunk in the files (``rerun rrd print``)."""
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    printed = subprocess.run(
        [str(RERUN), "rrd", "print", *map(str, paths)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    return {line.split(") - ", 1)[1] for line in printed.splitlines() if line.startswith("Chunk(")}


def verify(path: Path) -> None:
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    result = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


# ---------------------------------------------------------------------------- Recording


def test_a_partial_file_is_renamed_into_place_on_close(tmp_path):
    path = tmp_path / "out" / "x.rrd"
    recording = Recording("test", path=path, partial=True, blueprint=calibrate_blueprint(), name="x")
    # while it is written, the file has a hidden temporary name beside its final one
    assert not path.exists() and len(list(path.parent.glob(".x.rrd.*.tmp"))) == 1
    recording.time("frame", sequence=0)
    recording.scalar("metrics/value", 1.5)
    recording.close()
    assert [p.name for p in path.parent.iterdir()] == ["x.rrd"]
    verify(path)


def test_a_partial_file_not_kept_is_removed(tmp_path):
    path = tmp_path / "x.rrd"
    recording = Recording("test", path=path, partial=True)
    recording.text("events", "failed", warn=True, static=True)
    recording.close(keep=False)
    assert list(tmp_path.iterdir()) == []


def test_a_file_that_cannot_be_written_is_an_output_error_naming_the_option(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(OutputError, match=r"^--rrd .*a_file/x\.rrd: cannot write"):
        Recording("test", path=tmp_path / "a_file" / "x.rrd", partial=True, option="--rrd")
    with pytest.raises(OutputError, match="cannot write"):
        Recording("test", path=tmp_path)  # a folder


def test_after_a_flush_that_timed_out_close_raises_it_without_waiting_on_a_second_flush(tmp_path):
    # given a recording whose flush timed out (a viewer that accepts and never reads)
    recording = Recording("test", path=tmp_path / "x.rrd")
    flushes, disconnects = [], []

    class Stalled:
        def flush(self, timeout_sec: float) -> None:
            flushes.append(timeout_sec)
            raise RuntimeError("Flush timed out - not all log messages were sent")

        def disconnect(self) -> None:
            disconnects.append(True)

    real, recording.stream = recording.stream, Stalled()
    try:
        with pytest.raises(OutputError, match="Flush timed out") as first:
            recording.flush(timeout_s=10.0)
        # when it closes, then it says the same, flushing no more and closing the sinks
        with pytest.raises(OutputError) as closing:
            recording.close()
    finally:
        real.disconnect()
    assert str(closing.value) == str(first.value)
    assert flushes == [10.0] and disconnects == [True]


@pytest.mark.parametrize("viewer", [True, False], ids=["viewer", "file only"])
def test_after_a_flush_to_a_viewer_timed_out_close_waits_on_the_viewer_briefly(tmp_path, viewer):
    import threading
    import time

    # given a recording whose flush times out, and whose sinks never finish closing (a stalled viewer holds them)
    recording = Recording("test", path=tmp_path / "x.rrd")
    recording.viewer_url = "rerun+http://127.0.0.1:9/proxy" if viewer else None
    released = threading.Event()

    class Stalled:
        def flush(self, timeout_sec: float) -> None:
            raise RuntimeError("Flush timed out - not all log messages were sent")

        def disconnect(self) -> None:
            released.wait(30)

    real, recording.stream = recording.stream, Stalled()
    try:
        # when it closes (its own flush timing out) with a 2.5-s timeout
        started = time.monotonic()
        with pytest.raises(OutputError, match="Flush timed out"):
            recording.close(timeout_s=2.5)
        waited = time.monotonic() - started
    finally:
        released.set()
        real.disconnect()
    # then with a viewer it gives up on the closing after about a second, not a second full timeout; a file
    # alone (a slow disk, no viewer) gets the whole timeout to close
    if viewer:
        assert waited < 2.0, waited
    else:
        assert waited >= 2.5, waited


def test_next_file_closes_the_first_complete_and_goes_on_in_the_second(tmp_path):
    first, second = tmp_path / "r.rrd", tmp_path / "r.part2.rrd"
    recording = Recording("test", path=first, blueprint=run_blueprint(), name="r")
    recording.time("frame", sequence=0)
    recording.scalar("metrics/a", 1.0)
    recording.next_file(second)
    recording.time("frame", sequence=1)
    recording.scalar("metrics/b", 2.0)
    recording.close()
    assert recording.files == [first, second]
    verify(first)
    verify(second)
    assert "/metrics/a - data columns: [Scalars:scalars]" in rrd_chunks(first)
    assert "/metrics/b - data columns: [Scalars:scalars]" in rrd_chunks(second)
    assert "/metrics/b - data columns: [Scalars:scalars]" not in rrd_chunks(first)


def test_the_primitives_log_their_archetypes(tmp_path):
    path = tmp_path / "p.rrd"
    figure = tmp_path / "f.png"
    cv2.imwrite(str(figure), np.zeros((4, 6, 3), np.uint8))
    recording = Recording("test", path=path, blueprint=study_blueprint("s", [("s/plot", "Plot")]))
    recording.time("seed", sequence=3)
    recording.scalar("s/plot/none", None)  # skipped
    recording.scalar("s/plot/nan", float("nan"))  # skipped
    recording.scalar("s/plot/one", 1.0)
    recording.markdown("s/table", "| a |\n|---|\n| 1 |")
    recording.image_file("s/figure", figure)
    recording.jpeg("s/view", np.zeros((8, 8, 3), np.uint8), quality=80, scale=0.5)
    recording.image_points("s/view/points", np.zeros((2, 2), np.float32), radius=2.0, colours=[(1, 2, 3)])
    recording.points3d("s/world", np.zeros((1, 3)), radius=0.1, colours=[(1, 2, 3)], labels=["origin"], static=True)
    recording.clear("s/view/points")
    recording.close()
    chunks = rrd_chunks(path)
    assert not any(chunk.startswith(("/s/plot/none ", "/s/plot/nan ")) for chunk in chunks)
    for expected in (
        "/s/plot/one - data columns: [Scalars:scalars]",
        "/s/table - data columns: [TextDocument:media_type TextDocument:text]",
        "/s/figure - data columns: [EncodedImage:blob EncodedImage:media_type]",
        "/s/view - data columns: [EncodedImage:blob EncodedImage:media_type]",
        "/s/view/points - data columns: [Points2D:colors Points2D:positions Points2D:radii]",
        "/s/view/points - data columns: [Clear:is_recursive]",
        "/s/world - data columns: [Points3D:colors Points3D:labels Points3D:positions Points3D:radii]",
    ):
        assert expected in chunks, expected


# ---------------------------------------------------------------------------- the run recorder


def _result(index: int, names: list[str], camera, *, board: bool = False) -> FrameResult:
    """A frame's result with these marker targets in view (0.5 m ahead), each with two filter branches."""
    targets = {}
    for offset, text in enumerate(names):
        name = TargetId.parse(text)
        pose = Pose.from_matrix(np.eye(3), np.array([0.1 * offset, 0.0, 0.5]))
        targets[name] = TargetResult(
            name,
            TrackState.TRACKED,
            pose,
            pose,
            0.2,
            3.0,
            0.05,
            branch_poses=(pose, None),
            evidence_px=1.0,
            corners_in_image=np.zeros((1, 4, 2)) if name.is_board else None,
            inliers=4,
        )
    return FrameResult(index, index * 33_000_000, MarkerDetections.empty(), targets, camera=camera)


class _Spy:
    """Records the entities the recorder clears, per frame, where target shapes are logged, and what else
    it logs (entity -> [(frame, data)]; what is sent in batches under the frame it belongs to)."""

    def __init__(self, recorder: RerunRecorder) -> None:
        self.frame = -1
        self.cleared: dict[int, list[str]] = {}
        self.cleared_flat: dict[int, list[str]] = {}
        self.shapes: dict[int, list[str]] = {}
        self.logged: dict[str, list[tuple[int, object]]] = {}
        recording = recorder.recording
        clear, log = recording.clear, recording.log

        def spy_clear(entity: str, *, recursive: bool = False) -> None:
            (self.cleared if recursive else self.cleared_flat).setdefault(self.frame, []).append(entity)
            clear(entity, recursive=recursive)

        def spy_log(entity: str, data, *, static: bool = False) -> None:
            if entity.endswith("/outline"):
                self.shapes.setdefault(self.frame, []).append(entity)
            self.logged.setdefault(entity, []).append((self.frame, data))
            log(entity, data, static=static)

        recording.clear, recording.log = spy_clear, spy_log
        transform = recorder.series.transform

        def spy_transform(entity: str, translation, rotation) -> None:
            self.logged.setdefault(entity, []).append((self.frame, (translation, rotation)))
            transform(entity, translation, rotation)

        recorder.series.transform = spy_transform
        series_log = recorder.series.log

        def spy_series_log(entity: str, data) -> None:
            self.logged.setdefault(entity, []).append((self.frame, data))
            series_log(entity, data)

        recorder.series.log = spy_series_log


def test_a_gone_target_is_cleared_once_and_drawn_again_when_it_comes_back(tmp_path, camera):
    path = tmp_path / "recording.rrd"
    recorder = RerunRecorder(path, camera=camera, settings=RecordingConfig(image_every=0))
    spy = _Spy(recorder)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    seen = [["marker:1", "marker:2"], ["marker:1"], ["marker:1"], ["marker:1", "marker:2"], ["marker:1"], []]
    for index, names in enumerate(seen):
        spy.frame = index
        recorder.log_frame(Frame(image, index, index * 33_000_000), _result(index, names, camera))
    recorder.close()
    marker_2 = [
        "metrics/ambiguity/marker_2",
        "metrics/flip_evidence_px/marker_2",
        "metrics/reproj_px/marker_2",
        "world/targets/marker_2",
    ]
    marker_1 = [entity.replace("marker_2", "marker_1") for entity in marker_2 if "world/targets" not in entity]
    # marker:2 is cleared on the frame it is gone, not again while it stays gone; the anchor (marker:1)
    # when it goes too, but its shape is the world frame and stays
    assert spy.cleared == {1: marker_2, 4: marker_2, 5: marker_1}
    # a cleared target's axes are logged at zero length (the viewer would draw cleared axes at its default
    # length from the world origin), and at their own length again when it comes back
    lengths = [
        (frame, data.axis_length.as_arrow_array().to_pylist())
        for frame, data in spy.logged["world/targets/marker_2/axes"]
    ]
    assert [frame for frame, _ in lengths] == [0, 1, 3, 4]
    assert [length for _, (length,) in lengths] == pytest.approx([0.75 * 0.05, 0.0, 0.75 * 0.05, 0.0])
    # its shape is logged again when it comes back; the anchor's once
    assert spy.shapes == {0: ["world/outline", "world/targets/marker_2/outline"], 3: ["world/targets/marker_2/outline"]}
    # every target's hypotheses are one entity, logged whole each frame: a gone target's are not in it (one
    # branch each: its square and its normal), and with no target left it is cleared
    strips = {frame: len(data.strips.as_arrow_array()) for frame, data in spy.logged["world/hypotheses"]}
    assert strips == {0: 4, 1: 2, 2: 2, 3: 4, 4: 2}
    assert spy.cleared_flat == {5: ["world/labels", "world/hypotheses"]}
    # every target's 3D label is in one entity, logged whole each frame with the targets of that frame
    labels = {frame: data.labels.as_arrow_array().to_pylist() for frame, data in spy.logged["world/labels"]}
    assert labels == {
        0: ["marker:1", "marker:2"],
        1: ["marker:1"],
        2: ["marker:1"],
        3: ["marker:1", "marker:2"],
        4: ["marker:1"],
    }
    # and the file read back holds the clears
    chunks = rrd_chunks(path)
    for entity in marker_2 + marker_1:
        assert f"/{entity} - data columns: [Clear:is_recursive]" in chunks, entity
    verify(path)


def test_board_points_are_cleared_with_the_board(tmp_path, camera):
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, settings=RecordingConfig(image_every=0))
    spy = _Spy(recorder)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index, names in enumerate([["board:desk", "marker:3"], ["marker:3"]]):
        spy.frame = index
        recorder.log_frame(Frame(image, index, index * 33_000_000), _result(index, names, camera))
    recorder.close()
    assert "world/camera/image/boards/board_desk" in spy.cleared[1]
    assert "metrics/inliers/board_desk" in spy.cleared[1]
    assert "world/targets/board_desk" not in spy.cleared[1]  # the anchor: its shape is the world frame


def test_overlay_models_can_be_given_to_the_constructor(tmp_path, camera):
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, overlay_models=lambda target: [])
    assert recorder.overlay_models is not None
    recorder.close()


def _views(container) -> list:
    """The blueprint's views, depth first."""
    if isinstance(container, rrb.View):
        return [container]
    return [view for child in container.contents for view in _views(child)]


def _shows(view, entity: str) -> bool:
    """Does the view's entity filter take ``entity`` (rerun's rules: the last matching rule wins, ``/**``
    matches the path and everything under it)?"""
    rules = [view.contents] if isinstance(view.contents, str) else list(view.contents)
    taken = False
    for rule in rules:
        sign, _, pattern = rule.partition(" ") if rule[:2] in ("+ ", "- ") else ("+", " ", rule)
        pattern = "/" + pattern.replace("$origin", str(view.origin)).strip("/")
        path = "/" + entity.strip("/")
        if pattern.endswith("/**"):
            matched = path == pattern[:-3] or path.startswith(pattern[:-2])
        else:
            matched = path == pattern
        if matched:
            taken = sign == "+"
    return taken


def _run_frames(recorder: RerunRecorder, camera, seen: list[list[str]], spy: _Spy | None = None, **kwargs) -> None:
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index, names in enumerate(seen):
        if spy is not None:
            spy.frame = index
        recorder.log_frame(Frame(image, index, index * 33_000_000), _result(index, names, camera), **kwargs)


def test_the_camera_view_projects_every_targets_overlay_meshes_onto_the_image(tmp_path, camera):
    # given a recorder with an overlay model per target, and two targets seen (marker:1 anchors the world)
    cube = SimpleNamespace(model=cube_model(0.05))
    path = tmp_path / "r.rrd"
    recorder = RerunRecorder(path, camera=camera, overlay_models=lambda target: [cube])
    spy = _Spy(recorder)
    _run_frames(recorder, camera, [["marker:1", "marker:2"], ["marker:1", "marker:2"]], spy)
    recorder.close()
    # then the meshes, the image and its detections are where the "AR overlay" view draws them: its origin
    # is the camera's pinhole, the image its child, and the 3D world (the meshes) projected through it
    (view,) = [view for view in _views(run_blueprint().root_container) if view.name == "AR overlay"]
    assert isinstance(view, rrb.Spatial2DView) and view.origin == "world/camera"
    meshes = [entity for entity, logged in spy.logged.items() if isinstance(logged[0][1], rr.Mesh3D)]
    assert sorted(meshes) == ["world/overlay/0", "world/targets/marker_2/overlay/0"]
    for entity in [*meshes, "world/outline", "world/targets/marker_2/outline", IMAGE, f"{IMAGE}/markers"]:
        assert _shows(view, entity), entity
    assert IMAGE.startswith(f"{view.origin}/")
    for entity in ("world/camera_trajectory", "world/hypotheses", "world/truth_camera", OVERLAY_IMAGE):
        assert not _shows(view, entity), entity
    # the plain "Camera" view is the image and its detections alone
    (plain,) = [view for view in _views(run_blueprint().root_container) if view.name == "Camera"]
    assert _shows(plain, IMAGE) and not _shows(plain, "world/overlay/0")
    chunks = rrd_chunks(path)
    assert any(chunk.startswith("/world/camera - data columns: [Pinhole:") for chunk in chunks)
    assert f"/{IMAGE} - data columns: [EncodedImage:blob EncodedImage:media_type]" in chunks
    verify(path)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_the_pinhole_puts_a_point_where_it_is_on_the_logged_image(camera, scale):
    # given points in the camera frame, and their pixels as OpenCV sees them (integers at pixel centres)
    points = np.array([[0.0, 0.0, 1.0], [0.1, -0.05, 0.6], [-0.2, 0.1, 0.9]])
    opencv = camera.project(points)
    # then the viewer's pinhole maps them where the 2D detections are drawn on the image logged at scale
    projected = points @ image_from_camera(camera, scale).T
    np.testing.assert_allclose(projected[:, :2] / projected[:, 2:], (opencv + 0.5) * scale, atol=1e-9)


def test_the_overlay_image_is_logged_only_with_overlay_images(tmp_path, camera):
    overlay = np.zeros((camera.height, camera.width, 3), np.uint8)
    for overlay_images, expected in ((False, []), (True, [0, 1])):
        recorder = RerunRecorder(
            tmp_path / f"{overlay_images}.rrd", camera=camera, settings=RecordingConfig(overlay_images=overlay_images)
        )
        logged = []
        jpeg = recorder.recording.jpeg

        def spy_jpeg(entity, image, *, _jpeg=jpeg, _logged=logged, **kwargs):
            if entity == OVERLAY_IMAGE:
                _logged.append(len(_logged))
            _jpeg(entity, image, **kwargs)

        recorder.recording.jpeg = spy_jpeg
        frame = Frame(overlay, 0, 0)
        assert recorder.wants_overlay_image(frame) is overlay_images
        _run_frames(recorder, camera, [["marker:1"], ["marker:1"]], overlay=overlay)
        recorder.close()
        assert logged == expected
    # and the viewer gets a tab for it only then
    names = {view.name for view in _views(run_blueprint(overlay_image=True).root_container)}
    assert "Overlay image" in names
    assert "Overlay image" not in {view.name for view in _views(run_blueprint().root_container)}


def test_metrics_are_sent_in_batches_that_hold_every_frames_value(tmp_path, camera):
    # given a recorder that sends the metrics every 3 frames
    path = tmp_path / "r.rrd"
    recorder = RerunRecorder(path, camera=camera, settings=RecordingConfig(image_every=0, metrics_every=3))
    sent: dict[str, list[list[int]]] = {}
    columns = recorder.recording.scalar_columns

    def spy_columns(entity, values, times):
        sent.setdefault(entity, []).append(list(values))
        columns(entity, values, times)

    recorder.recording.scalar_columns = spy_columns
    # when 7 frames are logged, each with its stage times
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index in range(7):
        recorder.log_frame(Frame(image, index, index * 33_000_000), _result(index, ["marker:1"], camera))
        recorder.log_latency({"log_ms": float(index)})
    assert sent["metrics/latency/log"] == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]  # the 7th waits for its batch
    recorder.close()
    # then each series went in one call per 3 frames, the last frames' when the recording closed
    assert sent["metrics/latency/log"] == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0]]
    assert [len(values) for values in sent["metrics/reproj_px/marker_1"]] == [3, 3, 1]
    printed = subprocess.run(
        [str(RERUN), "rrd", "print", str(path)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    chunk = "/metrics/latency/log - data columns: [Scalars:scalars]"
    rows = [line for line in printed.splitlines() if line.endswith(chunk)]
    assert sum(int(line.split(" with ")[1].split(" rows")[0]) for line in rows) == 7  # every frame's value
    verify(path)


def test_a_new_part_holds_the_metrics_of_its_own_frames(tmp_path, camera):
    # given a recording that goes on in a new file every frame, and metrics sent every 10 frames
    settings = RecordingConfig(image_every=0, metrics_every=10, part_minutes=1e-9)
    recorder = RerunRecorder(tmp_path / "recording.rrd", camera=camera, settings=settings)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index in range(2):
        recorder.log_frame(Frame(image, index, index * 33_000_000), _result(index, ["marker:1"], camera))
        recorder.log_latency({"log_ms": 1.0})
    recorder.close()
    # then frame 0's metrics are in its file (sent before it closed), frame 1's in the next (the first file
    # ended before frame 0, when the recording was opened)
    first, second = recorder.parts[-2:]
    for part in (first, second):
        assert "/metrics/latency/log - data columns: [Scalars:scalars]" in rrd_chunks(part), part.name
        verify(part)


def test_a_referenced_video_is_the_camera_views_image_at_full_resolution(tmp_path):
    # given an H.264 MP4 (rerun decodes it) and a recording that downscales the images it encodes itself
    video = tmp_path / "clip.mp4"
    writer = AnnotatedVideoWriter(video, fps=30)
    for index in range(4):
        writer.write(np.full((48, 64, 3), 40 * index, np.uint8))
    writer.close()
    camera = CameraModel.from_fov(64, 48, 60.0)
    path = tmp_path / "r.rrd"
    recorder = RerunRecorder(path, camera=camera, settings=RecordingConfig(image_scale=0.5))
    spy = _Spy(recorder)
    # when it references the video
    assert recorder.use_video(video, expected_frames=4)
    _run_frames(recorder, camera, [["marker:1"]] * 4, spy)
    recorder.close()
    # then the video and its frames are the image under the camera's pinhole, and the pinhole is the video's
    # (full resolution), not that of the downscaled JPEGs
    kinds = [type(data).__name__ for _, data in spy.logged[IMAGE]]
    assert kinds == ["AssetVideo"] + ["VideoFrameReference"] * 4
    pinhole = [data for _, data in spy.logged["world/camera"] if isinstance(data, rr.Pinhole)][-1]
    resolution = pinhole.resolution.as_arrow_array().to_pylist()[0]
    assert resolution == [64.0, 48.0]
    chunks = rrd_chunks(path)
    assert any(chunk.startswith(f"/{IMAGE} - data columns: [VideoFrameReference:") for chunk in chunks), chunks
    verify(path)


def test_targets_stay_placed_from_the_last_camera_while_the_anchor_is_out_of_view(tmp_path, camera):
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, settings=RecordingConfig(image_every=0))
    spy = _Spy(recorder)
    _run_frames(recorder, camera, [["marker:1", "marker:2"], ["marker:2"]], spy)
    recorder.close()
    # the camera is not moved on frame 1 (the anchor, marker:1, is not seen), marker:2 is placed from it
    assert [frame for frame, _ in spy.logged["world/camera"] if frame >= 0] == [0]
    assert [frame for frame, _ in spy.logged["world/targets/marker_2"]] == [0, 1]


def test_the_distortion_the_viewer_leaves_out_is_said_once_in_the_events(tmp_path, camera):
    for model, expected in ((camera, 0), (distorted_camera(), 1)):
        recorder = RerunRecorder(tmp_path / "r.rrd", camera=model, settings=RecordingConfig(image_every=0))
        texts = []
        text = recorder.recording.text

        def spy_text(entity, line, *, _text=text, _texts=texts, **kwargs):
            _texts.append(line)
            _text(entity, line, **kwargs)

        recorder.recording.text = spy_text
        _run_frames(recorder, model, [["marker:1"], ["marker:1"]])
        recorder.close()
        notes = [line for line in texts if "without lens distortion" in line]
        assert len(notes) == expected, texts
    offset = float(notes[0].split("up to ")[1].split(" px")[0])
    assert 5.0 < offset < 200.0  # k1 = -0.32 at 640x480: tens of pixels at the corners


# ---------------------------------------------------------------------------- the viewer


def test_no_viewer_is_spawned_without_a_display(monkeypatch):
    monkeypatch.setattr(viewer.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert viewer.spawn_local_viewer() is None


# a viewer already listening is not reused by --spawn: tests/viz/test_viewer_connect.py


def test_an_offline_result_shows_the_live_filter_s_pose_beside_its_own(tmp_path, camera):
    # given offline results that carry the live (causal) filter's targets, one of them 30 deg off
    path = tmp_path / "recording.rrd"
    recorder = RerunRecorder(path, camera=camera, settings=RecordingConfig(image_every=0))
    spy = _Spy(recorder)
    added = {}
    add = recorder.series.add
    recorder.series.add = lambda entity, value: (added.setdefault(entity, []).append(value), add(entity, value))
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index, names in enumerate([["marker:1", "marker:2"], ["marker:1"], []]):
        offline = _result(index, names, camera)
        causal = {
            name: dataclasses.replace(t, pose=Pose(np.array([0.0, math.radians(30.0), 0.0]), t.pose.tvec))
            if name == "marker:2"
            else t
            for name, t in offline.targets.items()
        }
        spy.frame = index
        recorder.log_frame(Frame(image, index, index * 33_000_000), dataclasses.replace(offline, causal_targets=causal))
    recorder.close()
    # then every causal target's axes are one entity, three arrows a target, cleared when none is left
    arrows = {frame: len(data.vectors.as_arrow_array()) for frame, data in spy.logged["world/causal"]}
    assert arrows == {0: 6, 1: 3}
    assert "world/causal" in spy.cleared_flat[2]
    # and the angle between the offline and the live pose is a metric per target
    assert added["metrics/offline_vs_causal_deg/marker_1"] == pytest.approx([0.0, 0.0], abs=1e-6)
    assert added["metrics/offline_vs_causal_deg/marker_2"] == pytest.approx([30.0])
    verify(path)


def test_a_replay_faster_than_real_time_starts_its_parts_by_the_frames_own_time(tmp_path, camera):
    # given a recording in parts of 0.5 min, fed 2 minutes of frames (30 fps) in far less wall time
    settings = RecordingConfig(image_every=0, part_minutes=0.5)
    recorder = RerunRecorder(tmp_path / "recording.rrd", camera=camera, settings=settings)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index in range(0, 3600, 10):
        recorder.log_frame(Frame(image, index, index * 33_333_333), _result(index, ["marker:1"], camera))
    recorder.close()
    # then a new file starts every 30 s of the frames' time: four parts, each complete
    assert [part.name for part in recorder.parts] == [
        "recording.rrd",
        "recording.part2.rrd",
        "recording.part3.rrd",
        "recording.part4.rrd",
    ]
    for part in recorder.parts:
        verify(part)


def test_a_referenced_video_is_in_the_first_part_only_and_later_parts_say_where(tmp_path, camera):
    # given a recording in parts that references its source video
    video = tmp_path / "clip.mp4"
    writer = AnnotatedVideoWriter(video, fps=30)
    for index in range(90):
        writer.write(np.full((camera.height, camera.width, 3), index, np.uint8))
    writer.close()
    recorder = RerunRecorder(tmp_path / "recording.rrd", camera=camera, settings=RecordingConfig(part_minutes=1 / 60))
    assert recorder.use_video(video, expected_frames=90)
    texts: list[str] = []
    text = recorder.recording.text
    recorder.recording.text = lambda entity, line, **kw: (texts.append(line), text(entity, line, **kw))
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    for index in range(90):  # three seconds of the frames' own time: three parts
        recorder.log_frame(Frame(image, index, index * 33_333_333), _result(index, ["marker:1"], camera))
    recorder.close()
    # then the video's bytes are in the first file only (not logged again per part), every part has its
    # frame references and is a complete file, and each later part says once where the images are
    assert [part.name for part in recorder.parts] == ["recording.rrd", "recording.part2.rrd", "recording.part3.rrd"]
    for part in recorder.parts:
        kinds = [chunk.split(" - ")[1] for chunk in rrd_chunks(part) if chunk.startswith(f"/{IMAGE} - ")]
        assert any("VideoFrameReference" in kind for kind in kinds), (part.name, kinds)
        assert any("AssetVideo" in kind for kind in kinds) == (part.name == "recording.rrd"), (part.name, kinds)
        verify(part)
    notes = [line for line in texts if "source video" in line]
    assert notes == [notes[0]] * 2 and "recording.rrd" in notes[0] and "rerun recording*.rrd" in notes[0]
