"""The learner of rigid groups (:class:`GroupLearner`), one per stream. Per frame it takes the lone markers'
solutions as pair evidence (:mod:`.evidence`) and forms, grows and merges groups (:class:`~.layout.LearnedGroup`),
solves every group like a board, and keeps the recent frames a new group is warmed from; after the filter it
counts each member's agreement with its group's joint pose (members leave, groups dissolve) and refines the
layouts from the groups' own joint poses until they settle. See :mod:`ar_anchor.track.groups`.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ...camera import CameraModel
from ...config import TrackerConfig
from ...geometry import Pose
from ...targets import TargetId
from ..pose import BoardPose, MarkerPose, PoseFailure, PoseHypothesis
from .evidence import Mode, Pair, observe_pair
from .layout import LearnedGroup, add_sample, on_plane
from .members import GroupLayout

__all__ = ["GroupLearner"]

_NEIGHBOURS = 4  # each marker is paired with this many of its nearest neighbours in the image
_SETTLED_M = 0.0003  # a refinement that moves no corner more than this: the layout has settled
_REFINE_EVERY = 5  # frames between layout refinements
_TURN_DECAY = 0.9  # a member's own-vs-layout turn is averaged over about ten frames ...
_REFINE_MIN_INLIERS = 3  # a member's pose in the group frame is sampled only when others fix the group
_HISTORY_FRAMES = 120  # at most this many past frames kept for a new group's flip filter (see remember)
_PAST_STEP = 2  # a new group's layout is refined from every this-many-th frame kept ...
_REPLAY_FRAMES = 30  # ... and its flip filter replayed over the last this many (a few hundred ms, once)


@dataclass(frozen=True)
class _PastFrame:
    """One earlier frame's detections, as :meth:`GroupLearner.remember` keeps them."""

    timestamp_ns: int
    ids: np.ndarray
    corners: np.ndarray
    camera: CameraModel
    max_reproj_px: float
    blurred: bool


class GroupLearner:
    """The groups of one stream (see the module doc). Per frame: :meth:`learn` from the lone markers'
    solutions, :meth:`solve` every group, then (after the filter) :meth:`settle` with the results."""

    def __init__(self, config: TrackerConfig) -> None:
        self.settings = config.groups
        self.dictionary = config.detector.dictionary
        self.inlier_px = config.pose.board_inlier_px
        self.config = config
        self.pairs: dict[tuple[int, int], Pair] = {}
        self.groups: dict[TargetId, LearnedGroup] = {}
        self.member_of: dict[int, TargetId] = {}
        self._numbers = itertools.count(1)
        self._reserved = {board.name for board in config.boards}
        self._camera: CameraModel | None = None  # this frame's (the layouts' refinement needs it)
        self._history: deque[_PastFrame] = deque(maxlen=_HISTORY_FRAMES)  # (see remember)
        self.changed: set[TargetId] = set()  # groups formed or grown by this frame's learn

    # ------------------------------------------------------------------ learning
    def learn(self, measured: dict[TargetId, MarkerPose | BoardPose], camera: CameraModel) -> dict[TargetId, list[str]]:
        """Take this frame's lone-marker solutions as evidence; form, grow and merge groups. Returns the
        events, by the target they concern."""
        self._camera = camera
        self.changed = set()
        lone = {  # (a configured board's markers are solved with their board already)
            name.marker_id: solved
            for name, solved in measured.items()
            if isinstance(solved, MarkerPose) and self.config.board_of(name.marker_id) is None
        }
        if len(lone) < 2:
            return {}
        ids = sorted(lone)
        centres = np.stack([lone[i].corners_in_image.reshape(4, 2).mean(axis=0) for i in ids])
        distances = np.linalg.norm(centres[:, None] - centres[None], axis=2)
        nearest = np.argsort(distances, axis=1)[:, 1 : _NEIGHBOURS + 1]
        pairs = {(min(ids[a], ids[int(b)]), max(ids[a], ids[int(b)])) for a in range(len(ids)) for b in nearest[a]}
        events: dict[TargetId, list[str]] = {}
        for first, second in sorted(pairs):
            group = self.member_of.get(first)
            if group is not None and self.member_of.get(second) == group:
                continue  # already together
            pair = self.pairs.setdefault((first, second), Pair())
            observe_pair(pair, lone[first], lone[second], camera, self.config)
            mode = pair.rigid(self.settings)
            if mode is not None:
                self._join(first, second, mode, pair, events)
        return events

    def _join(self, first: int, second: int, mode: Mode, pair: Pair, events: dict[TargetId, list[str]]) -> None:
        """A rigid pair: a new group, a marker added to one, or two groups merged."""
        first_from_second = mode.pose()
        evidence = (
            f"relative pose held in {mode.count} of {pair.seen - mode.born + 1} frames seen together (all the "
            "images can say: two objects standing still together look the same; a member that moves leaves)"
        )
        g1, g2 = self.member_of.get(first), self.member_of.get(second)
        if g1 is None and g2 is None:
            group = LearnedGroup(
                next(self._numbers),
                first,
                {first: Pose.identity(), second: first_from_second},
                {i: self.config.marker_length(i) for i in (first, second)},
                self.dictionary,
                self.inlier_px,
            )
            while group.name in self._reserved:
                group.number = next(self._numbers)
                group.rebuild()
            group.recentre()
            self.groups[group.target] = group
            self.changed.add(group.target)
            self.member_of.update({first: group.target, second: group.target})
            events.setdefault(group.target, []).append(f"formed from markers {first} and {second}: {evidence}")
            return
        if g1 is not None and g2 is not None:  # merge the second group into the first
            a, b = self.groups[g1], self.groups[g2]
            a_from_b = a.layout[first].compose(first_from_second).compose(b.layout[second].inverse())
            for marker_id, pose in b.layout.items():
                a.layout[marker_id] = a_from_b.compose(pose)
                a.lengths[marker_id] = b.lengths[marker_id]
                self.member_of[marker_id] = g1
            del self.groups[g2]
            self.changed.discard(g2)
            self.changed.add(g1)
            a.samples.clear()
            a.settled = False
            a.recentre()
            events.setdefault(g1, []).append(
                f"merged {b.name} (markers {b.describe()}) through markers {first} and {second}: {evidence}"
            )
            events.setdefault(g2, []).append(f"merged into {a.name}")
            return
        if g1 is not None:
            group, new = self.groups[g1], second
            group.layout[new] = group.layout[first].compose(first_from_second)
        else:
            assert g2 is not None
            group, new = self.groups[g2], first
            group.layout[new] = group.layout[second].compose(first_from_second.inverse())
        group.lengths[new] = self.config.marker_length(new)
        self.member_of[new] = group.target
        self.changed.add(group.target)
        group.settled = False
        group.recentre()
        events.setdefault(group.target, []).append(f"marker {new} joined: {evidence}")

    # ------------------------------------------------------------------ solving
    def solve(
        self,
        ids: np.ndarray,
        corners: np.ndarray,
        camera: CameraModel,
        max_reproj_px: float,
        image: np.ndarray | None = None,
    ) -> dict[TargetId, BoardPose | PoseFailure]:
        """Every group's joint pose from this frame's detections (groups none of whose markers is seen: none)."""
        out: dict[TargetId, BoardPose | PoseFailure] = {}
        for name, group in self.groups.items():
            solved = group.solver.solve(ids, corners, camera, max_reproj_px, image=image)
            if solved is not None:
                out[name] = solved
        return out

    def remember(
        self, timestamp_ns: int, ids: np.ndarray, corners: np.ndarray, camera: CameraModel, max_reproj_px: float,
        blurred: bool,
    ) -> None:  # fmt: skip
        """Keep this frame's detections for :meth:`past_solves` (the last ``[filter] evidence_window_s``)."""
        self._history.append(_PastFrame(timestamp_ns, ids.copy(), corners.copy(), camera, max_reproj_px, blurred))
        oldest = timestamp_ns - int(self.config.filter.evidence_window_s * 1e9)
        while self._history and self._history[0].timestamp_ns < oldest:
            self._history.popleft()

    def refine_from_past(self, name: TargetId, rounds: int = 2) -> int:
        """A planar group formed or grown this frame: its layout refined at once from the frames kept by
        :meth:`remember` (``rounds`` times: each member's corners met with the group's plane in every frame
        the group's joint pose used three members or more, averaged), instead of only from the frames to
        come; a layout straight from pair evidence is a millimetre off, and at a distance that is enough to
        tip the flip evidence the wrong way. Returns the frames used (0: not refined)."""
        group = self.groups[name]
        if not group.solver.planar:
            return 0
        used = 0
        for _ in range(rounds):
            sums: dict[int, list] = {}
            used = 0
            for past in itertools.islice(self._history, 0, None, _PAST_STEP):
                solved = group.solver.solve(past.ids, past.corners, past.camera, past.max_reproj_px)
                if not isinstance(solved, BoardPose) or len(solved.markers_used) < _REFINE_MIN_INLIERS:
                    continue
                used += 1
                seen = {int(i): c for i, c in zip(past.ids.tolist(), past.corners)}
                for marker_id in solved.markers_used:
                    if marker_id not in seen:
                        continue
                    sample = on_plane(
                        seen[marker_id], group.lengths[marker_id], solved.best.pose, group.layout[group.anchor],
                        past.camera,
                    )  # fmt: skip
                    if sample is None:
                        continue
                    add_sample(sums, marker_id, sample)
            if not group.take_means(sums):
                return 0
        return used

    def past_solves(self, name: TargetId) -> Iterator[tuple[_PastFrame, BoardPose | None]]:
        """Group ``name``'s joint pose in each frame kept by :meth:`remember` (None where it has none), oldest
        first: the evidence a group formed or grown this frame (:attr:`changed`) would have had, had it been
        a board then (the tracker replays its flip filter over them)."""
        group = self.groups[name]
        start = max(len(self._history) - _REPLAY_FRAMES, 0)
        for past in itertools.islice(self._history, start, None):
            solved = group.solver.solve(past.ids, past.corners, past.camera, past.max_reproj_px)
            yield past, solved if isinstance(solved, BoardPose) else None

    def layouts(self) -> dict[TargetId, GroupLayout]:
        """The layout of each group whose members may take its pose (:func:`~.members.members_from_groups`): a
        settled one (refined from its own joint poses until a refinement moves no corner more than
        :data:`_SETTLED_M`), or a planar one (made flat: its remaining errors lie in its plane, where the
        members' own corners see them), which only members unsure of their own pose follow until it
        settles. A non-planar layout straight from pair evidence, or still moving, is not trusted over
        the members' own poses."""
        return {
            name: GroupLayout(dict(group.layout), group.settled, frozenset(i for i in group.turn if group.agrees(i)))
            for name, group in self.groups.items()
            if group.settled or group.solver.planar
        }

    # ------------------------------------------------------------------ after the filter
    def settle(
        self, measured: dict[TargetId, MarkerPose | BoardPose], tracked: set[TargetId] | None = None
    ) -> dict[TargetId, list[str]]:
        """Count each seen member's agreement with its group's joint pose this frame; members rejected
        ``leave_frames`` times in a row leave, groups that cannot agree dissolve; refine the layouts
        (:meth:`_sample`: a non-planar group's only from frames the filter says it is ``tracked`` in,
        ``tracked``; None: every group solved). Returns the events, by the target they concern."""
        events: dict[TargetId, list[str]] = {}
        for name, group in list(self.groups.items()):
            solved = measured.get(name)
            seen = [i for i in group.layout if TargetId.marker(i) in measured]
            if not isinstance(solved, BoardPose):
                if len(seen) >= 2 and name in measured:  # a failed joint solve over two or more members
                    group.disagreeing += 1
                    if group.disagreeing >= self.settings.leave_frames:
                        self._dissolve(group, f"its markers {group.describe()} no longer agree", events)
                continue
            used = set(solved.markers_used)
            group.disagreeing = group.disagreeing + 1 if len(seen) >= 2 and len(used) < 2 else 0
            if group.disagreeing >= self.settings.leave_frames:
                self._dissolve(group, f"its markers {group.describe()} no longer agree", events)
                continue
            for marker_id in seen:
                if marker_id in used or len(used) < 2:
                    group.rejected.pop(marker_id, None)
                    continue
                group.rejected[marker_id] = group.rejected.get(marker_id, 0) + 1
                if group.rejected[marker_id] >= self.settings.leave_frames:
                    self._leave(group, marker_id, events)
            if name in self.groups:
                self._compare_turns(group, solved, measured)
            vouched = tracked is None or name in tracked or group.solver.planar  # (see _sample)
            if name in self.groups and len(used) >= _REFINE_MIN_INLIERS and vouched:
                self._sample(group, solved, measured)
        return events

    def _compare_turns(
        self, group: LearnedGroup, solved: BoardPose, measured: dict[TargetId, MarkerPose | BoardPose]
    ) -> None:
        """Per member used by this frame's joint pose: the turn from its own solution nearest the layout's
        orientation for it to that orientation (a rotation vector in the member's frame), averaged over
        recent frames (:data:`_TURN_DECAY`). Noise averages out; a layout that bends a sheet differently
        from the sheet itself (a curl flattened: the pair evidence's planar candidate sees none) leaves a
        steady turn that a well-measured member's own corners see (see :meth:`layouts`)."""
        for marker_id in solved.markers_used:
            lone = measured.get(TargetId.marker(marker_id))
            if not isinstance(lone, MarkerPose) or marker_id not in group.layout:
                continue
            expected = solved.best.pose.compose(group.layout[marker_id]).rotation
            turn = Pose.from_matrix(_nearest(lone, expected).pose.rotation.T @ expected, np.zeros(3)).rvec
            stats = group.turn.get(marker_id)  # [mean turn, mean squared turn, weight]
            if stats is None:
                group.turn[marker_id] = [turn, float(turn @ turn), 1.0]
                continue
            stats[0] = _TURN_DECAY * stats[0] + (1.0 - _TURN_DECAY) * turn
            stats[1] = _TURN_DECAY * stats[1] + (1.0 - _TURN_DECAY) * float(turn @ turn)
            stats[2] = _TURN_DECAY * stats[2] + 1.0

    def _leave(self, group: LearnedGroup, marker_id: int, events: dict[TargetId, list[str]]) -> None:
        del group.layout[marker_id]
        group.rejected.pop(marker_id, None)
        group.samples.pop(marker_id, None)
        del self.member_of[marker_id]
        for other in group.layout:  # its evidence with the group is forgotten: it must earn its place again
            self.pairs.pop((min(marker_id, other), max(marker_id, other)), None)
        message = f"marker {marker_id} left: its pose no longer fits the group's ({self.settings.leave_frames} frames)"
        events.setdefault(group.target, []).append(message)
        events.setdefault(TargetId.marker(marker_id), []).append(f"left {group.name}")
        if len(group.layout) < 2:
            self._dissolve(group, "one marker left", events)
            return
        if marker_id == group.anchor:  # the group's frame stays where it was: only the anchor's name moves
            group.anchor = min(group.layout)
        group.rebuild()

    def _dissolve(self, group: LearnedGroup, why: str, events: dict[TargetId, list[str]]) -> None:
        for marker_id in list(group.layout):
            self.member_of.pop(marker_id, None)
            for other in group.layout:
                if other > marker_id:
                    self.pairs.pop((marker_id, other), None)
            events.setdefault(TargetId.marker(marker_id), []).append(f"{group.name} dissolved")
        self.groups.pop(group.target, None)
        events.setdefault(group.target, []).append(f"dissolved: {why}")

    def _sample(self, group: LearnedGroup, solved: BoardPose, measured: dict[TargetId, MarkerPose | BoardPose]) -> None:
        """Each inlier member's pose in the group's frame this frame, summed; every :data:`_REFINE_EVERY`
        frames the layout becomes those means (:meth:`~.layout.LearnedGroup.take_means`). A planar group's member: its
        corners' rays met with the group's plane (flip-free, and no lone depth in it: a small marker's
        distance is its least sure part). Sampled whether or not the group's flip is decided: the two
        solutions of an ambiguous planar group reproject its corners alike, so either plane gives the same
        layout within that frame's noise (a far group would otherwise never settle). Another's: its
        solution nearer the group's, only from frames where the group is ``tracked``."""
        group_pose = solved.best.pose
        group_from_camera = group_pose.inverse()
        camera = self._camera
        for marker_id in solved.markers_used:
            lone = measured.get(TargetId.marker(marker_id))
            if not isinstance(lone, MarkerPose):
                continue
            sample = None
            if group.solver.planar and camera is not None:
                sample = on_plane(lone.corners_in_image, lone.length_m, group_pose, group.layout[group.anchor], camera)
            if sample is None:
                expected = group_pose.compose(group.layout[marker_id]).rotation
                sample = group_from_camera.compose(_nearest(lone, expected).pose)
            add_sample(group.samples, marker_id, sample)
        group.since_refined += 1
        if group.since_refined < _REFINE_EVERY:
            return
        group.since_refined = 0
        before = group.corners()
        if group.take_means(group.samples):
            group.refinements += 1
            after = group.corners()
            moved = max(float(np.abs(after[i] - before[i]).max()) for i in after if i in before)
            group.settled = moved <= _SETTLED_M


def _nearest(lone: MarkerPose, rotation: np.ndarray) -> PoseHypothesis:
    """The marker's solution whose rotation is nearest ``rotation`` (the group's choice of its planar flip)."""
    return max(lone.hypotheses, key=lambda h: float(np.vdot(h.pose.rotation, rotation)))
