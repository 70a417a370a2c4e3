"""One target's track: the branches, the evidence and the smoothers put together, frame by frame, into
the pose to publish and its state (see the package doc)."""

from __future__ import annotations

import collections
import math
from collections.abc import Generator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...camera import CameraModel
from ...config import FilterConfig
from ...geometry import Pose, angle_between_deg, vector_norm
from ...targets import TrackState
from ..pose import BoardPose, MarkerPose, PoseHypothesis
from .branches import BranchPair
from .evidence import FlipEvidence, TrackEvent, raw_pick
from .linear import run_alone
from .noise import CornerNoise
from .smoothing import KalmanBatch, so3_exp, so3_log

__all__ = ["EVIDENCE_DOUBTS", "SEGMENT_STARTS", "TargetTrack", "TrackUpdate"]


@dataclass(frozen=True)
class TrackUpdate:
    """The track's answer for one frame."""

    state: TrackState
    pose: Pose
    branch: int  # the output branch (0 or 1)
    committed: bool
    evidence: float  # confidence bound of the window's mean error difference, in px (+: branch 0)
    hypotheses: tuple[Pose | None, Pose | None]  # this frame's measurement on each branch
    events: tuple[TrackEvent, ...] = ()
    run_frames: int = 0  # frames measured since the smoothers last (re)started (how much they have averaged)
    doubts: tuple[str, ...] = ()  # a measured frame's reasons not to be tracked (TargetTrack._doubts)


# Doubts about which solution is right (the evidence up to the frame, the frame's own lower-error pick), not
# about the frame's pose itself: evidence from later frames (the offline replay) may settle them.
EVIDENCE_DOUBTS = frozenset(
    {"undecided", "decided_elsewhere", "evidence_against", "close_call", "unconfirmed", "raw_pick_elsewhere"}
)

# The events of a frame that starts a new track segment: nothing of the frames before it is carried on (the
# offline replay's backward pass does not carry its evidence across either, nor are gaps bridged across).
SEGMENT_STARTS = frozenset({"start", "jump", "refit"})


class TargetTrack:
    """The filter state of one target (see the package doc)."""

    def __init__(self, config: FilterConfig, points_in_target: np.ndarray) -> None:
        self.config = config
        self.noise = CornerNoise(config, points_in_target)
        self.evidence = FlipEvidence(config, self.noise)
        self.branches: BranchPair | None = None  # None: no track
        self.output_branch = 0
        self.last_ns: int | None = None  # the last frame seen (measured or not)
        self._period_s: float | None = None  # the frame interval (the shortest recent one, smoothed)
        self.measured_ns: int | None = None  # the last frame measured
        self.frames = 0
        self.run_frames = 0  # measured frames since the branches last (re)started
        self._separation_deg = math.inf  # this frame's angle between its two solutions
        self._held_spike = False  # the last frame's output jump was held back (see _spike)
        self._was_tracked = False  # the last measured frame's state was tracked
        self._output: Pose | None = None  # the last published measured output
        self._velocity: tuple[np.ndarray, np.ndarray] = (np.zeros(3), np.zeros(3))  # omega (body), v (camera)
        self._was_still = False  # the output branch's measurements stayed put for still_s (see _Stillness)
        self._stillness = _Stillness(config)
        self._glide = np.zeros(3)  # body-frame offset still to glide off the published orientation (rad)
        self._halfway = False  # the last measured output was halfway between the two solutions

    @property
    def alive(self) -> bool:
        return self.branches is not None

    @property
    def committed(self) -> int | None:
        """The branch the evidence committed to (None: undecided)."""
        return self.evidence.committed

    # ------------------------------------------------------------------ per frame
    def update(
        self, measurement: MarkerPose | BoardPose | None, timestamp_ns: int, camera: CameraModel, **options: Any
    ) -> TrackUpdate | None:
        """Advance to ``timestamp_ns`` with this frame's measurement (None: not seen): :meth:`update_steps`
        (``options``: its ``blurred`` and ``unit_covariances``) run on its own, its Kalman steps taken at once."""
        if options.get("batch") is not None:
            raise ValueError("TargetTrack.update takes its Kalman steps itself: give a batch to update_steps")
        return run_alone(self.update_steps(measurement, timestamp_ns, camera, **options))

    def update_steps(
        self,
        measurement: MarkerPose | BoardPose | None,
        timestamp_ns: int,
        camera: CameraModel,
        *,
        blurred: bool = False,
        unit_covariances: Mapping[int, tuple[Pose, np.ndarray]] | None = None,
        batch: KalmanBatch | None = None,
    ) -> Generator[None, None, TrackUpdate | None]:
        """Advance to ``timestamp_ns`` with this frame's measurement (None: not seen). ``blurred``: the
        whole frame is much less sharp than usual (the camera moved fast): a measurement in it is not
        vouched for, and a target lost in it is not predicted (its motion is unknown).
        ``unit_covariances``: this frame's solutions' covariances at one pixel of noise, batched over all
        targets by the caller (:func:`~.noise.unit_covariances_of`); computed here for any pose not in it.

        In steps, for a caller that takes the Kalman steps of all its tracks at once: the smoothers' and the
        tilt tracker's steps are queued in ``batch`` (None: taken at once), and the generator pauses (yields)
        after queueing each kind, for the caller to :meth:`~.smoothing.KalmanBatch.run` them.

        Returns (as the generator's value) None when there is nothing to publish: no track, a gap too long
        to predict through (the track stays :attr:`alive`, keeping its flip memory, until ``memory_s``), or
        a reset.
        """
        timestamp_ns = self._tick(timestamp_ns)
        events: list[TrackEvent] = []
        self.noise.new_frame(unit_covariances)
        if measurement is None:
            return self._coast(timestamp_ns, events, blurred)
        assigned, restart_frame, gap_s = yield from self._measure(measurement, timestamp_ns, camera, events, batch)
        assert self.branches is not None
        if gap_s is not None:  # (a new track's branches start from this measurement)
            yield from self.branches.update_steps(assigned, measurement, camera, gap_s, restart_frame, batch)
        doubtful = self.branches.doubtful
        decided = self.evidence.judge(assigned, timestamp_ns, doubtful, self.frames, events)
        # which solution is which is unknown this frame, by motion or by tilt: the frame's own pick is shown,
        # where the frame leans (where it does not either, the committed branch goes on)
        unsure = (doubtful or self.branches.unclear) and self.evidence.leans(assigned) is not None
        snaps = self._separation_deg > 3.0 * self.config.glide_step_deg  # (a move too far to glide: see _glided)
        target = self.evidence.choose(assigned, decided, unsure, timestamp_ns, self.output_branch, snaps)
        moved_branch = self._move_output(target, events)
        halfway = self._halfway
        pose, covariance = self._measured_output(assigned, camera)
        changed = moved_branch or halfway != self._halfway
        pose = self._glided(pose, changed and not restart_frame, restart_frame, events)
        spike = not changed and not restart_frame and self._spike(pose)
        if spike:
            events.append(TrackEvent("spike", "orientation jump in place held for one frame"))
            assert self._output is not None
            pose = Pose.from_matrix(self._output.rotation, pose.tvec)
        doubts = self._doubts(assigned, decided, covariance, spike, blurred)
        if self._glide.any():
            doubts.append("glide")
        vouched = not doubts
        hypotheses = (
            assigned[0].pose if assigned[0] is not None else None,
            assigned[1].pose if assigned[1] is not None else None,
        )
        self._was_tracked = vouched
        state = TrackState.TRACKED if vouched else TrackState.AMBIGUOUS
        update = self._result(state, pose, hypotheses, events, tuple(doubts))
        self._output = pose
        return update

    def _tick(self, timestamp_ns: int) -> int:
        """This frame's time: a repeated or backward timestamp is 1 ns after the last (no time has passed);
        a later one updates the frame interval (a slow frame rate is not a gap)."""
        if self.last_ns is not None and timestamp_ns <= self.last_ns:
            timestamp_ns = self.last_ns + 1
        elif self.last_ns is not None:
            step = (timestamp_ns - self.last_ns) * 1e-9
            self._period_s = step if self._period_s is None else min(step, 0.8 * self._period_s + 0.2 * step)
        self.last_ns = timestamp_ns
        return timestamp_ns

    def _measure(
        self,
        measurement: MarkerPose | BoardPose,
        timestamp_ns: int,
        camera: CameraModel,
        events: list[TrackEvent],
        batch: KalmanBatch | None,
    ) -> Generator[None, None, tuple[list[PoseHypothesis | None], bool, float | None]]:
        """Take this frame's measurement: its noise, and its solutions assigned to the branches (a new
        track starts from them; the branches' smoothers take them next: ``BranchPair.update_steps``).
        Returns the assignment, whether the branches (re)started (a new track, or one seen again after a
        gap), and the time since the last measurement (None: the track started now)."""
        self.noise.observe(measurement)
        gap_s = math.inf if self.measured_ns is None else (timestamp_ns - self.measured_ns) * 1e-9
        self.measured_ns = timestamp_ns
        self.frames += 1
        hypotheses = measurement.hypotheses  # how far apart the two solutions are, asked for several times
        self._separation_deg = (
            angle_between_deg(hypotheses[0].pose.rotation, hypotheses[1].pose.rotation)
            if len(hypotheses) == 2
            else math.inf
        )
        jump = None if self.branches is None else self._jump(measurement, gap_s)
        if self.branches is None or jump is not None:
            if jump is not None:  # a cut, an unrelated still, a jump no motion explains: a new track segment
                events.append(TrackEvent("jump", jump))
                self._forget_output()
            self.run_frames = 1
            return self._start(measurement, camera, events), True, None
        restart = self._is_gap(gap_s)
        self.run_frames = 1 if restart else self.run_frames + 1
        if restart:
            events.append(TrackEvent("reacquired", f"seen again after {gap_s:.2f} s"))
            self.evidence.reacquired()
        branches = self.branches
        assigned = yield from branches.associate_steps(measurement, camera, gap_s, restart, self._separation_deg, batch)
        # Unclear for long while the solutions are far apart: which is which may have been lost. (While they
        # are within flip_angle_deg of each other either one is close enough, so unclarity costs nothing.)
        if branches.apart and branches.blind_s > self.config.crossing_blind_s and self.evidence.committed is not None:
            self.evidence.uncommit(branches.blind_s, events)
        return assigned, restart, gap_s

    def _jump(self, measurement: MarkerPose | BoardPose, gap_s: float) -> str | None:
        """Does this frame continue neither branch of the track (a cut, an unrelated still, a jump larger
        than the motion model allows)? Then it says why, and the track starts a new segment from this frame:
        no flip evidence, smoothing or held pose is carried across. Neither of the frame's solutions is
        within ``reset_angle_deg`` plus ``max_angular_rate_deg_s`` over the time since the last measurement
        (at most ``restart_gap_s`` of it: beyond that the motion model knows nothing, and a target seen again
        must look like it did) of either branch's last measured orientation, or the position moved more than
        :data:`_JUMP_SHARE` of the distance plus :data:`_JUMP_SPEED_M_S` over that time."""
        assert self.branches is not None
        cfg = self.config
        span = min(gap_s, cfg.restart_gap_s) if math.isfinite(gap_s) else cfg.restart_gap_s
        lasts = [branch.last for branch in self.branches.branches if branch is not None]
        solutions = [h.pose for h in measurement.hypotheses]
        turn = min(angle_between_deg(last, pose.rotation) for last in lasts for pose in solutions)
        allowed_deg = cfg.reset_angle_deg + cfg.max_angular_rate_deg_s * span
        if turn > allowed_deg:
            return (
                f"turned {turn:.0f} deg from both solutions of the track in {gap_s:.3g} s (the motion model allows "
                f"{allowed_deg:.0f}): a cut or a jump, a new track segment"
            )
        before = self.branches.translation_filter.translation
        shift = min(vector_norm(pose.tvec - before) for pose in solutions)
        allowed_m = _JUMP_SHARE * vector_norm(before) + _JUMP_SPEED_M_S * span
        if shift > allowed_m:
            return (
                f"moved {shift * 100:.1f} cm in {gap_s:.3g} s (the motion model allows {allowed_m * 100:.1f}): "
                "a cut or a jump, a new track segment"
            )
        return None

    def _forget_output(self) -> None:
        """Forget what the last segment published and how it moved (a new segment starts as a new track)."""
        self._held_spike = self._was_tracked = self._was_still = self._halfway = False
        self._output = None
        self._velocity = (np.zeros(3), np.zeros(3))
        self._stillness = _Stillness(self.config)
        self._glide = np.zeros(3)

    def restart_from(
        self, measurement: MarkerPose | BoardPose, timestamp_ns: int, camera: CameraModel, *, blurred: bool = False
    ) -> tuple[TrackEvent, ...]:
        """Start a new segment from this frame, whose published output is its own best solution (the output
        did not fit its frame: :mod:`ar_anchor.track.fit`): nothing of the track's past is carried on. Returns
        the events (a ``start``)."""
        self.branches = None
        self.measured_ns = None
        self._forget_output()
        update = self.update(measurement, timestamp_ns, camera, blurred=blurred)
        self._output = measurement.best.pose
        return update.events if update is not None else ()

    def _is_gap(self, gap_s: float) -> bool:
        """Were frames missed for longer than ``restart_gap_s``? (At 5 fps every frame is 0.2 s after the
        last one: that is the frame rate, not a gap; a gap is more than one and a half frame intervals.)"""
        period = self._period_s or 0.0
        return gap_s > self.config.restart_gap_s and gap_s > 1.5 * period

    def _start(
        self, measurement: MarkerPose | BoardPose, camera: CameraModel, events: list[TrackEvent]
    ) -> list[PoseHypothesis | None]:
        hypotheses = measurement.hypotheses
        self.branches = BranchPair(self.config, hypotheses, self.noise, camera)
        self.output_branch = 0
        self.evidence.restart()
        events.append(TrackEvent("start", "track started"))
        return [hypotheses[0], hypotheses[1] if len(hypotheses) > 1 else None]

    def _move_output(self, target: int, events: list[TrackEvent]) -> bool:
        """Output branch ``target`` from this frame on, if it has started: has the output moved?"""
        if target == self.output_branch or self.branches is None or not self.branches.has(target):
            return False
        events.append(
            TrackEvent(
                "branch",
                f"output moves to branch {target}" + ("" if self.evidence.committed is not None else " (best guess)"),
            )
        )
        self.output_branch = target
        return True

    def _doubts(
        self,
        assigned: list[PoseHypothesis | None],
        decided: int | None,
        covariance: np.ndarray | None,
        spike: bool,
        blurred: bool,
    ) -> list[str]:
        """Why this measured frame's output is not ``tracked`` (see the package doc): the names of the
        tests it fails, none when it is vouched for. (:data:`EVIDENCE_DOUBTS` are about which solution the
        evidence up to this frame favours; the others about this frame's pose itself.)"""
        assert self.branches is not None
        evidence, output = self.evidence, self.output_branch
        tests = (
            ("spike", spike),
            ("undecided", evidence.committed is None),
            ("committed_elsewhere", evidence.committed is not None and evidence.committed != output),
            ("not_measured_on_output", assigned[output] is None),
            ("decided_elsewhere", decided not in (None, output)),
            ("evidence_against", evidence.against != 0),
            ("doubtful", self.branches.doubtful),
            ("unclear", self.branches.unclear and decided is None),
            ("close_call", evidence.close_call(assigned, self._separation_deg)),
            ("unconfirmed", evidence.unconfirmed),
            ("outlier", self.noise.outlier),
            ("blurred", blurred),
            ("raw_pick_elsewhere", raw_pick(assigned) not in (None, output)),
            ("too_uncertain", self._too_uncertain(covariance)),
        )
        return [name for name, failed in tests if failed]

    def _measured_output(
        self, assigned: list[PoseHypothesis | None], camera: CameraModel
    ) -> tuple[Pose, np.ndarray | None]:
        """The output pose of a measured frame: the output branch's smoothed pose, held within
        ``output_sigmas`` standard deviations (the measurement's own covariance) of this frame's
        measurement on that branch, so smoothing can lower jitter but never lag behind real motion
        by more than the noise; a moving target whose last frame was not ``tracked`` shows the measurement
        itself (on a quick turn the smoother's half-sigma lag was enough to push a frame past a flip's
        worth where the measurement stayed within it). Returns the pose and the measurement's rotation
        covariance."""
        assert self.branches is not None
        smoother = self.branches.smoother(self.output_branch)
        rotation, translation = smoother.rotation, self.branches.translation_filter.translation
        hypothesis = assigned[self.output_branch]
        covariance = None
        if hypothesis is not None:
            measured = hypothesis.pose
            cov_rot, cov_t = self.noise.covariance(measured, camera)
            # a still target is averaged over many frames; a moving one follows its measurements closely
            assert self.measured_ns is not None
            still = self._was_still = self._stillness.observe(
                self.output_branch, self.measured_ns, measured, cov_rot, cov_t
            )
            k = self.config.output_sigmas if still and not self.noise.outlier else self.config.output_sigmas_moving
            if not still and not self._was_tracked:
                k = 0.0  # moving and not vouched for: the measurement itself (the smoother's lag buys nothing)
            error = so3_log(measured.rotation.T @ rotation)  # body-frame error, as the covariance's
            rotation = measured.rotation @ so3_exp(_within(error, cov_rot, k))
            translation = measured.tvec + _within(translation - measured.tvec, cov_t, k)
            covariance = cov_rot
            other = self._undecided_other(assigned)
            self._halfway = other is not None
            if other is not None:
                rotation = _halfway(rotation, self._held(other, assigned, camera, k))
        omega = smoother.omega
        velocity = self.branches.translation_filter.velocity
        self._velocity = (omega, velocity)
        return Pose.from_matrix(rotation, translation), covariance

    def _glided(self, pose: Pose, changed: bool, restart: bool, events: list[TrackEvent]) -> Pose:
        """The output shown gliding from the last one when it changed branch (or went into or out of
        halfway): the orientation moves at most ``glide_step_deg`` per frame towards the new one, when
        that takes at most three frames (a farther jump is shown at once: a glide could not hide it);
        the glide rides on the new branch, so real motion passes through. Frames with glide left are
        not ``tracked``."""
        step = math.radians(self.config.glide_step_deg)
        if restart or self._output is None or step <= 0.0:
            self._glide = np.zeros(3)
            return pose
        if changed:
            self._glide = so3_log(pose.rotation.T @ self._output.rotation)
            if vector_norm(self._glide) > 3.0 * step:
                self._glide = np.zeros(3)
            elif vector_norm(self._glide) > step:  # more than one frame's step: a glide to show
                events.append(TrackEvent("glide", f"{math.degrees(vector_norm(self._glide)):.1f} deg glided off"))
        size = vector_norm(self._glide)
        self._glide = self._glide * (max(size - step, 0.0) / size) if size > 0.0 else self._glide
        if not self._glide.any():
            return pose
        return Pose.from_matrix(pose.rotation @ so3_exp(self._glide), pose.tvec)

    def _spike(self, pose: Pose) -> bool:
        """Is this output an orientation jump in place: more than ``flip_angle_deg`` from the last
        frame's output on the same branch while the position moved less than ``spike_translation_m``
        (no hand turns a marker that fast about its own centre: a measurement that jumped, from blur or
        a bad corner)? Such an output is held back for one frame, never two: if the next frame keeps
        the new orientation, it is taken."""
        previous, held = self._output, self._held_spike
        self._held_spike = False
        if previous is None or held:
            return False
        jumped = angle_between_deg(previous.rotation, pose.rotation) > self.config.flip_angle_deg
        in_place = vector_norm(previous.tvec - pose.tvec) < self.config.spike_translation_m
        self._held_spike = jumped and in_place
        return self._held_spike

    def _undecided_other(self, assigned: list[PoseHypothesis | None]) -> int | None:
        """The other branch, when this uncommitted frame's output should be halfway between the two:
        nothing in this frame or the recent evidence chooses (no decisive or leaning frame), and the two
        solutions are within twice ``flip_angle_deg`` of each other, so halfway is within a flip's
        worth of the truth whichever is right (a fronto-parallel marker: the steady, unbiased answer)."""
        if self.evidence.committed is not None or None in assigned or self.branches is None:
            return None
        if not self.branches.complete or self.evidence.leaning:
            return None
        if self._separation_deg > 2.0 * self.config.flip_angle_deg:
            return None
        return 1 - self.output_branch

    def _held(self, index: int, assigned: list[PoseHypothesis | None], camera: CameraModel, k: float) -> np.ndarray:
        """Branch ``index``'s smoothed rotation held within ``k`` sigma of its measurement this frame."""
        assert self.branches is not None
        smoother, hypothesis = self.branches.smoother(index), assigned[index]
        assert hypothesis is not None
        cov_rot, _ = self.noise.covariance(hypothesis.pose, camera)
        error = so3_log(hypothesis.pose.rotation.T @ smoother.rotation)
        return hypothesis.pose.rotation @ so3_exp(_within(error, cov_rot, k))

    def _coast(self, timestamp_ns: int, events: list[TrackEvent], blurred: bool = False) -> TrackUpdate | None:
        """A frame without a measurement: a short prediction (velocity decaying with
        ``predict_damping_s``) for up to ``predict_s``; then nothing is published, but the track keeps
        its branches and evidence until ``memory_s``, so a target that returns is not a new track."""
        if self.branches is None or self.measured_ns is None:
            return None
        cfg = self.config
        gap_s = (timestamp_ns - self.measured_ns) * 1e-9
        if gap_s > cfg.memory_s:
            self.branches = None
            events.append(TrackEvent("reset", f"lost for more than {cfg.memory_s:g} s: reset"))
            return None
        if gap_s > cfg.predict_s or self._output is None or blurred or not self._was_tracked:
            return None  # (an undecided target is not predicted: which pose to continue is not known)
        tau = cfg.predict_damping_s
        reach = tau * (1.0 - math.exp(-gap_s / tau))  # integral of exp(-t / tau) over the gap
        omega, velocity = self._velocity
        settled = self._was_still and self._stillness.settled_deg <= cfg.predict_max_deg
        if not settled and math.degrees(self._prediction_doubt(omega, gap_s, reach)) > cfg.predict_max_deg:
            return None  # not trustworthy: publish nothing rather than a guess
        rotation = self._output.rotation @ so3_exp(omega * reach)
        pose = Pose.from_matrix(rotation, self._output.tvec + velocity * reach)
        return self._result(TrackState.PREDICTED, pose, (None, None), events)

    def _prediction_doubt(self, omega: np.ndarray, gap_s: float, reach_s: float) -> float:
        """How much more a prediction over ``gap_s`` may be off than the last measured output (radians):
        the turn the damping leaves out if the motion went on or, if larger, the turn plus the shift (as an
        angle seen from the camera) at the rate last measured."""
        return max(vector_norm(omega) * (gap_s - reach_s), self._stillness.rate * gap_s)

    def _too_uncertain(self, covariance: np.ndarray | None) -> bool:
        """3 sigma of the measured orientation beyond flip_angle_deg: even the right branch may be off
        by a flip's worth."""
        if covariance is None:
            return True
        sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(covariance))), 0.0))
        return math.degrees(3.0 * sigma) > self.config.flip_angle_deg

    def _result(
        self,
        state: TrackState,
        pose: Pose,
        hypotheses: tuple[Pose | None, Pose | None],
        events: list[TrackEvent],
        doubts: tuple[str, ...] = (),
    ) -> TrackUpdate:
        return TrackUpdate(
            state,
            pose,
            self.output_branch,
            self.evidence.committed is not None,
            self.evidence.bound(0.0, 0.0),
            hypotheses,
            tuple(events),
            self.run_frames,
            doubts,
        )


# A frame whose position moved more than this share of the distance, plus this speed over the time since the
# last measurement (at most restart_gap_s of it), from the track's: a jump (a hand-held webcam at 30 fps moves
# a marker at 0.35 m by about 3 cm a frame at 1 m/s).
_JUMP_SHARE = 0.3
_JUMP_SPEED_M_S = 3.0


class _Stillness:
    """Has the output branch's measurement stayed put, within its noise, for ``still_s``? And how fast
    has it moved lately (what a prediction may miss)?"""

    _STILL_CHI2 = 16.0  # still: each difference within this squared Mahalanobis distance (chi2, 3 dof: 99.9 %)

    def __init__(self, config: FilterConfig) -> None:
        self.config = config
        self.settled_deg = math.inf  # how much the measurement turned over still_s (see observe)
        self.rate = math.inf  # last measured rate of change (turn + shift / distance), rad/s
        self._rates: collections.deque[tuple[int, float]] = collections.deque()  # (ns, rad/s) over still_s
        self._history: collections.deque[tuple[int, int, Pose]] = collections.deque()  # (branch, ns, measured)

    def observe(self, branch: int, measured_ns: int, measured: Pose, cov_rot: np.ndarray, cov_t: np.ndarray) -> bool:
        """Has branch ``branch``'s measurement stayed put, within its noise, for ``still_s``, up to this
        one (measured at ``measured_ns``, with these covariances)? (The difference of two measurements
        has twice a measurement's covariance; ``_STILL_CHI2``.) A change of branch starts over."""
        history = self._history
        if history and history[0][0] != branch:
            history.clear()
        if history:  # how fast it moved since the last measurement (what a prediction may miss), rad/s
            _, last_ns, last = history[-1]
            dt = max((measured_ns - last_ns) * 1e-9, 1e-3)
            turn = vector_norm(so3_log(last.rotation.T @ measured.rotation))
            shift = vector_norm(measured.tvec - last.tvec) / max(vector_norm(measured.tvec), 1e-6)
            self._rates.append((measured_ns, (turn + shift) / dt))
        horizon = measured_ns - int(self.config.still_s * 1e9)
        while self._rates and self._rates[0][0] < horizon:
            self._rates.popleft()
        # the fastest over the last still_s: one slow step (a repeated frame) says little
        self.rate = max((rate for _, rate in self._rates), default=math.inf)
        history.append((branch, measured_ns, measured))
        while len(history) > 1 and history[1][1] <= horizon:
            history.popleft()
        _, then_ns, then = history[0]
        if then_ns > horizon:
            return False  # not seen long enough to tell
        turned = so3_log(then.rotation.T @ measured.rotation)
        moved = measured.tvec - then.tvec
        shift = vector_norm(moved) / max(vector_norm(measured.tvec), 1e-6)
        self.settled_deg = math.degrees(vector_norm(turned) + shift)  # turn + shift seen from the camera
        return bool(
            turned @ np.linalg.solve(2.0 * cov_rot, turned) < self._STILL_CHI2
            and moved @ np.linalg.solve(2.0 * cov_t, moved) < self._STILL_CHI2
        )


def _halfway(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation halfway between ``a`` and ``b`` on the geodesic."""
    return a @ so3_exp(0.5 * so3_log(a.T @ b))


def _within(error: np.ndarray, covariance: np.ndarray, sigmas: float) -> np.ndarray:
    """``error`` shrunk (along itself) to at most ``sigmas`` Mahalanobis distance under ``covariance``."""
    try:
        distance = math.sqrt(max(float(error @ np.linalg.solve(covariance, error)), 0.0))
    except np.linalg.LinAlgError:
        return np.zeros_like(error)
    if distance <= sigmas or distance == 0.0:
        return error
    return error * (sigmas / distance)
