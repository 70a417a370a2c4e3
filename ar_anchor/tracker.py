"""One frame's trip through the pipeline: detect -> solve -> filter -> :class:`FrameResult`.

With the filter on (the default), each marker's output pose comes from its
:class:`~ar_anchor.filtering.TargetTrack` (flip resolved with evidence over time, smoothed,
predicted through short gaps). With it off (``--no-filter``), the output is the plain per-frame
lower-error IPPE solution, state ``tracked``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .camera import CameraModel
from .config import TrackerConfig
from .detection import Detector, MarkerDetections
from .filtering import TargetTrack
from .geometry import Pose, marker_corners_in_marker
from .pose import MarkerPose, PoseFailure, PoseHypothesis, reprojection_rms, solve_marker
from .sources.base import Frame

__all__ = ["FrameResult", "TargetResult", "Tracker"]

log = logging.getLogger(__name__)

STATES = ("tracked", "ambiguous", "predicted")


@dataclass(frozen=True)
class TargetResult:
    """What the tracker says about one target (``marker:<id>`` or ``board:<name>``) in one frame.

    Attributes
    ----------
    pose : output ``camera_from_target`` (what is rendered).
    raw : this frame's plain per-frame solution before filtering (None when not measured).
    state : ``tracked`` | ``ambiguous`` | ``predicted``.
    reproj_px : RMS reprojection error of ``pose`` on this frame's corners (NaN when predicted).
    ambiguity : error ratio worse / better of the two IPPE solutions (NaN for boards or unknown).
    hypotheses : the validated per-frame solutions, lower error first.
    corners_in_image : (N, 4, 2) corners used this frame.
    """

    target: str
    state: str
    pose: Pose
    raw: Pose | None
    reproj_px: float
    ambiguity: float
    length_m: float
    hypotheses: tuple[PoseHypothesis, ...] = ()
    corners_in_image: np.ndarray | None = None
    branch_poses: tuple[Pose | None, ...] = ()  # this frame's solution on each filter branch
    evidence_px: float = math.nan  # signed flip evidence (+: branch 0), see filtering.py
    events: tuple[str, ...] = ()  # filter events this frame (commits, switches, rejected flips, resets)

    def __post_init__(self) -> None:
        if self.state not in STATES:
            raise ValueError(f"state must be one of {STATES}, got {self.state!r}")

    @property
    def measured(self) -> bool:
        return self.state != "predicted"


@dataclass(frozen=True)
class FrameResult:
    """Everything the tracker found in one frame."""

    index: int
    timestamp_ns: int
    detections: MarkerDetections
    targets: dict[str, TargetResult]
    failures: tuple[PoseFailure, ...] = ()
    latency_ms: dict[str, float] = field(default_factory=dict)
    camera: CameraModel | None = None


class Tracker:
    """Stateful per-stream tracker. Feed frames in order to :meth:`process`.

    Example
    -------
    >>> tracker = Tracker(load_config(), CameraModel.from_yaml("configs/camera_synthetic.yml"))
    >>> result = tracker.process(frame)        # doctest: +SKIP
    >>> result.targets["marker:0"].pose.tvec   # doctest: +SKIP
    """

    def __init__(self, config: TrackerConfig, camera: CameraModel) -> None:
        self.config = config
        self.camera = camera
        self.detector = Detector(config.detector)
        self._cameras: dict[tuple[int, int], CameraModel] = {camera.size: camera}
        self.tracks: dict[str, TargetTrack] = {}

    def camera_for(self, size: tuple[int, int]) -> CameraModel:
        """The calibration scaled to a frame size (warns once per new size)."""
        if size not in self._cameras:
            self._cameras[size] = self.camera.scaled_to(*size)
        return self._cameras[size]

    def reports(self, target: str) -> bool:
        """Does this tracker output poses for ``target`` (``marker:<id>`` / ``board:<name>``)?

        Boards are detected through their markers; their joint pose is not solved yet.
        """
        kind, _, ident = target.partition(":")
        return kind == "marker" and ident.isdigit() and self.config.tracks_marker(int(ident))

    def process(self, frame: Frame) -> FrameResult:
        camera = self.camera_for(frame.size)
        t0 = time.perf_counter()
        detections = self.detector.detect(frame.image)
        t1 = time.perf_counter()
        measured: dict[str, MarkerPose] = {}
        failures: list[PoseFailure] = []
        for marker_id, corners in zip(detections.ids.tolist(), detections.corners):
            if not self.config.tracks_marker(marker_id):
                continue
            solved = solve_marker(
                marker_id, corners, self.config.marker_length(marker_id), camera, self.config.pose.max_reproj_px
            )
            if isinstance(solved, PoseFailure):
                failures.append(solved)
                continue
            measured[f"marker:{marker_id}"] = solved
        t2 = time.perf_counter()
        if self.config.filter.enabled:
            targets = self._filter(measured, frame.timestamp_ns, camera)
        else:
            targets = {name: _marker_result(solved) for name, solved in measured.items()}
        t3 = time.perf_counter()
        latency = {"detect_ms": (t1 - t0) * 1e3, "pose_ms": (t2 - t1) * 1e3, "filter_ms": (t3 - t2) * 1e3}
        return FrameResult(frame.index, frame.timestamp_ns, detections, targets, tuple(failures), latency, camera)

    def _filter(
        self, measured: dict[str, MarkerPose], timestamp_ns: int, camera: CameraModel
    ) -> dict[str, TargetResult]:
        targets: dict[str, TargetResult] = {}
        for name in sorted(set(measured) | set(self.tracks), key=_marker_order):
            solved = measured.get(name)
            track = self.tracks.get(name)
            if track is None:
                assert solved is not None
                track = self.tracks[name] = TargetTrack(self.config.filter, marker_corners_in_marker(solved.length_m))
            update = track.update(solved, timestamp_ns, camera)
            for event in update.events if update is not None else ():
                log.info("%s: %s", name, event.message)
            if update is None:  # lost for too long: the track is reset
                del self.tracks[name]
                continue
            length = solved.length_m if solved is not None else self.config.marker_length(int(name.split(":")[1]))
            targets[name] = TargetResult(
                target=name,
                state=update.state,
                pose=update.pose,
                raw=solved.best.pose if solved is not None else None,
                reproj_px=(
                    reprojection_rms(update.pose, track.points, solved.corners_in_image, camera)
                    if solved is not None
                    else math.nan
                ),
                ambiguity=solved.ambiguity if solved is not None else math.nan,
                length_m=length,
                hypotheses=solved.hypotheses if solved is not None else (),
                corners_in_image=solved.corners_in_image[None] if solved is not None else None,
                branch_poses=update.hypotheses,
                evidence_px=update.evidence,
                events=tuple(f"{e.kind}: {e.message}" for e in update.events),
            )
        return targets

    def reset(self) -> None:
        """Forget all tracks (e.g. after a cut in the video)."""
        self.tracks.clear()


def _marker_order(name: str) -> tuple[str, int]:
    kind, _, ident = name.partition(":")
    return kind, int(ident) if ident.isdigit() else -1


def _marker_result(solved: MarkerPose) -> TargetResult:
    best = solved.best
    return TargetResult(
        target=f"marker:{solved.marker_id}",
        state="tracked",
        pose=best.pose,
        raw=best.pose,
        reproj_px=best.reproj_px,
        ambiguity=solved.ambiguity if math.isfinite(solved.ambiguity) else math.nan,
        length_m=solved.length_m,
        hypotheses=solved.hypotheses,
        corners_in_image=solved.corners_in_image[None],
    )
