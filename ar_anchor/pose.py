"""Per-marker pose: both IPPE_SQUARE solutions, validated, with fallbacks.

OpenCV's solvers can return garbage without failing (non-finite or huge ``rvec``, a target
behind the camera, a large reprojection error on near-degenerate input). Every solution goes
through :func:`check_pose`; a marker whose solutions all fail falls back to the next solver
(``IPPE_SQUARE`` -> ``IPPE`` -> ``SQPNP``) and is dropped for this frame when none passes.

A low reprojection error is not a correct pose: a small or distant square has two poses that
reproject almost equally well (the planar ambiguity), so both IPPE solutions are kept, sorted
by error, with their error ratio (``ambiguity``, worse / better, >= 1, near 1 = ambiguous).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import CameraModel
from .geometry import Pose, marker_corners_in_marker

__all__ = [
    "MarkerPose",
    "PoseFailure",
    "PoseHypothesis",
    "check_pose",
    "reprojection_rms",
    "solve_marker",
]

log = logging.getLogger(__name__)

# A translation beyond this is a solver artefact, not a marker anyone can see.
MAX_DISTANCE_M = 1000.0
# Keeps the error ratio finite (and meaningful) when the better solution is exact.
_RATIO_EPS_PX = 1e-3

_SOLVERS: tuple[tuple[str, int], ...] = (
    ("ippe_square", cv2.SOLVEPNP_IPPE_SQUARE),
    ("ippe", cv2.SOLVEPNP_IPPE),
    ("sqpnp", cv2.SOLVEPNP_SQPNP),
)


@dataclass(frozen=True)
class PoseHypothesis:
    """One candidate ``camera_from_target`` and its RMS corner reprojection error (pixels)."""

    pose: Pose
    reproj_px: float


@dataclass(frozen=True)
class MarkerPose:
    """Validated pose hypotheses of one marker in one frame.

    ``hypotheses`` holds one or two entries sorted by reprojection error (the lower first);
    ``ambiguity`` is the error ratio of the two solutions the solver returned (NaN when it
    returned one).
    """

    marker_id: int
    length_m: float
    corners_in_image: np.ndarray
    hypotheses: tuple[PoseHypothesis, ...]
    ambiguity: float
    solver: str

    @property
    def best(self) -> PoseHypothesis:
        return self.hypotheses[0]


@dataclass(frozen=True)
class PoseFailure:
    """Why a marker got no pose this frame."""

    marker_id: int
    reason: str


def reprojection_rms(
    pose: Pose, points_in_target: np.ndarray, points_in_image: np.ndarray, camera: CameraModel
) -> float:
    """RMS over points of the Euclidean pixel distance between projected and observed points."""
    projected, _ = cv2.projectPoints(
        np.asarray(points_in_target, np.float64), pose.rvec, pose.tvec, camera.camera_matrix, camera.dist_or_none
    )
    residual = projected.reshape(-1, 2) - np.asarray(points_in_image, np.float64).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(residual * residual, axis=1))))


def check_pose(
    pose: Pose,
    points_in_target: np.ndarray,
    points_in_image: np.ndarray,
    camera: CameraModel,
    max_reproj_px: float,
    *,
    require_front: bool = True,
) -> tuple[float, str | None]:
    """Validate a solver result. Returns (RMS reprojection error, reason it is rejected or None).

    ``require_front``: the target's +z side faces the camera (a printed marker is opaque; its
    frame's z points toward the viewer), i.e. the camera centre has z > 0 in the target frame.
    """
    if not pose.is_finite():
        return math.nan, "non-finite rvec/tvec"
    angle = float(np.linalg.norm(pose.rvec))
    if angle > math.pi + 1e-9:
        return math.nan, f"rvec norm {angle:.3g} > pi"
    if float(np.linalg.norm(pose.tvec)) > MAX_DISTANCE_M:
        return math.nan, f"translation {np.linalg.norm(pose.tvec):.3g} m is implausible"
    depth = pose.apply(points_in_target)[:, 2]
    if np.any(depth <= 1e-6):
        return math.nan, "target (partly) behind the camera"
    if require_front and pose.camera_centre()[2] <= 0:
        return math.nan, "target seen from behind (camera on the back side of its plane)"
    error = reprojection_rms(pose, points_in_target, points_in_image, camera)
    if not math.isfinite(error) or error > max_reproj_px:
        return error, f"reprojection error {error:.3g} px > {max_reproj_px:g} px"
    return error, None


def _quad_problem(corners: np.ndarray) -> str | None:
    """Reject corner sets no real square can produce: non-finite, tiny, non-convex or self-intersecting."""
    if corners.shape != (4, 2):
        return f"expected 4x2 corners, got shape {corners.shape}"
    if not np.all(np.isfinite(corners)):
        return "non-finite corner coordinates"
    if np.max(np.abs(corners)) > 1e6:
        return "corner coordinates out of range"
    edges = np.roll(corners, -1, axis=0) - corners
    following = np.roll(edges, -1, axis=0)
    cross = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
    area = 0.5 * abs(
        float(np.sum(corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1]))
    )
    if area < 1.0:
        return f"degenerate quadrilateral (area {area:.3g} px^2)"
    if not (np.all(cross > 0) or np.all(cross < 0)):
        return "corners do not form a convex quadrilateral"
    return None


def solve_marker(
    marker_id: int,
    corners_in_image: np.ndarray,
    length_m: float,
    camera: CameraModel,
    max_reproj_px: float = 3.0,
) -> MarkerPose | PoseFailure:
    """Pose of one square marker from its 4 corners (TL, TR, BR, BL), with validation and fallbacks."""
    corners = (
        np.asarray(corners_in_image, dtype=np.float64).reshape(-1, 2) if np.size(corners_in_image) else np.zeros((0, 2))
    )
    problem = _quad_problem(corners)
    if problem is not None:
        return PoseFailure(marker_id, problem)
    if not (math.isfinite(length_m) and length_m > 0):
        return PoseFailure(marker_id, f"marker length must be > 0, got {length_m}")
    points_in_marker = marker_corners_in_marker(length_m)
    reasons = []
    for name, flag in _SOLVERS:
        try:
            count, rvecs, tvecs, _errors = cv2.solvePnPGeneric(
                points_in_marker, corners, camera.camera_matrix, camera.dist_or_none, flags=flag
            )
        except cv2.error as err:
            reasons.append(f"{name}: {str(err).strip().splitlines()[-1]}")
            continue
        candidates = []
        all_errors = []
        for rvec, tvec in zip(rvecs[:count], tvecs[:count]):
            pose = Pose(np.asarray(rvec).reshape(3), np.asarray(tvec).reshape(3))
            error, reason = check_pose(pose, points_in_marker, corners, camera, max_reproj_px)
            all_errors.append(error)
            if reason is None:
                candidates.append(PoseHypothesis(pose, error))
            else:
                reasons.append(f"{name}: {reason}")
        if not candidates:
            continue
        candidates.sort(key=lambda h: h.reproj_px)
        finite = sorted(e for e in all_errors if math.isfinite(e))
        ambiguity = (finite[1] + _RATIO_EPS_PX) / (finite[0] + _RATIO_EPS_PX) if len(finite) >= 2 else math.nan
        return MarkerPose(marker_id, length_m, corners, tuple(candidates), ambiguity, name)
    reason = "; ".join(reasons) or "no solution"
    log.debug("marker %d: no valid pose (%s)", marker_id, reason)
    return PoseFailure(marker_id, reason)
