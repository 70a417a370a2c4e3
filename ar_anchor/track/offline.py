"""Offline replay: every frame decided with the whole recording, not only its past.

``live`` must decide each frame from the frames before it; a replay has the recording. Here the same
flip filter that ran forwards (the causal pass, :class:`~ar_anchor.track.tracker.Tracker`) runs again
**backwards** over the same per-frame solutions (both IPPE solutions of every target, kept in
:attr:`FrameResult.measurements <ar_anchor.track.tracker.FrameResult.measurements>`), and each frame
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
import io
import math
import os
import pickle
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from ..config import FilterConfig, TrackerConfig
from ..geometry import Pose, angle_between_deg, mean_rotation
from ..targets import TargetId, TrackState
from .filtering import KalmanBatch, TargetTrack, TrackEvent, TrackUpdate, so3_exp, so3_log, unit_covariances_of
from .filtering.track import EVIDENCE_DOUBTS
from .pose import BoardPose, MarkerPose, reprojection_rms
from .tracker import FrameResult, TargetResult, run_filter_steps

__all__ = ["FrameStore", "OfflinePlan", "SpoolStore", "decide", "offline_results", "smooth"]

T = TypeVar("T")
Progress = Callable[[int, int], Any]  # (done, total)


class FrameStore(Protocol[T]):
    """Frames kept for the offline passes, read by position (any order)."""

    def __len__(self) -> int: ...

    def __getitem__(self, position: int) -> T: ...


class _SpoolUnpickler(pickle.Unpickler):
    """Reads back only what the spool writes: the package's own classes and numpy arrays. (The spool is an
    unnamed temporary file this process wrote itself, never input; this is defence in depth.)"""

    _NUMPY = {("numpy", "dtype"), ("numpy._core.numeric", "_frombuffer"), ("numpy.core.numeric", "_frombuffer")}
    _NUMPY |= {("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct")}
    _NUMPY |= {("numpy", "ndarray")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._NUMPY:
            return super().find_class(module, name)
        if module.startswith("ar_anchor.") and "." not in name:
            found = super().find_class(module, name)
            if isinstance(found, type):
                return found
        raise pickle.UnpicklingError(f"the offline spool holds no {module}.{name}")


class SpoolStore(Generic[T]):
    """Items pickled one after another into an unnamed temporary file (gone when closed, or when the
    process ends), read back by position (:class:`_SpoolUnpickler`: the package's classes and numpy arrays
    only): a long recording's frames on disk, not in memory."""

    def __init__(self, directory: str | os.PathLike[str] | None = None) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix="ar-anchor-offline-")
        self._offsets: list[int] = []
        self._end = 0

    def append(self, item: T) -> None:
        """Pickle ``item`` at the end of the file."""
        data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
        self._file.seek(self._end)
        self._file.write(data)
        self._offsets.append(self._end)
        self._end += len(data)

    def __len__(self) -> int:
        return len(self._offsets)

    def __getitem__(self, position: int) -> T:
        start = self._offsets[position]
        stop = self._offsets[position + 1] if position + 1 < len(self._offsets) else self._end
        self._file.seek(start)
        return _SpoolUnpickler(io.BytesIO(self._file.read(stop - start))).load()

    @property
    def size_bytes(self) -> int:
        return self._end

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> SpoolStore[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class _Decided:
    """The offline answer for the measured targets of one frame (a few numbers each: the plan of a long
    recording stays small)."""

    names: tuple[TargetId, ...]
    states: tuple[TrackState, ...]
    poses: np.ndarray  # (K, 6): rvec, tvec
    choices: tuple[int, ...]  # index of the chosen solution in the frame's measurement
    causal_choices: tuple[int, ...]  # the forward (live) pass's, -1 where it published nothing

    def pose(self, k: int) -> Pose:
        return Pose(self.poses[k, :3], self.poses[k, 3:])


@dataclass
class OfflinePlan:
    """What :func:`decide` found: per frame position, the measured targets' offline answers (None for a
    repeated frame), and every frame's timestamp."""

    config: FilterConfig
    timestamps_ns: np.ndarray
    decided: list[_Decided | None]
    blurred: np.ndarray  # (frames,) bool: motion-blurred frames (no gap is bridged across one)
    detail: np.ndarray  # (frames,) each frame's fine-scale contrast (FrameResult.detail)
    measured: np.ndarray  # (frames,) how many targets each frame measured

    def __len__(self) -> int:
        return len(self.decided)


def decide(
    frames: FrameStore[FrameResult], config: FilterConfig | TrackerConfig, progress: Progress | None = None
) -> OfflinePlan:
    """The backward pass over ``frames`` (the causal pass's results, in order) and, frame by frame, the
    flip and pose decided from both passes (see the module doc). ``progress(done, total)`` after each
    frame."""
    config = config.filter if isinstance(config, TrackerConfig) else config
    count = len(frames)
    timestamps = np.zeros(count, np.int64)
    blurred = np.zeros(count, bool)
    detail = np.full(count, np.nan)
    measured = np.zeros(count, np.int32)
    decided: list[_Decided | None] = [None] * count
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
            updates = _backward_step(tracks, result, end_ns - result.timestamp_ns, config)
            decided[position] = _decide_frame(result, updates)
        if progress is not None:
            progress(done, count)
    return OfflinePlan(config, timestamps, decided, blurred, detail, measured)


def _backward_step(
    tracks: dict[TargetId, TargetTrack], result: FrameResult, reversed_ns: int, config: FilterConfig
) -> dict[TargetId, TrackUpdate]:
    """One frame of the backward pass (its time ``reversed_ns``: counted back from the last frame), all
    targets' Kalman steps batched as :meth:`Tracker._filter <ar_anchor.track.tracker.Tracker._filter>` does."""
    measured = result.measurements
    camera = result.camera
    assert camera is not None, "a FrameResult from Tracker.process carries its camera"
    unit = unit_covariances_of(list(measured.values()), camera)
    batch = KalmanBatch()
    steps = {}
    for name in TargetId.ordered(set(measured) | set(tracks)):
        solved = measured.get(name)
        track = tracks.get(name)
        if track is None:
            assert solved is not None
            track = tracks[name] = TargetTrack(config, solved.points_in_target)
        steps[name] = track.update_steps(
            solved, reversed_ns, camera, blurred=result.blurred, unit_covariances=unit, batch=batch
        )
    updates = run_filter_steps(steps, batch)
    for name, update in list(updates.items()):
        if update is None:
            if not tracks[name].alive:
                del tracks[name]
            del updates[name]
    return updates


def _chosen(hypotheses: Sequence[Pose], pose: Pose) -> int:
    """The index of the solution ``pose`` stands on (the nearest in orientation)."""
    if len(hypotheses) == 1:
        return 0
    angles = [angle_between_deg(h.rotation, pose.rotation) for h in hypotheses]
    return int(np.argmin(angles))


def _branch_of(branch_poses: Sequence[Pose | None], pose: Pose) -> int:
    """The index of the filter branch whose measurement is ``pose``'s solution (-1: none)."""
    angles = [angle_between_deg(p.rotation, pose.rotation) if p is not None else math.inf for p in branch_poses]
    return int(np.argmin(angles)) if angles and min(angles) < math.inf else -1


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


def _decide_frame(result: FrameResult, backward: dict[TargetId, TrackUpdate]) -> _Decided:
    """The flip and the pose of every target measured in ``result``, from the forward pass (``result``'s
    own targets) and the backward pass's ``backward`` updates (see the module doc)."""
    names, states, poses, choices, causal = [], [], [], [], []
    for name in TargetId.ordered(result.measurements):
        hypotheses = [h.pose for h in result.measurements[name].hypotheses]
        forward = result.targets.get(name)
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
        state, choice = _flip(result.blurred, forward, f_choice, back, b_choice)
        if state is TrackState.TRACKED:  # both passes' smoothed poses on the chosen solution, weighted
            on_choice = [(p.pose, p.run_frames) for p, c in ((forward, f_choice), (back, b_choice)) if c == choice]
            pose = _mean_pose(on_choice)  # type: ignore[union-attr]
        else:  # undecided: the live filter's output as it is (halfway between the solutions when it holds both)
            pose = forward.pose if forward is not None else back.pose if back is not None else hypotheses[choice]
        names.append(name)
        states.append(state)
        poses.append(np.concatenate([pose.rvec, pose.tvec]))
        choices.append(choice)
        causal.append(f_choice)
    array = np.array(poses, np.float64).reshape(-1, 6)
    return _Decided(tuple(names), tuple(states), array, tuple(choices), tuple(causal))


def _flip(
    blurred: bool, forward: TargetResult | None, f_choice: int, back: TrackUpdate | None, b_choice: int
) -> tuple[TrackState, int]:
    """A measured frame's state and solution from the two passes (measured there, else None):

    - a pass that vouches (``tracked``) decides, the forward one first; both vouching for different
      solutions leaves the frame ``ambiguous``;
    - the backward pass vouches only where the forward one doubts nothing but which solution is right
      (:data:`~.filtering.track.EVIDENCE_DOUBTS`: undecided yet, a close call...), not this frame's pose
      itself (blur, an outlier, a spike, a glide);
    - neither vouching, both committed to the same solution with only such doubts: the evidence before
      and after the frame agree, the frame's own close call cannot overturn them: ``tracked``;
    - else ``ambiguous`` on the forward pass's solution (the live filter's)."""
    f_sure = forward is not None and forward.state is TrackState.TRACKED
    b_sure = back is not None and back.state is TrackState.TRACKED
    if f_sure:
        return (TrackState.TRACKED if not b_sure or b_choice == f_choice else TrackState.AMBIGUOUS), f_choice
    choice = f_choice if f_choice >= 0 else max(b_choice, 0)
    pose_doubted = blurred or any(not EVIDENCE_DOUBTS.issuperset(p.doubts) for p in (forward, back) if p is not None)
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
    bridge = _Bridge(plan)
    previous: FrameResult | None = None
    for position in range(len(plan)):
        causal = frames[position]
        decided = plan.decided[position]
        if decided is None:  # a repeated frame: the last answer again
            base = previous if previous is not None else causal
            previous = dataclasses.replace(base, index=causal.index, timestamp_ns=causal.timestamp_ns, repeated=True)
            yield previous
            continue
        targets: dict[TargetId, TargetResult] = {}
        for k, name in enumerate(decided.names):
            targets[name] = bridge.measured(position, causal, decided, k)
        for name, target in bridge.gaps(position, set(decided.names)):
            targets[name] = target
        ordered = {name: targets[name] for name in TargetId.ordered(targets)}
        previous = dataclasses.replace(causal, targets=ordered, causal_targets=causal.targets)
        yield previous


# A gap frame whose fine-scale contrast fell below this share of the gap ends' is taken for a quick camera
# motion (motion blur the tracker's blur test, a ratio of scales, may miss under sensor noise): not bridged.
# (Hand-held synthetic clip with 200 deg/s turns: 0.2-0.35 in the turn's frames; a hidden marker: about 1.)
_DETAIL_DROP = 0.5
# A gap frame that measured fewer than this share of the other targets the gap's ends measured, and whose
# detail dipped below _DETAIL_DIP of theirs, lost them to the camera (mild motion blur, a jerk): not bridged
# in time. (chessboard.avi, frame 72: 2 of 17 markers found, detail 0.82 of the ends'; interpolated, its
# markers were 1.2 deg and 6 mm off.) Targets hidden together in a sharp view (a hand) are bridged.
_OTHERS_DROP = 0.5
_DETAIL_DIP = 0.9
# Two targets move together across a gap when their relative pose at its two ends differs by at most this
# turn and this share of the companion's distance (measured relative poses on chessboard.avi's rigid sheet:
# 0.24 deg, 0.6 mm RMS at about 0.3 m).
_RIGID_DEG = 1.0
_RIGID_SHARE = 0.01


class _Bridge:
    """Measured targets' offline results, and the gaps between them bridged (see :func:`offline_results`)."""

    def __init__(self, plan: OfflinePlan) -> None:
        self.plan = plan
        self.limit_ns = int(plan.config.interpolate_s * 1e9)
        self.last: dict[TargetId, tuple[int, TargetResult]] = {}  # name -> (its last measured frame's ns, result)
        self.last_position: dict[TargetId, int] = {}  # name -> its last measured frame's position
        # name -> the frame position that ends its current gap (None: none within reach), and whether the
        # motion through it is steady enough to interpolate in time
        self.following: dict[TargetId, tuple[int | None, bool]] = {}

    def measured(self, position: int, causal: FrameResult, decided: _Decided, k: int) -> TargetResult:
        name = decided.names[k]
        measurement = causal.measurements[name]
        pose = decided.pose(k)
        template = causal.targets.get(name)
        if template is None or not template.measured:
            template = _from_measurement(name, measurement, self.last.get(name))
        camera = causal.camera
        assert camera is not None
        events: tuple[TrackEvent, ...] = template.events
        if decided.causal_choices[k] >= 0 and decided.choices[k] != decided.causal_choices[k]:
            events = (
                *events,
                TrackEvent("offline", "the whole recording chose the other solution than the live filter"),
            )
        branch = _branch_of(template.branch_poses, measurement.hypotheses[decided.choices[k]].pose)
        target = dataclasses.replace(
            template,
            state=decided.states[k],
            pose=pose,
            reproj_px=reprojection_rms(pose, measurement.points_in_target, measurement.points_in_image, camera),
            branch=branch,
            events=events,
        )
        self.last[name] = (int(self.plan.timestamps_ns[position]), target)
        self.last_position[name] = position
        self.following.pop(name, None)
        return target

    def gaps(self, position: int, measured: set[TargetId]) -> Iterator[tuple[TargetId, TargetResult]]:
        """The targets not measured at ``position`` whose gap is bridged, each with its interpolated result."""
        now_ns = int(self.plan.timestamps_ns[position])
        for name in list(self.last):
            if name in measured:
                continue
            then_ns, before = self.last[name]
            if now_ns - then_ns > self.limit_ns:
                del self.last[name]
                self.following.pop(name, None)
                continue
            if name not in self.following:
                self.following[name] = self._next_measured(name, self.last_position[name], then_ns)
            after_position, steady = self.following[name]
            if after_position is None:
                continue
            after_ns = int(self.plan.timestamps_ns[after_position])
            fraction = (now_ns - then_ns) / max(after_ns - then_ns, 1)
            pose = self._via_companion(name, self.last_position[name], after_position, position, fraction)
            if pose is None and steady:
                pose = _interpolated(before.pose, self._pose(name, after_position), fraction)
            if pose is not None:
                yield name, _gap_result(before, pose)

    def _via_companion(self, name: TargetId, before: int, after: int, now: int, fraction: float) -> Pose | None:
        """``name``'s pose at ``now`` from its companions: targets ``tracked`` at ``now``, measured at both ends of the
        gap whose pose relative to ``name`` is the same at both ends (they move together: one sheet, one
        object), each with its relative pose interpolated across the gap; the mean over all companions (each
        carries its own measurement noise). None if there is none."""
        plan = self.plan
        decided_now = plan.decided[now]
        if decided_now is None:
            return None
        found: list[Pose] = []
        for k, companion in enumerate(decided_now.names):
            if decided_now.states[k] is not TrackState.TRACKED:
                continue  # (a doubtful measurement, a frame's bad pose, would carry its error over)
            ends = [plan.decided[before], plan.decided[after]]
            if any(d is None or companion not in d.names for d in ends):
                continue
            relative = [self._pose(companion, end).inverse().compose(self._pose(name, end)) for end in (before, after)]
            turn = angle_between_deg(relative[0].rotation, relative[1].rotation)
            shift = float(np.linalg.norm(relative[1].tvec - relative[0].tvec))
            scale = max(float(np.linalg.norm(self._pose(companion, before).tvec)), 1e-6)
            if turn > _RIGID_DEG or shift > _RIGID_SHARE * scale:
                continue
            between = _interpolated_plain(relative[0], relative[1], fraction)
            found.append(decided_now.pose(decided_now.names.index(companion)).compose(between))
        if not found:
            return None
        return Pose.from_matrix(mean_rotation([p.rotation for p in found]), np.mean([p.tvec for p in found], axis=0))

    def _next_measured(self, name: TargetId, position: int, then_ns: int) -> tuple[int | None, bool]:
        """The first frame after ``position`` (where ``name`` was last measured, at ``then_ns``) measuring
        it again within ``interpolate_s`` (None if none), and whether the motion through the gap is steady
        enough to interpolate in time: no motion-blurred frame between (a quick turn: the motion in the gap
        is unknown: blurred, with much less fine detail than at the gap's ends, or with most other targets
        lost too), and :meth:`_smooth_enough`."""
        plan = self.plan
        lowest_detail, fewest_others, blurred = math.inf, np.iinfo(np.int32).max, False
        for later in range(position + 1, len(plan)):
            if int(plan.timestamps_ns[later]) - then_ns > self.limit_ns:
                return None, False
            decided = plan.decided[later]
            if decided is not None and name in decided.names:
                steady = not (
                    blurred
                    # the whole view lost its fine detail: the camera jerked
                    or lowest_detail < _DETAIL_DROP * min(plan.detail[position], plan.detail[later])
                    # most of the other targets went with it, and the view lost some detail: a bad frame
                    or (
                        fewest_others < _OTHERS_DROP * (min(plan.measured[position], plan.measured[later]) - 1)
                        and lowest_detail < _DETAIL_DIP * min(plan.detail[position], plan.detail[later])
                    )
                )
                return later, steady and self._smooth_enough(name, position, later)
            blurred = blurred or bool(plan.blurred[later])
            lowest_detail = min(lowest_detail, float(plan.detail[later]))
            fewest_others = min(fewest_others, int(plan.measured[later]))
        return None, False

    def _smooth_enough(self, name: TargetId, before: int, after: int) -> bool:
        """May the gap of ``name`` between the frames ``before`` and ``after`` be bridged by interpolation?
        Only if the motion is steady: the velocity at each end (to its neighbouring measurement) is the
        velocity across the gap, within ``interpolate_max_deg`` over half the gap (what a straight
        interpolation may then miss); a motion that starts or stops in the gap (a quick turn, out and
        back) is not bridged, nor a gap with no measurement next to either end."""
        plan = self.plan
        gap_s = max((int(plan.timestamps_ns[after]) - int(plan.timestamps_ns[before])) * 1e-9, 1e-6)
        across = _velocity(self._pose(name, before), self._pose(name, after), gap_s)
        limit = math.radians(plan.config.interpolate_max_deg)
        for end, step in ((before, -1), (after, +1)):
            neighbour = self._neighbour(name, end, step)
            if neighbour is None:
                return False
            other, dt = neighbour
            first, second = (self._pose(name, other), self._pose(name, end))
            velocity = _velocity(*((first, second) if step < 0 else (second, first)), dt)
            distance = max(float(np.linalg.norm(self._pose(name, end).tvec)), 1e-6)
            turn = float(np.linalg.norm(velocity[0] - across[0]))
            shift = float(np.linalg.norm(velocity[1] - across[1])) / distance
            if (turn + shift) * gap_s / 2.0 > limit:
                return False
        return True

    def _pose(self, name: TargetId, position: int) -> Pose:
        decided = self.plan.decided[position]
        assert decided is not None
        return decided.pose(decided.names.index(name))

    def _neighbour(self, name: TargetId, position: int, step: int) -> tuple[int, float] | None:
        """The nearest frame measuring ``name`` from ``position`` in direction ``step``, within
        ``interpolate_s``, and its time from ``position`` (s); None when there is none."""
        plan = self.plan
        at_ns = int(plan.timestamps_ns[position])
        other = position + step
        while 0 <= other < len(plan) and abs(int(plan.timestamps_ns[other]) - at_ns) <= self.limit_ns:
            decided = plan.decided[other]
            if decided is not None and name in decided.names:
                return other, max(abs(int(plan.timestamps_ns[other]) - at_ns) * 1e-9, 1e-6)
            other += step
        return None


def _velocity(earlier: Pose, later: Pose, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The angular (body frame, rad/s) and linear (m/s) velocity from ``earlier`` to ``later``."""
    return so3_log(earlier.rotation.T @ later.rotation) / dt_s, (later.tvec - earlier.tvec) / dt_s


def _interpolated_plain(before: Pose, after: Pose, fraction: float) -> Pose:
    """The pose ``fraction`` of the way from ``before`` to ``after``: geodesic rotation, straight translation."""
    rotation = before.rotation @ so3_exp(fraction * so3_log(before.rotation.T @ after.rotation))
    return Pose.from_matrix(rotation, before.tvec + fraction * (after.tvec - before.tvec))


def _interpolated(before: Pose, after: Pose, fraction: float) -> Pose:
    """The pose ``fraction`` of the way from ``before`` to ``after``: the rotation along the geodesic, the
    camera centre in the target's frame (``C = -R^T t``) along the straight line between. (A hand-held
    camera mostly turns about itself: its centre then hardly moves, while ``t`` sweeps an arc that a
    straight line in ``t`` would cut: on chessboard.avi that doubled the translation error.)"""
    rotation = before.rotation @ so3_exp(fraction * so3_log(before.rotation.T @ after.rotation))
    centre_before, centre_after = before.camera_centre(), after.camera_centre()
    centre = centre_before + fraction * (centre_after - centre_before)
    return Pose.from_matrix(rotation, -rotation @ centre)


def _gap_result(before: TargetResult, pose: Pose) -> TargetResult:
    """A bridged frame's result: the last measured one's description, no measurement of its own."""
    return dataclasses.replace(
        before,
        state=TrackState.INTERPOLATED,
        pose=pose,
        raw=None,
        reproj_px=math.nan,
        ambiguity=math.nan,
        hypotheses=(),
        corners_in_image=None,
        branch_poses=(),
        branch=-1,
        evidence_px=math.nan,
        events=(),
        markers_used=(),
        outlier_ids=(),
        inliers=0,
        outlier_points_in_image=None,
    )


def _from_measurement(
    name: TargetId, measurement: MarkerPose | BoardPose, last: tuple[int, TargetResult] | None
) -> TargetResult:
    """A measured target's result when the causal pass published none for it (its track was reset)."""
    length = getattr(measurement, "length_m", math.nan)
    if last is not None:
        length = last[1].length_m
    board = isinstance(measurement, BoardPose)
    return TargetResult(
        target=name,
        state=TrackState.AMBIGUOUS,
        pose=measurement.best.pose,
        raw=measurement.best.pose,
        reproj_px=math.nan,
        ambiguity=math.nan if board else measurement.ambiguity,
        length_m=length,
        hypotheses=measurement.hypotheses,
        corners_in_image=np.asarray(measurement.corners_in_image).reshape(-1, 4, 2),
        outline_in_target=last[1].outline_in_target if last is not None else None,
        markers_used=measurement.markers_used if board else (measurement.marker_id,),
        inliers=len(measurement.points_in_target),
    )


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
