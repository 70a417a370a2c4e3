"""One pass over a real video: the tracker and the plain OpenCV baseline on the same decoded frames,
then scored (:func:`score_real_run`)."""

from __future__ import annotations

import math
import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ...boards import Layout
from ...camera import CameraModel
from ...config import TrackerConfig, dictionary_id
from ...targets import TargetId
from .scoring import PoseTable, score_against_layout, score_rigid_sheet

__all__ = [
    "OUTPUT_ROWS",
    "PlainOpenCV",
    "RealRun",
    "detection_comparison",
    "plain_opencv_poses",
    "run_real",
    "score_real_run",
]

# (key, label, state filter) of the tracker's output rows scored
OUTPUT_ROWS = (
    ("output", "filtered output, all rows", None),
    ("output_tracked", "filtered output, tracked only", "tracked"),
    ("output_ambiguous", "filtered output, ambiguous only", "ambiguous"),
    ("output_predicted", "filtered output, predicted only", "predicted"),
)


class PlainOpenCV:
    """The plain loop: default ``cv2.aruco.ArucoDetector`` on the BGR image, then
    ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker (exactly rigid_sheet.py's ``plain``)."""

    def __init__(self, camera: CameraModel, dictionary: str, length_m: float) -> None:
        dictionary_object = cv2.aruco.getPredefinedDictionary(dictionary_id(dictionary))
        self.detector = cv2.aruco.ArucoDetector(dictionary_object, cv2.aruco.DetectorParameters())
        self.camera_matrix = camera.camera_matrix
        self.dist = camera.dist_coeffs if camera.dist_coeffs.size else None
        h = length_m / 2
        self.object_points = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float32)

    def process(self, image: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``marker:<id>`` -> (rvec, tvec) for one BGR image (a repeated id: the last one)."""
        corners, ids, _ = self.detector.detectMarkers(image)
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for c, marker_id in zip(corners, [] if ids is None else ids.ravel()):
            _, rvec, tvec = cv2.solvePnP(
                self.object_points, c.reshape(-1, 2), self.camera_matrix, self.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            out[TargetId.marker(int(marker_id))] = (rvec.ravel().astype(np.float64), tvec.ravel().astype(np.float64))
        return out


def plain_opencv_poses(
    video: str | os.PathLike[str], camera: CameraModel | str | os.PathLike[str], dictionary: str, length_m: float
) -> PoseTable:
    """The plain OpenCV baseline over a video (or image folder): ``marker:<id>`` -> frame -> (rvec, tvec).

    ``camera``: a :class:`CameraModel` or a calibration file, scaled to the video's frame size.
    """
    from ...sources import open_source

    poses: PoseTable = defaultdict(dict)
    with open_source(video, live=False) as source:
        model = camera if isinstance(camera, CameraModel) else CameraModel.from_yaml(camera)
        plain = PlainOpenCV(model.scaled_to(*source.resolution), dictionary, length_m)
        for frame in source:
            for target, pose in plain.process(frame.image).items():
                poses[target][frame.index] = pose
    return dict(poses)


@dataclass
class RealRun:
    """What one pass over the video collected.

    ``output``: the tracker's output pose per target and frame; ``states``: its state there;
    ``raw``: the per-frame pick (``TargetResult.raw``) where measured; ``plain``: the plain OpenCV
    baseline on the same frames. Times are seconds summed over frames.
    """

    frames: int = 0
    resolution: tuple[int, int] = (0, 0)
    output: PoseTable = field(default_factory=lambda: defaultdict(dict))
    states: dict[str, dict[int, str]] = field(default_factory=lambda: defaultdict(dict))
    raw: PoseTable = field(default_factory=lambda: defaultdict(dict))
    plain: PoseTable = field(default_factory=lambda: defaultdict(dict))
    tracker_s: float = 0.0
    plain_s: float = 0.0
    wall_s: float = 0.0

    def output_in(self, state: str | None) -> PoseTable:
        """The output poses, only those in ``state`` (None: all)."""
        if state is None:
            return dict(self.output)
        return {
            target: {f: p for f, p in frames.items() if self.states[target][f] == state}
            for target, frames in self.output.items()
        }


def run_real(
    video: str | os.PathLike[str],
    camera: CameraModel,
    config: TrackerConfig,
    *,
    progress: Callable[[int, int | None], None] | None = None,
) -> RealRun:
    """Run :class:`~ar_anchor.track.tracker.Tracker` and the plain OpenCV baseline over the same decoded frames.

    The camera is scaled to the video's size as ``ar-anchor replay`` does; the baseline uses the
    config's dictionary and (default) marker length.
    """
    from ...sources import open_source
    from ...track.tracker import Tracker

    run = RealRun()
    start = time.perf_counter()
    with open_source(video, live=False) as source:
        scaled = camera.scaled_to(*source.resolution)
        run.resolution = source.resolution
        tracker = Tracker(config, scaled)
        plain = PlainOpenCV(scaled, config.detector.dictionary, config.markers.length_m)
        total = source.info.frame_count
        for frame in source:
            t0 = time.perf_counter()
            result = tracker.process(frame)
            t1 = time.perf_counter()
            found = plain.process(frame.image)
            t2 = time.perf_counter()
            run.tracker_s += t1 - t0
            run.plain_s += t2 - t1
            for target, tr in result.targets.items():
                run.output[target][frame.index] = (np.array(tr.pose.rvec), np.array(tr.pose.tvec))
                run.states[target][frame.index] = tr.state
                if tr.raw is not None:
                    run.raw[target][frame.index] = (np.array(tr.raw.rvec), np.array(tr.raw.tvec))
            for target, pose in found.items():
                run.plain[target][frame.index] = pose
            run.frames += 1
            if progress is not None:
                progress(run.frames, total)
    run.wall_s = time.perf_counter() - start
    return run


def _ids_by_frame(poses: PoseTable) -> dict[int, set[int]]:
    out: dict[int, set[int]] = defaultdict(set)
    for target, frames in poses.items():
        marker_id = TargetId.parse(target).marker_id
        if marker_id is not None:
            for f in frames:
                out[f].add(marker_id)
    return out


def detection_comparison(ours: PoseTable, plain: PoseTable, worst: int = 8) -> dict[str, Any]:
    """Marker-frames we measured vs plain OpenCV's, and per frame the ids one found and the other did not."""
    mine, theirs = _ids_by_frame(ours), _ids_by_frame(plain)
    frames = sorted(set(mine) | set(theirs))
    missed = {f: sorted(theirs.get(f, set()) - mine.get(f, set())) for f in frames}
    extra = {f: sorted(mine.get(f, set()) - theirs.get(f, set())) for f in frames}
    worst_frames = sorted((f for f in frames if missed[f]), key=lambda f: (-len(missed[f]), f))[:worst]
    return {
        "ours_marker_frames": sum(len(v) for v in mine.values()),
        "plain_marker_frames": sum(len(v) for v in theirs.values()),
        "ours_frames_with_markers": len(mine),
        "plain_frames_with_markers": len(theirs),
        "plain_not_ours": sum(len(v) for v in missed.values()),
        "frames_plain_not_ours": sum(1 for v in missed.values() if v),
        "ours_not_plain": sum(len(v) for v in extra.values()),
        "frames_ours_not_plain": sum(1 for v in extra.values() if v),
        "worst_frames": [
            {"frame": f, "missed_ids": missed[f], "plain_found": len(theirs.get(f, ()))} for f in worst_frames
        ],
        "ours_not_plain_by_frame": {str(f): v for f, v in extra.items() if v},
    }


def score_real_run(run: RealRun, layout: Layout | None = None) -> dict[str, Any]:
    """The report's figures for a :class:`RealRun` (rows as :func:`score_rigid_sheet`, plus
    ``vs_layout`` as :func:`score_against_layout` when a layout is given)."""
    tables: list[tuple[str, str, PoseTable]] = [(k, label, run.output_in(s)) for k, label, s in OUTPUT_ROWS]
    tables += [
        ("raw", "raw per-frame pick (TargetResult.raw)", dict(run.raw)),
        ("plain_opencv", "plain OpenCV (ArucoDetector + IPPE_SQUARE)", dict(run.plain)),
    ]
    rows = []
    for key, label, poses in tables:
        row: dict[str, Any] = {"key": key, "label": label, **score_rigid_sheet(poses)}
        if layout is not None:
            row["vs_layout"] = score_against_layout(poses, layout)
        rows.append(row)
    tracker_fps = run.frames / run.tracker_s if run.tracker_s > 0 else math.nan
    return {
        "rows": rows,
        "detection": detection_comparison(dict(run.raw), dict(run.plain)),
        "speed": {
            "frames": run.frames,
            "tracker_fps": tracker_fps,
            "tracker_ms_per_frame": 1e3 * run.tracker_s / max(run.frames, 1),
            "plain_fps": run.frames / run.plain_s if run.plain_s > 0 else math.nan,
            "wall_s": run.wall_s,
        },
    }
