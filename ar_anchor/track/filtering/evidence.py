"""Which branch is right: the evidence for branch 0 against branch 1 over ``evidence_window_s``, the
commitment it makes, the frames that contradict it, and an undecided target's best guess (see the package
doc)."""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...config import FilterConfig
from ...geometry import angle_between_deg
from ..pose import PoseHypothesis
from .noise import CornerNoise

__all__ = [
    "AGREE_DEG",
    "FlipEvidence",
    "TrackEvent",
    "decided_alone",
    "decisive",
    "margin_scale",
    "raw_pick",
    "solutions_agree",
]


@dataclass(frozen=True)
class TrackEvent:
    """Something a user may want to see on the timeline: a start, commit, switch, uncommit, re-acquisition, reset."""

    kind: str
    message: str


def margin_scale(points: int) -> float:
    """The decision margins are set for one marker's four corners. A board's error difference is an RMS
    over more points, whose detector biases (independent from marker to marker) partly cancel: its
    margin shrinks with the square root of the number of points (four per marker)."""
    return min(1.0, math.sqrt(4.0 / max(points, 4)))


def decisive(better_px: float, worse_px: float, config: FilterConfig, sigma_px: float, scale: float = 1.0) -> bool:
    """Does one frame alone decide between two solutions with these RMS reprojection errors: the worse
    one ``decisive_ratio`` times the better's and worse by ``decisive_sigmas`` corner-noise standard
    deviations ``sigma_px``, and at least by ``decisive_px``? ``scale`` (:func:`margin_scale`, 1 for one
    marker's four corners) shrinks every margin of a board with the square root of its points: the floor
    and the ratio's excess over 1. An RMS over many points measures the difference that finely, so a
    49-corner ChArUco board's flipped solution is decisively worse at 1.6 times the error and 0.29 of
    the floor, where a lone marker's must be 3 times worse."""
    floor = max(config.decisive_px, config.decisive_sigmas * sigma_px) * scale
    ratio = 1.0 + (config.decisive_ratio - 1.0) * scale
    return worse_px - better_px >= floor and worse_px >= ratio * better_px


AGREE_DEG = 2.0  # a board's two solutions this close are one pose as far as the flip goes (either is right)


def solutions_agree(hypotheses: Sequence[PoseHypothesis], points: int) -> bool:
    """Are a board's (more than four points) two solutions within :data:`AGREE_DEG` of each other? A
    board seen nearly face-on can keep a second solution a degree or two from the first: not a flip to
    resolve, since either pose is right. (A lone marker's are not judged so: its doubt is settled by
    evidence over time, the filter's ``close_call``.)"""
    if points <= 4 or len(hypotheses) < 2:
        return False
    return angle_between_deg(hypotheses[0].pose.rotation, hypotheses[1].pose.rotation) <= AGREE_DEG


def decided_alone(hypotheses: Sequence[PoseHypothesis], config: FilterConfig, points: int = 4) -> bool:
    r"""Does this frame alone decide the planar flip between its solutions (lower error first): one valid
    solution, or the other :func:`decisive`\ ly worse, with the frame's own noise floor (the better error
    times sqrt 2, at least ``corner_noise_px``) and the margins of ``points`` points (:func:`margin_scale`)?
    A board (more than four points) is decided by its own geometry: also when its two solutions agree
    (:func:`solutions_agree`)."""
    if len(hypotheses) < 2:
        return len(hypotheses) == 1
    if solutions_agree(hypotheses, points):
        return True
    better, worse = hypotheses[0].reproj_px, hypotheses[1].reproj_px
    sigma = max(config.corner_noise_px, better * math.sqrt(2.0))
    return decisive(better, worse, config, sigma, margin_scale(points))


def raw_pick(assigned: list[PoseHypothesis | None]) -> int | None:
    """The branch of this frame's lower-error solution (None with fewer than two)."""
    if assigned[0] is None or assigned[1] is None:
        return None
    return 0 if assigned[0].reproj_px <= assigned[1].reproj_px else 1


class FlipEvidence:
    """One target's evidence, per frame the difference of the two branches' RMS reprojection errors
    (+: branch 0 is better), and what it decides: the committed branch (None: undecided), moved on
    sustained evidence or on a run of contradicting frames."""

    _RECENT_S = 0.3  # the best guess of an undecided target leans on this much recent evidence
    _GUESS_Z = 2.0  # ... else on the whole window's (when a move would snap: its mean this many standard errors from 0)

    def __init__(self, config: FilterConfig, noise: CornerNoise) -> None:
        self.config = config
        self.noise = noise  # (the track's: the margins scale with its points, a decisive frame with its noise)
        self.values: collections.deque[tuple[int, float]] = collections.deque()  # (timestamp_ns, px)
        self.committed: int | None = None
        self.against = 0.0  # contradicting frames in a row (a decisive one counts 1, a leaning one 1/3)
        self.run = 0  # ... and how many frames that run has: from its second, the output is the frame's pick
        self.unconfirmed = False  # re-acquired after a gap, no frame has confirmed the commitment yet
        self.leaning = False  # an undecided target's frame or recent evidence chose its output branch

    def restart(self) -> None:
        """A new track: undecided, no evidence (whether a re-acquisition is :attr:`unconfirmed` is kept)."""
        self.committed = None
        self.values.clear()
        self.against = 0
        self.run = 0

    def reacquired(self) -> None:
        """Seen again after a gap: which solution is which was carried over it, so the frame's own pick is
        shown, and nothing vouched for, until a frame leans the committed way."""
        self.unconfirmed = True

    def uncommit(self, blind_s: float, events: list[TrackEvent]) -> None:
        """The two solutions stayed indistinguishable for ``blind_s``: which is which may have been lost."""
        events.append(
            TrackEvent(
                "uncommit",
                f"the two solutions stayed indistinguishable for {blind_s:.2f} s: which is which is undecided again",
            )
        )
        self.committed = None
        self.values.clear()
        self.against = 0
        self.run = 0

    def judge(
        self,
        assigned: list[PoseHypothesis | None],
        timestamp_ns: int,
        doubtful: bool,
        frames: int,
        events: list[TrackEvent],
    ) -> int | None:
        """Take this frame (its evidence unless its assignment is ``doubtful``; ``frames``: the track's
        measured frames so far), commit or switch, and count it for or against the commitment. Returns the
        branch this frame alone vouches for (see :meth:`_verdict`), if any."""
        if not doubtful:
            self._add(assigned, timestamp_ns)
        decided, lean = self._verdict(assigned)
        self._decide(events, frames)
        if self.committed is None and decided is not None and not doubtful and self._board:
            self._commit_alone(decided, assigned, frames, events)
        if self.committed is not None:
            self._weigh(decided, lean, events)
        return decided

    def choose(
        self,
        assigned: list[PoseHypothesis | None],
        decided: int | None,
        doubtful: bool,
        now_ns: int,
        current: int,
        snaps: bool = False,
    ) -> int:
        """The branch to output this frame (``current``: the last frame's): the committed one, or the frame's
        lower-error solution while a contradicting run is open (from its second frame, or a decisive one),
        the assignment is ``doubtful`` or a re-acquisition unconfirmed; an undecided target's best guess
        (``snaps``: a move to the other branch would be shown at once, too far to glide: only on evidence).
        The only solution of a frame (the other failed validation) is always shown."""
        if self.committed is None:
            target = self._best_guess(decided, now_ns, current, snaps)
        elif (self.run >= 2 or (self.run and decided is not None) or doubtful or self.unconfirmed) and (
            None not in assigned
        ):
            target = 0 if assigned[0].reproj_px <= assigned[1].reproj_px else 1
        else:
            target = self.committed
        if assigned[target] is None and assigned[1 - target] is not None:
            target = 1 - target  # the only solution this frame (the other failed validation) is shown
        return target

    def _weigh(self, decided: int | None, lean: int | None, events: list[TrackEvent]) -> None:
        """Self-correcting: a run of frames that contradict the commitment moves it after
        ``decisive_frames`` (a decisive frame counts one, a leaning one a third). The output is the
        frame's lower-error solution from a decisive frame or the run's second frame on (on hand-held
        clips with truth such frames are right far more often than the commitment), and nothing is
        vouched for while the run is open."""
        favoured = decided if decided is not None else lean
        if favoured == self.committed:
            self.against = 0
            self.run = 0
            self.unconfirmed = False
        elif favoured is not None:
            self.against += 1.0 if decided is not None else 1.0 / 3.0  # a leaning frame counts a third
            self.run += 1
            if self.against >= self.config.decisive_frames - 1e-9:
                self._switch(favoured, "on contradicting frames", events)

    def _window(self, since_ns: int) -> np.ndarray:
        return np.fromiter((v for t, v in self.values if t >= since_ns), dtype=np.float64)

    def bound(self, margin: float, z: float) -> float:
        """Lower confidence bound of |mean difference| above ``margin``, signed (+ favours branch 0)."""
        if not self.values:
            return 0.0
        values = np.fromiter((v for _, v in self.values), dtype=np.float64)
        mean = float(values.mean())
        # per-frame spread, shrunk toward the configured floor as if it were a few frames of prior data:
        # one or two frames cannot claim to be precise, thirty consistent ones can
        prior = 5.0
        squares = float(np.sum((values - mean) ** 2)) + prior * self.config.evidence_noise_px**2
        spread = math.sqrt(squares / (values.size - 1 + prior))
        stderr = spread / math.sqrt(values.size)
        bound = abs(mean) - z * stderr - margin
        return math.copysign(bound, mean) if bound > 0 else 0.0

    def _margin_scale(self) -> float:
        return margin_scale(len(self.noise.points))

    @property
    def _board(self) -> bool:
        """Is this a board's track (more than one marker's four points)? Its own geometry decides its flip."""
        return len(self.noise.points) > 4

    def _commit_alone(
        self, branch: int, assigned: list[PoseHypothesis | None], frames: int, events: list[TrackEvent]
    ) -> None:
        """An undecided board's frame that alone decides (:meth:`_verdict`: the only valid solution, or the
        other decisively worse at the board's margins) commits to it: the board's own points settle the flip,
        as :func:`decided_alone` says of a still. (A lone marker's four corners wait for the evidence.)"""
        self.committed = branch
        chosen, other = assigned[branch], assigned[1 - branch]
        assert chosen is not None
        why = (
            "the other solution failed validation"
            if other is None
            else f"the other solution reprojects {other.reproj_px:.3f} px, this one {chosen.reproj_px:.3f} px"
        )
        events.append(
            TrackEvent(
                "commit", f"committed to branch {branch} after {frames} frame(s): the board decides alone ({why})"
            )
        )

    def _decide(self, events: list[TrackEvent], frames: int) -> None:
        cfg = self.config
        if self.committed is None:
            bound = self.bound(cfg.decide_margin_px * self._margin_scale(), cfg.decide_z)
            if bound != 0.0:
                self.committed = 0 if bound > 0 else 1
                events.append(
                    TrackEvent(
                        "commit",
                        f"committed to branch {self.committed} after {frames} "
                        f"frame(s) (evidence {bound:+.3f} px beyond the margin)",
                    )
                )
        else:
            bound = self.bound(cfg.switch_margin_px * self._margin_scale(), cfg.switch_z)
            favoured = None if bound == 0.0 else (0 if bound > 0 else 1)
            if favoured is not None and favoured != self.committed:
                self._switch(favoured, f"on sustained evidence ({bound:+.3f} px)", events)

    def _switch(self, branch: int, why: str, events: list[TrackEvent]) -> None:
        events.append(TrackEvent("switch", f"switched from branch {self.committed} to {branch} {why}"))
        self.committed = branch
        latest = self.values[-1] if self.values else None
        self.values.clear()
        if latest is not None:
            self.values.append(latest)
        self.against = 0
        self.run = 0

    def leans(self, assigned: list[PoseHypothesis | None]) -> int | None:
        """The branch this frame alone leans to (see :meth:`_verdict`), None when it does not."""
        return self._verdict(assigned)[1]

    def _verdict(self, assigned: list[PoseHypothesis | None]) -> tuple[int | None, int | None]:
        """What this frame alone says: the branch it vouches for (the only solution, or the one the other
        reprojects ``decisive_ratio`` times and ``decisive_sigmas`` corner-noise standard deviations, at
        least ``decisive_px``, worse), and the branch it leans to (the other reprojects twice as badly and
        worse by more than the decision margin). Either is None when the frame says nothing. A board's margins
        shrink with its points (:func:`decisive`), and its two solutions that agree (:func:`solutions_agree`)
        decide for the better one."""
        cfg = self.config
        if assigned[0] is None or assigned[1] is None:
            only = None if assigned[0] is None and assigned[1] is None else (0 if assigned[0] is not None else 1)
            return only, only
        low, high = sorted((0, 1), key=lambda i: assigned[i].reproj_px)  # type: ignore[union-attr]
        if self._board and solutions_agree((assigned[low], assigned[high]), len(self.noise.points)):  # type: ignore[arg-type]
            return low, low  # a board's two solutions that agree: either is right
        better, worse = assigned[low].reproj_px, assigned[high].reproj_px  # type: ignore[union-attr]
        strong = low if decisive(better, worse, cfg, self.noise.frame_sigma_px, self._margin_scale()) else None
        lean = low if worse - better > cfg.decide_margin_px * self._margin_scale() and worse >= 2.0 * better else None
        return strong, lean

    def _best_guess(self, decided: int | None, now_ns: int, current: int, snaps: bool = False) -> int:
        """While undecided: this frame's decisive solution if there is one, else the branch the recent
        evidence leans to (by more than half the decision margin), else the branch the whole window's
        evidence favours (on far, undecidable markers the per-frame pick is right more often than not, and
        the window's mean more often still), else the current output branch. Where a move would snap
        (``snaps``: the two solutions too far apart to glide), the window's mean must be ``_GUESS_Z``
        standard errors from 0: the difference of two frames' noise does not make an undecidable static
        marker twitch from its first frame's branch to the other."""
        self.leaning = True
        if decided is not None:
            return decided
        recent = self._window(now_ns - int(self._RECENT_S * 1e9))
        if recent.size:
            mean = float(recent.mean())
            if abs(mean) > 0.5 * self.config.decide_margin_px * self._margin_scale():
                return 0 if mean > 0 else 1
        self.leaning = False
        lean = self.bound(0.0, self._GUESS_Z if snaps else 0.0)
        if lean != 0.0:
            return 0 if lean > 0 else 1
        return current

    def _add(self, assigned: list[PoseHypothesis | None], timestamp_ns: int) -> None:
        cfg = self.config
        if assigned[0] is None or assigned[1] is None:
            value = cfg.single_solution_evidence_px * (1 if assigned[0] is not None else -1)
        else:
            difference = assigned[1].reproj_px - assigned[0].reproj_px
            value = float(np.clip(difference, -cfg.evidence_cap_px, cfg.evidence_cap_px))
        self.values.append((timestamp_ns, value))
        oldest = timestamp_ns - int(cfg.evidence_window_s * 1e9)
        while self.values and self.values[0][0] < oldest:
            self.values.popleft()

    def close_call(self, assigned: list[PoseHypothesis | None], separation_deg: float) -> bool:
        """Are the two solutions within twice ``flip_angle_deg`` of each other while this frame barely
        tells them apart (their errors differ by less than the decision margin)? Then noise alone can
        carry the pose past a flip's worth: not vouched for, however sure the commitment."""
        if None in assigned:
            return False
        a, b = assigned  # type: ignore[misc]
        if self._board and separation_deg <= AGREE_DEG:
            return False  # a board's two solutions that agree: either is right (see solutions_agree)
        margin = self.config.decide_margin_px * self._margin_scale()
        return abs(a.reproj_px - b.reproj_px) < margin and separation_deg <= 2.0 * self.config.flip_angle_deg
