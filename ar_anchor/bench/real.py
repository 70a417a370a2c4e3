"""Real-video benchmark without ground truth: ``ar-anchor bench real``.

Markers printed on one rigid sheet keep their relative pose. For every pair of markers ``a``, ``b``
seen in the same frame, ``marker_a_from_marker_b = inv(camera_from_a) @ camera_from_b`` is compared
with that pair's mean over the video (rotation: the chordal mean, the SVD projection of the summed
rotation matrices; translation: the per-axis median). A pair-frame whose relative rotation is more
than ``flip_deg`` (10 deg) from the pair's mean is a **flip** (one of the two markers is on the wrong
planar solution, or badly wrong); the RMS of the other pair-frames' rotation (deg) and translation
(mm) differences measures noise. Pairs seen together in fewer than 10 frames are not scored.

Blind spot: a flip of *all* markers together (every marker on its mirror solution at once) keeps the
relative poses consistent and is not seen. With a printed layout (``--layout``, an ArUco marker map),
each pair is also compared with its true relative pose from the layout, which a video-wide mean cannot
give (a pair that is wrong most of the time pulls its own mean).

The figures are the ones ``../shared/tools/rigid_sheet.py`` computes (its ``score``), computed here
the same way (exact agreement on the same poses is tested), and the plain OpenCV baseline is its
``plain`` (default ``ArucoDetector`` + ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker).

Reusable pieces: :func:`score_rigid_sheet`, :func:`score_against_layout`, :func:`read_poses_csv`,
:func:`plain_opencv_poses` (and :class:`PlainOpenCV` per frame), :func:`run_real` (tracker and
baseline over one video), :func:`score_real_run`, :func:`write_real_report`.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
import platform
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .. import __version__
from ..boards import Layout, read_layout
from ..camera import CameraModel
from ..config import TrackerConfig, dictionary_id
from ..errors import InputError
from ..geometry import marker_corners_in_marker
from .speed import _jsonable

__all__ = [
    "DEFAULT_DICTIONARY",
    "DEFAULT_MARKER_LENGTH_M",
    "FLIP_DEG",
    "MIN_COMMON_FRAMES",
    "PlainOpenCV",
    "PoseTable",
    "RealInputs",
    "RealRun",
    "default_realdata_root",
    "layout_relative_poses",
    "plain_opencv_poses",
    "read_poses_csv",
    "real_inputs",
    "real_markdown",
    "real_summary",
    "run_real",
    "score_against_layout",
    "score_real_run",
    "score_rigid_sheet",
    "write_real_report",
]

# target ("marker:<id>") -> frame index -> (rvec (3,), tvec (3,) metres), camera_from_target
PoseTable = dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]

FLIP_DEG = 10.0
MIN_COMMON_FRAMES = 10

DEFAULT_DICTIONARY = "DICT_ARUCO_ORIGINAL"
DEFAULT_MARKER_LENGTH_M = 0.034
_CHESSBOARD = Path("aruco_testdata") / "chessboard"

# (key, label, state filter) of the tracker's output rows scored
OUTPUT_ROWS = (
    ("output", "filtered output, all rows", None),
    ("output_tracked", "filtered output, tracked only", "tracked"),
    ("output_ambiguous", "filtered output, ambiguous only", "ambiguous"),
    ("output_predicted", "filtered output, predicted only", "predicted"),
)


# ---------------------------------------------------------------------------- scoring


def _homogeneous(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    matrix[:3, 3] = tvec
    return matrix


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))))


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else math.nan


def _markers(poses: Mapping[str, Any]) -> list[str]:
    """Marker targets in rigid_sheet.py's order (sorted as strings: the RMS sums in the same order)."""
    return sorted(k for k in poses if k.startswith("marker:"))


def _pairs(poses: PoseTable, min_common_frames: int) -> Iterable[tuple[str, str, list[np.ndarray]]]:
    """(a, b, [marker_a_from_marker_b per common frame, frames ascending]) for pairs seen together enough."""
    for a, b in itertools.combinations(_markers(poses), 2):
        common = sorted(set(poses[a]) & set(poses[b]))
        if len(common) < min_common_frames:
            continue
        yield a, b, [np.linalg.inv(_homogeneous(*poses[a][f])) @ _homogeneous(*poses[b][f]) for f in common]


def _marker_frames(poses: PoseTable) -> int:
    return sum(len(v) for k, v in poses.items() if k.startswith("marker:"))


def score_rigid_sheet(
    poses: PoseTable, *, flip_deg: float = FLIP_DEG, min_common_frames: int = MIN_COMMON_FRAMES
) -> dict[str, Any]:
    """Relative-pose consistency of markers on one rigid sheet (see the module doc).

    Parameters
    ----------
    poses : ``marker:<id>`` -> frame -> (rvec, tvec) ``camera_from_marker`` (other targets ignored).
    flip_deg : a pair-frame this far (deg) from its pair's mean relative rotation is a flip.
    min_common_frames : pairs seen together in fewer frames are not scored.

    Returns
    -------
    ``pair_frames``, ``flip_pct``, ``rel_rot_rms_deg``, ``rel_trans_rms_mm`` (NaN with nothing to
    score) and ``marker_frames``, as ``rigid_sheet.py``'s ``score``; plus ``flips`` and ``pairs``.
    """
    tally = _Tally(flip_deg)
    for _a, _b, relative in _pairs(poses, min_common_frames):
        u, _, vt = np.linalg.svd(sum(m[:3, :3] for m in relative))
        reference = np.eye(4)
        reference[:3, :3] = u @ vt
        reference[:3, 3] = np.median([m[:3, 3] for m in relative], axis=0)
        tally.add(reference, relative)
    return tally.scores(poses)


class _Tally:
    """Pair-frames scored against a reference relative pose per pair: flips and the RMS of the rest."""

    def __init__(self, flip_deg: float) -> None:
        self.flip_deg = flip_deg
        self.rotation_deg: list[float] = []
        self.translation_mm: list[float] = []
        self.flips = self.pair_frames = self.pairs = 0

    def add(self, reference: np.ndarray, relative: list[np.ndarray]) -> None:
        self.pairs += 1
        for m in relative:
            angle = _angle_deg(reference[:3, :3].T @ m[:3, :3])
            self.pair_frames += 1
            if angle > self.flip_deg:
                self.flips += 1
                continue
            self.rotation_deg.append(angle)
            self.translation_mm.append(1000 * np.linalg.norm(m[:3, 3] - reference[:3, 3]))

    def scores(self, poses: PoseTable) -> dict[str, Any]:
        return {
            "pair_frames": self.pair_frames,
            "flip_pct": 100 * self.flips / max(self.pair_frames, 1),
            "rel_rot_rms_deg": _rms(self.rotation_deg),
            "rel_trans_rms_mm": _rms(self.translation_mm),
            "marker_frames": _marker_frames(poses),
            "flips": self.flips,
            "pairs": self.pairs,
        }


def layout_relative_poses(layout: Layout) -> dict[int, np.ndarray]:
    """``board_from_marker`` (4x4) per marker id of a layout (a rigid fit of the centred marker square,
    x right, y up, to the layout's TL, TR, BR, BL corners; the side is the layout's own)."""
    out: dict[int, np.ndarray] = {}
    for marker_id, corners in layout:
        target = np.asarray(corners, dtype=np.float64)
        side = float(np.mean(np.linalg.norm(np.roll(target, -1, axis=0) - target, axis=1)))
        model = marker_corners_in_marker(side)
        model_c, target_c = model.mean(axis=0), target.mean(axis=0)
        u, _, vt = np.linalg.svd((target - target_c).T @ (model - model_c))
        d = np.sign(np.linalg.det(u @ vt)) or 1.0
        rotation = u @ np.diag([1.0, 1.0, d]) @ vt
        matrix = np.eye(4)
        matrix[:3, :3] = rotation
        matrix[:3, 3] = target_c - rotation @ model_c
        out[marker_id] = matrix
    return out


def score_against_layout(
    poses: PoseTable, layout: Layout, *, flip_deg: float = FLIP_DEG, min_common_frames: int = MIN_COMMON_FRAMES
) -> dict[str, Any]:
    """Like :func:`score_rigid_sheet`, but each pair-frame is compared with the pair's true relative
    pose from the printed ``layout`` instead of the pair's mean. Same pairs (seen together in at least
    ``min_common_frames`` frames); pairs with a marker the layout lacks are left out (``pairs_unknown``).

    Also ``mean_offset_rms_deg`` (RMS over pairs of the angle between the pair's mean relative rotation
    and the layout's) and ``distance_ratio`` (median over pair-frames of measured / printed centre
    distance): a sheet that is not flat, or printed at another scale, shows there, and inflates the
    per-frame figures against the layout (an offset of several degrees eats into the 10 deg flip margin).
    """
    board_from = layout_relative_poses(layout)
    tally = _Tally(flip_deg)
    offsets_deg: list[float] = []
    ratios: list[float] = []
    unknown = 0
    for a, b, relative in _pairs(poses, min_common_frames):
        id_a, id_b = int(a.split(":")[1]), int(b.split(":")[1])
        if id_a not in board_from or id_b not in board_from:
            unknown += 1
            continue
        truth = np.linalg.inv(board_from[id_a]) @ board_from[id_b]
        u, _, vt = np.linalg.svd(sum(m[:3, :3] for m in relative))
        offsets_deg.append(_angle_deg(truth[:3, :3].T @ (u @ vt)))
        printed = float(np.linalg.norm(truth[:3, 3]))
        ratios += [float(np.linalg.norm(m[:3, 3])) / printed for m in relative if printed > 0]
        tally.add(truth, relative)
    return {
        **tally.scores(poses),
        "pairs_unknown": unknown,
        "mean_offset_rms_deg": _rms(offsets_deg),
        "distance_ratio": float(np.median(ratios)) if ratios else math.nan,
    }


def read_poses_csv(
    path: str | os.PathLike[str], *, raw: bool = False, states: Iterable[str] | None = None
) -> PoseTable:
    """A ``poses.csv`` (ours, or rigid_sheet.py's ``--plain`` output) as a :data:`PoseTable`: the
    output columns, or the ``raw_*`` ones; only rows whose ``state`` is in ``states`` when given; rows
    without a pose skipped."""
    keep = set(states) if states else None
    prefix = "raw_" if raw else ""
    poses: PoseTable = defaultdict(dict)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if keep and row.get("state") not in keep:
                continue
            try:
                rvec = np.array([float(row[prefix + "rvec_" + a]) for a in "xyz"])
                tvec = np.array([float(row[prefix + "tvec_" + a]) for a in "xyz"])
            except (ValueError, KeyError, TypeError):
                continue
            poses[row["target"]][int(row["frame"])] = (rvec, tvec)
    return dict(poses)


# ---------------------------------------------------------------------------- plain OpenCV baseline


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
            out[f"marker:{int(marker_id)}"] = (rvec.ravel().astype(np.float64), tvec.ravel().astype(np.float64))
        return out


def plain_opencv_poses(
    video: str | os.PathLike[str], camera: CameraModel | str | os.PathLike[str], dictionary: str, length_m: float
) -> PoseTable:
    """The plain OpenCV baseline over a video (or image folder): ``marker:<id>`` -> frame -> (rvec, tvec).

    ``camera``: a :class:`CameraModel` or a calibration file, scaled to the video's frame size.
    """
    from ..sources import open_file_source

    poses: PoseTable = defaultdict(dict)
    with open_file_source(video) as source:
        model = camera if isinstance(camera, CameraModel) else CameraModel.from_yaml(camera)
        plain = PlainOpenCV(model.scaled_to(*source.resolution), dictionary, length_m)
        for frame in source:
            for target, pose in plain.process(frame.image).items():
                poses[target][frame.index] = pose
    return dict(poses)


# ---------------------------------------------------------------------------- inputs


def default_realdata_root() -> Path:
    """``$AR_ANCHOR_REALDATA``, else ``../shared/realdata`` beside the repository."""
    env = os.environ.get("AR_ANCHOR_REALDATA")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "shared" / "realdata"


@dataclass(frozen=True)
class RealInputs:
    """The data files of a run, checked to exist. ``dictionary`` / ``marker_length_m``: overrides of
    the tracker config (None: the config's own, as ``ar-anchor replay``)."""

    video: Path
    camera: Path
    dictionary: str | None
    marker_length_m: float | None
    layout: Path | None


def real_inputs(
    video: str | os.PathLike[str] | None = None,
    camera: str | os.PathLike[str] | None = None,
    dictionary: str | None = None,
    marker_length_m: float | None = None,
    layout: str | os.PathLike[str] | None = None,
) -> RealInputs:
    """Resolve the options: without ``video``, chessboard.avi from the real data (its camera, dictionary,
    marker length and layout unless given). Raises :class:`InputError` (exit 2) for missing files."""
    if video is None:
        root = default_realdata_root()
        folder = root / _CHESSBOARD
        default_video = folder / "chessboard.avi"
        if not default_video.is_file():
            raise InputError(
                f"bench real: the default video {default_video} is missing (the real data lives in "
                f"../shared/realdata, or set AR_ANCHOR_REALDATA); give --video FILE --camera FILE instead"
            )
        video_path = default_video
        camera_path = Path(camera) if camera is not None else folder / "intrinsics.yml"
        dictionary = dictionary or DEFAULT_DICTIONARY
        marker_length_m = marker_length_m or DEFAULT_MARKER_LENGTH_M
        layout_path = Path(layout) if layout is not None else folder / "chessboardinfo_meters.yml"
    else:
        video_path = Path(video)
        if not video_path.exists():
            raise InputError(f"--video {video_path}: not found")
        if camera is None:
            beside = [video_path.parent / n for n in ("camera.yml", "intrinsics.yml")]
            found = next((p for p in beside if p.is_file()), None)
            if found is None:
                raise InputError(
                    f"--camera FILE is required: the calibration of the camera that took {video_path} "
                    f"(none found at {beside[0]} or {beside[1]})"
                )
            camera_path = found
        else:
            camera_path = Path(camera)
        layout_path = Path(layout) if layout is not None else None
    if not camera_path.is_file():
        raise InputError(f"--camera {camera_path}: not found")
    if layout_path is not None and not layout_path.is_file():
        raise InputError(f"--layout {layout_path}: not found")
    return RealInputs(video_path, camera_path, dictionary, marker_length_m, layout_path)


# ---------------------------------------------------------------------------- the run


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
    from ..sources import open_file_source
    from ..track.tracker import Tracker

    run = RealRun()
    start = time.perf_counter()
    with open_file_source(video) as source:
        scaled = camera.scaled_to(*source.resolution)
        run.resolution = source.resolution
        tracker = Tracker(config, scaled)
        plain = PlainOpenCV(scaled, config.detector.dictionary, config.markers.length_m)
        total = source.frame_count
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
        if target.startswith("marker:"):
            for f in frames:
                out[f].add(int(target.split(":")[1]))
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


# ---------------------------------------------------------------------------- report


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def real_markdown(results: Mapping[str, Any]) -> str:
    meta, speed, det = results["meta"], results["speed"], results["detection"]
    layout = meta.get("layout")
    lines = [
        "# Real video: rigid-sheet consistency (no ground truth)",
        "",
        f"Produced by: `{meta['command']}`",
        "",
        f"Video `{meta['video']}` ({speed['frames']} frames, {meta['resolution'][0]}x{meta['resolution'][1]}), "
        f"camera `{meta['camera']}`, {meta['dictionary']}, markers {1000 * meta['marker_length_m']:g} mm"
        + (f", layout `{layout}`" if layout else "")
        + f"; tracker config: {meta['config']}. ar_anchor {meta['ar_anchor']}, OpenCV {meta['opencv']}, "
        f"{meta['date']}.",
        "",
        "## What is measured",
        "",
        "The markers are printed on one rigid sheet, so each pair's relative pose `marker_a_from_marker_b` "
        "(from `camera_from_a` and `camera_from_b` in the same frame) should be constant. Each pair-frame is "
        "compared with that pair's mean over the video (rotation: chordal mean; translation: median). "
        f"A **flip** is a pair-frame more than {FLIP_DEG:g} deg from the pair's mean: one of the two markers "
        "is on the wrong planar (IPPE) solution, or badly wrong. The RMS columns are over the other "
        "pair-frames (rotation in degrees, translation in mm from the pair's median). Pairs seen together "
        f"in fewer than {MIN_COMMON_FRAMES} frames are not scored. Marker-frames: (marker, frame) poses scored.",
        "",
        "**Blind spot**: a flip of all markers together (every marker on its mirror solution at once, as "
        "a lone sheet seen face-on can do) keeps the relative poses consistent and is not counted"
        + (
            "; so is a pair that is wrong most of the time (it pulls its own mean), which the columns "
            "against the printed layout do catch."
            if layout
            else ". Give `--layout` (the printed marker map) to compare with the true relative poses as well."
        ),
        "",
        "## Relative pose consistency",
        "",
    ]
    header = "| poses | pair-frames | flips % | rel. rot RMS deg | rel. trans RMS mm | marker-frames |"
    rule = "|---|---:|---:|---:|---:|---:|"
    if layout:
        header += " vs layout: flips % | rot RMS deg | trans RMS mm | pair mean offset deg | distance ratio |"
        rule += "---:|---:|---:|---:|---:|"
    lines += [header, rule]
    for row in results["rows"]:
        cells = [
            row["label"],
            str(row["pair_frames"]),
            _fmt(row["flip_pct"]),
            _fmt(row["rel_rot_rms_deg"]),
            _fmt(row["rel_trans_rms_mm"], 1),
            str(row["marker_frames"]),
        ]
        if layout:
            vs = row["vs_layout"]
            cells += [_fmt(vs["flip_pct"]), _fmt(vs["rel_rot_rms_deg"]), _fmt(vs["rel_trans_rms_mm"], 1)]
            cells += [_fmt(vs["mean_offset_rms_deg"]), _fmt(vs["distance_ratio"], 3)]
        lines.append("| " + " | ".join(cells) + " |")
    if layout:
        lines += [
            "",
            "The *vs layout* columns compare each pair-frame with the pair's relative pose in the printed "
            "layout instead of its mean (same flip threshold, same pairs). *Pair mean offset*: RMS over pairs "
            "of the angle between the pair's mean and the layout; *distance ratio*: median measured / printed "
            "centre distance. Both are about the sheet as much as the tracker: a sheet that is not flat, or "
            "printed at another scale than the layout (or than --marker-length), offsets every pair-frame and "
            "leaves less of the flip margin, so read the layout columns next to these two.",
        ]
    lines += [
        "",
        "## Detection",
        "",
        "| | marker-frames | frames with a marker |",
        "|---|---:|---:|",
        f"| ar_anchor (raw pose measured) | {det['ours_marker_frames']} | {det['ours_frames_with_markers']} |",
        f"| plain OpenCV | {det['plain_marker_frames']} | {det['plain_frames_with_markers']} |",
        "",
        f"Plain OpenCV found {det['plain_not_ours']} marker-frames that ar_anchor did not measure "
        f"(in {det['frames_plain_not_ours']} frames); ar_anchor measured {det['ours_not_plain']} that plain "
        f"OpenCV did not find (in {det['frames_ours_not_plain']} frames).",
    ]
    if det["worst_frames"]:
        lines += ["", "Worst frames (plain OpenCV found, ar_anchor did not):", ""]
        lines += ["| frame | missed ids | plain found |", "|---:|---|---:|"]
        for w in det["worst_frames"]:
            lines.append(f"| {w['frame']} | {', '.join(map(str, w['missed_ids']))} | {w['plain_found']} |")
    lines += [
        "",
        "## Speed",
        "",
        f"Tracker: {_fmt(speed['tracker_fps'], 1)} frames/s ({_fmt(speed['tracker_ms_per_frame'], 2)} ms/frame, "
        f"Tracker.process only); plain OpenCV: {_fmt(speed['plain_fps'], 1)} frames/s; whole run (decode, both, "
        f"collection) {_fmt(speed['wall_s'], 1)} s.",
        "",
    ]
    return "\n".join(lines)


def real_summary(results: Mapping[str, Any]) -> str:
    """A few lines for the terminal."""
    lines = []
    for row in results["rows"]:
        if row["key"] not in ("output", "raw", "plain_opencv"):
            continue
        text = (
            f"{row['label']}: {row['pair_frames']} pair-frames, flips {_fmt(row['flip_pct'])} %, "
            f"rel. rot RMS {_fmt(row['rel_rot_rms_deg'])} deg, rel. trans RMS {_fmt(row['rel_trans_rms_mm'], 1)} mm, "
            f"{row['marker_frames']} marker-frames"
        )
        if "vs_layout" in row:
            vs = row["vs_layout"]
            text += f" (vs layout: flips {_fmt(vs['flip_pct'])} %, rot {_fmt(vs['rel_rot_rms_deg'])} deg)"
        lines.append(text)
    det, speed = results["detection"], results["speed"]
    lines.append(
        f"detection: {det['ours_marker_frames']} marker-frames measured vs {det['plain_marker_frames']} plain OpenCV; "
        f"{det['plain_not_ours']} found by plain OpenCV only; tracker {_fmt(speed['tracker_fps'], 1)} frames/s"
    )
    return "\n".join(lines)


def write_real_report(
    out_dir: str | os.PathLike[str],
    inputs: RealInputs,
    config: TrackerConfig,
    *,
    command: str = "ar-anchor bench real",
    progress: Callable[[int, int | None], None] | None = None,
) -> dict[str, Any]:
    """Run :func:`run_real` on ``inputs`` with ``config`` (already carrying the dictionary / length
    overrides), score it, write ``real.md`` and ``real.json`` to ``out_dir`` and return the results."""
    camera = CameraModel.from_yaml(inputs.camera)
    layout = read_layout(inputs.layout) if inputs.layout is not None else None
    run = run_real(inputs.video, camera, config, progress=progress)
    results = score_real_run(run, layout)
    results["meta"] = {
        "command": command,
        "video": str(inputs.video),
        "camera": str(inputs.camera),
        "layout": str(inputs.layout) if inputs.layout is not None else None,
        "dictionary": config.detector.dictionary,
        "marker_length_m": config.markers.length_m,
        "config": str(config.source) if getattr(config, "source", None) else "defaults",
        "resolution": list(run.resolution),
        "flip_deg": FLIP_DEG,
        "min_common_frames": MIN_COMMON_FRAMES,
        "ar_anchor": __version__,
        "opencv": cv2.__version__,
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real.json").write_text(json.dumps(_jsonable(results), indent=2) + "\n")
    (out / "real.md").write_text(real_markdown(results))
    return results
