"""TargetId and TrackState: the one place target names are built, parsed and ordered."""

from __future__ import annotations

import dataclasses
import json

import pytest

from ar_anchor import SyntheticSource, demo_scene
from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.targets import TargetId, TrackState, target_pattern_problem
from ar_anchor.track.tracker import Tracker


def test_names_round_trip_and_parts():
    marker = TargetId.marker(12)
    assert marker == "marker:12" and marker.kind == "marker" and marker.marker_id == 12 and not marker.is_board
    board = TargetId.parse("board:desk")
    assert board == TargetId.board("desk") and board.name == "desk" and board.marker_id is None and board.is_board
    assert TargetId.parse(marker) is marker
    assert {marker: 1}["marker:12"] == 1  # a TargetId is its name as a dict key
    assert marker.path_part == "marker_12"


@pytest.mark.parametrize(
    "text", ["marker:x", "marker:-1", "marker:007", "marker:" + "9" * 5000, "boards:a", "board:", "board:a:b", "7", ""]
)
def test_bad_names_are_refused_with_the_reason(text):
    with pytest.raises(ValueError, match="marker|board"):
        TargetId.parse(text)


def test_one_order_boards_first_markers_by_number():
    names = ["marker:10", "marker:2", "board:zeta", "board:alpha", "marker:0"]
    assert TargetId.ordered(names) == ["board:alpha", "board:zeta", "marker:0", "marker:2", "marker:10"]


def test_patterns():
    assert TargetId.marker(3).matches("*") and TargetId.marker(3).matches("marker:*")
    assert not TargetId.marker(3).matches("board:*") and TargetId.board("a").matches("board:a")
    assert target_pattern_problem("marker:*") is None and target_pattern_problem("board:desk") is None
    assert "marker:7" in target_pattern_problem("marker:007")
    assert target_pattern_problem("markers:*") is not None


def test_track_state_is_its_text():
    assert TrackState("tracked") is TrackState.TRACKED
    assert f"{TrackState.AMBIGUOUS}" == str(TrackState.AMBIGUOUS) == "ambiguous"
    assert json.dumps([TrackState.PREDICTED]) == '["predicted"]'
    assert {"tracked": 0}.get(TrackState.TRACKED) == 0
    assert not TrackState.PREDICTED.measured and TrackState.TRACKED.measured


@pytest.mark.parametrize("filtered", [True, False])
def test_frame_results_come_in_target_order_with_and_without_filter(filtered):
    config = demo_config()
    config = dataclasses.replace(config, filter=dataclasses.replace(config.filter, enabled=filtered))
    camera = CameraModel.default_synthetic()
    tracker = Tracker(config, camera)
    seen_both = False
    for frame in SyntheticSource(demo_scene(config, camera, frames=6)):
        names = list(tracker.process(frame).targets)
        assert names == TargetId.ordered(names)
        assert all(isinstance(name, TargetId) for name in names)
        seen_both |= any(n.is_board for n in names) and any(not n.is_board for n in names)
    assert seen_both  # the demo shows a board and lone markers: the order was really tested
