"""What the tracker hands on, frame by frame: a frame after detection (:class:`DetectedFrame`, what
:meth:`Tracker.detect <ar_anchor.track.tracker.Tracker.detect>` passes to
:meth:`Tracker.track <ar_anchor.track.tracker.Tracker.track>`), and the results (:class:`FrameResult`, one per
frame, with a :class:`TargetResult` per target), which the offline replay, the overlay, the recorder and the
outputs read; :func:`as_member`, a learned group's member given its group's pose.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import CameraModel
from ..geometry import Pose
from ..sources.base import Frame
from ..targets import TargetId, TrackState
from .detection import MarkerDetections
from .filtering import TrackEvent
from .groups import GroupLayout
from .pose import BoardPose, MarkerPose, PoseFailure, PoseHypothesis

__all__ = ["DetectedFrame", "FrameResult", "TargetResult", "as_member"]


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
    blurred: bool  # motion-blurred (see MarkerSearch._blurred, search.py)
    detail: float  # the fine-scale contrast (FrameResult.detail)
    repeated: bool  # the last new frame's pixels and markers again: its answer stands
    detect_ms: float


def as_member(target: TargetResult, pose: Pose, reproj_px: float, state: TrackState) -> TargetResult:
    """A group member's result with its group's pose (see :func:`~.groups.members_from_groups`)."""
    return dataclasses.replace(target, pose=pose, state=state, reproj_px=reproj_px)
