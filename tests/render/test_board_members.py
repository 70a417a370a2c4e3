"""A marker a board's pose was solved from is drawn as part of that board: no label of its own in the
annotated video, a thin outline in the board's colour without an id in rerun's 2D overlay, and one row
for the board in the summary table; poses.csv keeps its rows."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ar_anchor.cli.report import format_summary
from ar_anchor.config import BoardConfig, TrackerConfig
from ar_anchor.geometry import Pose
from ar_anchor.render import overlay as overlay_module
from ar_anchor.render.overlay import OverlayRenderer
from ar_anchor.run.outputs import RunSummary
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory
from ar_anchor.targets import TargetId
from ar_anchor.track.tracker import FrameResult, Tracker
from ar_anchor.viz import recorder as recorder_module
from ar_anchor.viz.recorder import RerunRecorder

BOARD = BoardConfig(name="desk", cols=3, rows=3, marker_length_m=0.04, separation_m=0.01, first_id=10)


@pytest.fixture(scope="module")
def stills(camera) -> list[tuple[np.ndarray, FrameResult]]:
    """Rendered stills of a 3x3 grid board (ids 10..18) and a lone marker 3 beside it, each replayed alone
    with the filter off (what `replay` does with an image folder): the board is tracked from its nine
    markers, which alone (four corners each) are mostly ambiguous."""
    placed = PlacedBoard(BOARD, Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), np.zeros(3)))
    lone = PlacedMarker(3, 0.05, Pose(np.zeros(3), np.array([-0.12, -0.07, 0.0])))
    scene = SyntheticScene(
        camera=camera,
        markers=(lone,),
        boards=(placed,),
        trajectory=Trajectory(
            kind="static", near_m=0.9, azimuth_deg=8.0, elevation_deg=4.0, roll_deg=3.0, look_at=(0.0, -0.05, 0.0)
        ),
        frames=3,
        noise_sigma=2.0,
        blur_sigma=0.6,
        seed=4,
    )
    config = TrackerConfig(boards=(BOARD,)).with_overrides(filter_enabled=False)
    tracker = Tracker(config, camera, stills=True)
    with SyntheticSource(scene) as source:
        return [(frame.image, tracker.process(frame)) for frame in source]


def _members_ambiguous(result: FrameResult) -> list[TargetId]:
    members = result.board_members()
    assert result.targets[TargetId.board("desk")].state == "tracked"
    assert set(members) == {TargetId.marker(i) for i in range(10, 19)}
    assert set(members.values()) == {TargetId.board("desk")}
    return [name for name in members if result.targets[name].state == "ambiguous"]


def test_the_annotated_video_labels_no_member_of_a_drawn_board(stills, camera, monkeypatch):
    # given stills whose board members are ambiguous on their own
    assert any(_members_ambiguous(result) for _, result in stills)
    drawn: list[tuple[str, TargetId]] = []
    monkeypatch.setattr(
        overlay_module, "_draw_label", lambda image, text, target, cam: drawn.append((text, target.target))
    )
    renderer = OverlayRenderer(TrackerConfig(boards=(BOARD,)), camera)
    for image, result in stills:
        drawn.clear()
        # when the frame is drawn
        renderer.annotate(image, result)
        # then no member has a label; the lone marker keeps its own when it is not tracked
        assert not [target for _, target in drawn if target in result.board_members()], drawn
        lone = result.targets.get(TargetId.marker(3))
        if lone is not None and lone.state != "tracked":
            assert ("ambiguous", TargetId.marker(3)) in drawn


def test_rerun_outlines_members_thinly_in_the_boards_colour_without_ids(stills, camera, tmp_path):
    # given a recorder whose logged entities are kept
    recorder = RerunRecorder(tmp_path / "recording.rrd", camera=camera)
    logged: dict[str, object] = {}
    recorder.recording.log = lambda path, entity, **kwargs: logged.__setitem__(path, entity)
    try:
        for _, result in stills:
            # when a frame's detections are logged
            recorder._log_detections(result, 1.0)
            strips = logged[f"{recorder_module.IMAGE}/markers"]
            batches = {batch.component_descriptor().component: batch for batch in strips.as_component_batches()}
            labels = [str(text) for text in batches["LineStrips2D:labels"].as_arrow_array().to_pylist()]
            radii = batches["LineStrips2D:radii"].as_arrow_array().to_pylist()
            colours = batches["LineStrips2D:colors"].as_arrow_array().to_pylist()
            members = result.board_members()
            board_state = result.targets[TargetId.board("desk")].state
            expected = recorder_module._STATE_COLOURS[board_state]
            board_colour = (expected[0] << 24) | (expected[1] << 16) | (expected[2] << 8) | 0xFF
            # then every member is a thin outline in the board's colour, with no id; the lone marker keeps its id
            assert len(labels) == len(radii) == len(colours) == len(result.detections.ids)
            for marker_id, label, radius, colour in zip(result.detections.ids.tolist(), labels, radii, colours):
                if TargetId.marker(marker_id) in members:
                    assert (label, colour) == ("", board_colour), marker_id
                    assert radius < 1.0
                else:
                    assert label == str(marker_id) and radius == 1.0
            assert str(3) in labels
    finally:
        recorder.close()


def test_the_summary_folds_members_under_their_board_and_keeps_their_rows(stills):
    # given the run's summary of those stills
    summary = RunSummary()
    for _, result in stills:
        summary.add(result, None)
    data = summary.as_dict(1.0)
    # then summary.json keeps every member's entry, saying which board it was drawn as part of ...
    for marker_id in range(10, 19):
        assert data["targets"][f"marker:{marker_id}"]["member_of"] == {"board:desk": len(stills)}
    assert "member_of" not in data["targets"]["marker:3"]
    # ... and the table shows one row for the board and its nine markers, and the lone marker's own
    table = format_summary(data)
    assert "board:desk (9 markers)" in table
    assert "marker:3 " in table
    assert not any(f"marker:{marker_id} " in table for marker_id in range(10, 19)), table


def test_a_marker_also_seen_on_its_own_keeps_its_row():
    # given a marker drawn as part of a board in one of its two frames
    entry = {"frames_measured": 2, "states": {"tracked": 2, "ambiguous": 0}, "detection_rate": 1.0}
    summary = {
        "frames": 2,
        "frames_with_markers": 2,
        "frames_with_pose": 2,
        "wall_time_s": 1.0,
        "fps": 2.0,
        "targets": {
            "board:desk": entry,
            "marker:10": {**entry, "member_of": {"board:desk": 1}},
            "marker:11": {**entry, "member_of": {"board:desk": 2}},
        },
    }
    # then only the marker that was part of the board in every frame is folded
    table = format_summary(summary)
    assert "board:desk (1 marker)" in table and "marker:10 " in table and "marker:11 " not in table


def test_a_member_with_gap_rows_is_still_folded_under_its_board():
    """Found by trying an offline replay of a mapped sheet: a member with an interpolated frame (not seen then,
    so not drawn as part of the board) was listed beside the board as if it were a marker on its own."""
    board = {"frames_measured": 3, "states": {"tracked": 3}, "detection_rate": 1.0}
    gaps = {"frames_measured": 2, "detection_rate": 2 / 3, "member_of": {"board:desk": 2}}
    summary = {
        "frames": 3,
        "frames_with_markers": 3,
        "frames_with_pose": 3,
        "wall_time_s": 1.0,
        "fps": 3.0,
        "targets": {
            "board:desk": board,
            # a member in both frames it was seen in, bridged in the third (offline) or predicted through it
            "marker:10": {**gaps, "states": {"tracked": 2, "interpolated": 1}},
            "marker:11": {**gaps, "states": {"tracked": 1, "ambiguous": 1, "predicted": 1}},
            # seen in three frames, a member in two: on its own in one
            "marker:12": {**gaps, "frames_measured": 3, "states": {"tracked": 3}},
        },
    }
    table = format_summary(summary)
    assert "board:desk (2 markers)" in table, table
    assert "marker:10 " not in table and "marker:11 " not in table and "marker:12 " in table, table


def test_board_members_are_the_markers_the_board_was_solved_from(stills):
    _, result = stills[0]
    board = result.targets[TargetId.board("desk")]
    rejected = dataclasses.replace(board, markers_used=board.markers_used[1:], outlier_ids=board.markers_used[:1])
    changed = dataclasses.replace(result, targets={**result.targets, TargetId.board("desk"): rejected})
    # a marker the board rejected is not drawn as part of it
    assert TargetId.marker(board.markers_used[0]) not in changed.board_members()
    assert len(changed.board_members()) == len(board.markers_used) - 1
