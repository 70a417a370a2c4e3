"""Per-marker pose: both IPPE_SQUARE solutions, validated, with fallbacks.

OpenCV's solvers can return garbage without failing (non-finite or huge ``rvec``, a target
behind the camera, a large reprojection error on near-degenerate input). Every solution goes
through :func:`check_pose`; a marker whose solutions all fail falls back to the next solver
(``IPPE_SQUARE`` -> ``IPPE`` -> ``SQPNP``) and is dropped for this frame when none passes.
Each solution is polished with ``solvePnPRefineLM`` within its own branch (IPPE's closed form is
not the least-squares pose).

A low reprojection error is not a correct pose: a small or distant square has two poses that
reproject almost equally well (the planar ambiguity), so both IPPE solutions are kept, sorted
by error, with their error ratio (``ambiguity``, worse / better, >= 1, near 1 = ambiguous).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..camera import CameraModel
from ..geometry import Pose, angle_between_deg, marker_corners_in_marker, vector_norm
from ..targets import TargetId

__all__ = [
    "BoardPose",
    "BoardSolver",
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


class _Solved:
    """What a marker's and a board's solved pose (:class:`MarkerPose`, :class:`BoardPose`) share."""

    hypotheses: tuple[PoseHypothesis, ...]  # one or two, lower reprojection error first

    @property
    def best(self) -> PoseHypothesis:
        return self.hypotheses[0]


@dataclass(frozen=True)
class MarkerPose(_Solved):
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
    def target(self) -> TargetId:
        return TargetId.marker(self.marker_id)

    @property
    def points_in_target(self) -> np.ndarray:
        return marker_corners_in_marker(self.length_m)

    @property
    def points_in_image(self) -> np.ndarray:
        return self.corners_in_image


@dataclass(frozen=True)
class PoseFailure:
    """Why a marker got no pose this frame."""

    marker_id: int  # -1 for a board
    reason: str
    target: TargetId | None = None  # the board's, for a board

    def __post_init__(self) -> None:
        if self.target is None:
            object.__setattr__(self, "target", TargetId.marker(self.marker_id))


def reprojection_rms(
    pose: Pose, points_in_target: np.ndarray, points_in_image: np.ndarray, camera: CameraModel
) -> float:
    """RMS over points of the Euclidean pixel distance between projected and observed points."""
    return _rms(
        pose,
        np.asarray(points_in_target, np.float64),
        np.asarray(points_in_image, np.float64).reshape(-1, 2),
        camera.camera_matrix,
        camera.dist_or_none,
    )


def check_pose(
    pose: Pose,
    points_in_target: np.ndarray,
    points_in_image: np.ndarray,
    camera: CameraModel,
    max_reproj_px: float,
    *,
    require_front: bool = True,
    error: float | None = None,
) -> tuple[float, str | None]:
    """Validate a solver result. Returns (RMS reprojection error, reason it is rejected or None).

    ``require_front``: the target's +z side faces the camera (a printed marker is opaque; its
    frame's z points toward the viewer), i.e. the camera centre has z > 0 in the target frame.
    ``error``: the pose's RMS reprojection error when the caller has it already.
    """
    if not pose.is_finite():
        return math.nan, "non-finite rvec/tvec"
    angle = vector_norm(pose.rvec)
    if angle > math.pi + 1e-9:
        return math.nan, f"rvec norm {angle:.3g} > pi"
    if vector_norm(pose.tvec) > MAX_DISTANCE_M:
        return math.nan, f"translation {np.linalg.norm(pose.tvec):.3g} m is implausible"
    depth = pose.apply(points_in_target)[:, 2]
    if np.any(depth <= 1e-6):
        return math.nan, "target (partly) behind the camera"
    if require_front and pose.camera_centre()[2] <= 0:
        return math.nan, "target seen from behind (camera on the back side of its plane)"
    if error is None:
        error = reprojection_rms(pose, points_in_target, points_in_image, camera)
    if not math.isfinite(error) or error > max_reproj_px:
        return error, f"reprojection error {error:.3g} px > {max_reproj_px:g} px"
    return error, None


def _quad_problem(corners: np.ndarray) -> str | None:
    """Reject corner sets no real square can produce: non-finite, tiny, non-convex or self-intersecting."""
    if corners.shape != (4, 2):
        return f"expected 4x2 corners, got shape {corners.shape}"
    points = corners.tolist()  # four points: plain floats are several times faster than numpy here
    if not all(math.isfinite(v) for point in points for v in point):
        return "non-finite corner coordinates"
    if max(abs(v) for point in points for v in point) > 1e6:
        return "corner coordinates out of range"
    crosses, twice_area = [], 0.0
    for k in range(4):
        (x0, y0), (x1, y1), (x2, y2) = points[k], points[(k + 1) % 4], points[(k + 2) % 4]
        crosses.append((x1 - x0) * (y2 - y1) - (y1 - y0) * (x2 - x1))
        twice_area += x0 * y1 - x1 * y0
    area = 0.5 * abs(twice_area)
    if area < 1.0:
        return f"degenerate quadrilateral (area {area:.3g} px^2)"
    if not (all(c > 0 for c in crosses) or all(c < 0 for c in crosses)):
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
        polished: list[Pose] = []
        for rvec, tvec in zip(rvecs[:count], tvecs[:count]):
            pose = Pose(np.asarray(rvec).reshape(3), np.asarray(tvec).reshape(3))
            error = None
            if pose.is_finite():
                # IPPE is a closed form, not the least-squares pose: on precise corners it can be off by
                # 0.1 px and 0.2 deg (12 cm marker at 0.5 m). LM polishes each solution within its own
                # branch; one that slides into the other branch's minimum keeps IPPE's version.
                refined, refined_error, start_error = _refine_lm_rms(
                    pose, points_in_marker, corners, camera.camera_matrix, camera.dist_or_none
                )
                if not any(angle_between_deg(refined.rotation, p.rotation) < 1.0 for p in polished):
                    pose, error = refined, refined_error
                else:
                    error = start_error
                polished.append(pose)
            error, reason = check_pose(pose, points_in_marker, corners, camera, max_reproj_px, error=error)
            all_errors.append(error)
            if reason is None:
                candidates.append(PoseHypothesis(pose, error))
            else:
                reasons.append(f"{name}: {reason}")
        if not candidates:
            continue
        candidates.sort(key=lambda h: h.reproj_px)
        candidates = candidates[:2]  # a square has two poses; a generic solver (SQPNP) may offer more minima
        finite = sorted(e for e in all_errors if math.isfinite(e))
        ambiguity = (finite[1] + _RATIO_EPS_PX) / (finite[0] + _RATIO_EPS_PX) if len(finite) >= 2 else math.nan
        return MarkerPose(marker_id, length_m, corners, tuple(candidates), ambiguity, name)
    reason = "; ".join(reasons) or "no solution"
    log.debug("marker %d: no valid pose (%s)", marker_id, reason)
    return PoseFailure(marker_id, reason)


# ---------------------------------------------------------------------------- boards


@dataclass(frozen=True)
class BoardPose(_Solved):
    """Validated pose hypotheses of one rigid board in one frame, solved jointly from its markers.

    ``hypotheses``: one or two (a planar board's two IPPE solutions, which differ clearly once
    several markers are seen, and are as ambiguous as a lone marker's when only one is), lower
    error first. ``points_in_target`` / ``points_in_image``: the inlier correspondences the
    hypotheses were solved from (marker corners, or ChArUco chessboard corners).
    """

    name: str
    hypotheses: tuple[PoseHypothesis, ...]
    ambiguity: float
    points_in_target: np.ndarray
    points_in_image: np.ndarray
    markers_used: tuple[int, ...]  # ids of the inlier markers
    outlier_ids: tuple[int, ...]  # board markers seen but rejected (wrong id, bad corners)
    outlier_points_in_image: np.ndarray  # corners rejected individually or with their marker
    corners_in_image: np.ndarray  # (M, 4, 2) the inlier markers' corners
    solver: str

    @property
    def target(self) -> TargetId:
        return TargetId.board(self.name)

    @property
    def inliers(self) -> int:
        return len(self.points_in_target)


def _faces_camera(pose: Pose, quads_in_target: np.ndarray) -> bool:
    """Is the camera on the printed side of every marker? (A marker's printed side is where
    (TR - TL) x (TL - BL) points, the +z of its own IPPE frame.)"""
    quads = np.asarray(quads_in_target, dtype=np.float64).reshape(-1, 4, 3)
    normals = np.cross(quads[:, 1] - quads[:, 0], quads[:, 0] - quads[:, 3])
    centre = pose.camera_centre()
    return bool(np.all(np.einsum("ij,ij->i", normals, centre - quads.mean(axis=1)) > 0))


class BoardSolver:
    """Joint pose of one board from the detected corners of its markers (see :meth:`solve`).

    1. **Candidates**: every detected board marker alone gives up to two board poses (IPPE on its
       four corners in the board frame); with four or more markers, ``solvePnPRansac`` over all
       corners gives one more.
    2. **Consensus** (RANSAC across markers, each marker a minimal sample; exhaustive, so
       deterministic): a candidate's inliers are the markers whose corners it reprojects within
       ``inlier_px``; the candidate with most inliers (then lowest error) wins and is refined on
       them and re-scored until the inlier set is stable. Wrong ids and mangled markers fall out.
    3. **Refinement** on the inliers: planar boards IPPE (both solutions kept, as for a lone
       marker), others SQPNP; then ``solvePnPRefineLM``; single corners still off by more than
       ``inlier_px`` are dropped and the pose refined once more.
    4. **Validation** as for markers (:func:`check_pose`), and the camera must see the printed
       side of every inlier marker. ChArUco boards solve from the chessboard corners interpolated
       from the inlier markers when there are enough of them.
    """

    def __init__(self, board: Any, inlier_px: float = 3.0) -> None:
        self.board = board
        self.name: str = board.name
        self.target = TargetId.board(board.name)
        self.corners = board.corners_in_board()
        self.planar: bool = board.planar
        self.marker_length_m = min(board.marker_length_of(i) for i in self.corners)  # for drawing
        self.outline = np.stack([self.corners[i] for i in board.marker_ids])  # (K, 4, 3) marker squares
        self.inlier_px = inlier_px
        self.cv_board = board.cv_board()
        self.charuco = None
        self._charuco_detectors: dict[tuple[bytes, bytes | None], Any] = {}
        if board.kind == "charuco":
            self.charuco = self.cv_board
            self.chessboard = np.asarray(self.cv_board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def solve(
        self,
        ids: np.ndarray,
        corners: np.ndarray,
        camera: CameraModel,
        max_reproj_px: float = 3.0,
        image: np.ndarray | None = None,
    ) -> BoardPose | PoseFailure | None:
        """Pose from this frame's detections (all of them: other ids are ignored). None: no marker of the board."""
        members = [
            (int(i), np.asarray(c, np.float64).reshape(4, 2))
            for i, c in zip(np.asarray(ids).reshape(-1), np.asarray(corners).reshape(-1, 4, 2))
            if int(i) in self.corners and _quad_problem(np.asarray(c, np.float64).reshape(4, 2)) is None
        ]
        if not members:
            return None
        member_ids = [m for m, _ in members]
        obj = np.stack([self.corners[m] for m in member_ids])  # (M, 4, 3)
        img = np.stack([c for _, c in members])  # (M, 4, 2)
        k, dist = camera.camera_matrix, camera.dist_or_none

        candidates = self._candidates(obj, img, k, dist)
        if not candidates:
            return self._fail("no solver gave a finite pose")
        best_pose, inliers = None, np.zeros(len(members), bool)
        best_key = (-1, math.inf)
        for pose in candidates:
            errors = self._marker_errors(pose, obj, img, k, dist)
            mask = errors < self.inlier_px
            key = (int(mask.sum()), float(np.sum(np.where(mask, errors, 0.0))))
            if key[0] > best_key[0] or (key[0] == best_key[0] and key[1] < best_key[1]):
                best_key, best_pose, inliers = key, pose, mask
        if best_pose is None or not inliers.any():
            return self._fail("no pose agrees with any of its markers")
        for _ in range(3):  # refine on the consensus, re-score, until the inlier set is stable
            refined = _refine_lm(best_pose, obj[inliers].reshape(-1, 3), img[inliers].reshape(-1, 2), k, dist)
            mask = self._marker_errors(refined, obj, img, k, dist) < self.inlier_px
            best_pose = refined
            if not mask.any() or np.array_equal(mask, inliers):
                break
            inliers = mask
        used = [m for m, ok in zip(member_ids, inliers) if ok]
        outliers = tuple(m for m, ok in zip(member_ids, inliers) if not ok)
        points_obj, points_img = obj[inliers].reshape(-1, 3), img[inliers].reshape(-1, 2)
        outlier_points = [img[~inliers].reshape(-1, 2)]
        solver = "markers"
        if self.charuco is not None and image is not None:
            chess = self._charuco_corners(image, obj[inliers], img[inliers], np.array(used), camera)
            if chess is not None and len(chess[0]) >= 6:
                points_obj, points_img = chess
                solver = "charuco"
        # single corners still off (a marker half occluded, a smeared corner): drop them
        residual = _residuals(best_pose, points_obj, points_img, k, dist)
        keep = residual < self.inlier_px
        if 4 <= keep.sum() < len(keep):
            outlier_points.append(points_img[~keep])
            points_obj, points_img = points_obj[keep], points_img[keep]
        hypotheses = self._final(best_pose, points_obj, points_img, obj[inliers], camera, max_reproj_px)
        if isinstance(hypotheses, str):
            return self._fail(hypotheses)
        errors = [h.reproj_px for h in hypotheses]
        ambiguity = (errors[1] + _RATIO_EPS_PX) / (errors[0] + _RATIO_EPS_PX) if len(errors) == 2 else math.nan
        return BoardPose(
            name=self.name,
            hypotheses=hypotheses,
            ambiguity=ambiguity,
            points_in_target=points_obj,
            points_in_image=points_img,
            markers_used=tuple(used),
            outlier_ids=outliers,
            outlier_points_in_image=np.concatenate(outlier_points) if outlier_points else np.zeros((0, 2)),
            corners_in_image=img[inliers],
            solver=solver,
        )

    # -------------------------------------------------------------- steps
    def _fail(self, reason: str) -> PoseFailure:
        log.debug("board %s: %s", self.name, reason)
        return PoseFailure(-1, reason, target=self.target)

    def _candidates(self, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None) -> list[Pose]:
        out = []
        for quad_obj, quad_img in zip(obj, img):
            try:
                count, rvecs, tvecs, _ = cv2.solvePnPGeneric(quad_obj, quad_img, k, dist, flags=cv2.SOLVEPNP_IPPE)
            except cv2.error:
                continue
            out.extend(Pose(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs[:count], tvecs[:count]))
        if len(obj) >= 4:
            try:
                ok, rvec, tvec, _ = cv2.solvePnPRansac(
                    obj.reshape(-1, 3),
                    img.reshape(-1, 2),
                    k,
                    dist,
                    iterationsCount=100,
                    reprojectionError=self.inlier_px,
                    confidence=0.999,
                    flags=cv2.SOLVEPNP_SQPNP if not self.planar else cv2.SOLVEPNP_EPNP,
                )
                if ok:
                    out.append(Pose(np.ravel(rvec), np.ravel(tvec)))
            except cv2.error:
                pass
        return [p for p in out if p.is_finite() and np.linalg.norm(p.tvec) < MAX_DISTANCE_M]

    @staticmethod
    def _marker_errors(
        pose: Pose, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None
    ) -> np.ndarray:
        """RMS corner error per marker (inf where a marker is behind the camera)."""
        residual = _residuals(pose, obj.reshape(-1, 3), img.reshape(-1, 2), k, dist).reshape(-1, 4)
        errors = np.sqrt(np.mean(residual**2, axis=1))
        depth = pose.apply(obj.reshape(-1, 3))[:, 2].reshape(-1, 4)
        errors[np.any(depth <= 1e-6, axis=1)] = np.inf
        return errors

    def _charuco_corners(
        self, image: np.ndarray, obj: np.ndarray, img: np.ndarray, ids: np.ndarray, camera: CameraModel
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """ChArUco chessboard corners interpolated from the inlier markers (calibrated, so the
        interpolation follows the lens), with their board coordinates."""
        key = (camera.camera_matrix.tobytes(), None if camera.dist_or_none is None else camera.dist_or_none.tobytes())
        detector = self._charuco_detectors.get(key)
        if detector is None:  # one per calibration, not per frame
            params = cv2.aruco.CharucoParameters()
            params.cameraMatrix = camera.camera_matrix
            if camera.dist_or_none is not None:
                params.distCoeffs = camera.dist_or_none
            detector = self._charuco_detectors[key] = cv2.aruco.CharucoDetector(self.charuco, params)
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        try:
            chess_corners, chess_ids, _, _ = detector.detectBoard(
                grey,
                markerCorners=[c.reshape(1, 4, 2).astype(np.float32) for c in img],
                markerIds=ids.reshape(-1, 1).astype(np.int32),
            )
        except cv2.error as err:
            log.debug("board %s: ChArUco interpolation failed: %s", self.name, str(err).strip().splitlines()[-1])
            return None
        if chess_ids is None or len(chess_ids) == 0:
            return None
        chess_ids = chess_ids.reshape(-1)
        return self.chessboard[chess_ids], np.asarray(chess_corners, np.float64).reshape(-1, 2)

    def _final(
        self,
        start: Pose,
        points_obj: np.ndarray,
        points_img: np.ndarray,
        quads_obj: np.ndarray,
        camera: CameraModel,
        max_reproj_px: float,
    ) -> tuple[PoseHypothesis, ...] | str:
        k, dist = camera.camera_matrix, camera.dist_or_none
        flag = cv2.SOLVEPNP_IPPE if self.planar else cv2.SOLVEPNP_SQPNP
        seeds = [start]
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points_obj, points_img, k, dist, flags=flag)
            seeds += [Pose(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs[:count], tvecs[:count])]
        except cv2.error:
            pass
        found: list[PoseHypothesis] = []
        reasons = []
        for seed in seeds:
            if not seed.is_finite():
                continue
            pose = _refine_lm(seed, points_obj, points_img, k, dist)
            error, reason = check_pose(pose, points_obj, points_img, camera, max_reproj_px, require_front=False)
            if reason is None and not _faces_camera(pose, quads_obj):
                reason = "board seen from behind"
            if reason is not None:
                reasons.append(reason)
                continue
            if any(angle_between_deg(pose.rotation, h.pose.rotation) < 0.5 for h in found):
                continue  # the same solution reached twice
            found.append(PoseHypothesis(pose, error))
        if not found:
            return "; ".join(dict.fromkeys(reasons)) or "no valid solution"
        found.sort(key=lambda h: h.reproj_px)
        return tuple(found[:2])


def _residuals(pose: Pose, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    projected, _ = cv2.projectPoints(np.asarray(obj, np.float64), pose.rvec, pose.tvec, k, dist)
    return np.linalg.norm(projected.reshape(-1, 2) - np.asarray(img, np.float64).reshape(-1, 2), axis=1)


def _rms(pose: Pose, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None) -> float:
    residual = (cv2.projectPoints(obj, pose.rvec, pose.tvec, k, dist)[0].reshape(-1, 2) - img).ravel()
    return math.sqrt(float(residual @ residual) * 2.0 / len(residual))  # the RMS of the points' distances


def _folded(rvec: np.ndarray) -> np.ndarray:
    """The same rotation with its angle in [0, pi] (LM may step past pi)."""
    angle = math.sqrt(float(rvec @ rvec))
    if angle <= math.pi:
        return rvec
    turns = math.floor((angle + math.pi) / (2.0 * math.pi))  # angle - 2 pi turns lies in (-pi, pi]
    return rvec * ((angle - 2.0 * math.pi * turns) / angle)


def _refine_lm_rms(
    pose: Pose, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None
) -> tuple[Pose, float, float]:
    """``solvePnPRefineLM`` from ``pose``: (the better of the refined and the start pose, its RMS
    reprojection error, the start pose's RMS error). The start pose when LM fails or diverges."""
    obj, img = np.asarray(obj, np.float64), np.asarray(img, np.float64).reshape(-1, 2)
    before = _rms(pose, obj, img, k, dist)
    if len(obj) < 4:
        return pose, before, before
    try:
        rvec, tvec = cv2.solvePnPRefineLM(
            obj, img, k, dist, pose.rvec.reshape(3, 1).copy(), pose.tvec.reshape(3, 1).copy()
        )
    except cv2.error:
        return pose, before, before
    rvec, tvec = rvec.reshape(3), tvec.reshape(3)
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return pose, before, before
    refined = Pose(_folded(rvec), tvec)
    after = _rms(refined, obj, img, k, dist)
    return (refined, after, before) if after <= before else (pose, before, before)


def _refine_lm(pose: Pose, obj: np.ndarray, img: np.ndarray, k: np.ndarray, dist: np.ndarray | None) -> Pose:
    """``solvePnPRefineLM`` from ``pose``; the start pose when the refinement fails or diverges."""
    return _refine_lm_rms(pose, obj, img, k, dist)[0]
