"""One frame's trip through the pipeline: detect -> solve -> filter -> :class:`FrameResult`, run by
:class:`Tracker`, stage after stage: the markers looked for (:mod:`.search`), the rolling shutter undone
(:mod:`.shutter`), every marker and board solved (:mod:`.marker_poses`, :mod:`.pose`), learned groups
(:mod:`.groups`), each target's track (:mod:`.tracks`), the results (:mod:`.results`).

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

import numpy as np

from ..camera import CameraModel
from ..config import TrackerConfig
from ..geometry import Pose, marker_corners_in_marker
from ..sources.base import Frame, check_frame
from ..targets import TargetId, TrackState
from .detection import Detector, MarkerDetections
from .filtering import TargetTrack, TrackEvent, decided_alone
from .groups import (
    GroupLayout,
    GroupLearner,
    disagrees_with_layout,
    doubt_layouts,
    is_learned_group,
    members_from_groups,
)
from .marker_poses import solve_markers
from .pose import BoardPose, BoardSolver, MarkerPose, PoseFailure, reprojection_rms
from .results import DetectedFrame, FrameResult, TargetResult, as_member
from .search import MarkerSearch
from .search import _every_4th_pixel as _every_4th_pixel  # (its home is .search)
from .shutter import RollingShutter
from .shutter import _jumped as _jumped  # (its home is .shutter)
from .tracks import end_at_a_cut, end_group_tracks, fit_to_frame, update_tracks, warm_group_track

__all__ = ["DetectedFrame", "FrameResult", "TargetResult", "Tracker"]

log = logging.getLogger(__name__)


class Tracker:
    """Stateful per-stream tracker. Feed frames in order to :meth:`process`. ``stills``: the frames are
    independent photos, each processed alone (as by a new tracker: nothing carried from one to the next).

    Example
    -------
    >>> from ar_anchor import SyntheticSource, demo_scene
    >>> from ar_anchor.config import demo_config
    >>> config, camera = demo_config(), CameraModel.default_synthetic()
    >>> tracker = Tracker(config, camera)
    >>> for frame in SyntheticSource(demo_scene(config, camera, frames=1)):
    ...     result = tracker.process(frame)
    >>> list(result.targets)[:3]
    ['board:desk', 'marker:0', 'marker:7']
    >>> result.targets[TargetId.marker(0)].state
    <TrackState.TRACKED: 'tracked'>
    """

    def __init__(self, config: TrackerConfig, camera: CameraModel, *, stills: bool = False) -> None:
        self.config = config
        # independent stills (photos that may be unrelated): each frame processed as by a new tracker
        self.stills = stills
        self.camera = camera
        self._search = MarkerSearch(config, Detector(config.detector))  # (the detection stage's state)
        self._cameras: dict[tuple[int, int], CameraModel] = {camera.size: camera}
        self.tracks: dict[TargetId, TargetTrack] = {}
        self.board_solvers = [BoardSolver(board, config.pose.board_inlier_px) for board in config.boards]
        self.groups = GroupLearner(config) if config.groups.learn else None
        self._previous: FrameResult | None = None
        self._shutter = RollingShutter(config)

    @property
    def detector(self) -> Detector:
        """The marker detector (its search's: :class:`~.search.MarkerSearch`)."""
        return self._search.detector

    @detector.setter
    def detector(self, detector: Detector) -> None:
        self._search.detector = detector

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
        and its markers (detection state only: ROI regions, repeats, sharpness; see :meth:`track` and
        :class:`~.search.MarkerSearch`). :class:`~ar_anchor.errors.FrameError` (a ValueError) for a frame that
        is not a valid :class:`Frame` (a non-finite timestamp, an image that is not a non-empty (H, W, 3) uint8
        array): nothing changes."""
        check_frame(frame)
        if self.stills:
            self._search.reset()
        return self._search.look(frame, self.camera_for(frame.size), self.board_solvers)

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
        detections = self._shutter.to_first_row(detected.detections, frame)
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
        end_group_tracks(self.tracks, self.groups, self._configured_boards())
        if self.config.filter.enabled:  # (before this frame's solve: it uses the layout refined there)
            for name in sorted(self.groups.changed & set(self.groups.groups)):
                events.setdefault(name, []).append(warm_group_track(self.tracks, self.groups, name, self.config.filter))
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
            targets = fit_to_frame(self.tracks, targets, measured, frame, camera, blurred, self.config)
            targets = end_at_a_cut(self.tracks, targets, frame.index)
            if self.groups is not None:  # (a refit may have called a disagreeing group tracked again)
                targets = doubt_layouts(targets, self._disagreeing(measured))
        return targets

    def _disagreeing(self, measured: dict[TargetId, MarkerPose | BoardPose]) -> set[TargetId]:
        """Learned groups whose joint solve this frame saw two members or more but found fewer than two that
        agree with the layout (:func:`~.groups.disagrees_with_layout`: swapped or moved members)."""
        configured = self._configured_boards()
        return {
            name
            for name, solved in measured.items()
            if isinstance(solved, BoardPose) and name not in configured and is_learned_group(name)
            and disagrees_with_layout(solved)
        }  # fmt: skip

    def _configured_boards(self) -> set[TargetId]:
        """The configured boards' names (not learned groups)."""
        return {solver.target for solver in self.board_solvers}

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
        end_group_tracks(self.tracks, self.groups, self._configured_boards())
        for name, messages in events.items():
            for message in messages:
                log.info("frame %d: %s: %s", index, name, message)
            if name in targets:
                extra = tuple(TrackEvent("group", message) for message in messages)
                targets[name] = dataclasses.replace(targets[name], events=(*targets[name].events, *extra))
        return targets

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
        self._search.reset()
        self._reset_tracking()

    def _reset_tracking(self) -> None:
        """:meth:`reset`'s part that :meth:`track` keeps: the tracks, the last answer, learned groups."""
        self.tracks.clear()
        self._previous = None
        self._shutter.forget()
        if self.groups is not None:
            self.groups = GroupLearner(self.config)


def _finite_or_nan(value: float) -> float:
    return value if math.isfinite(value) else math.nan
