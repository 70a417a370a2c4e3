"""Rigid groups learned while tracking (ar_anchor.track.groups): joining, leaving, outliers, independence.

The learner is driven here with the real per-marker solver (both IPPE solutions, validated) on corners
projected from known poses with pixel noise, so the planar flip appears as it does in video; the rendered,
hand-held test of the whole tracker is tests/track/test_groups_tracker.py.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import TrackerConfig, parse_config
from ar_anchor.geometry import Pose, angle_between_deg, look_at, marker_corners_in_marker
from ar_anchor.targets import TargetId
from ar_anchor.track.groups import GroupLayout, GroupLearner, members_from_groups
from ar_anchor.track.groups.evidence import _joint_fit_rms, _opencv_joint_fit_rms
from ar_anchor.track.kernels import compiled_refine
from ar_anchor.track.marker_poses import solve_markers
from ar_anchor.track.pose import BoardPose, MarkerPose, PoseHypothesis, solve_marker
from ar_anchor.track.tracker import as_member

CAMERA = CameraModel.from_fov(640, 480, 500.0)
LENGTH = 0.05


def _config(**groups) -> TrackerConfig:
    config = TrackerConfig()
    return dataclasses.replace(config, groups=dataclasses.replace(config.groups, learn=True, **groups))


def _sheet(ids, origin=(0.0, 0.0, 0.0), cols=3, step=0.075) -> dict[int, Pose]:
    """object_from_marker of markers on a flat sheet (marker frames: x right, y up, z out of the sheet)."""
    return {
        marker_id: Pose(np.zeros(3), np.array(origin) + np.array([(k % cols) * step, -(k // cols) * step, 0.0]))
        for k, marker_id in enumerate(ids)
    }


def _camera(frame: int, distance: float = 0.6) -> Pose:
    """camera_from_world of a hand-held camera swaying around the sheets (viewpoints 40 degrees apart)."""
    t = frame / 30.0
    azimuth = math.radians(20.0 * math.sin(1.6 * t))
    elevation = math.radians(12.0 * math.sin(1.1 * t + 1.0))
    eye = distance * np.array(
        [math.sin(azimuth) * math.cos(elevation), math.sin(elevation), math.cos(azimuth) * math.cos(elevation)]
    )
    return look_at(eye + np.array([0.07, -0.04, 0.0]), np.array([0.07, -0.04, 0.0]))


def _measure(camera_from_marker: dict[int, Pose], rng: np.random.Generator, noise_px: float = 0.3) -> dict:
    """Each marker's per-frame solution from its projected corners plus noise (both IPPE solutions), all of a
    frame's markers in one call, as the tracker solves them."""
    if not camera_from_marker:
        return {}
    ids = np.array(list(camera_from_marker), np.int32)
    quads = []
    for pose in camera_from_marker.values():
        corners = CAMERA.project(pose.apply(marker_corners_in_marker(LENGTH)))
        quads.append(corners + rng.normal(0.0, noise_px, corners.shape))
    solved = solve_markers(ids, np.stack(quads), np.full(len(ids), LENGTH), CAMERA)
    return {s.target: s for s in solved if isinstance(s, MarkerPose)}


def _step(learner: GroupLearner, measured: dict) -> tuple[dict, dict]:
    """One frame through the learner: learn, solve every group, settle. Returns (measured with the
    groups' joint poses, events)."""
    events = learner.learn(measured, CAMERA)
    ids = np.array([name.marker_id for name in measured], np.int32)
    corners = np.stack([m.corners_in_image for m in measured.values()]) if measured else np.zeros((0, 4, 2))
    for name, solved in learner.solve(ids, corners, CAMERA, 3.0).items():
        if isinstance(solved, BoardPose):
            measured = {**measured, name: solved}
    for name, messages in learner.settle(measured).items():
        events.setdefault(name, []).extend(messages)
    return measured, events


def _groups(learner: GroupLearner) -> list[set[int]]:
    return [set(group.layout) for group in learner.groups.values()]


def test_markers_on_one_sheet_join_one_group_whose_layout_is_the_sheets():
    rng = np.random.default_rng(1)
    sheet = _sheet((0, 1, 2, 3, 4, 5))
    learner = GroupLearner(_config())
    formed_at = None
    for frame in range(240):
        camera = _camera(frame)
        measured, events = _step(learner, _measure({i: camera.compose(p) for i, p in sheet.items()}, rng))
        if formed_at is None and learner.groups:
            formed_at = frame
            assert any("formed" in m for messages in events.values() for m in messages)
    assert formed_at is not None and formed_at >= learner.settings.min_frames - 1
    assert _groups(learner) == [{0, 1, 2, 3, 4, 5}]
    group = next(iter(learner.groups.values()))
    anchor = sheet[group.anchor]
    for marker_id, group_from_marker in group.layout.items():  # each marker's pose relative to the anchor's
        truth = anchor.inverse().compose(sheet[marker_id])
        learned = group.layout[group.anchor].inverse().compose(group_from_marker)
        assert angle_between_deg(learned.rotation, truth.rotation) < 1.0
        assert np.linalg.norm(learned.tvec - truth.tvec) < 0.003
    assert group.solver.planar  # a sheet is solved as a planar board (both IPPE solutions kept)


@pytest.mark.parametrize(
    ("moving", "distance"),
    [(False, 0.7), (False, 1.6), (True, 0.7), (True, 1.6)],
    ids=["still", "still far", "moving", "moving far"],
)
def test_markers_in_two_planes_join_only_with_their_true_relative_pose(moving, distance):
    # markers on two faces of a box (60 degrees apart), seen from one viewpoint or many, near or far (where
    # each lone marker's flip is a coin toss): the vote over the candidates decides the relative rotation
    # only when the frames agree on one, so a group that forms has the box's layout, never a flipped one
    fold = Pose(np.array([0.0, math.radians(60.0), 0.0]), np.array([0.12, 0.0, -0.03]))
    box = {0: Pose.identity(), 1: Pose(np.zeros(3), np.array([0.0, -0.075, 0.0])), 2: fold}
    rng = np.random.default_rng(2)
    learner = GroupLearner(_config())
    for frame in range(300):
        camera = _camera(frame if moving else 0, distance=distance)
        _step(learner, _measure({i: camera.compose(p) for i, p in box.items()}, rng))
    if moving and distance < 1.0:
        assert _groups(learner) == [{0, 1, 2}]  # (the test can fail: near and moving, the box is learned)
    for group in learner.groups.values():
        anchor = group.layout[group.anchor]
        for marker_id, pose in group.layout.items():
            truth = box[group.anchor].inverse().compose(box[marker_id])
            learned = anchor.inverse().compose(pose)
            assert angle_between_deg(learned.rotation, truth.rotation) < 3.0, (marker_id, sorted(group.layout))
            assert np.linalg.norm(learned.tvec - truth.tvec) < 0.006, (marker_id, sorted(group.layout))


def _wobble(frame: int, phase: float) -> Pose:
    """world_from_object of an object moved by hand: rotating up to 25 degrees, sliding up to 6 cm."""
    t = frame / 30.0
    rvec = np.radians(25.0) * np.array([math.sin(0.9 * t + phase), math.sin(0.6 * t + 2 * phase), 0.3])
    return Pose(rvec, np.array([0.06 * math.sin(0.5 * t + phase), 0.03 * math.cos(0.8 * t + phase), 0.0]))


def test_two_objects_moving_independently_are_never_merged():
    rng = np.random.default_rng(3)
    first = _sheet((0, 1, 2), cols=3)
    second = _sheet((10, 11, 12), origin=(0.0, -0.2, 0.0), cols=3)
    learner = GroupLearner(_config())
    for frame in range(600):
        camera = _camera(frame, distance=0.7)
        a, b = camera.compose(_wobble(frame, 0.0)), camera.compose(_wobble(frame, 2.0))
        poses = {i: a.compose(p) for i, p in first.items()} | {i: b.compose(p) for i, p in second.items()}
        _step(learner, _measure(poses, rng))
        for members in _groups(learner):
            assert members <= {0, 1, 2} or members <= {10, 11, 12}, f"frame {frame}: merged {members}"
    # each object on its own is learned (the test could fail: the learner does group what is rigid)
    assert sorted(map(sorted, _groups(learner))) == [[0, 1, 2], [10, 11, 12]]


def test_a_marker_that_moves_leaves_its_group_and_the_others_stay():
    rng = np.random.default_rng(4)
    sheet = _sheet((0, 1, 2, 3))
    learner = GroupLearner(_config())
    for frame in range(240):
        camera = _camera(frame)
        _step(learner, _measure({i: camera.compose(p) for i, p in sheet.items()}, rng))
    assert _groups(learner) == [{0, 1, 2, 3}]
    left_at = None
    for frame in range(240, 290):  # marker 3 is picked up and carried away: 1 cm per frame
        camera = _camera(frame)
        moved = dict(sheet)
        moved[3] = Pose(
            np.array([0.0, 0.2, 0.0]) * min(frame - 240, 10) / 10, sheet[3].tvec + [0, 0, 0.01 * (frame - 240)]
        )
        _, events = _step(learner, _measure({i: camera.compose(p) for i, p in moved.items()}, rng))
        if left_at is None and any("marker 3 left" in m for messages in events.values() for m in messages):
            left_at = frame
            assert any("left" in m for m in events.get(TargetId.marker(3), []))
    assert left_at is not None and left_at - 240 <= learner.settings.leave_frames + 5
    assert _groups(learner) == [{0, 1, 2}]


def test_wrong_detections_in_single_frames_do_not_move_the_group_or_its_members():
    rng = np.random.default_rng(5)
    sheet = _sheet((0, 1, 2, 3, 4, 5))
    learner = GroupLearner(_config())
    errors = []
    for frame in range(260):
        camera = _camera(frame)
        measured = _measure({i: camera.compose(p) for i, p in sheet.items()}, rng)
        if frame >= 150 and frame % 3 == 0:  # marker 4 mis-detected every third frame: its corners 15 px off
            bad = measured[TargetId.marker(4)]
            corners = bad.corners_in_image + np.array([15.0, -9.0])
            measured[TargetId.marker(4)] = solve_marker(4, corners, LENGTH, CAMERA)
        measured, _ = _step(learner, measured)
        group = next(iter(learner.groups.values()), None)
        if frame >= 150 and group is not None and group.target in measured:
            truth = camera.compose(sheet[group.anchor])
            estimate = measured[group.target].best.pose.compose(group.layout[group.anchor])
            errors.append(angle_between_deg(estimate.rotation, truth.rotation))
            if frame % 3 == 0:
                assert 4 in measured[group.target].outlier_ids
    assert _groups(learner) == [{0, 1, 2, 3, 4, 5}]  # never 5 rejections in a row: marker 4 stays
    assert len(errors) > 100 and max(errors) < 3.0  # (the joint pose's noise, no flip)


def test_members_take_their_groups_pose_where_it_fits_their_corners_and_say_who_vouches_for_it():
    from ar_anchor.targets import TrackState
    from ar_anchor.track.tracker import TargetResult

    group_name = TargetId.board("group-1")
    members = {0: Pose.identity(), 1: Pose(np.zeros(3), np.array([0.1, 0.0, 0.0]))}
    group_pose = Pose(np.array([0.1, 0.2, 0.0]), np.array([0.0, 0.0, 0.5]))
    member_truth = group_pose.compose(members[1])
    near = Pose(member_truth.rvec + np.array([0.02, 0.0, 0.0]), member_truth.tvec)  # the member's own output
    flipped = Pose(member_truth.rvec + np.array([0.0, 0.5, 0.0]), member_truth.tvec)  # its other solution

    def result(name, state, pose, used=(), corners=None, solutions=None):
        solutions = solutions or (PoseHypothesis(pose, 0.1), PoseHypothesis(pose, 5.0))
        return TargetResult(name, state, pose, pose, 0.1, 1.0, LENGTH, hypotheses=solutions, markers_used=used,
                            corners_in_image=corners)  # fmt: skip

    on_the_group = CAMERA.project(member_truth.apply(marker_corners_in_marker(LENGTH)))
    off_the_group = on_the_group + np.array([2.0, 0.0])
    both = (PoseHypothesis(near, 0.1), PoseHypothesis(flipped, 0.12))
    cases = [  # group state, layout settled, member's state, its output, its corners -> member's state (None: own)
        (TrackState.TRACKED, True, TrackState.AMBIGUOUS, near, on_the_group, TrackState.TRACKED),
        (TrackState.AMBIGUOUS, True, TrackState.AMBIGUOUS, near, on_the_group, TrackState.AMBIGUOUS),  # a guess
        (TrackState.AMBIGUOUS, True, TrackState.TRACKED, near, on_the_group, TrackState.TRACKED),  # own vouches
        (TrackState.AMBIGUOUS, True, TrackState.TRACKED, flipped, on_the_group, TrackState.AMBIGUOUS),  # not here
        (TrackState.TRACKED, True, TrackState.AMBIGUOUS, near, off_the_group, None),  # the pose misses its corners
        (TrackState.PREDICTED, True, TrackState.AMBIGUOUS, near, on_the_group, None),  # the group not measured
        (TrackState.TRACKED, False, TrackState.AMBIGUOUS, near, on_the_group, TrackState.TRACKED),  # unsure: follows
        (TrackState.TRACKED, False, TrackState.TRACKED, near, on_the_group, None),  # sure: waits for it to settle
    ]
    for group_state, settled, own_state, own_pose, corners, expected in cases:
        layout = {group_name: GroupLayout(members, settled)}
        targets = {
            group_name: result(group_name, group_state, group_pose, (0, 1)),
            TargetId.marker(1): result(TargetId.marker(1), own_state, own_pose, corners=corners, solutions=both),
        }
        out = members_from_groups(targets, layout, CAMERA, as_member)
        member = out[TargetId.marker(1)]
        if expected is None:
            assert member is targets[TargetId.marker(1)]
            continue
        assert member.state is expected and member.reproj_px < 1e-6
        np.testing.assert_allclose(member.pose.tvec, member_truth.tvec)
    # a member sure of its own pose follows only a layout its own orientation agrees with (a curl flattened)
    sure = result(TargetId.marker(1), TrackState.TRACKED, near, corners=on_the_group, solutions=both)
    group = result(group_name, TrackState.TRACKED, group_pose, (0, 1))
    for agree, follows in ((frozenset({1}), True), (frozenset({0}), False)):
        layout = {group_name: GroupLayout(members, True, agree)}
        out = members_from_groups({group_name: group, TargetId.marker(1): sure}, layout, CAMERA, as_member)
        assert (out[TargetId.marker(1)] is not sure) is follows


def _layout_error_mm(group, sheet) -> float:
    """RMS distance of a group's member corners from the truth, both in the anchor marker's frame."""
    anchor = group.layout[group.anchor]
    errors = []
    for marker_id, pose in group.layout.items():
        learned = anchor.inverse().compose(pose).apply(marker_corners_in_marker(LENGTH))
        truth = sheet[group.anchor].inverse().compose(sheet[marker_id]).apply(marker_corners_in_marker(LENGTH))
        errors.append(np.sum((learned - truth) ** 2, axis=1))
    return 1e3 * float(np.sqrt(np.mean(np.concatenate(errors))))


def test_a_planar_group_formed_or_grown_is_refined_at_once_from_the_frames_before():
    # far enough that the pair evidence leaves a layout a fraction of a millimetre off: the frames kept
    # (remember) refine it the moment the group forms or grows, before any frame to come
    sheet = _sheet((0, 1, 2, 3, 4, 5))
    rng = np.random.default_rng(11)
    learner = GroupLearner(_config())
    refined = []
    for frame in range(150):
        camera = _camera(frame, distance=1.2)
        measured = _measure({i: camera.compose(p) for i, p in sheet.items()}, rng, noise_px=0.5)
        learner.learn(measured, CAMERA)
        for name in sorted(learner.changed):
            group = learner.groups[name]
            before = _layout_error_mm(group, sheet)
            used = learner.refine_from_past(name)
            if len(group.layout) >= 3:
                assert used >= 15, used  # (every other frame of the last 2 s at 30 fps, solved from 3 markers)
                refined.append((before, _layout_error_mm(group, sheet)))
        ids = np.array([name.marker_id for name in measured], np.int32)
        corners = np.stack([m.corners_in_image for m in measured.values()])
        for name, solved in learner.solve(ids, corners, CAMERA, 3.0).items():
            if isinstance(solved, BoardPose):
                measured = {**measured, name: solved}
        learner.remember(int(frame * 1e9 / 30), ids, corners, CAMERA, 3.0, False)
        learner.settle(measured)
    assert refined, "no group of three markers or more formed"
    # measured: 2.15 to 0.84 mm when the third marker joins, then 0.7-1.0 mm (the 0.5 px noise is 1.2 mm here)
    assert refined[0][1] < 0.6 * refined[0][0], refined
    assert all(after < 1.5 for _, after in refined), refined
    for group in learner.groups.values():  # the group's frame: at its members' centroid (recentred at each join)
        assert np.linalg.norm(np.concatenate(list(group.corners().values())).mean(axis=0)) < 0.002
    solved = [list(learner.past_solves(name)) for name in learner.groups]
    assert all(len(frames) == 30 and all(s is not None for _, s in frames) for frames in solved)  # (the last 1 s)


def test_groups_config_reads_and_rejects_bad_values():
    config = parse_config({"groups": {"learn": True, "min_frames": 60}})
    assert config.groups.learn and config.groups.min_frames == 60
    assert not TrackerConfig().groups.learn  # opt-in
    with pytest.raises(Exception, match=r"\[groups\] agreement"):
        parse_config({"groups": {"agreement": 0.2}})
    assert TrackerConfig().with_overrides(learn_groups=True).groups.learn


def test_markers_of_a_configured_board_are_never_learned_again():
    from ar_anchor.config import BoardConfig

    board = BoardConfig(name="desk", cols=2, rows=2, marker_length_m=LENGTH, separation_m=0.025, first_id=0)
    config = dataclasses.replace(_config(), boards=(board,))
    rng = np.random.default_rng(6)
    sheet = _sheet((0, 1, 2, 3, 7))
    learner = GroupLearner(config)
    for frame in range(120):
        camera = _camera(frame)
        _step(learner, _measure({i: camera.compose(p) for i, p in sheet.items()}, rng))
    assert not learner.groups and not learner.pairs  # (marker 7, the only lone one, has no partner)


# ---------------------------------------------------------------------------- members that swap places (issue 34)


def _swap_run(ids, swap, cols, frames, swap_at):
    """The whole tracker with learned groups on a sheet of ``ids`` (``cols`` a row) whose markers ``swap``
    places at frame ``swap_at`` (detections projected from the truth, 0.3 px noise). Its results."""
    from ar_anchor.sources.base import Frame
    from ar_anchor.track.detection import MarkerDetections
    from ar_anchor.track.tracker import DetectedFrame, Tracker

    config = _config()
    length = config.marker_length(ids[0])
    sheet = _sheet(ids, cols=cols)
    tracker = Tracker(config, CAMERA)
    rng = np.random.default_rng(7)
    image = np.zeros((480, 640, 3), np.uint8)
    results = []
    for frame in range(frames):
        placed = dict(sheet)
        if frame >= swap_at:
            a, b = swap
            placed[a], placed[b] = sheet[b], sheet[a]
        camera = _camera(frame)
        corners = [CAMERA.project(camera.compose(placed[i]).apply(marker_corners_in_marker(length))) for i in ids]
        corners = np.array(corners) + rng.normal(0.0, 0.3, (len(ids), 4, 2))
        detections = MarkerDetections(np.array(ids), corners)
        frame_in = Frame(image, frame, frame * 33_333_333)
        results.append(tracker.track(DetectedFrame(frame_in, CAMERA, detections, False, math.nan, False, 0.0)))
    return config, results


@pytest.mark.parametrize(
    ("ids", "swap", "cols"), [((0, 1, 2), (0, 2), 3), ((0, 1), (0, 1), 2)], ids=["row-of-3", "pair"]
)
def test_a_group_whose_members_swap_places_is_not_tracked_while_its_layout_disagrees(ids, swap, cols):
    """Two members swapped: the joint pose rests on one member's place, whichever RANSAC picks, and jumped
    8-17 cm a frame while `tracked`. Now: not tracked (doubt layout_disagrees) until the group dissolves, its
    poses as they were; then the markers learn their new layout; the offline replay keeps the doubt."""
    from ar_anchor.targets import TrackState
    from ar_anchor.track.groups import LAYOUT_DOUBT
    from ar_anchor.track.offline import decide, offline_results

    swap_at = 150
    config, results = _swap_run(ids, swap, cols, swap_at + 70, swap_at)
    group = TargetId.board("group-1")
    before = [r.targets[group] for r in results[swap_at - 30 : swap_at] if group in r.targets]
    assert len(before) == 30 and all(t.state is TrackState.TRACKED for t in before)
    after = [(r.index, r.targets[group]) for r in results[swap_at:] if group in r.targets and r.targets[group].measured]
    assert after, "the group was not measured after the swap"
    jumps = [np.linalg.norm(t.pose.tvec - results[i - 1].targets[group].pose.tvec) for i, t in after[1:]]
    assert max(jumps) > 0.05  # (the case: its pose jumps by a member's place)
    for _, target in after:
        assert target.state is not TrackState.TRACKED and LAYOUT_DOUBT in target.doubts
        messages = [e.message for e in target.events if e.kind == "group"]
        assert any("members seen agree with its layout (moved or swapped?): not tracked" in m for m in messages)
    dissolved = [
        r.index for r in results if any("dissolved" in e.message for t in r.targets.values() for e in t.events)
    ]
    assert dissolved and dissolved[0] - swap_at <= config.groups.leave_frames + 1
    relearned = [n for n in results[-1].targets if n.is_board and n != group]
    assert relearned and results[-1].targets[relearned[0]].state is TrackState.TRACKED  # the new layout
    # the offline replay decides the same frames with hindsight: still not tracked
    plan = decide(results, config)
    offline = list(offline_results(results, plan))
    for index, _ in after:
        target = offline[index].targets.get(group)
        assert target is None or target.state is not TrackState.TRACKED, (index, target.state)


def test_a_group_that_keeps_a_consensus_when_two_members_swap_stays_tracked_on_it():
    """Six members, two swapped: four still agree, the group's pose rests on them (tracked, no jump) and the
    two leave."""
    from ar_anchor.targets import TrackState

    swap_at = 150
    _, results = _swap_run((0, 1, 2, 3, 4, 5), (1, 4), 3, swap_at + 20, swap_at)
    group = TargetId.board("group-1")
    after = [r.targets[group] for r in results[swap_at:]]
    assert all(t.state is TrackState.TRACKED and set(t.markers_used) == {0, 2, 3, 5} for t in after)
    steps = [np.linalg.norm(b.pose.tvec - a.pose.tvec) for a, b in itertools.pairwise(after)]
    assert max(steps) < 0.01


@pytest.mark.skipif(compiled_refine() is None, reason="the compiled pose polish is not built")
def test_the_compiled_joint_fit_reaches_opencvs_fit_from_every_start():
    # given two markers' eight corners (0.3 px noise) and starts near and far from the camera's pose,
    # through a distorted camera, as the pair evidence fits them
    rng = np.random.default_rng(11)
    camera = CameraModel(CAMERA.camera_matrix, np.array([-0.2, 0.05, 0.001, -0.001, 0.0]), 640, 480)
    square = marker_corners_in_marker(LENGTH)
    points = np.concatenate([square, square + [0.09, 0.01, 0.0]])
    compared = 0
    for frame in range(40):
        truth = _camera(frame).compose(Pose(np.zeros(3), np.array([0.02, -0.03, 0.0])))
        image = camera.project(truth.apply(points)) + rng.normal(0.0, 0.3, (8, 2))
        starts = [
            Pose(truth.rvec + rng.normal(0.0, spread, 3), truth.tvec + rng.normal(0.0, spread / 10, 3))
            for spread in (0.01, 0.05, 0.2)
        ]
        # when both refine from each start
        compiled = _joint_fit_rms(points, image, starts, camera)
        opencv = np.array([_opencv_joint_fit_rms(start, points, image, camera) for start in starts])
        # then they agree wherever OpenCV converges (a fit within 1 px), to well below the 1 px agreement limit
        converged = opencv < 1.0
        assert np.all(np.abs(compiled[converged] - opencv[converged]) < 1e-3), (frame, compiled, opencv)
        compared += int(converged.sum())
    assert compared >= 100
