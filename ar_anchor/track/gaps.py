"""The offline replay's gaps (:mod:`ar_anchor.track.offline`): each frame's measured targets written from
the plan, and the targets unseen between two measured frames bridged (``interpolated``) where the motion
through the gap is known: through companions that move with the target, else in time where the motion
is steady and nothing says the camera jerked. Nothing is extrapolated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence

import numpy as np

from ..geometry import Pose, angle_between_deg, mean_rotation
from ..targets import TargetId, TrackState
from .filtering import TrackEvent, so3_exp, so3_log
from .plan import FrameDecision, OfflinePlan
from .pose import BoardPose, MarkerPose, reprojection_rms
from .results import FrameResult, TargetResult

__all__ = ["Bridge"]

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


def _branch_of(branch_poses: Sequence[Pose | None], pose: Pose) -> int:
    """The index of the filter branch whose measurement is ``pose``'s solution (-1: none)."""
    angles = [angle_between_deg(p.rotation, pose.rotation) if p is not None else math.inf for p in branch_poses]
    return int(np.argmin(angles)) if angles and min(angles) < math.inf else -1


class Bridge:
    """Measured targets' offline results, and the gaps between them bridged (see the module doc): one per
    offline pass over the frames, in order."""

    def __init__(self, plan: OfflinePlan) -> None:
        self.plan = plan
        self.limit_ns = int(plan.config.interpolate_s * 1e9)
        self.last: dict[TargetId, tuple[int, TargetResult]] = {}  # name -> (its last measured frame, result)
        # name -> the frame position that ends its current gap (None: none within reach), and whether the
        # motion through it is steady enough to interpolate in time
        self.following: dict[TargetId, tuple[int | None, bool]] = {}

    def measured(self, position: int, causal: FrameResult, decided: FrameDecision, k: int) -> TargetResult:
        """The ``k``-th measured target of frame ``position``: the causal result (its description, corners,
        hypotheses) with the plan's state and pose; remembered as the start of a possible gap."""
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
        self.last[name] = (position, target)
        self.following.pop(name, None)
        return target

    def gaps(self, position: int, measured: set[TargetId]) -> Iterator[tuple[TargetId, TargetResult]]:
        """The targets not measured at ``position`` whose gap is bridged, each with its interpolated result."""
        now_ns = int(self.plan.timestamps_ns[position])
        for name in list(self.last):
            if name in measured:
                continue
            then, before = self.last[name]
            then_ns = int(self.plan.timestamps_ns[then])
            if now_ns - then_ns > self.limit_ns:
                del self.last[name]
                self.following.pop(name, None)
                continue
            if name not in self.following:
                self.following[name] = self._next_measured(name, then, then_ns)
            after_position, steady = self.following[name]
            if after_position is None:
                continue
            after_ns = int(self.plan.timestamps_ns[after_position])
            fraction = (now_ns - then_ns) / max(after_ns - then_ns, 1)
            pose = self._via_companion(name, then, after_position, position, fraction)
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
                if decided.segment_starts[decided.names.index(name)]:
                    return None, False  # a new track segment starts there (a cut, a jump): nothing bridges to it
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
