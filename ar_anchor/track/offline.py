"""Offline replay: every frame decided with the whole recording, not only its past.

``live`` must decide each frame from the frames before it; a replay has the recording. Here the same
flip filter that ran forwards (the causal pass, :class:`~ar_anchor.track.tracker.Tracker`) runs again
**backwards** over the same per-frame solutions (both IPPE solutions of every target, kept in
:attr:`FrameResult.measurements <ar_anchor.track.results.FrameResult.measurements>`), and each frame
takes what the two passes say together:

- **The planar flip** (which of the frame's solutions): the evidence of the frames before it (the
  forward pass) and of the frames after it (the backward pass). A pass that vouches for a solution
  (``tracked``) decides it; if both vouch and disagree, the forward choice stays and the frame is
  ``ambiguous``; if neither vouches, the frame is ``ambiguous`` with the forward choice. So a marker
  that is ambiguous far away and decisive once near is ``tracked`` from its first frame, and a scene
  that never decides stays ``ambiguous``.
- **The pose** on that solution: the mean (on SO(3) and in translation) of the forward and the
  backward pass's outputs where both are on it: a two-filter fixed-interval smoother. Each pass's
  smoother lags its own way; the two lags cancel, and the noise averages over frames on both sides.
- **Gaps**: a target unseen for at most ``[filter] interpolate_s`` between two measured frames is
  bridged by interpolating between them (geodesic rotation, straight translation), state
  ``interpolated``; a longer gap, or one with no measurement after it (the end of the recording), has
  no pose: nothing is extrapolated.

Both passes run the filter exactly as ``live`` does (:class:`~.filtering.TargetTrack`), so every
guard of the causal filter (outliers, motion blur, close calls, glides) holds in both directions.

Memory: the backward pass reads the frames from a :class:`FrameStore` (a list, or
:class:`SpoolStore`, a temporary file) and keeps only a few numbers per target and frame, so a long
replay stays flat in memory (the replay spools its frames to disk, then decodes the video again for
its outputs).

API: :func:`smooth` over a list of :class:`FrameResult`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import numpy as np

from ..config import FilterConfig, PoseConfig, TrackerConfig
from ..geometry import Pose, angle_between_deg
from ..targets import TargetId, TrackState
from .filtering import TargetTrack, TrackUpdate, decided_alone, so3_exp, so3_log
from .filtering.track import EVIDENCE_DOUBTS, SEGMENT_STARTS
from .fit import refit
from .gaps import Bridge
from .groups import LAYOUT_DOUBT, doubt_layouts, members_from_groups
from .plan import FrameDecision, OfflinePlan
from .results import FrameResult, TargetResult, as_member
from .spool import FrameStore, SpoolStore
from .tracks import update_tracks

__all__ = ["FrameStore", "OfflinePlan", "SpoolStore", "decide", "offline_results", "smooth"]

Progress = Callable[[int, int], Any]  # (done, total)


def decide(
    frames: FrameStore[FrameResult], config: FilterConfig | TrackerConfig, progress: Progress | None = None
) -> OfflinePlan:
    """The backward pass over ``frames`` (the causal pass's results, in order) and, frame by frame, the
    flip and pose decided from both passes (see the module doc). ``progress(done, total)`` after each
    frame."""
    margin = config.pose.fit_margin_px if isinstance(config, TrackerConfig) else PoseConfig().fit_margin_px
    config = config.filter if isinstance(config, TrackerConfig) else config
    count = len(frames)
    timestamps = np.zeros(count, np.int64)
    blurred = np.zeros(count, bool)
    detail = np.full(count, np.nan)
    measured = np.zeros(count, np.int32)
    decided: list[FrameDecision | None] = [None] * count
    tracks: dict[TargetId, TargetTrack] = {}
    end_ns: int | None = None
    for done, position in enumerate(reversed(range(count)), start=1):
        result = frames[position]
        timestamps[position] = result.timestamp_ns
        blurred[position] = result.blurred
        detail[position] = result.detail
        measured[position] = len(result.measurements)
        if not result.repeated:  # (a repeated frame is no new measurement: it repeats its answer)
            if end_ns is None:
                end_ns = result.timestamp_ns
            assert result.camera is not None, "a FrameResult from Tracker.process carries its camera"
            updates = update_tracks(
                tracks, result.measurements, end_ns - result.timestamp_ns, result.camera, result.blurred, config
            )
            answer = decided[position] = _decide_frame(
                result, {k: u for k, u in updates.items() if u is not None}, config
            )
            for name, starts in zip(answer.names, answer.segment_starts):
                if starts:  # a new segment of the live track: the backward pass carries none of its past either
                    tracks.pop(name, None)
        if progress is not None:
            progress(done, count)
    return OfflinePlan(config, timestamps, decided, blurred, detail, measured, margin)


def _chosen(hypotheses: Sequence[Pose], pose: Pose) -> int:
    """The index of the solution ``pose`` stands on (the nearest in orientation)."""
    if len(hypotheses) == 1:
        return 0
    angles = [angle_between_deg(h.rotation, pose.rotation) for h in hypotheses]
    return int(np.argmin(angles))


def _branch_pose(branch_poses: Sequence[Pose | None], branch: int, fallback: Pose) -> Pose:
    """The output branch's measurement this frame (what a pass chose), else its output pose."""
    if 0 <= branch < len(branch_poses) and branch_poses[branch] is not None:
        return branch_poses[branch]  # type: ignore[return-value]
    return fallback


def _mean_pose(weighted: Sequence[tuple[Pose, int]]) -> Pose:
    """The weighted mean of one or two poses (weight: the frames the pass's smoothers have taken since
    they last started, a proxy for how much each has averaged: a pass that has just started, at its end
    of the recording or after a gap, is little more than its measurement): on the rotations' geodesic,
    and of the translations."""
    if len(weighted) == 1:
        return weighted[0][0]
    (a, wa), (b, wb) = ((pose, max(run, 1)) for pose, run in weighted)
    share = wb / (wa + wb)
    rotation = a.rotation @ so3_exp(share * so3_log(a.rotation.T @ b.rotation))
    return Pose.from_matrix(rotation, a.tvec + share * (b.tvec - a.tvec))


def _decide_frame(result: FrameResult, backward: dict[TargetId, TrackUpdate], config: FilterConfig) -> FrameDecision:
    """The flip and the pose of every target measured in ``result``, from the forward pass (``result``'s
    own targets) and the backward pass's ``backward`` updates (see the module doc)."""
    names, states, poses, choices, causal, starts = [], [], [], [], [], []
    for name in TargetId.ordered(result.measurements):
        measurement = result.measurements[name]
        hypotheses = [h.pose for h in measurement.hypotheses]
        alone = decided_alone(measurement.hypotheses, config, len(measurement.points_in_target))
        forward = result.targets.get(name)
        starts.append(forward is None or any(event.kind in SEGMENT_STARTS for event in forward.events))
        if forward is not None and not forward.measured:
            forward = None
        back = backward.get(name)
        if back is not None and not back.state.measured:
            back = None
        f_choice = (
            -1
            if forward is None
            else _chosen(hypotheses, _branch_pose(forward.branch_poses, forward.branch, forward.pose))
        )
        b_choice = -1 if back is None else _chosen(hypotheses, _branch_pose(back.hypotheses, back.branch, back.pose))
        state, choice = _flip(result.blurred, forward, f_choice, back, b_choice, alone)
        if state is TrackState.TRACKED:  # both passes' smoothed poses on the chosen solution, weighted
            passes = ((forward, f_choice), (back, b_choice))
            on_choice = [(p.pose, p.run_frames) for p, c in passes if c == choice and p is not None]
            # (a pass whose own pose is in doubt, a spike held back, a glide, is left out where the other is not)
            sound = [(p.pose, p.run_frames) for p, c in passes if c == choice and p and _pose_sound(p, c, alone)]
            pose = _mean_pose(sound or on_choice)
        else:  # undecided: the output of the pass on that solution as it is (the live filter's first: halfway
            # between the solutions when it holds both)
            on = [p for p, c in ((forward, f_choice), (back, b_choice)) if p is not None and c == choice]
            pose = on[0].pose if on else forward.pose if forward is not None else hypotheses[choice]
        names.append(name)
        states.append(state)
        poses.append(np.concatenate([pose.rvec, pose.tvec]))
        choices.append(choice)
        causal.append(f_choice)
    array = np.array(poses, np.float64).reshape(-1, 6)
    return FrameDecision(tuple(names), tuple(states), array, tuple(choices), tuple(causal), tuple(starts))


def _doubts(p: TargetResult | TrackUpdate, choice: int, alone: bool) -> set[str]:
    """A pass's doubts about the frame, where it stands on solution ``choice``: motion blur is none on the
    frame's lower-error solution when the frame alone decides the flip (``alone``; see :func:`_flip`)."""
    return set(p.doubts) - {"blurred"} if alone and choice == 0 else set(p.doubts)


def _pose_sound(p: TargetResult | TrackUpdate, choice: int, alone: bool) -> bool:
    """Does the pass doubt nothing about the frame's pose itself (only, at most, which solution is right)?"""
    return EVIDENCE_DOUBTS.issuperset(_doubts(p, choice, alone))


def _flip(
    blurred: bool,
    forward: TargetResult | None,
    f_choice: int,
    back: TrackUpdate | None,
    b_choice: int,
    alone: bool = False,
) -> tuple[TrackState, int]:
    """A measured frame's state and solution from the two passes (measured there, else None):

    - a pass that vouches (``tracked``) decides, the forward one first; both vouching for different
      solutions leaves the frame ``ambiguous``;
    - the backward pass vouches only where the forward one doubts nothing but which solution is right
      (:data:`~.filtering.track.EVIDENCE_DOUBTS`: undecided yet, a close call...), not this frame's pose
      itself (blur, an outlier, a spike, a glide);
    - neither vouching, both committed to the same solution with only such doubts: the evidence before
      and after the frame agree, the frame's own close call cannot overturn them: ``tracked``;
    - else ``ambiguous`` on the forward pass's solution (the live filter's), or, where the passes stand on
      different solutions and only the backward pass, committed, doubts nothing of the frame's pose, on its.

    Motion blur (``blurred``) is no doubt on a pass standing on the frame's lower-error solution when the
    frame alone decides the flip (``alone``: :func:`~.filtering.decided_alone`): the frame settles its own
    flip, as a later frame settles an earlier one's. (The whole-frame blur test compares sharpness with its
    running typical value, which a slow change of view, a marker growing to fill the image, can leave
    behind for good: on an approach every near frame, each decisive, was ``blurred``.)"""

    def sure(p: TargetResult | TrackUpdate | None, c: int) -> bool:
        return p is not None and (p.state is TrackState.TRACKED or bool(p.doubts) and not _doubts(p, c, alone))

    f_sure, b_sure = sure(forward, f_choice), sure(back, b_choice)
    if f_sure:
        return (TrackState.TRACKED if not b_sure or b_choice == f_choice else TrackState.AMBIGUOUS), f_choice
    choice = f_choice if f_choice >= 0 else max(b_choice, 0)
    if forward is not None and back is not None and f_choice != b_choice and back.committed:
        if not _pose_sound(forward, f_choice, alone) and _pose_sound(back, b_choice, alone):
            choice = b_choice  # the passes disagree, neither sure: the committed one that doubts nothing of the pose
    pose_doubted = (blurred and not (alone and choice == 0)) or any(
        not _pose_sound(p, c, alone) for p, c in ((forward, f_choice), (back, b_choice)) if p is not None
    )
    if pose_doubted:
        return TrackState.AMBIGUOUS, choice
    if b_sure:
        return TrackState.TRACKED, b_choice
    if forward is not None and back is not None and forward.committed and back.committed and f_choice == b_choice:
        return TrackState.TRACKED, f_choice
    return TrackState.AMBIGUOUS, choice


def offline_results(frames: FrameStore[FrameResult], plan: OfflinePlan) -> Iterator[FrameResult]:
    """Each frame's offline :class:`FrameResult`, in order: the causal result with its targets' states and
    poses replaced by the plan's, gaps bridged (``interpolated``) and causal predictions dropped."""
    bridge = Bridge(plan)
    previous: FrameResult | None = None
    for position in range(len(plan)):
        causal = frames[position]
        decided = plan.decided[position]
        if decided is None:  # a repeated frame: the last answer again (its events happened once, then)
            base = previous if previous is not None else causal
            targets = {name: dataclasses.replace(t, events=()) for name, t in base.targets.items()}
            previous = dataclasses.replace(
                base, index=causal.index, timestamp_ns=causal.timestamp_ns, repeated=True, targets=targets
            )
            yield previous
            continue
        targets: dict[TargetId, TargetResult] = {}
        for k, name in enumerate(decided.names):
            targets[name] = bridge.measured(position, causal, decided, k)
        for name, target in bridge.gaps(position, set(decided.names)):
            targets[name] = target
        ordered = {name: targets[name] for name in TargetId.ordered(targets)}
        if causal.groups:  # learned rigid groups: members of a tracked group take its pose
            ordered = doubt_layouts(ordered, {n for n, t in causal.targets.items() if LAYOUT_DOUBT in t.doubts})
            ordered = members_from_groups(ordered, causal.groups, causal.camera, as_member)
        for name in decided.names:  # every output fits its own frame (see track/fit.py)
            assert causal.camera is not None
            fitted = refit(ordered[name], causal.measurements[name], causal.camera, plan.config, plan.fit_margin_px)
            if fitted is not None:
                ordered[name] = fitted[0]
        # a learned group whose frame contradicts its layout stays not tracked (see groups.doubt_layouts)
        ordered = doubt_layouts(ordered, {n for n, t in causal.targets.items() if LAYOUT_DOUBT in t.doubts})
        previous = dataclasses.replace(causal, targets=ordered, causal_targets=causal.targets)
        yield previous


def smooth(results: Iterable[FrameResult], config: FilterConfig | TrackerConfig) -> list[FrameResult]:
    """The offline answer for a whole sequence of :class:`FrameResult` (one stream, in order, as
    :meth:`Tracker.process <ar_anchor.track.tracker.Tracker.process>` returned them, filter on)::

        tracker = Tracker(config, camera)
        causal = [tracker.process(frame) for frame in frames]
        offline = smooth(causal, tracker.config)

    Everything is kept in memory; ``ar-anchor replay`` spools long recordings to disk instead
    (:class:`SpoolStore`, :func:`decide`, :func:`offline_results`).
    """
    frames = list(results)
    if any(r.camera is None for r in frames):
        raise ValueError("smooth() needs the results of Tracker.process (each carries its camera)")
    return list(offline_results(frames, decide(frames, config)))
