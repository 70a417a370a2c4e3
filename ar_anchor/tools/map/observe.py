"""Frames to observations: every considered frame of every input (video file, image folder or glob) is
searched for markers of the one dictionary with the project's :class:`~ar_anchor.track.detection.Detector`
(edge-fitted corners), and each marker gets both IPPE solutions (:func:`~ar_anchor.track.pose.solve_marker`).

A frame showing fewer than two markers says nothing about where markers sit relative to each other, so it
is counted but not kept.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ...camera import CameraModel
from ...config import DetectorConfig
from ...errors import CameraError, SourceError, printable
from ...track.detection import Detector
from ...track.marker_poses import solve_markers
from ...track.pose import MarkerPose
from .model import FrameObservations

__all__ = ["Observed", "Progress", "observe_sources"]

log = logging.getLogger(__name__)

Progress = Callable[[str], None]
_PROGRESS_EVERY_S = 2.0


@dataclass
class Observed:
    """What the inputs showed: the kept frames (two markers or more) and counts for the report.

    ``cameras``: the camera per input (scaled to its resolution); ``markers_seen``: id -> frames showing it
    (kept or not); ``frames_read`` / ``frames_considered``: read from the inputs, and searched (``--step``).
    """

    frames: list[FrameObservations] = field(default_factory=list)
    cameras: list[CameraModel] = field(default_factory=list)
    sizes: list[tuple[int, int]] = field(default_factory=list)
    frames_read: int = 0
    frames_considered: int = 0
    frames_with_markers: int = 0
    detections: int = 0
    pose_failures: int = 0
    markers_seen: Counter[int] = field(default_factory=Counter)


def observe_sources(
    sources: Sequence[str],
    camera: CameraModel,
    dictionary: str,
    length_m: float,
    *,
    step: int = 1,
    max_frames: int | None = None,
    progress: Progress | None = None,
) -> Observed:
    """Detect markers in every ``step``-th frame of each input (at most ``max_frames`` considered in all).

    ``camera`` is scaled to each input's resolution (a different aspect ratio is a
    :class:`~ar_anchor.errors.CameraError` naming the input). An input that cannot be opened is a
    :class:`~ar_anchor.errors.SourceError` naming it.
    """
    from ...sources import open_source

    detector = Detector(DetectorConfig(dictionary=dictionary))
    observed = Observed()
    last_report = time.monotonic()
    for number, spec in enumerate(sources):
        if max_frames is not None and observed.frames_considered >= max_frames:
            break
        try:
            opened = open_source(spec, live=False)
        except SourceError as err:
            message = str(err)
            raise SourceError(message if str(spec) in message else f"{printable(spec)}: {message}") from None
        with opened as frames:
            try:
                source_camera = camera.scaled_to(*frames.resolution)
            except CameraError as err:
                raise CameraError(f"--camera for {printable(spec)}: {err}") from None
            observed.cameras.append(source_camera)
            observed.sizes.append(tuple(frames.resolution))
            count = frames.info.frame_count
            for frame in frames:
                observed.frames_read += 1
                if frame.index % step:
                    continue
                if max_frames is not None and observed.frames_considered >= max_frames:
                    break
                observed.frames_considered += 1
                kept = _observe(detector, frame.image, source_camera, length_m, number, frame.index, observed)
                if kept is not None:
                    observed.frames.append(kept)
                if progress is not None and time.monotonic() - last_report > _PROGRESS_EVERY_S:
                    last_report = time.monotonic()
                    total = f"/{math.ceil(count / step)}" if count else ""
                    progress(
                        f"{printable(spec)}: {observed.frames_considered}{total} frames searched, "
                        f"{len(observed.frames)} with two markers or more, {len(observed.markers_seen)} ids"
                    )
    return observed


def _observe(
    detector: Detector,
    image: np.ndarray,
    camera: CameraModel,
    length_m: float,
    source: int,
    index: int,
    observed: Observed,
) -> FrameObservations | None:
    """One frame's markers with their IPPE solutions (all solved in one call, as the tracker solves them); None
    when fewer than two have a pose."""
    detections = detector.detect(image, camera)
    if len(detections) == 0:
        return None
    observed.frames_with_markers += 1
    observed.detections += len(detections)
    ids, corners, hypotheses, ambiguity = [], [], [], []
    lengths = np.full(len(detections), length_m)
    for marker_id, marker_corners, solved in zip(
        detections.ids.tolist(), detections.corners, solve_markers(detections.ids, detections.corners, lengths, camera)
    ):
        observed.markers_seen[int(marker_id)] += 1
        if not isinstance(solved, MarkerPose):
            observed.pose_failures += 1
            continue
        ids.append(int(marker_id))
        corners.append(np.asarray(marker_corners, np.float64))
        hypotheses.append(tuple(h.pose for h in solved.hypotheses))
        ambiguity.append(solved.ambiguity)
    if len(ids) < 2:
        return None
    return FrameObservations(source, index, np.array(ids), np.stack(corners), tuple(hypotheses), np.array(ambiguity))
