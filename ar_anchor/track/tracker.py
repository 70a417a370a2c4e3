"""One frame's trip through the pipeline: detect -> solve -> filter -> :class:`FrameResult`.

With the filter on (the default), each marker's output pose comes from its
:class:`~ar_anchor.track.filtering.TargetTrack` (flip resolved with evidence over time, smoothed,
predicted through short gaps). With it off (``--no-filter``), the output is the plain per-frame
lower-error IPPE solution, state ``tracked`` where the frame alone decides the planar flip and
``ambiguous`` where it does not.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import FilterConfig, TrackerConfig
from ..geometry import Pose, marker_corners_in_marker
from ..sources.base import Frame, check_frame
from ..targets import TargetId, TrackState
from .detection import FAST_MIN_SIDE_PX, Detector, MarkerDetections, mean_side, plan_regions
from .filtering import (
    SEGMENT_STARTS,
    KalmanBatch,
    TargetTrack,
    TrackEvent,
    TrackUpdate,
    decided_alone,
    unit_covariances_of,
)
from .fit import refit
from .groups import (
    GroupLayout,
    GroupLearner,
    disagrees_with_layout,
    doubt_layouts,
    is_learned_group,
    members_from_groups,
)
from .marker_poses import solve_markers
from .pose import BoardPose, BoardSolver, MarkerPose, PoseFailure, PoseHypothesis, reprojection_rms

__all__ = ["FrameResult", "TargetResult", "Tracker"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TargetResult:
    """What the tracker says about one target (``marker:<id>`` or ``board:<name>``) in one frame.

    Attributes
    ----------
    pose : output ``camera_from_target`` (what is rendered).
    raw : this frame's plain per-frame solution before filtering (None when not measured).
    state : ``tracked`` | ``ambiguous`` | ``predicted`` (| ``interpolated``, offline replay).
    reproj_px : RMS reprojection error of ``pose`` on this frame's corners (NaN when predicted).
    ambiguity : error ratio worse / better of the two IPPE solutions (NaN for boards or unknown).
    hypotheses : the validated per-frame solutions, lower error first.
    corners_in_image : (N, 4, 2) corners used this frame.
    """

    target: TargetId
    state: TrackState
    pose: Pose
    raw: Pose | None
    reproj_px: float
    ambiguity: float
    length_m: float
    hypotheses: tuple[PoseHypothesis, ...] = ()
    corners_in_image: np.ndarray | None = None
    branch_poses: tuple[Pose | None, ...] = ()  # this frame's solution on each filter branch
    evidence_px: float = math.nan  # signed flip evidence (+: branch 0), see track/filtering/evidence.py
    events: tuple[TrackEvent, ...] = ()  # filter events this frame (commits, switches, re-acquisitions, resets)
    outline_in_target: np.ndarray | None = None  # (K, 4, 3) the target's marker squares, target frame
    markers_used: tuple[int, ...] = ()  # boards: ids of the inlier markers this frame
    outlier_ids: tuple[int, ...] = ()  # boards: markers seen but rejected this frame
    inliers: int = 0  # corners (or ChArUco corners) the pose was solved from
    outlier_points_in_image: np.ndarray | None = None  # boards: rejected corners this frame
    branch: int = -1  # the filter's output branch (index into branch_poses; -1: no filter)
    run_frames: int = 0  # the filter's frames measured since its smoothers last (re)started
    committed: bool = False  # the filter's evidence has committed to a solution (undecided otherwise)
    doubts: tuple[str, ...] = ()  # a measured, not tracked frame: the filter's reasons (TargetTrack._doubts)

    def __post_init__(self) -> None:
        object.__setattr__(self, "target", TargetId.parse(self.target))
        object.__setattr__(self, "state", TrackState(self.state))

    @property
    def measured(self) -> bool:
        return self.state.measured


@dataclass(frozen=True)
class FrameResult:
    """Everything the tracker found in one frame."""

    index: int
    timestamp_ns: int
    detections: MarkerDetections
    targets: dict[TargetId, TargetResult]  # in TargetId order
    failures: tuple[PoseFailure, ...] = ()
    latency_ms: dict[str, float] = field(default_factory=dict)
    camera: CameraModel | None = None
    repeated: bool = False  # the same pixels as the frame before: the previous answer, not a new measurement
    blurred: bool = False  # the frame was motion-blurred (its measurements are not vouched for)
    detail: float = math.nan  # the fine-scale contrast of the whole frame (Laplacian variance at 1/4 size)
    # this frame's per-frame solutions, by target (both IPPE solutions): what the filter took in, kept for
    # the offline pass (:mod:`ar_anchor.track.offline`) to run the filter again, backwards
    measurements: dict[TargetId, MarkerPose | BoardPose] = field(default_factory=dict)
    # offline replay: what the live (causal) filter said of this frame, for comparison (None otherwise)
    causal_targets: dict[TargetId, TargetResult] | None = None
    # learned rigid groups (``[groups] learn``): the layouts members may follow this frame (GroupLearner.layouts)
    groups: dict[TargetId, GroupLayout] = field(default_factory=dict)

    def board_members(self) -> dict[TargetId, TargetId]:
        """Each marker drawn as part of a board this frame -> that board (a configured board or a learned
        group, in any state it is drawn in): the markers the board's pose was solved from
        (:attr:`TargetResult.markers_used`; a marker the board rejected is not one). Such a marker keeps its
        own row in poses.csv; the overlay draws it as part of its board (no label of its own) and the run's
        summary folds it under the board."""
        members: dict[TargetId, TargetId] = {}
        for target in self.targets.values():
            if target.target.is_board:
                for marker_id in target.markers_used:
                    members.setdefault(TargetId.marker(marker_id), target.target)
        return members


@dataclass(frozen=True)
class DetectedFrame:
    """A frame after :meth:`Tracker.detect`, the first stage: its markers and what the stages after need."""

    frame: Frame
    camera: CameraModel  # the calibration at the frame's size
    detections: MarkerDetections
    blurred: bool  # motion-blurred (see Tracker._blurred)
    detail: float  # the fine-scale contrast (FrameResult.detail)
    repeated: bool  # the last new frame's pixels and markers again: its answer stands
    detect_ms: float


class Tracker:
    """Stateful per-stream tracker. Feed frames in order to :meth:`process`. ``stills``: the frames are
    independent photos, each processed alone (as by a new tracker: nothing carried from one to the next).

    Example
    -------
    >>> tracker = Tracker(load_config(), CameraModel.from_yaml("configs/camera_synthetic.yml"))
    >>> result = tracker.process(frame)        # doctest: +SKIP
    >>> result.targets["marker:0"].pose.tvec   # doctest: +SKIP
    """

    _BLUR_RATIO = 0.6  # a frame this much less sharp than usual is motion-blurred

    def __init__(self, config: TrackerConfig, camera: CameraModel, *, stills: bool = False) -> None:
        self.config = config
        # independent stills (photos that may be unrelated): each frame processed as by a new tracker
        self.stills = stills
        self.camera = camera
        self.detector = Detector(config.detector)
        self._cameras: dict[tuple[int, int], CameraModel] = {camera.size: camera}
        self.tracks: dict[TargetId, TargetTrack] = {}
        self.board_solvers = [BoardSolver(board, config.pose.board_inlier_px) for board in config.boards]
        self.groups = GroupLearner(config) if config.groups.learn else None
        # ROI tracking state: the last two frames' corners per marker id
        self._last_corners: dict[int, np.ndarray] = {}
        self._before_corners: dict[int, np.ndarray] = {}
        self._fingerprint: np.ndarray | None = None  # every 4th pixel of the last frame (repeats)
        self._sharpness: float | None = None  # typical variance of the fingerprint's Laplacian (blur)
        self._detail = math.nan  # this frame's fine-scale contrast (see FrameResult.detail)
        self._previous: FrameResult | None = None
        self._last_observed: MarkerDetections | None = None  # the last new frame's markers (repeats)
        self._seen: dict[int, tuple[np.ndarray, int]] = {}  # marker id -> (last corners, when)
        self._shutter_previous: tuple[int, dict[int, np.ndarray]] | None = None  # (see _at_first_row)
        self._shutter_warned = False
        self._frames_since_full = 0
        self._frames_since_thorough = 0  # frames since the last thorough full-frame search (see _search_whole_frame)
        self._last_size: tuple[int, int] | None = None

    def camera_for(self, size: tuple[int, int]) -> CameraModel:
        """The calibration scaled to a frame size (warns once per new size)."""
        if size not in self._cameras:
            self._cameras[size] = self.camera.scaled_to(*size)
        return self._cameras[size]

    def reports(self, target: str) -> bool:
        """Does this tracker output poses for ``target`` (``marker:<id>`` / ``board:<name>``)?"""
        try:
            target = TargetId.parse(target)
        except ValueError:
            return False
        if target.is_board:
            return self._board_solver(target) is not None or any(b.name == target.name for b in self.config.boards)
        return self.config.tracks_marker(target.marker_id)

    def _board_solver(self, target: TargetId) -> BoardSolver | None:
        """The solver of a configured board or of a learned group (None: neither, or a group since dissolved)."""
        for solver in self.board_solvers:
            if solver.target == target:
                return solver
        group = self.groups.groups.get(target) if self.groups is not None else None
        return group.solver if group is not None else None

    def outline(self, target: str) -> np.ndarray:
        """The target's marker squares (K, 4, 3) in its own frame (for drawing it in 3D)."""
        target = TargetId.parse(target)
        if target.is_board:
            solver = self._board_solver(target)
            if solver is None:
                raise KeyError(f"{target}: no such board or learned group")
            return solver.outline
        return marker_corners_in_marker(self.config.marker_length(target.marker_id))[None]

    def _detect(
        self, image: np.ndarray, camera: CameraModel, timestamp_ns: int, blurred: bool = False
    ) -> MarkerDetections:
        """Full-frame detection, or ROI tracking between full-frame searches (``[detector] roi``).

        Regions are searched only while every marker seen in the last ``[filter] memory_s`` was seen in
        the previous frame too. The whole frame is searched on the first frame, every ``roi_full_every``
        frames, after a frame size change, in every frame while a recently seen marker is missing (a
        marker lost to one blurred frame is looked for everywhere until it is back or forgotten), and
        again in the same frame whenever a region search misses a marker the previous frame had. So ROI
        tracking never finds fewer of the known markers than full-frame detection; a marker never seen
        before is found within ``roi_full_every`` frames. ``blurred``: the frame is motion-blurred (see
        :meth:`_blurred`), so it is not given the fast whole-frame search.
        """
        settings = self.config.detector
        size = (image.shape[1], image.shape[0])
        memory_ns = int(self.config.filter.memory_s * 1e9)
        self._seen = {i: seen for i, seen in self._seen.items() if timestamp_ns - seen[1] <= memory_ns}
        missing = any(i not in self._last_corners for i in self._seen)
        full = (
            not settings.roi
            or not self._last_corners
            or missing
            or self._frames_since_full + 1 >= settings.roi_full_every
            or size != self._last_size
        )
        detections = None
        if not full:
            moving = {i: c for i, c in self._before_corners.items() if i in self._last_corners}
            regions = plan_regions(self._last_corners, moving, size, settings.roi_margin, cells=self.detector.cells)
            area = sum((r.x1 - r.x0) * (r.y1 - r.y0) for r in regions)
            if area <= _MOST_OF_THE_FRAME * size[0] * size[1] or not self._fast_allowed(size, blurred):
                detections = self.detector.detect_regions(image, regions, camera)
                if not set(self._last_corners) <= set(detections.ids.tolist()):
                    detections = None  # a marker was missed: search everywhere
            # (else regions as large as most of the frame: the fast whole-frame search costs less)
        if detections is None:
            detections = self._search_whole_frame(image, camera, size, blurred)
            self._frames_since_full = 0
        else:
            self._frames_since_full += 1
            if self.config.detector.fast_search:
                self._frames_since_thorough += 1
        self._last_size = size
        self._before_corners = self._last_corners
        self._last_corners = {int(i): c for i, c in zip(detections.ids, detections.corners)}
        for marker_id, corners in self._last_corners.items():
            if self.config.tracks_marker(marker_id):  # (a stray id of no interest is not searched for)
                self._seen[marker_id] = (corners, timestamp_ns)
        return detections

    def _search_whole_frame(
        self, image: np.ndarray, camera: CameraModel, size: tuple[int, int], blurred: bool
    ) -> MarkerDetections:
        """A full-frame search: the fast one (:meth:`Detector.detect` ``fast``: big markers only) while ROI
        tracking may use it, else the thorough one, which finds markers of any size.

        Fast only while every marker seen in the last ``memory_s`` was at least ``FAST_MIN_SIDE_PX`` on its
        last sighting, on a frame of the same size that is not motion-blurred (one threshold can outline a
        smeared marker, corners many pixels off, that the thorough search rejects), and never for
        ``roi_full_every`` frames in a row (``[detector] fast_search``, off by default: see
        docs/architecture.md). A marker the previous frame had that the fast search misses is looked for
        again, thoroughly, in its region (as ROI tracking does). So no marker the previous frame had is
        lost, and a marker never seen before (or a small one coming back) is found within
        ``roi_full_every`` frames.
        """
        settings = self.config.detector
        if not self._fast_allowed(size, blurred):
            self._frames_since_thorough = 0
            return self.detector.detect(image, camera)
        self._frames_since_thorough += 1
        detections = self.detector.detect(image, camera, fast=True)
        found = set(detections.ids.tolist())
        lost = {i: c for i, c in self._last_corners.items() if i not in found}
        if not lost:
            return detections
        # (mostly markers really gone this frame, blurred or hidden: a region each costs little to make sure)
        rejected = self.detector.rejected
        moving = {i: c for i, c in self._before_corners.items() if i in lost}
        regions = plan_regions(lost, moving, size, settings.roi_margin, cells=self.detector.cells)
        again = self.detector.detect_regions(image, regions, camera, thorough=True)
        self.detector.rejected = (*rejected, *self.detector.rejected)
        new = ~np.isin(again.ids, detections.ids)
        if not new.any():
            return detections
        return MarkerDetections(
            np.concatenate([detections.ids, again.ids[new]]),
            np.concatenate([detections.corners, again.corners[new]]),
            np.union1d(detections.duplicated, again.duplicated),
        )

    def _fast_allowed(self, size: tuple[int, int], blurred: bool) -> bool:
        """May the next whole-frame search be the fast one (see :meth:`_search_whole_frame`)?"""
        settings = self.config.detector
        return (
            settings.roi
            and settings.fast_search
            and not blurred
            and size == self._last_size
            and bool(self._seen)
            and self._frames_since_thorough + 1 < settings.roi_full_every
            and all(mean_side(corners) >= FAST_MIN_SIDE_PX for corners, _ in self._seen.values())
        )

    def process(self, frame: Frame) -> FrameResult:
        """Track one frame (frames of one stream, in order): detect the markers (in regions around
        where they were, or the whole frame while any is missing), solve every marker and board
        (both IPPE solutions kept), and pass them through each target's flip filter.

        Returns the frame's :class:`FrameResult`: ``targets`` maps each :class:`~ar_anchor.targets.TargetId`
        with a pose this frame to its :class:`TargetResult` (state ``tracked``, ``ambiguous`` or
        ``predicted``), in :class:`~ar_anchor.targets.TargetId` order; ``failures`` says why markers
        seen got no pose; ``latency_ms`` the stage times. A frame that repeats the previous one's
        pixels (a 30 fps container carrying 12 fps content) returns the previous answer, marked
        ``repeated``: it is no new measurement.

        The same as ``track(detect(frame))``: the two halves may run in two threads, :meth:`detect` of
        a frame while :meth:`track` takes the one before (:func:`detected_ahead`), with the same results.
        """
        return self.track(self.detect(frame))

    def detect(self, frame: Frame) -> DetectedFrame:
        """The first stage of :meth:`process`: whether the frame repeats the last one or is motion-blurred,
        and its markers (detection state only: ROI regions, repeats, sharpness; see :meth:`track`).
        :class:`~ar_anchor.errors.FrameError` (a ValueError) for a frame that is not a valid :class:`Frame`
        (a non-finite timestamp, an image that is not a non-empty (H, W, 3) uint8 array): nothing changes."""
        check_frame(frame)
        if self.stills:
            self._reset_detection()
        fingerprint = _every_4th_pixel(frame.image)
        candidate = self._last_observed is not None and self._repeats(fingerprint)
        blurred = self._blurred(fingerprint)
        camera = self.camera_for(frame.size)
        t0 = time.perf_counter()
        detections = self._detect(frame.image, camera, frame.timestamp_ns, blurred)
        if candidate and self._last_observed is not None and _same_corners(detections, self._last_observed):
            detect_ms = (time.perf_counter() - t0) * 1e3
            return DetectedFrame(frame, camera, detections, blurred, self._detail, True, detect_ms)
        if self.config.pose.recover_markers:
            for solver in self.board_solvers:
                detections = self.detector.recover(
                    frame.image, detections, solver.cv_board, camera.camera_matrix, camera.dist_or_none
                )
        self._fingerprint, self._last_observed = fingerprint, detections
        return DetectedFrame(frame, camera, detections, blurred, self._detail, False, (time.perf_counter() - t0) * 1e3)

    def track(self, detected: DetectedFrame) -> FrameResult:
        """The rest of :meth:`process` for a frame :meth:`detect` took (frames in order): solve, filter,
        check against the frame, results."""
        if self.stills:
            self._reset_tracking()
        if detected.repeated and self._previous is not None:
            # a repeated frame (a 30 fps container carrying 12 fps content): the same content is no new
            # evidence; the last answer stands, with this frame's index and time
            return self._repeat(detected.frame, detected.detect_ms)
        result = self._process(detected)
        self._previous = result
        return result

    def _blurred(self, fingerprint: np.ndarray) -> bool:
        """Is this frame motion-blurred (a quick turn), not merely missing a marker? Sharpness is the
        Laplacian's variance of every 4th pixel over that of a half-size copy: blur takes the fine scale
        away first, while removing content (a marker out of view) lowers both alike. Blurred: below
        ``_BLUR_RATIO`` of its running typical value."""
        grey = cv2.cvtColor(fingerprint, cv2.COLOR_BGR2GRAY) if fingerprint.ndim == 3 else fingerprint
        grey = grey.astype(np.float32)
        self._detail = float(cv2.Laplacian(grey, cv2.CV_32F).var())
        coarse = float(cv2.Laplacian(cv2.pyrDown(grey), cv2.CV_32F).var()) if min(grey.shape[:2]) >= 16 else 0.0
        if coarse <= 1e-6:
            return False
        sharpness = self._detail / coarse
        typical = self._sharpness
        blurred = typical is not None and sharpness < self._BLUR_RATIO * typical
        if not blurred:
            self._sharpness = sharpness if typical is None else 0.9 * typical + 0.1 * sharpness
        return blurred

    def _repeats(self, fingerprint: np.ndarray) -> bool:
        """Might this be the last tracked frame's content again: every 4th pixel the same to within
        ``[filter] repeat_grey`` grey levels on average (a repeated frame re-encoded by a lossy codec is
        not bit-identical)? It is a repeat only if it also shows the same markers at the same corners
        (``_REPEAT_PX``): a slowly moving real video differs as little in its pixels, but not there."""
        previous = self._fingerprint
        if previous is None or previous.shape != fingerprint.shape:
            return False
        tolerance = self.config.filter.repeat_grey
        if tolerance <= 0:
            return bool(np.array_equal(previous, fingerprint))
        return float(cv2.absdiff(previous, fingerprint).mean()) < tolerance

    def _repeat(self, frame: Frame, detect_ms: float) -> FrameResult:
        """The last answer again for a repeated frame (``latency_ms`` holds only the detection it took
        to know: pose and filter did not run, and their statistics cover the frames where they did)."""
        assert self._previous is not None
        targets = {name: dataclasses.replace(t, events=()) for name, t in self._previous.targets.items()}
        return dataclasses.replace(
            self._previous,
            index=frame.index,
            timestamp_ns=frame.timestamp_ns,
            targets=targets,
            latency_ms={"detect_ms": detect_ms},
            repeated=True,
        )

    def _process(self, detected: DetectedFrame) -> FrameResult:
        """A new frame's trip after detection, one stage after the other: its corners taken back to the first
        row's time (rolling shutter), every marker and board solved, learned groups, the flip filter, the
        check that every output fits the frame, the result."""
        frame, camera, blurred = detected.frame, detected.camera, detected.blurred
        t1 = time.perf_counter()
        detections = self._at_first_row(detected.detections, frame)
        measured, failures = self._solve(detections, frame, camera)
        events, layouts = self._learn_groups(measured, failures, detections, frame, camera, blurred)
        t2 = time.perf_counter()
        targets = self._decide(measured, layouts, events, frame, camera, blurred)
        t3 = time.perf_counter()
        latency = {"detect_ms": detected.detect_ms, "pose_ms": (t2 - t1) * 1e3, "filter_ms": (t3 - t2) * 1e3}
        return FrameResult(
            frame.index,
            frame.timestamp_ns,
            detected.detections,  # (as seen: for the next search and the drawing)
            targets,
            tuple(failures),
            latency,
            camera,
            blurred=blurred,
            detail=detected.detail,
            measurements=measured,
            groups=layouts,
        )

    def _solve(
        self, detections: MarkerDetections, frame: Frame, camera: CameraModel
    ) -> tuple[dict[TargetId, MarkerPose | BoardPose], list[PoseFailure]]:
        """Every tracked marker's poses (one pass over the frame's arrays: :func:`.marker_poses.solve_markers`)
        and every configured board's; the failures say why a marker or board got none."""
        measured: dict[TargetId, MarkerPose | BoardPose] = {}
        failures: list[PoseFailure] = []
        wanted = np.array([self.config.tracks_marker(i) for i in detections.ids.tolist()], bool)
        ids = detections.ids[wanted]
        lengths = np.array([self.config.marker_length(i) for i in ids.tolist()], np.float64)
        max_px = self.config.pose.max_reproj_px
        for solved in solve_markers(ids, detections.corners[wanted], lengths, camera, max_px):
            if isinstance(solved, PoseFailure):
                failures.append(solved)
            else:
                measured[solved.target] = solved
        for solver in self.board_solvers:
            board = solver.solve(detections.ids, detections.corners, camera, max_px, image=frame.image)
            if isinstance(board, PoseFailure):
                failures.append(board)
            elif board is not None:
                measured[board.target] = board
        return measured, failures

    def _learn_groups(
        self,
        measured: dict[TargetId, MarkerPose | BoardPose],
        failures: list[PoseFailure],
        detections: MarkerDetections,
        frame: Frame,
        camera: CameraModel,
        blurred: bool,
    ) -> tuple[dict[TargetId, list[str]], dict[TargetId, GroupLayout]]:
        """Learned rigid groups (``[groups] learn``): this frame's evidence, then every group solved like a
        board (added to ``measured`` / ``failures``). Returns the groups' events and the layouts members may
        follow this frame."""
        events: dict[TargetId, list[str]] = {}
        if self.groups is None:
            return events, {}
        max_px = self.config.pose.max_reproj_px
        events = self.groups.learn(measured, camera)
        self._end_group_tracks()
        if self.config.filter.enabled:  # (before this frame's solve: it uses the layout refined there)
            for name in sorted(self.groups.changed & set(self.groups.groups)):
                events.setdefault(name, []).append(self._warm_group_track(name))
        for name, solved_group in self.groups.solve(
            detections.ids, detections.corners, camera, max_px, image=frame.image
        ).items():
            if isinstance(solved_group, PoseFailure):
                failures.append(solved_group)
            else:
                measured[name] = solved_group
        layouts = self.groups.layouts()
        if self.config.filter.enabled:  # (kept only for the catch-up above)
            self.groups.remember(frame.timestamp_ns, detections.ids, detections.corners, camera, max_px, blurred)
        return events, layouts

    def _decide(
        self,
        measured: dict[TargetId, MarkerPose | BoardPose],
        layouts: dict[TargetId, GroupLayout],
        events: dict[TargetId, list[str]],
        frame: Frame,
        camera: CameraModel,
        blurred: bool,
    ) -> dict[TargetId, TargetResult]:
        """Every target's output: the flip filter (without it, each frame's own best solution), members of
        settled groups, then the check that every output fits this frame and the end of a cut's tracks."""
        if self.config.filter.enabled:
            targets = self._filter(measured, frame, camera, blurred)
        else:
            targets = {name: self._raw_result(name, measured[name], camera) for name in TargetId.ordered(measured)}
        if self.groups is not None:
            targets = self._settle_groups(targets, measured, layouts, events, camera, frame.index)
        if self.config.filter.enabled:  # (without it every output is the frame's own best solution)
            targets = self._fit_to_frame(targets, measured, frame, camera, blurred)
            targets = self._after_a_cut(targets, frame.index)
            if self.groups is not None:  # (a refit may have called a disagreeing group tracked again)
                targets = doubt_layouts(targets, self._disagreeing(measured))
        return targets

    def _disagreeing(self, measured: dict[TargetId, MarkerPose | BoardPose]) -> set[TargetId]:
        """Learned groups whose joint solve this frame saw two members or more but found fewer than two that
        agree with the layout (:func:`~.groups.disagrees_with_layout`: swapped or moved members)."""
        configured = {solver.target for solver in self.board_solvers}
        return {
            name
            for name, solved in measured.items()
            if isinstance(solved, BoardPose) and name not in configured and is_learned_group(name)
            and disagrees_with_layout(solved)
        }  # fmt: skip

    def _at_first_row(self, detections: MarkerDetections, frame: Frame) -> MarkerDetections:
        """``detections`` with every corner taken back to the frame's first-row time, for a rolling shutter
        (``[pose] rolling_shutter_s``, the readout time from the first row to the last; 0: unchanged). A
        corner on row ``y`` was exposed ``y / height * readout`` after the first row, while the camera moved:
        each corner moves back by its image velocity (its shift since the last frame processed, over the
        time between them: per corner, since a turning marker's corners move apart) times that delay. A
        marker not seen in that frame, one whose corners did not move as one square (:func:`_jumped`: a
        detection that jumped, whose velocity would be made of the jump), the first frame, or one after a
        gap of more than ``restart_gap_s`` is left as detected. Without this, a hand-held camera's pose is
        a mix of moments that varies with its motion: sheared markers, and the main jitter of a joint
        pose far away (docs/tracking-and-states.md)."""
        readout = self.config.pose.rolling_shutter_s
        now = {int(i): c.copy() for i, c in zip(detections.ids.tolist(), detections.corners)}
        previous, self._shutter_previous = self._shutter_previous, (frame.timestamp_ns, now)
        if readout <= 0 or previous is None or not now:
            return detections
        then_ns, before = previous
        dt = (frame.timestamp_ns - then_ns) * 1e-9
        if not 0 < dt <= max(self.config.filter.restart_gap_s, 1e-9):
            return detections
        if readout > dt * 1.05 and not self._shutter_warned:  # a camera reads its frame out within the frame
            self._shutter_warned = True
            log.warning(
                "[pose] rolling_shutter_s = %g s is longer than the time between frames (%.3g s): no camera reads "
                "out slower than its frame rate; is it the readout of this camera, in seconds?",
                readout,
                dt,
            )
        height = frame.image.shape[0]
        corners = detections.corners.copy()
        for k, marker_id in enumerate(detections.ids.tolist()):
            earlier = before.get(int(marker_id))
            if earlier is None:
                continue
            if _jumped(earlier, corners[k]):
                continue  # not the same square moved: a detection that jumped (this one or the last)
            velocity = (corners[k] - earlier) / dt  # px/s, per corner (a turning marker's corners move apart)
            delay = corners[k][:, 1:2] / height * readout  # s after the first row, per corner
            corners[k] = corners[k] - velocity * delay
        return dataclasses.replace(detections, corners=corners)

    def _warm_group_track(self, name: TargetId) -> str:
        """A group formed or grown this frame starts from the frames the learner kept (the last
        ``[filter] evidence_window_s``), not from nothing: a planar group's layout is first refined from
        them (:meth:`~.groups.GroupLearner.refine_from_past`), then its flip filter is replayed over its
        joint pose in each (:meth:`~.groups.GroupLearner.past_solves`). Far away, a layout straight from
        pair evidence tips the flip evidence the wrong way, and a filter started now shows its first
        frames' coin-toss pick, where the frames before already hold the evidence. Returns the event's text."""
        assert self.groups is not None
        refined = self.groups.refine_from_past(name)
        track: TargetTrack | None = None
        frames = 0
        for past, solved in self.groups.past_solves(name):
            if track is None and solved is None:
                continue
            if track is None:
                assert solved is not None
                track = TargetTrack(self.config.filter, solved.points_in_target)
            track.update(solved, past.timestamp_ns, past.camera, blurred=past.blurred)
            frames += solved is not None
        self.tracks.pop(name, None)
        layout = f"its layout refined from {refined} earlier frames; " if refined else ""
        if track is None:
            return f"{layout}its flip filter starts now (no earlier frame of its markers kept)"
        self.tracks[name] = track
        decided = "decided" if track.committed is not None else "undecided"
        return f"{layout}its flip filter replayed over the {frames} earlier frames that solve it (flip {decided})"

    def _end_group_tracks(self) -> None:
        """Forget the tracks of learned groups that are gone (merged into another, or dissolved)."""
        assert self.groups is not None
        configured = {solver.target for solver in self.board_solvers}
        for name in [n for n in self.tracks if n.is_board and n not in configured and n not in self.groups.groups]:
            del self.tracks[name]

    def _settle_groups(
        self,
        targets: dict[TargetId, TargetResult],
        measured: dict[TargetId, MarkerPose | BoardPose],
        layouts: dict[TargetId, GroupLayout],
        events: dict[TargetId, list[str]],
        camera: CameraModel,
        index: int = -1,
    ) -> dict[TargetId, TargetResult]:
        """After the filter: members of a tracked group take its pose (:func:`members_from_groups`); the
        groups count agreements (members leave, groups dissolve: a dissolved group's track ends); every
        group event goes on its target's result (or is logged only, when that target has none)."""
        assert self.groups is not None
        disagreeing = self._disagreeing(measured)
        targets = doubt_layouts(targets, disagreeing)  # (before members follow the group's state)
        for name in sorted(disagreeing):
            solved = measured[name]
            assert isinstance(solved, BoardPose)
            seen = len(solved.markers_used) + len(solved.outlier_ids)
            events.setdefault(name, []).append(
                f"{len(solved.markers_used)} of the {seen} members seen agree with its layout (moved or swapped?): "
                "not tracked"
            )
        targets = members_from_groups(targets, layouts, camera, as_member)
        tracked = {name for name, target in targets.items() if target.state is TrackState.TRACKED}
        for name, messages in self.groups.settle(measured, tracked if self.config.filter.enabled else None).items():
            events.setdefault(name, []).extend(messages)
        self._end_group_tracks()
        for name, messages in events.items():
            for message in messages:
                log.info("frame %d: %s: %s", index, name, message)
            if name in targets:
                extra = tuple(TrackEvent("group", message) for message in messages)
                targets[name] = dataclasses.replace(targets[name], events=(*targets[name].events, *extra))
        return targets

    def _fit_to_frame(
        self,
        targets: dict[TargetId, TargetResult],
        measured: dict[TargetId, MarkerPose | BoardPose],
        frame: Frame,
        camera: CameraModel,
        blurred: bool,
    ) -> dict[TargetId, TargetResult]:
        """Every measured output checked against its own frame (:func:`~.fit.refit`): one that misses the
        frame's corners is moved just enough to fit (a spike held back, a lag) or, held over a cut or on the
        other solution, replaced by the frame's own best solution, and the target's track restarts from it."""
        for name, target in targets.items():
            solved = measured.get(name)
            fitted = (
                None
                if solved is None
                else refit(target, solved, camera, self.config.filter, self.config.pose.fit_margin_px)
            )
            if fitted is None:
                continue
            assert solved is not None
            replaced, restart = fitted
            log.info("frame %d: %s: %s", frame.index, name, replaced.events[-1].message)
            track = self.tracks.get(name)
            if restart and track is not None:
                started = track.restart_from(solved, frame.timestamp_ns, camera, blurred=blurred)
                replaced = dataclasses.replace(replaced, events=(*replaced.events, *started))
            targets[name] = replaced
        return targets

    def _after_a_cut(self, targets: dict[TargetId, TargetResult], index: int) -> dict[TargetId, TargetResult]:
        """A cut (every target measured this frame whose track went on from earlier frames jumped: see
        :meth:`~.filtering.TargetTrack.update_steps`, event ``jump``; at least one): the tracks of the targets
        not seen in it end too, and none is predicted: their poses belong to the scene before the cut."""
        measured = [target for target in targets.values() if target.measured]
        jumped = [t for t in measured if any(event.kind == "jump" for event in t.events)]
        went_on = [t for t in measured if not any(event.kind in SEGMENT_STARTS for event in t.events)]
        if not jumped or went_on:
            return targets
        ended = sorted(name for name in self.tracks if name not in targets or not targets[name].measured)
        for name in ended:
            del self.tracks[name]
        if ended:
            log.info(
                "frame %d: a cut (every target seen jumped): the tracks of %s end", index, ", ".join(map(str, ended))
            )
        return {name: target for name, target in targets.items() if target.measured}

    def _filter(
        self, measured: dict[TargetId, MarkerPose | BoardPose], frame: Frame, camera: CameraModel, blurred: bool
    ) -> dict[TargetId, TargetResult]:
        """Every track's update (:func:`update_tracks`), as each target's :class:`TargetResult`."""
        targets: dict[TargetId, TargetResult] = {}
        updates = update_tracks(self.tracks, measured, frame.timestamp_ns, camera, blurred, self.config.filter)
        for name, update in updates.items():
            for event in update.events if update is not None else ():
                log.info("frame %d: %s: %s", frame.index, name, event.message)
            if update is None:  # nothing to publish: a gap too long to predict through, or lost for good
                continue
            solved = measured.get(name)
            targets[name] = self._result(
                name,
                update.state,
                update.pose,
                solved,
                camera,
                branch_poses=update.hypotheses,
                branch=update.branch,
                run_frames=update.run_frames,
                committed=update.committed,
                doubts=update.doubts,
                evidence_px=update.evidence,
                events=tuple(update.events),
            )
        return targets

    def _raw_result(self, name: TargetId, solved: MarkerPose | BoardPose, camera: CameraModel) -> TargetResult:
        """``--no-filter``: the lower-error solution as it is; ``tracked`` only when this frame alone
        decides the planar flip (one valid solution, or the other far worse: see
        :func:`~ar_anchor.track.filtering.decided_alone`), else ``ambiguous``."""
        sure = decided_alone(solved.hypotheses, self.config.filter, len(solved.points_in_target))
        return self._result(
            name, TrackState.TRACKED if sure else TrackState.AMBIGUOUS, solved.best.pose, solved, camera
        )

    def _result(
        self,
        name: TargetId,
        state: TrackState,
        pose: Pose,
        solved: MarkerPose | BoardPose | None,
        camera: CameraModel,
        **extra,
    ) -> TargetResult:
        board = isinstance(solved, BoardPose) or name.is_board
        if not name.is_board:
            length = self.config.marker_length(name.marker_id)
        else:
            solver = self._board_solver(name)
            length = solver.marker_length_m if solver is not None else math.nan
        if solved is None:
            return TargetResult(
                target=name,
                state=state,
                pose=pose,
                raw=None,
                reproj_px=math.nan,
                ambiguity=math.nan,
                length_m=length,
                outline_in_target=self.outline(name),
                **extra,
            )
        return TargetResult(
            target=name,
            state=state,
            pose=pose,
            raw=solved.best.pose,
            reproj_px=reprojection_rms(pose, solved.points_in_target, solved.points_in_image, camera),
            ambiguity=math.nan if board else _finite_or_nan(solved.ambiguity),
            length_m=length,
            hypotheses=solved.hypotheses,
            corners_in_image=solved.corners_in_image.reshape(-1, 4, 2),
            outline_in_target=self.outline(name),
            markers_used=solved.markers_used if isinstance(solved, BoardPose) else (solved.marker_id,),
            outlier_ids=solved.outlier_ids if isinstance(solved, BoardPose) else (),
            inliers=len(solved.points_in_target),
            outlier_points_in_image=solved.outlier_points_in_image if isinstance(solved, BoardPose) else None,
            **extra,
        )

    def reset(self) -> None:
        """Forget everything learned from earlier frames (e.g. after a cut in the video): the tracks
        with their flip evidence, where markers were (ROI search), repeats and sharpness. The next
        frame is processed exactly as a new tracker would."""
        self._reset_detection()
        self._reset_tracking()

    def _reset_detection(self) -> None:
        """:meth:`reset`'s part that :meth:`detect` keeps: where markers were, repeats, sharpness."""
        self._fingerprint = self._last_observed = None
        self._sharpness = None
        self._last_corners, self._before_corners, self._seen = {}, {}, {}
        self._frames_since_full = self._frames_since_thorough = 0
        self._last_size = None

    def _reset_tracking(self) -> None:
        """:meth:`reset`'s part that :meth:`track` keeps: the tracks, the last answer, learned groups."""
        self.tracks.clear()
        self._previous = None
        self._shutter_previous = None
        if self.groups is not None:
            self.groups = GroupLearner(self.config)


def as_member(target: TargetResult, pose: Pose, reproj_px: float, state: TrackState) -> TargetResult:
    """A group member's result with its group's pose (see :func:`~.groups.members_from_groups`)."""
    return dataclasses.replace(target, pose=pose, state=state, reproj_px=reproj_px)


def _every_4th_pixel(image: np.ndarray) -> np.ndarray:
    """``image[::4, ::4]``, contiguous: by OpenCV's nearest-neighbour resize where that picks the same pixels
    (sides divisible by 4: a third of numpy's strided copy's time, without the GIL), else by numpy."""
    height, width = image.shape[:2]
    if height % 4 or width % 4 or height < 4 or width < 4:
        return np.ascontiguousarray(image[::4, ::4])
    return cv2.resize(image, (width // 4, height // 4), interpolation=cv2.INTER_NEAREST)


def update_tracks(
    tracks: dict[TargetId, TargetTrack],
    measured: dict[TargetId, MarkerPose | BoardPose],
    timestamp_ns: int,
    camera: CameraModel,
    blurred: bool,
    config: FilterConfig,
) -> dict[TargetId, TrackUpdate | None]:
    """Every track's update for one frame (a track started for a target measured for the first time; one
    lost for good removed), in :class:`TargetId` order, the numeric steps taken for all targets at once:
    the pose covariances (:func:`~.filtering.unit_covariances_of`) and the smoothers' Kalman steps (each
    track's update runs as steps, :meth:`~.filtering.TargetTrack.update_steps`, paused while a
    :class:`KalmanBatch` takes the steps they queued). The live tracker's, and the offline replay's
    backward pass's (:mod:`ar_anchor.track.offline`)."""
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
            solved, timestamp_ns, camera, blurred=blurred, unit_covariances=unit, batch=batch
        )
    updates = run_filter_steps(steps, batch)
    for name, update in updates.items():
        if update is None and not tracks[name].alive:
            del tracks[name]
    return {name: updates[name] for name in steps}


def run_filter_steps(steps: dict[TargetId, Generator[None, None, Any]], batch: KalmanBatch) -> dict[TargetId, Any]:
    """Advance every generator a step at a time, taking ``batch``'s queued steps after each round; their
    return values, by name."""
    results: dict[TargetId, Any] = {}
    pending = dict(steps)
    while pending:
        for name, generator in list(pending.items()):
            try:
                next(generator)
            except StopIteration as done:
                results[name] = done.value
                del pending[name]
        batch.run()
    return results


_MOST_OF_THE_FRAME = 0.4  # regions covering more than this share of the frame: a fast whole-frame search instead
_REPEAT_PX = 0.25  # corners that moved less than this (every one) are a repeated frame's


def _same_corners(now: MarkerDetections, before: MarkerDetections) -> bool:
    """Does every marker found now sit where it was found before (each corner within ``_REPEAT_PX``)?
    (A marker the repeat lost to compression noise changes nothing; one found only now does.)"""
    if len(now.ids) == 0:
        return False
    where = {int(i): c for i, c in zip(before.ids, before.corners)}
    return all(
        int(i) in where and float(np.abs(c - where[int(i)]).max()) < _REPEAT_PX for i, c in zip(now.ids, now.corners)
    )


_JUMP_SHARE = 0.05  # corners that moved this share of the marker's side (at least 1 px) otherwise than ...


def _jumped(before: np.ndarray, now: np.ndarray) -> bool:
    """Did a marker's corners (4, 2) move from ``before`` to ``now`` otherwise than one square turned,
    scaled and shifted in the image (a similarity fitted by least squares), by more than
    :data:`_JUMP_SHARE` of its side or 1 px? Then one of the two detections jumped (or is not finite)."""
    z0 = before[:, 0] + 1j * before[:, 1]
    z1 = now[:, 0] + 1j * now[:, 1]
    c0, c1 = z0.mean(), z1.mean()
    spread = float(np.sum(np.abs(z0 - c0) ** 2))
    if not spread > 0 or not np.all(np.isfinite(z1)):
        return True
    a = np.sum((z1 - c1) * np.conj(z0 - c0)) / spread
    off = float(np.abs(z1 - (a * (z0 - c0) + c1)).max())
    side = float(np.abs(np.diff(np.append(z1, z1[0]))).mean())
    return not off <= max(1.0, _JUMP_SHARE * side)


def _finite_or_nan(value: float) -> float:
    return value if math.isfinite(value) else math.nan
