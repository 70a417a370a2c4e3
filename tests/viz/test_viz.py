"""``ar_anchor.viz``: sinks and files of a recording, the run recorder's entities (gone targets cleared), the viewer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.config import RecordingConfig
from ar_anchor.errors import OutputError
from ar_anchor.geometry import Pose
from ar_anchor.sources.base import Frame
from ar_anchor.targets import TargetId, TrackState
from ar_anchor.track.detection import MarkerDetections
from ar_anchor.track.tracker import FrameResult, TargetResult
from ar_anchor.viz import viewer
from ar_anchor.viz.blueprints import calibrate_blueprint, run_blueprint, study_blueprint
from ar_anchor.viz.recorder import RerunRecorder
from ar_anchor.viz.sinks import Recording

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
    """Records the entities the recorder clears, per frame, and where target shapes are logged."""

    def __init__(self, recorder: RerunRecorder) -> None:
        self.frame = -1
        self.cleared: dict[int, list[str]] = {}
        self.shapes: dict[int, list[str]] = {}
        recording = recorder.recording
        clear, log = recording.clear, recording.log

        def spy_clear(entity: str, *, recursive: bool = False) -> None:
            if recursive:  # the branch a filter does not hold this frame is cleared flat: not a gone target
                self.cleared.setdefault(self.frame, []).append(entity)
            clear(entity, recursive=recursive)

        def spy_log(entity: str, data, *, static: bool = False) -> None:
            if entity.endswith("/outline"):
                self.shapes.setdefault(self.frame, []).append(entity)
            log(entity, data, static=static)

        recording.clear, recording.log = spy_clear, spy_log


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
        "world/hypotheses/marker_2",
        "world/targets/marker_2",
    ]
    marker_1 = [entity.replace("marker_2", "marker_1") for entity in marker_2 if "world/targets" not in entity]
    # marker:2 is cleared on the frame it is gone, not again while it stays gone; the anchor (marker:1)
    # when it goes too, but its shape is the world frame and stays
    assert spy.cleared == {1: marker_2, 4: marker_2, 5: marker_1}
    # its shape is logged again when it comes back; the anchor's once
    assert spy.shapes == {0: ["world/outline", "world/targets/marker_2/outline"], 3: ["world/targets/marker_2/outline"]}
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
    assert "camera/image/boards/board_desk" in spy.cleared[1]
    assert "metrics/inliers/board_desk" in spy.cleared[1]
    assert "world/targets/board_desk" not in spy.cleared[1]  # the anchor: its shape is the world frame


def test_overlay_models_can_be_given_to_the_constructor(tmp_path, camera):
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, overlay_models=lambda target: [])
    assert recorder.overlay_models is not None
    recorder.close()


# ---------------------------------------------------------------------------- the viewer


def test_no_viewer_is_spawned_without_a_display(monkeypatch):
    monkeypatch.setattr(viewer.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert viewer.spawn_local_viewer() is None


# a viewer already listening is not reused by --spawn: tests/viz/test_viewer_connect.py
