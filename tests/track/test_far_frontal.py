"""A far, nearly fronto-parallel, static marker (4 cm at 3 m): its two IPPE solutions reproject within
a few thousandths of a pixel of each other, so a corner bias that depends on the marker's bits, not on the
geometry, picks the branch (issue 32). Edge-fitted corners are corrected for the pull of the inner cells
(:mod:`ar_anchor.track.corners`), and the undecided filter holds one branch (no twitch)."""

from __future__ import annotations

import functools

import numpy as np

from ar_anchor.bench.stability.scenarios import Scenario
from ar_anchor.camera import CameraModel
from ar_anchor.config import FilterConfig, TrackerConfig
from ar_anchor.geometry import Pose, angle_between_deg, marker_corners_in_marker
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.targets import TargetId
from ar_anchor.track.filtering import TargetTrack
from ar_anchor.track.tracker import FrameResult, Tracker
from tests.track.test_pose_truth import CAMERA, DT_NS, measurement, tilted

M0 = TargetId.marker(0)
FRAMES = 60


@functools.cache
def far_frontal() -> tuple[list[FrameResult], list[Pose]]:
    """The scene that showed the bias: tilt -3 deg, noise 1 grey level, blur 0.6 px (raw pick wrong in
    every frame before the correction)."""
    scenario = Scenario("far frontal", 0.04, 3.0, "static", tilt_deg=-3, noise=1.0, blur=0.6, frames=FRAMES)
    camera = CameraModel.default_synthetic()
    tracker = Tracker(scenario.tracker_config(TrackerConfig()), camera)
    results, truths = [], []
    for frame in SyntheticSource(scenario.scene(camera)):
        results.append(tracker.process(frame))
        truths.append(frame.truth[M0])
    return results, truths


def _wrong(pose: Pose | None, truth: Pose) -> bool:
    return pose is not None and angle_between_deg(pose.rotation, truth.rotation) > 10.0


def test_the_raw_pick_is_not_biased_towards_one_branch() -> None:
    """The two solutions are only 9-12 deg apart here: "wrong" is the pick of the one farther from the
    truth. Before the inner cells' pull was corrected, the raw pick took it in 60 of 60 frames (plain
    OpenCV's SUBPIX corners: about a fifth); now in 4."""
    results, truths = far_frontal()
    measured = [(r.targets[M0], t) for r, t in zip(results, truths) if M0 in r.targets]
    assert len(measured) >= 0.9 * FRAMES
    farther = sum(
        angle_between_deg(target.hypotheses[0].pose.rotation, truth.rotation)
        > angle_between_deg(target.hypotheses[1].pose.rotation, truth.rotation)
        for target, truth in measured
        if len(target.hypotheses) == 2
    )
    assert farther <= 0.25 * len(measured), f"raw pick on the farther solution in {farther} of {len(measured)}"


def test_noise_level_evidence_does_not_move_an_undecided_output() -> None:
    """An undecidable marker whose solutions are far apart (50 deg): the frames' error differences are
    noise, their sign changing from frame to frame. The output holds its first frame's branch (no twitch);
    it used to follow the sign of the window's mean from the second frame on."""
    truth = tilted(25, 5)
    track = TargetTrack(FilterConfig(), marker_corners_in_marker(0.05))
    first = None
    for k in range(40):
        excess = 0.006 if k % 3 else -0.007  # the mirror reprojects a hair worse, then a hair better
        update = track.update(measurement(truth, 0.05, 0.05 + excess), k * DT_NS, CAMERA)
        assert update is not None and update.state.value == "ambiguous"
        first = first or update.pose
        assert angle_between_deg(update.pose.rotation, first.rotation) < 10.0, k
        assert not any(e.kind == "branch" for e in update.events), k


def test_the_output_holds_one_branch_without_a_twitch() -> None:
    results, truths = far_frontal()
    outputs = [(r.targets[M0], t) for r, t in zip(results, truths) if M0 in r.targets]
    poses = [target.pose for target, _ in outputs]
    jumps = [angle_between_deg(a.rotation, b.rotation) for a, b in zip(poses, poses[1:])]
    assert max(jumps) < 10.0, f"a twitch of {max(jumps):.1f} deg"
    moves = [i for i, (target, _) in enumerate(outputs) if any(e.kind == "branch" for e in target.events)]
    assert not moves, f"the output moved branch at {moves}"
    wrong_output = sum(_wrong(target.pose, truth) for target, truth in outputs)
    wrong_raw = sum(_wrong(target.raw, truth) for target, truth in outputs)
    assert wrong_output <= wrong_raw
    assert not any(target.state.value == "tracked" and _wrong(target.pose, truth) for target, truth in outputs), (
        "a wrong tracked frame"
    )
    assert np.isfinite([p.tvec for p in poses]).all()
