"""What a marker map is made of: each frame's observations, the map itself, and the similarity
alignment that compares two maps (:func:`similarity_align`, Umeyama's method).

Frames: the map frame is the reference marker's own frame (centre, x right, y up, z toward the viewer,
as :func:`~ar_anchor.geometry.marker_corners_in_marker`); ``world_from_marker`` maps a marker's own
frame into it. A frame's camera pose is ``camera_from_world``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...geometry import Pose, marker_corners_in_marker

__all__ = [
    "FrameObservations",
    "MarkerMap",
    "frame_label",
    "Similarity",
    "aligned_errors",
    "rms_m",
    "similarity_align",
]


@dataclass(frozen=True)
class FrameObservations:
    """The markers one frame shows, with their per-marker pose hypotheses (:func:`~ar_anchor.track.pose.solve_marker`).

    Attributes
    ----------
    source : position of the frame's input among the command's inputs (0-based).
    frame : the frame's index in its input.
    ids : (N,) marker ids.
    corners : (N, 4, 2) detected corners, pixels, TL TR BR BL.
    hypotheses : per marker, its one or two ``camera_from_marker`` poses, the lower reprojection error first.
    ambiguity : (N,) error ratio of the worse to the better IPPE solution (>= 1; NaN when only one).
    """

    source: int
    frame: int
    ids: np.ndarray
    corners: np.ndarray
    hypotheses: tuple[tuple[Pose, ...], ...]
    ambiguity: np.ndarray

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(self.corners, dtype=np.float64).reshape(-1, 4, 2)
        ambiguity = np.asarray(self.ambiguity, dtype=np.float64).reshape(-1)
        if not (len(ids) == len(corners) == len(self.hypotheses) == len(ambiguity)):
            raise ValueError(
                f"FrameObservations: {len(ids)} ids, {len(corners)} corner sets, {len(self.hypotheses)} hypothesis "
                f"sets and {len(ambiguity)} ambiguities (expected one of each per marker)"
            )
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners", corners)
        object.__setattr__(self, "ambiguity", ambiguity)

    @property
    def name(self) -> str:
        """The short key, ``<input index>:<frame>``; :func:`frame_label` is how reports name it."""
        return f"{self.source}:{self.frame}"

    def __len__(self) -> int:
        return len(self.ids)


def frame_label(name: str, several: bool) -> str:
    """A frame's key (:attr:`FrameObservations.name`) as reports name it: ``frame 12``, or ``input 2 frame 12``
    when the map was made from several inputs.

    >>> frame_label("1:12", several=True), frame_label("0:12", several=False)
    ('input 2 frame 12', 'frame 12')
    """
    source, _, frame = name.partition(":")
    return f"input {int(source) + 1} frame {frame}" if several else f"frame {frame}"


@dataclass(frozen=True)
class MarkerMap:
    """Markers that sit rigidly together: each one's pose in the map frame (the reference marker's frame).

    ``world_from_marker``: marker id -> pose; ``sigma_mm``: marker id -> 1-sigma 3D position uncertainty of
    its centre (millimetres, relative to the reference marker; 0 for the reference itself).
    """

    length_m: float
    reference_id: int
    world_from_marker: dict[int, Pose]
    sigma_mm: dict[int, float] = field(default_factory=dict)

    @property
    def ids(self) -> list[int]:
        """The mapped ids, ascending."""
        return sorted(self.world_from_marker)

    def corners(self, marker_id: int) -> np.ndarray:
        """(4, 3) corners TL, TR, BR, BL of one marker in the map frame, metres."""
        return self.world_from_marker[marker_id].apply(marker_corners_in_marker(self.length_m))

    def all_corners(self) -> dict[int, np.ndarray]:
        """Every marker's corners (4, 3), by id ascending."""
        return {marker_id: self.corners(marker_id) for marker_id in self.ids}

    def layout(self) -> tuple[tuple[int, tuple[tuple[float, float, float], ...]], ...]:
        """The map as a :data:`ar_anchor.boards.Layout` (id -> four corners, sorted by id)."""
        return tuple(
            (marker_id, tuple(tuple(float(v) for v in point) for point in corners))
            for marker_id, corners in self.all_corners().items()
        )

    @property
    def extent_m(self) -> float:
        """The diagonal of the box holding every corner, metres (the map's size)."""
        points = np.concatenate(list(self.all_corners().values()))
        return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


@dataclass(frozen=True)
class Similarity:
    """``y = scale * R x + t``: the similarity that best maps one point set onto another."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (N, 3)."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation


def similarity_align(source: np.ndarray, target: np.ndarray, *, with_scale: bool = True) -> Similarity:
    """The least-squares similarity (Umeyama 1991) taking ``source`` (N, 3) onto ``target`` (N, 3), N >= 3
    points not all on one line; ``with_scale=False``: a rigid motion (scale 1)."""
    x = np.asarray(source, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    if len(x) != len(y) or len(x) < 3:
        raise ValueError(f"similarity_align: need two sets of N >= 3 matching points, got {len(x)} and {len(y)}")
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    covariance = yc.T @ xc / len(x)
    u, d, vt = np.linalg.svd(covariance)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0  # a reflection is no rotation: take the best proper one
    rotation = u @ s @ vt
    variance = float((xc**2).sum() / len(x))
    scale = float(np.trace(np.diag(d) @ s) / variance) if with_scale and variance > 0 else 1.0
    translation = mean_y - scale * rotation @ mean_x
    return Similarity(scale, rotation, translation)


def aligned_errors(
    estimate: dict[int, np.ndarray], truth: dict[int, np.ndarray], *, with_scale: bool = True
) -> tuple[Similarity, dict[int, np.ndarray]]:
    """Align the corners of ``estimate`` (id -> (4, 3)) onto ``truth``'s over their shared ids; the
    alignment and each shared marker's per-corner residual vectors (4, 3) after it, metres."""
    shared = sorted(set(estimate) & set(truth))
    if len(shared) < 1:
        raise ValueError("aligned_errors: the two maps share no marker")
    source = np.concatenate([np.asarray(estimate[i], np.float64).reshape(4, 3) for i in shared])
    target = np.concatenate([np.asarray(truth[i], np.float64).reshape(4, 3) for i in shared])
    alignment = similarity_align(source, target, with_scale=with_scale)
    residual = alignment.apply(source) - target
    return alignment, {marker_id: residual[4 * k : 4 * k + 4] for k, marker_id in enumerate(shared)}


def rms_m(residuals: dict[int, np.ndarray]) -> float:
    """RMS of the corner distances of :func:`aligned_errors`' residuals, metres."""
    stacked = np.concatenate(list(residuals.values()))
    return math.sqrt(float(np.mean(np.sum(stacked**2, axis=1))))
