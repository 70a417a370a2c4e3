"""The whole tracker with learned groups on a rendered hand-held clip (issue 23's acceptance, one scene of
``ar-anchor bench groups``): a 6-marker sheet, no layout given, motion blur, quick turns and JPEG."""

from __future__ import annotations

import numpy as np
import pytest

from ar_anchor.bench.groups import run_scene, scene_failures, score_member
from ar_anchor.bench.stability.scenarios import handheld_scenarios
from ar_anchor.camera import CameraModel
from ar_anchor.config import TrackerConfig
from ar_anchor.geometry import Pose


@pytest.mark.slow
def test_members_of_a_learned_group_are_never_worse_and_steadier_than_alone():
    scenario = next(s for s in handheld_scenarios() if s.name == "hh vga strong blur turns 200deg/s")
    scene = run_scene(scenario, TrackerConfig(), CameraModel.from_fov(640, 480, 500.0))
    assert scene_failures(scene) == []  # a group formed; per member: wrong % <= lone, no wrong tracked frame
    members = [m for m in scene["members"].values() if m.get("joined") is not None]
    assert len(members) == 6
    steadier = [m for m in members if m["groups"]["jitter_deg"] < 0.8 * m["lone"]["jitter_deg"]]
    assert len(steadier) >= 4, members
    # the reference: the sheet's exact layout given as a board, each member from the board's pose
    assert all(m["layout"]["wrong_pct"] == 0.0 and m["layout"]["jitter_deg"] < m["lone"]["jitter_deg"] for m in members)


def test_score_member_counts_wrong_frames_and_jitter_from_the_join():
    truth = [Pose(np.zeros(3), np.array([0.0, 0.0, 1.0]))] * 4
    flipped = Pose(np.array([0.0, np.radians(30.0), 0.0]), np.array([0.0, 0.0, 1.0]))
    shaky = Pose(np.array([0.0, np.radians(1.0), 0.0]), np.array([0.001, 0.0, 1.0]))
    output = [flipped, truth[1], shaky, truth[3]]
    score = score_member(output, truth, ["tracked", "tracked", "ambiguous", "tracked"], start=1)
    assert score["frames"] == 3 and score["wrong_pct"] == 0.0 and score["wrong_tracked"] == 0
    assert score["jitter_deg"] == pytest.approx(np.sqrt(2 / 2), rel=1e-6)  # steps 1 deg then 1 deg
    assert score["jitter_mm"] == pytest.approx(1.0, rel=1e-6)
    assert score_member(output, truth, ["tracked"] * 4, start=0)["wrong_tracked"] == 1
