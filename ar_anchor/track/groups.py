"""Rigid groups learned while tracking: lone markers that move together are solved together.

Users stick several markers on one sheet, wall or object and rarely write a board layout for them. Each
lone marker then flips and jitters alone, though its neighbours, seen in the same frame, settle its pose.
With ``[groups] learn = true`` (``--learn-groups``) the tracker learns such groups as it goes:

1. **Pairs** (:class:`_Pair`). For two lone markers measured in one frame, every combination of their
   validated IPPE solutions gives a candidate relative pose ``i_from_j`` (up to four: the planar flip of
   each). The true one recurs frame after frame; a flipped one moves with the viewpoint. A pair keeps a
   few *modes* (running means of candidates). A frame supports a mode when the two markers' eight
   corners fit it jointly: one camera pose, refined by Levenberg-Marquardt from either of the first
   marker's solutions, reprojects them within ``[groups] agree_px`` RMS. A joint fit, not a comparison
   of the two lone poses: a lone marker's rotation is often degrees off, the pair's corners are not.
   When no mode fits, the frame's candidates start new ones. Each marker is paired with its
   :data:`_NEIGHBOURS` nearest in the image (the cost stays linear in the markers seen). Markers of a
   configured board are solved with it and never learned.
2. **Rigid** when a mode has held ``min_frames`` frames, in at least ``agreement`` of the frames that saw
   both since it first appeared, and its frames' candidates agree on one relative rotation
   (:meth:`_Mode._consensus`: a vote, decided only when no other rotation comes near its support). That
   vote is where viewpoints count: the flipped candidates move with the viewpoint and the true one stays,
   so markers in different planes seen from one viewpoint only keep two rotations level and never join;
   markers in one plane have the flip-free planar candidate, which needs no second viewpoint. Two objects
   moving independently keep changing their relative pose, so no mode of theirs lasts. Two objects that
   only stand still together look exactly like one rigid object (nothing in the images tells them apart
   while nothing moves): they are grouped, the event says the evidence is a constant pose across
   viewpoints, and the first one to move leaves (4).
3. **Groups**: rigid pairs link markers into groups (a rigid pair with a member adds a marker; one
   between two groups merges them). A group's layout is its members' poses in the group's frame: turned
   as its anchor (its first marker), centred on its members' corners (:meth:`LearnedGroup.recentre`); a
   layout whose markers lie in one plane (within :data:`_PLANAR_SHARE` of its extent, normals within
   :data:`_PLANAR_TILT_DEG`) is made exactly planar, so the group is solved as a planar board (both IPPE
   solutions kept). Each group is a target of its own,
   ``board:group-N``, solved like a board (:class:`~.pose.BoardSolver`: RANSAC over its members'
   corners, then LM on the inliers) and passed through the same flip filter. When a group forms or
   grows, the tracker does not start it from nothing: a planar group's layout is refined at once from the
   frames kept (:meth:`GroupLearner.remember`, the last ``[filter] evidence_window_s``;
   :meth:`GroupLearner.refine_from_past`) and its flip filter is replayed over its joint pose in each
   (:meth:`GroupLearner.past_solves`). Its layout is then refined every :data:`_REFINE_EVERY` frames from
   the frames where three members or more fix the group's pose (each member's pose in the group's frame,
   averaged: a planar group's from any such frame, a non-planar group's only while it is ``tracked``; see
   :meth:`GroupLearner._sample`), until a refinement moves no corner more than :data:`_SETTLED_M`: it has
   *settled*.
4. **Members** (:func:`members_from_groups`): a member measured this frame and used by its group's joint
   pose outputs the group's output composed with its layout (``tracked`` when the group or its own track
   vouches for it, else ``ambiguous``) if that fits its corners, and if the layout is one to follow
   (:meth:`GroupLearner.layouts`): a member unsure of its own pose follows a settled or a planar (flat)
   layout; one whose own track vouches for it only a settled layout whose orientation for it agrees with
   its own solutions over recent frames (:meth:`LearnedGroup.agrees`: the pair evidence sees a curled
   sheet as flat). Otherwise its own lone track's output stands (its lone track keeps running, so a
   member that leaves goes on as before). A member the joint pose rejects ``leave_frames`` measured
   frames in a row leaves (its pair evidence with the group is forgotten); a group left with one marker,
   or whose joint pose agrees with fewer than two of the members it sees for ``leave_frames`` frames,
   dissolves.

Joins, leaves, merges and dissolutions are :class:`~.filtering.TrackEvent` (kind ``group``) on the
group's and the members' results, so they reach the log and rerun's ``events``.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, FilterConfig, GroupsConfig, TrackerConfig
from ..geometry import Pose, angle_between_deg, marker_corners_in_marker, mean_rotation
from ..targets import TargetId, TrackState
from .filtering import decided_alone
from .pose import BoardPose, BoardSolver, MarkerPose, PoseFailure, PoseHypothesis, reprojection_rms

__all__ = [
    "GROUP_PREFIX",
    "LAYOUT_DOUBT",
    "GroupLayout",
    "GroupLearner",
    "LearnedGroup",
    "disagrees_with_layout",
    "doubt_layouts",
    "members_from_groups",
]

log = logging.getLogger(__name__)

GROUP_PREFIX = "group-"
_NEIGHBOURS = 4  # each marker is paired with this many of its nearest neighbours in the image
_MAX_MODES = 6  # relative poses a pair keeps in mind at once
_PLANAR_SHARE = 0.005  # out-of-plane spread (RMS) below this share of the layout's extent: a planar group
_PLANAR_TILT_DEG = 3.0  # ... and no marker's normal farther than this from the plane's (a curled sheet is not flat)
_NEW_MODE_DEG, _NEW_MODE_M = 2.0, 0.003  # a candidate this near an existing mode starts no new one
_TESTED_MODES = 2  # a frame is fitted against this many of the most supported modes and of the youngest
_MODE_FRAMES = 150  # frames of candidates a mode keeps for its consensus
_VOTE_DEG = 6.0  # candidates of two frames this near vote for the same relative rotation
_VOTE_SHARE = 0.8  # the winner must have a candidate in this share of the frames ...
_VOTE_RIVAL = 0.6  # ... and no rotation farther than 3 _VOTE_DEG from it more than this share of its votes
_PLANAR_FIT = 0.1  # a square fitted to the second marker in the first's plane within this share of its side
_MEMBER_SLACK_PX = 0.3  # a member takes its group's pose only if that fits its corners within this of its own
_SETTLED_M = 0.0003  # a refinement that moves no corner more than this: the layout has settled
_REFINE_EVERY = 5  # frames between layout refinements
_TURN_DECAY = 0.9  # a member's own-vs-layout turn is averaged over about ten frames ...
_AGREE_TURN_DEG = 1.0  # ... and a member sure of its pose follows a layout only while it is below this
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


_Fits = Callable[["_Mode"], bool]


class _Mode:
    """One recurring relative pose of a pair: the candidates of the frames that fit it, their consensus
    (:meth:`_consensus`) and its support."""

    __slots__ = ("born", "count", "decided", "frames", "rotation", "translation")

    def __init__(self, rotation: np.ndarray, translation: np.ndarray, born: int) -> None:
        self.frames: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=_MODE_FRAMES)
        self.frames.append((rotation[None], translation[None], np.zeros(1, bool)))
        self.rotation, self.translation = rotation, translation
        self.count, self.born = 1, born
        self.decided = False  # the frames' candidates agree on one relative rotation (see _consensus)

    def add(self, rotations: np.ndarray, translations: np.ndarray, planar: np.ndarray) -> None:
        """A frame that fits: its candidates (the first marker's better-fitting solution with each of the
        second's, and the planar one when there is one: ``planar`` marks it)."""
        self.frames.append((rotations, translations, planar))
        self.count += 1
        if self.count <= 10 or self.count % 5 == 0 or not self.decided:
            self._consensus()

    def _consensus(self) -> None:
        """The relative rotation most frames have a candidate near (within :data:`_VOTE_DEG`: the flipped
        candidates move with the viewpoint, the true one stays), then the mean rotation and the median
        translation of each frame's candidate nearest it."""
        rotations = np.concatenate([r for r, _, _ in self.frames])
        translations = np.concatenate([t for _, t, _ in self.frames])
        planar = np.concatenate([p for _, _, p in self.frames])
        frame_of = np.concatenate([np.full(len(r), k) for k, (r, _, _) in enumerate(self.frames)])
        cosines = (np.einsum("nab,mab->nm", rotations, rotations) - 1.0) / 2.0
        near = cosines > math.cos(math.radians(_VOTE_DEG))
        one_hot = np.zeros((len(rotations), len(self.frames)), bool)
        one_hot[np.arange(len(rotations)), frame_of] = True
        support = ((near.astype(np.int32) @ one_hot) > 0).sum(axis=1)
        best = int(np.argmax(support))
        rival = support[cosines[best] < math.cos(math.radians(3 * _VOTE_DEG))]  # rotations clearly elsewhere
        self.decided = support[best] >= _VOTE_SHARE * len(self.frames) and (
            len(rival) == 0 or rival.max() <= _VOTE_RIVAL * support[best]
        )
        chosen = {}
        for n in np.flatnonzero(near[best]):  # per frame, its candidate nearest the winner (the planar first)
            k = frame_of[n]
            if k not in chosen or (planar[n], cosines[best, n]) > (planar[chosen[k]], cosines[best, chosen[k]]):
                chosen[k] = n
        picked = np.array(sorted(chosen.values()))
        self.rotation = mean_rotation(list(rotations[picked]))
        self.translation = np.median(translations[picked], axis=0)

    def pose(self) -> Pose:
        return Pose.from_matrix(self.rotation, self.translation)


@dataclass
class _Pair:
    """Evidence about one pair of markers ``(i, j)``, ``i < j``: the frames that saw both, and the modes
    of their relative pose ``i_from_j``."""

    seen: int = 0
    modes: list[_Mode] = field(default_factory=list)

    def observe(self, rotations: np.ndarray, translations: np.ndarray, planar: np.ndarray, fits: _Fits) -> None:
        """One frame's candidates (K, 3, 3), (K, 3), which is the planar one (``planar``, (K,) bool), and
        ``fits(mode)``: do this frame's corners fit the mode?"""
        self.seen += 1
        supported = sorted(self.modes, key=lambda m: -m.count)[:_TESTED_MODES]
        young = [m for m in sorted(self.modes, key=lambda m: -m.born) if m not in supported][:_TESTED_MODES]
        for mode in supported + young:
            if fits(mode):
                mode.add(rotations, translations, planar)
                return
        for k in range(len(rotations)):  # nothing fits: each candidate may be the start of the true pose
            if any(_near(mode, rotations[k], translations[k]) for mode in self.modes):
                continue
            if len(self.modes) >= _MAX_MODES:
                self.modes.remove(min(self.modes, key=lambda mode: (mode.count, -mode.born)))
            self.modes.append(_Mode(rotations[k].copy(), translations[k].copy(), self.seen))

    def rigid(self, settings: GroupsConfig) -> _Mode | None:
        """The mode that makes the pair rigid (see the module doc), if any."""
        if not self.modes:
            return None
        mode = max(self.modes, key=lambda m: m.count)
        share = mode.count / max(self.seen - mode.born + 1, 1)
        enough = mode.count >= settings.min_frames and share >= settings.agreement and mode.decided
        return mode if enough else None


def _planar_candidate(first: MarkerPose, second: MarkerPose, camera: CameraModel) -> Pose | None:
    """``first_from_second`` if both markers lie in one plane: the second's corners taken into the first's
    plane through the homography of the first's four corners (unique: the planar flip is a choice made only
    when that homography is split into a rotation and a translation), and a square of the second's side
    fitted to them (in-plane turn and shift). None when they do not form such a square (not one plane)."""
    pixels = np.concatenate([first.corners_in_image.reshape(4, 2), second.corners_in_image.reshape(4, 2)])
    undistorted = pixels.astype(np.float64)
    if camera.dist_or_none is not None:  # (the homography holds between undistorted points)
        k = camera.camera_matrix
        undistorted = cv2.undistortPoints(pixels.reshape(-1, 1, 2), k, camera.dist_or_none, P=k).reshape(-1, 2)
    square_first = marker_corners_in_marker(first.length_m)[:, :2]
    try:
        homography = cv2.getPerspectiveTransform(undistorted[:4].astype(np.float32), square_first.astype(np.float32))
    except cv2.error:
        return None
    points = cv2.perspectiveTransform(undistorted[4:].reshape(-1, 1, 2), homography).reshape(4, 2)
    square = marker_corners_in_marker(second.length_m)[:, :2]
    centre = points.mean(axis=0)
    u, _, vt = np.linalg.svd((square - square.mean(axis=0)).T @ (points - centre))
    turn = (u @ vt).T
    if np.linalg.det(turn) < 0:
        return None  # a mirrored square: not the second marker seen in the first's plane
    residual = float(np.sqrt(np.mean(np.sum((square @ turn.T + centre - points) ** 2, axis=1))))
    if not np.isfinite(residual) or residual > _PLANAR_FIT * second.length_m:
        return None
    rotation = np.eye(3)
    rotation[:2, :2] = turn
    return Pose.from_matrix(rotation, np.array([centre[0], centre[1], 0.0]))


def _plausible(solved: MarkerPose, config: FilterConfig) -> tuple:
    """A marker's solutions that this frame leaves possible: both, unless the frame alone decides its flip
    (:func:`~.filtering.decided_alone`): then a flipped candidate would only vote for a wrong relative rotation."""
    return solved.hypotheses[:1] if decided_alone(solved.hypotheses, config) else solved.hypotheses


def _near(mode: _Mode, rotation: np.ndarray, translation: np.ndarray) -> bool:
    cosine = (float(np.vdot(mode.rotation, rotation)) - 1.0) / 2.0
    near_turn = math.degrees(math.acos(min(1.0, max(-1.0, cosine)))) < _NEW_MODE_DEG
    return near_turn and float(np.linalg.norm(mode.translation - translation)) < _NEW_MODE_M


@dataclass
class LearnedGroup:
    """A group of markers found rigid together: its layout (``group_from_marker`` per member, in a frame
    turned as its anchor and centred on its members, :meth:`recentre`) and the board solver built from it."""

    number: int
    anchor: int
    layout: dict[int, Pose]
    lengths: dict[int, float]
    dictionary: str
    inlier_px: float = 3.0  # [pose] board_inlier_px: a member farther than this from the joint pose is an outlier
    solver: BoardSolver = field(init=False)
    rejected: dict[int, int] = field(default_factory=dict)  # member -> measured frames in a row rejected
    disagreeing: int = 0  # frames in a row the joint pose agreed with fewer than two seen members
    samples: dict[int, list[np.ndarray]] = field(default_factory=dict)  # member -> [rotation sum, t sum, n]
    since_refined: int = 0
    refinements: int = 0  # layout refinements from the group's own joint poses (see GroupLearner._sample)
    turn: dict[int, list] = field(default_factory=dict)  # member -> own-vs-layout turn statistics (_compare_turns)
    settled: bool = False  # its last refinement moved no corner more than _SETTLED_M (its members may follow it)

    def __post_init__(self) -> None:
        self.rebuild()

    @property
    def name(self) -> str:
        return f"{GROUP_PREFIX}{self.number}"

    @property
    def target(self) -> TargetId:
        return TargetId.board(self.name)

    def rebuild(self) -> None:
        """Flatten a planar layout and build its board solver (after a join, a leave or a refinement)."""
        self.layout = _flattened(self.layout, self.lengths)
        corners = []
        for marker_id, pose in sorted(self.layout.items()):
            points = pose.apply(marker_corners_in_marker(self.lengths[marker_id]))
            corners.append((marker_id, tuple(tuple(float(v) for v in p) for p in points)))
        board = BoardConfig(name=self.name, kind="custom", layout=tuple(corners), dictionary=self.dictionary)
        self.solver = BoardSolver(board, self.inlier_px)

    def recentre(self) -> None:
        """Move the group's frame to its members' centroid (turned as it was), after a join or a merge: a
        joint pose's position is surest there, uncoupled from its rotation, so the filter smooths the two
        apart, as it does a board's (a frame at one corner marker would carry the rotation's noise, times
        the lever, into every member's position). The tracker then restarts the group's track."""
        centre = np.concatenate(list(self.corners().values())).mean(axis=0)
        shift = Pose(np.zeros(3), -centre)
        self.layout = {i: shift.compose(pose) for i, pose in self.layout.items()}
        self.samples.clear()  # (measured in the frame before)
        self.rebuild()

    def take_means(self, sums: dict[int, list]) -> bool:
        """The layout becomes the members' mean poses in the group's frame (``sums``: member -> [rotation
        sum, translation sum, count]; those with five samples or more), the anchor's included, then
        re-expressed so that the anchor stays where the layout had it (the group's frame does not move
        with its anchor's sampling noise, and the others are not left to absorb the anchor's own error).
        Returns whether anything changed (the solver is rebuilt then)."""
        means = {
            i: Pose.from_matrix(mean_rotation([rotation_sum]), translation_sum / count)
            for i, (rotation_sum, translation_sum, count) in sums.items()
            if count >= 5 and i in self.layout
        }
        if not means:
            return False
        fix = Pose.identity()
        if self.anchor in means:  # (group_from_marker of the anchor kept as it was)
            fix = self.layout[self.anchor].compose(means[self.anchor].inverse())
        for marker_id, pose in means.items():
            self.layout[marker_id] = fix.compose(pose)
        for marker_id in set(self.layout) - set(means):
            self.layout[marker_id] = fix.compose(self.layout[marker_id])
        self.rebuild()
        return True

    def agrees(self, marker_id: int) -> bool:
        """Does the layout's orientation for this member agree with the member's own solutions (recent
        frames, :meth:`GroupLearner._compare_turns`): their mean turn below :data:`_AGREE_TURN_DEG`, or
        below three standard errors of that mean (a far, noisy member cannot tell a degree apart)?"""
        stats = self.turn.get(marker_id)
        if stats is None or stats[2] < 3.0:
            return False
        mean, square, weight = stats
        spread = max(square - float(mean @ mean), 0.0)
        standard_error = math.sqrt(spread / weight)
        return float(np.linalg.norm(mean)) <= max(math.radians(_AGREE_TURN_DEG), 3.0 * standard_error)

    def corners(self) -> dict[int, np.ndarray]:
        """Each member's corners (4, 3) in the group's frame."""
        return {i: pose.apply(marker_corners_in_marker(self.lengths[i])) for i, pose in self.layout.items()}

    def describe(self) -> str:
        return ", ".join(str(i) for i in sorted(self.layout))


def _flattened(layout: dict[int, Pose], lengths: dict[int, float]) -> dict[int, Pose]:
    """``layout`` made exactly planar when its markers nearly share one plane (see the module doc): each
    marker's centre projected onto the best-fit plane and its normal turned onto the plane's."""
    if len(layout) < 2:
        return layout
    normals = np.stack([pose.rotation[:, 2] for pose in layout.values()])
    mean_normal = normals.sum(axis=0)
    mean_normal /= max(float(np.linalg.norm(mean_normal)), 1e-12)
    corners = np.concatenate([pose.apply(marker_corners_in_marker(lengths[i])) for i, pose in layout.items()])
    centroid = corners.mean(axis=0)
    _, singular, vt = np.linalg.svd(corners - centroid, full_matrices=False)
    normal = vt[2] if float(vt[2] @ mean_normal) >= 0 else -vt[2]
    extent = float(np.ptp(corners @ vt[0]))
    out_of_plane = singular[2] / math.sqrt(len(corners))
    tilt = max(math.degrees(math.acos(float(np.clip(n @ normal, -1.0, 1.0)))) for n in normals)
    if out_of_plane > _PLANAR_SHARE * extent or tilt > _PLANAR_TILT_DEG:
        return layout
    flat = {}
    for marker_id, pose in layout.items():
        rotation = pose.rotation
        axis = np.cross(rotation[:, 2], normal)
        sine, cosine = float(np.linalg.norm(axis)), float(rotation[:, 2] @ normal)
        turn = np.eye(3)
        if sine > 1e-12:
            k = axis / sine
            skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            turn = np.eye(3) + sine * skew + (1 - cosine) * skew @ skew
        centre = pose.tvec - float((pose.tvec - centroid) @ normal) * normal
        flat[marker_id] = Pose.from_matrix(turn @ rotation, centre)
    return flat


class GroupLearner:
    """The groups of one stream (see the module doc). Per frame: :meth:`learn` from the lone markers'
    solutions, :meth:`solve` every group, then (after the filter) :meth:`settle` with the results."""

    def __init__(self, config: TrackerConfig) -> None:
        self.settings = config.groups
        self.dictionary = config.detector.dictionary
        self.inlier_px = config.pose.board_inlier_px
        self.config = config
        self.pairs: dict[tuple[int, int], _Pair] = {}
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
            pair = self.pairs.setdefault((first, second), _Pair())
            self._observe(pair, lone[first], lone[second], camera)
            mode = pair.rigid(self.settings)
            if mode is not None:
                self._join(first, second, mode, pair, events)
        return events

    def _observe(self, pair: _Pair, first: MarkerPose, second: MarkerPose, camera: CameraModel) -> None:
        rotations, translations, planar = [], [], []
        for mine in _plausible(first, self.config.filter):
            ra, ta = mine.pose.rotation, mine.pose.tvec
            for theirs in _plausible(second, self.config.filter):
                rotations.append(ra.T @ theirs.pose.rotation)
                translations.append(ra.T @ (theirs.pose.tvec - ta))
                planar.append(False)
        in_plane = _planar_candidate(first, second, camera)
        if in_plane is not None:  # (both markers in one plane: a candidate the planar flip has no part in)
            rotations.append(in_plane.rotation)
            translations.append(in_plane.tvec)
            planar.append(True)
        image = np.concatenate([first.corners_in_image.reshape(4, 2), second.corners_in_image.reshape(4, 2)])
        square = marker_corners_in_marker(second.length_m)

        def fits(mode: _Mode) -> bool:
            points = np.concatenate([first.points_in_target, square @ mode.rotation.T + mode.translation])
            limit = self.settings.agree_px
            return any(_joint_fit(points, image, h.pose, camera)[1] <= limit for h in first.hypotheses)

        pair.observe(np.stack(rotations), np.stack(translations), np.array(planar), fits)

    def _join(self, first: int, second: int, mode: _Mode, pair: _Pair, events: dict[TargetId, list[str]]) -> None:
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
                    sample = _on_plane(
                        seen[marker_id], group.lengths[marker_id], solved.best.pose, group.layout[group.anchor],
                        past.camera,
                    )  # fmt: skip
                    if sample is None:
                        continue
                    _add_sample(sums, marker_id, sample)
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
        """The layout of each group whose members may take its pose (:func:`members_from_groups`): a
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
        frames the layout becomes those means (:meth:`LearnedGroup.take_means`). A planar group's member: its
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
                sample = _on_plane(lone.corners_in_image, lone.length_m, group_pose, group.layout[group.anchor], camera)
            if sample is None:
                expected = group_pose.compose(group.layout[marker_id]).rotation
                sample = group_from_camera.compose(_nearest(lone, expected).pose)
            _add_sample(group.samples, marker_id, sample)
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


def _add_sample(sums: dict[int, list], marker_id: int, sample: Pose) -> None:
    """Add a member's pose in the group's frame to ``sums`` (member -> [rotation sum, translation sum, count],
    as :meth:`LearnedGroup.take_means` reads them)."""
    total = sums.setdefault(marker_id, [np.zeros((3, 3)), np.zeros(3), 0])
    total[0] = total[0] + sample.rotation
    total[1] = total[1] + sample.tvec
    total[2] += 1


def _nearest(lone: MarkerPose, rotation: np.ndarray) -> PoseHypothesis:
    """The marker's solution whose rotation is nearest ``rotation`` (the group's choice of its planar flip)."""
    return max(lone.hypotheses, key=lambda h: float(np.vdot(h.pose.rotation, rotation)))


def _on_plane(
    corners: np.ndarray, length_m: float, camera_from_group: Pose, group_from_anchor: Pose, camera: CameraModel
) -> Pose | None:
    """``group_from_marker`` of a marker of a planar group from its ``corners`` (in the image) and side:
    their rays (undistorted) met with the group's plane (the anchor's x-y plane), and a square of its side
    fitted there."""
    pixels = np.asarray(corners, dtype=np.float64).reshape(4, 1, 2)
    rays = cv2.undistortPoints(pixels, camera.camera_matrix, camera.dist_or_none).reshape(4, 2)
    rays = np.column_stack([rays, np.ones(4)])
    camera_from_anchor = camera_from_group.compose(group_from_anchor)
    normal, origin = camera_from_anchor.rotation[:, 2], camera_from_anchor.tvec
    along = rays @ normal
    if np.any(np.abs(along) < 1e-9):
        return None
    points = rays * ((origin @ normal) / along)[:, None]  # in the camera frame
    if np.any(points[:, 2] <= 0):
        return None
    in_plane = (points - origin) @ camera_from_anchor.rotation[:, :2]  # the anchor's x, y
    square = marker_corners_in_marker(length_m)[:, :2]
    centre = in_plane.mean(axis=0)
    u, _, vt = np.linalg.svd(square.T @ (in_plane - centre))
    turn = (u @ vt).T
    if np.linalg.det(turn) < 0:
        return None
    rotation = np.eye(3)
    rotation[:2, :2] = turn
    anchor_from_marker = Pose.from_matrix(rotation, np.array([centre[0], centre[1], 0.0]))
    return group_from_anchor.compose(anchor_from_marker)


def _joint_fit(points: np.ndarray, image: np.ndarray, start: Pose, camera: CameraModel) -> tuple[Pose, float]:
    """The camera pose refined (LM) from ``start`` on ``points`` (N, 3) and ``image`` (N, 2), and its RMS
    reprojection error (inf when the solver fails)."""
    rvec, tvec = start.rvec.reshape(3, 1).copy(), start.tvec.reshape(3, 1).copy()
    try:
        rvec, tvec = cv2.solvePnPRefineLM(points, image, camera.camera_matrix, camera.dist_or_none, rvec, tvec)
    except cv2.error:
        return start, math.inf
    pose = Pose(rvec.ravel(), tvec.ravel())
    return pose, (reprojection_rms(pose, points, image, camera) if pose.is_finite() else math.inf)


@dataclass(frozen=True)
class GroupLayout:
    """A group's layout as its members may follow it this frame (:meth:`GroupLearner.layouts`):
    ``group_from_marker`` by member, and whether it has settled."""

    members: dict[int, Pose]
    settled: bool = True
    agree: frozenset[int] | None = None  # members whose own orientation agrees with it (LearnedGroup.agrees; None: all)


def members_from_groups(
    targets: dict,
    layouts: dict[TargetId, GroupLayout],
    camera: CameraModel | None,
    replace: Callable,
) -> dict:
    """``targets`` (a frame's :class:`~.tracker.TargetResult` by name) with each member that its group's
    joint pose used this frame given the group's output composed with its layout (``replace(target, pose,
    reproj_px, state)`` makes the new result), when that pose reprojects the member's own corners within
    :data:`_MEMBER_SLACK_PX` of the member's own solution (a layout still off by a millimetre moves the
    member off its corners: its own pose is then better). ``layouts``: :meth:`GroupLearner.layouts`; a
    member whose own track vouches for its pose (``tracked``) follows only a settled one that its
    orientation agrees with (:attr:`GroupLayout.agree`): on the real chessboard.avi, the pair evidence
    learns the slightly curled sheet as flat, and following such layouts made well-tracked members'
    relative rotations up to 30 % less steady.

    Whether or not the group's filter has decided its planar flip: undecided, its output is a best guess
    from 8 or more corners where each member's is one from four (at 2-3 m, a 6-marker sheet's guess is
    right where its members' flip). The member's state says which: ``tracked`` when its group is, or when
    the member's own track vouches for the solution the group's pose lies on (nearer its own output than
    its other solution); ``ambiguous`` otherwise. Others are unchanged."""
    out = dict(targets)
    for name, layout in layouts.items():
        group = targets.get(name)
        if group is None or not group.state.measured:
            continue
        for marker_id in group.markers_used:
            member = TargetId.marker(marker_id)
            own = targets.get(member)
            if own is None or not own.measured or marker_id not in layout.members:
                continue
            if camera is None or own.corners_in_image is None or not own.hypotheses:
                continue
            if own.state is TrackState.TRACKED and not (
                layout.settled and (layout.agree is None or marker_id in layout.agree)
            ):
                continue  # a member sure of its own pose: only a settled layout its orientation agrees with
            pose = group.pose.compose(layout.members[marker_id])
            reproj = reprojection_rms(
                pose, marker_corners_in_marker(own.length_m), own.corners_in_image.reshape(-1, 2), camera
            )
            if not reproj <= own.hypotheses[0].reproj_px + _MEMBER_SLACK_PX:
                continue  # the group's pose does not fit this member's corners as its own does: a layout error
            sure = group.state is TrackState.TRACKED or (own.state is TrackState.TRACKED and _on_own_branch(pose, own))
            out[member] = replace(own, pose, reproj, TrackState.TRACKED if sure else TrackState.AMBIGUOUS)
    return out


LAYOUT_DOUBT = "layout_disagrees"  # a learned group's joint pose agrees with fewer than two of the members seen


def disagrees_with_layout(solved: BoardPose) -> bool:
    """Did a group's joint solve see two members or more but find fewer than two that agree with its layout
    (``markers_used`` and ``outlier_ids``: seen, rejected)? Then this frame contradicts the layout, and its
    pose rests on one member's place in it, whichever RANSAC happened to pick."""
    used = len(solved.markers_used)
    return used < 2 <= used + len(solved.outlier_ids)


def doubt_layouts(targets: dict, names: set[TargetId] | frozenset[TargetId]) -> dict:
    """``targets`` (a frame's results by name) with each measured one of ``names`` (groups whose frame
    :func:`disagrees_with_layout`) not ``tracked``: ``ambiguous``, with the doubt :data:`LAYOUT_DOUBT` (which
    the offline replay keeps: see :mod:`.offline`). Poses are left as they are."""
    if not names:
        return targets
    out = dict(targets)
    for name in names:
        target = out.get(name)
        if target is None or not target.state.measured:
            continue
        doubts = target.doubts if LAYOUT_DOUBT in target.doubts else (*target.doubts, LAYOUT_DOUBT)
        out[name] = dataclasses.replace(target, state=TrackState.AMBIGUOUS, doubts=doubts)
    return out


def _on_own_branch(pose: Pose, own) -> bool:
    """Is ``pose`` nearer the member's own output than the member's other solution (the one farther from
    that output)? With one solution: yes."""
    if len(own.hypotheses) < 2:
        return True
    other = max(own.hypotheses, key=lambda h: angle_between_deg(h.pose.rotation, own.pose.rotation))
    return angle_between_deg(pose.rotation, own.pose.rotation) < angle_between_deg(pose.rotation, other.pose.rotation)
