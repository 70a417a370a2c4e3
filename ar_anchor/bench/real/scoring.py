"""Relative-pose consistency of markers on one rigid sheet, against the pair's mean over the video or
against a printed layout (see :mod:`ar_anchor.bench.real`), and ``poses.csv`` read back as poses."""

from __future__ import annotations

import csv
import itertools
import math
import os
from collections import defaultdict
from collections.abc import Iterable, Mapping
from typing import Any

import cv2
import numpy as np

from ...boards import Layout
from ...geometry import marker_corners_in_marker
from ...targets import TargetId
from ..report import FLIP_DEG

__all__ = [
    "MIN_COMMON_FRAMES",
    "PoseTable",
    "layout_relative_poses",
    "read_poses_csv",
    "score_against_layout",
    "score_rigid_sheet",
]

PoseTable = dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]


MIN_COMMON_FRAMES = 10


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
    return sorted(k for k in poses if TargetId.parse(k).kind == "marker")


def _pairs(poses: PoseTable, min_common_frames: int) -> Iterable[tuple[str, str, list[np.ndarray]]]:
    """(a, b, [marker_a_from_marker_b per common frame, frames ascending]) for pairs seen together enough."""
    for a, b in itertools.combinations(_markers(poses), 2):
        common = sorted(set(poses[a]) & set(poses[b]))
        if len(common) < min_common_frames:
            continue
        yield a, b, [np.linalg.inv(_homogeneous(*poses[a][f])) @ _homogeneous(*poses[b][f]) for f in common]


def _marker_frames(poses: PoseTable) -> int:
    return sum(len(v) for k, v in poses.items() if TargetId.parse(k).kind == "marker")


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
        id_a, id_b = TargetId.parse(a).marker_id, TargetId.parse(b).marker_id
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
