"""Several cameras, one recording: ``--name`` puts a camera's entities under ``cameras/<name>/``, ``--recording-id``
makes every process's stream one recording (in a viewer, and in their files merged); without ``--name`` the run's
entity tree is what it always was."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from ar_anchor.config import RecordingConfig
from ar_anchor.viz.blueprints import run_blueprint
from ar_anchor.viz.recorder import RerunRecorder
from tests.helpers import assert_no_traceback, cli, describe, error_lines, run_main
from tests.viz.test_viz import _run_frames, _views, verify

RERUN = Path(sys.executable).with_name("rerun")
SEEN = [["board:desk", "marker:1", "marker:2"], ["board:desk", "marker:1"], ["board:desk"]]

# the run's entity tree for SEEN (a board anchoring the world, two markers, one gone, then the other): what a
# recording without --name has always held
UNNAMED_ENTITIES = {
    "events",
    "metrics/ambiguity/board_desk",
    "metrics/ambiguity/marker_1",
    "metrics/ambiguity/marker_2",
    "metrics/flip_evidence_px/board_desk",
    "metrics/flip_evidence_px/marker_1",
    "metrics/flip_evidence_px/marker_2",
    "metrics/inliers/board_desk",
    "metrics/latency/detect",
    "metrics/reproj_px/board_desk",
    "metrics/reproj_px/marker_1",
    "metrics/reproj_px/marker_2",
    "world",
    "world/axes",
    "world/camera",
    "world/camera/image",
    "world/camera/image/boards/board_desk/inliers",
    "world/camera/image/boards/board_desk/outliers",
    "world/camera/image/corners",
    "world/camera/image/markers",
    "world/camera_trajectory",
    "world/hypotheses",
    "world/labels",
    "world/outline",
    "world/targets/marker_1",
    "world/targets/marker_1/axes",
    "world/targets/marker_1/outline",
    "world/targets/marker_2",
    "world/targets/marker_2/axes",
    "world/targets/marker_2/outline",
}


def entities(path: Path) -> set[str]:
    """The entities with data in the file's recording (its first), without the leading ``/`` (rerun's own
    ``__properties`` left out)."""
    found = {entity.strip("/") for entity in RrdReader(path).store().schema().entity_paths()}
    return {entity for entity in found if not entity.startswith("__properties")}


def record(path: Path, camera, **kwargs) -> RerunRecorder:
    recorder = RerunRecorder(path, camera=camera, settings=RecordingConfig(image_every=1), **kwargs)
    _run_frames(recorder, camera, SEEN, stages={"detect_ms": 1.0})
    recorder.close()
    return recorder


def stores(path: Path) -> tuple[list[tuple[str, str]], int]:
    """The file's recordings (application id, recording id) and its number of blueprints."""
    reader = RrdReader(path)
    return [(entry.application_id, entry.recording_id) for entry in reader.recordings()], len(reader.blueprints())


def merge(paths: list[Path], into: Path) -> None:
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    merged = subprocess.run(
        [str(RERUN), "rrd", "merge", *map(str, paths), "-o", str(into)], capture_output=True, text=True, timeout=120
    )
    assert merged.returncode == 0, merged.stdout + merged.stderr


# ---------------------------------------------------------------------------- the recorder


def test_without_a_name_the_entity_tree_and_layout_are_unchanged(tmp_path, camera):
    # given a recorder without a camera name or recording id (every command's default)
    recorder = record(tmp_path / "r.rrd", camera)
    # then its entities are the run's tree, at the root, and it sends the run layout
    assert recorder.root is None
    assert entities(tmp_path / "r.rrd") == UNNAMED_ENTITIES
    recordings, blueprints = stores(tmp_path / "r.rrd")
    assert len(recordings) == 1 and recordings[0][0] == "ar_anchor" and blueprints >= 1
    views = {view.name: view.origin for view in _views(run_blueprint().root_container)}
    assert views["AR overlay"] == "world/camera" and views["3D scene"] == "world"
    verify(tmp_path / "r.rrd")


def test_a_named_camera_holds_the_same_tree_under_its_name_with_its_own_layout(tmp_path, camera):
    # given a named camera recording alone (its own recording id)
    record(tmp_path / "r.rrd", camera, camera_name="left")
    # then every entity is the unnamed tree's under cameras/left
    assert entities(tmp_path / "r.rrd") == {f"cameras/left/{entity}" for entity in UNNAMED_ENTITIES}
    # and it sends a layout whose every view's origin is one of its entities (or a parent of them)
    _, blueprints = stores(tmp_path / "r.rrd")
    assert blueprints >= 1  # (sent again, its 3D eye framed on the targets, once they are placed)
    layout = run_blueprint(root="cameras/left", overlay_image=False)
    parents = {"/".join(e.split("/")[:i]) for e in entities(tmp_path / "r.rrd") for i in range(1, e.count("/") + 2)}
    views = _views(layout.root_container)
    assert len(views) == 10
    for view in views:
        if view.origin != "cameras/left/metrics/rotation_error_deg":  # (no ground truth in these frames)
            assert str(view.origin) in parents, view.origin
    names = sorted(view.name for view in views if not isinstance(view, rrb.TimeSeriesView))
    assert names == ["3D scene (left)", "AR overlay (left)", "Camera (left)", "Tracker events (left)"]
    (ar_view,) = [view for view in views if view.name == "AR overlay (left)"]
    assert "+ /cameras/left/world/**" in ar_view.contents and "- /cameras/left/world/labels" in ar_view.contents


def test_named_cameras_sharing_a_recording_id_merge_into_one_recording_without_a_layout(tmp_path, camera):
    # given two cameras' recorders with one recording id, each writing its own file
    for name in ("left", "right"):
        record(tmp_path / f"{name}.rrd", camera, camera_name=name, recording_id="lab")
        # then each file is that recording, without a layout (each process's would replace the other's)
        assert stores(tmp_path / f"{name}.rrd") == ([("ar_anchor", "lab")], 0)
    # when the files are merged
    merge([tmp_path / "left.rrd", tmp_path / "right.rrd"], tmp_path / "merged.rrd")
    # then the merged file is one recording holding both cameras' trees, side by side
    assert stores(tmp_path / "merged.rrd") == ([("ar_anchor", "lab")], 0)
    assert entities(tmp_path / "merged.rrd") == {
        f"cameras/{name}/{entity}" for name in ("left", "right") for entity in UNNAMED_ENTITIES
    }
    verify(tmp_path / "merged.rrd")


# ---------------------------------------------------------------------------- the options


@pytest.mark.parametrize("name", ["", "a b", "a/b", "../x", "-x", "_x", "x" * 65, "caméra", "a\\b", "$origin"])
def test_a_bad_camera_name_is_one_clear_usage_error(name):
    result = run_main(["demo", "--frames", "1", f"--name={name}"])  # (=: a name starting with - too)
    assert result.code == 2, result.describe()
    assert "argument --name: expected a camera name such as left" in result.stderr, result.describe()
    assert "Traceback" not in result.stderr


def test_an_empty_recording_id_is_a_usage_error():
    result = run_main(["live", "--device", "synthetic", "--recording-id", ""])
    assert result.code == 2 and "argument --recording-id: empty recording id" in result.stderr, result.describe()


@pytest.mark.parametrize("command", [["live"], ["replay", "x.mp4"], ["demo"]])
def test_the_run_commands_take_a_recording_id_and_a_name(command):
    from ar_anchor.cli.main import build_parser

    args = build_parser().parse_args([*command, "--recording-id", "lab 1", "--name", "cam-2_b"])
    assert (args.recording_id, args.camera_name) == ("lab 1", "cam-2_b")
    defaults = build_parser().parse_args(command)
    assert (defaults.recording_id, defaults.camera_name) == (None, None)


# ---------------------------------------------------------------------------- two live processes


@pytest.mark.slow
def test_two_live_cameras_with_one_recording_id_are_one_recording(tmp_path):
    # given two synthetic cameras run at the same time, one recording id, each its own name and output
    common = ["-q", "live", "--device", "synthetic", "--max-frames", "30", "--width", "320", "--height", "180"]
    processes = {
        name: subprocess.Popen(
            cli([*common, "--seed", str(seed), "--recording-id", "lab", "--name", name, "--out", name]),
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for seed, name in enumerate(("left", "right"))
    }
    for process in processes.values():
        try:
            stdout, stderr = process.communicate(timeout=180)
        except subprocess.TimeoutExpired:
            process.kill()
            stdout, stderr = process.communicate()
        result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
        assert result.returncode == 0, describe(result)
        assert_no_traceback(result)
        assert not error_lines(result.stderr), describe(result)
    # then each wrote its own recording.rrd, of the shared recording
    files = [tmp_path / name / "recording.rrd" for name in processes]
    for path in files:
        assert stores(path) == ([("ar_anchor", "lab")], 0)
        verify(path)
    # when they are merged into one file
    merged = tmp_path / "lab.rrd"
    merge(files, merged)
    # then it is one recording holding both cameras' entities, and nothing outside them
    assert stores(merged) == ([("ar_anchor", "lab")], 0)
    found = entities(merged)
    for name in processes:
        for entity in ("world", "world/camera", "world/camera/image", "world/camera/image/markers", "events"):
            assert f"cameras/{name}/{entity}" in found, (name, entity)
        assert any(entity.startswith(f"cameras/{name}/metrics/reproj_px/") for entity in found), name
    assert all(entity.startswith(("cameras/left/", "cameras/right/")) for entity in found), sorted(found)[:5]
    verify(merged)
