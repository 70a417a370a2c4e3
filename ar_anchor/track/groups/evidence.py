"""The learned groups' pair evidence: for two lone markers measured in one frame, the candidates for their
relative pose (their solutions combined, and the flip-free planar one) and which recurring relative pose, a
*mode*, the frame's corners fit jointly (:func:`observe_pair`); each pair's modes and when one makes the
pair rigid (:class:`Pair`, :class:`Mode`). Steps 1 and 2 of :mod:`ar_anchor.track.groups`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...camera import CameraModel
from ...config import FilterConfig, GroupsConfig, TrackerConfig
from ...geometry import Pose, marker_corners_in_marker, mean_rotation
from ..filtering import decided_alone
from ..kernels import compiled_refine, distortion12
from ..marker_poses import refine_poses
from ..pose import MarkerPose, reprojection_rms

__all__ = ["Mode", "Pair", "observe_pair"]

_MAX_MODES = 6  # relative poses a pair keeps in mind at once
_NEW_MODE_DEG, _NEW_MODE_M = 2.0, 0.003  # a candidate this near an existing mode starts no new one
_TESTED_MODES = 2  # a frame is fitted against this many of the most supported modes and of the youngest
_MODE_FRAMES = 150  # frames of candidates a mode keeps for its consensus
_VOTE_DEG = 6.0  # candidates of two frames this near vote for the same relative rotation
_VOTE_SHARE = 0.8  # the winner must have a candidate in this share of the frames ...
_VOTE_RIVAL = 0.6  # ... and no rotation farther than 3 _VOTE_DEG from it more than this share of its votes
_PLANAR_FIT = 0.1  # a square fitted to the second marker in the first's plane within this share of its side

_Fits = Callable[["Mode"], bool]


class Mode:
    """One recurring relative pose of a pair: the candidates of the frames that fit it, their consensus
    (:meth:`_consensus`) and its support."""

    __slots__ = ("born", "count", "decided", "frames", "rotation", "translation")

    def __init__(self, rotation: np.ndarray, translation: np.ndarray, born: int) -> None:
        self.frames: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=_MODE_FRAMES)
        self.frames.append((rotation[None], translation[None], np.zeros(1, bool)))
        self.rotation, self.translation = rotation, translation
        self.count, self.born = 1, born
        self.decided = False  # the frames' candidates agree on one relative rotation (see _consensus)

    def add(self, rotations: np.ndarray, translations: np.ndarray, planar: np.ndarray) -> None:
        """A frame that fits: its candidates (the first marker's better-fitting solution with each of the
        second's, and the planar one when there is one: ``planar`` marks it)."""
        self.frames.append((rotations, translations, planar))
        self.count += 1
        if self.count <= 10 or self.count % 5 == 0 or not self.decided:
            self._consensus()

    def _consensus(self) -> None:
        """The relative rotation most frames have a candidate near (within :data:`_VOTE_DEG`: the flipped
        candidates move with the viewpoint, the true one stays), then the mean rotation and the median
        translation of each frame's candidate nearest it."""
        rotations = np.concatenate([r for r, _, _ in self.frames])
        translations = np.concatenate([t for _, t, _ in self.frames])
        planar = np.concatenate([p for _, _, p in self.frames])
        counts = np.array([len(r) for r, _, _ in self.frames])  # every frame has a candidate
        frame_of = np.repeat(np.arange(len(counts)), counts)
        cosines = (np.einsum("nab,mab->nm", rotations, rotations) - 1.0) / 2.0
        near = cosines > math.cos(math.radians(_VOTE_DEG))
        # support: the frames with a candidate near each one (a frame's candidates are consecutive columns)
        starts = np.concatenate(([0], np.cumsum(counts[:-1])))
        support = np.logical_or.reduceat(near, starts, axis=1).sum(axis=1)
        best = int(np.argmax(support))
        rival = support[cosines[best] < math.cos(math.radians(3 * _VOTE_DEG))]  # rotations clearly elsewhere
        self.decided = support[best] >= _VOTE_SHARE * len(self.frames) and (
            len(rival) == 0 or rival.max() <= _VOTE_RIVAL * support[best]
        )
        chosen = {}
        for n in np.flatnonzero(near[best]):  # per frame, its candidate nearest the winner (the planar first)
            k = frame_of[n]
            if k not in chosen or (planar[n], cosines[best, n]) > (planar[chosen[k]], cosines[best, chosen[k]]):
                chosen[k] = n
        picked = np.array(sorted(chosen.values()))
        self.rotation = mean_rotation(list(rotations[picked]))
        self.translation = np.median(translations[picked], axis=0)

    def pose(self) -> Pose:
        return Pose.from_matrix(self.rotation, self.translation)


@dataclass
class Pair:
    """Evidence about one pair of markers ``(i, j)``, ``i < j``: the frames that saw both, and the modes
    of their relative pose ``i_from_j``."""

    seen: int = 0
    modes: list[Mode] = field(default_factory=list)

    def observe(self, rotations: np.ndarray, translations: np.ndarray, planar: np.ndarray, fits: _Fits) -> None:
        """One frame's candidates (K, 3, 3), (K, 3), which is the planar one (``planar``, (K,) bool), and
        ``fits(mode)``: do this frame's corners fit the mode?"""
        self.seen += 1
        supported = sorted(self.modes, key=lambda m: -m.count)[:_TESTED_MODES]
        young = [m for m in sorted(self.modes, key=lambda m: -m.born) if m not in supported][:_TESTED_MODES]
        for mode in supported + young:
            if fits(mode):
                mode.add(rotations, translations, planar)
                return
        for k in range(len(rotations)):  # nothing fits: each candidate may be the start of the true pose
            if any(_near(mode, rotations[k], translations[k]) for mode in self.modes):
                continue
            if len(self.modes) >= _MAX_MODES:
                self.modes.remove(min(self.modes, key=lambda mode: (mode.count, -mode.born)))
            self.modes.append(Mode(rotations[k].copy(), translations[k].copy(), self.seen))

    def rigid(self, settings: GroupsConfig) -> Mode | None:
        """The mode that makes the pair rigid (see :mod:`ar_anchor.track.groups`, 2.), if any."""
        if not self.modes:
            return None
        mode = max(self.modes, key=lambda m: m.count)
        share = mode.count / max(self.seen - mode.born + 1, 1)
        enough = mode.count >= settings.min_frames and share >= settings.agreement and mode.decided
        return mode if enough else None


def observe_pair(pair: Pair, first: MarkerPose, second: MarkerPose, camera: CameraModel, config: TrackerConfig) -> None:
    """One frame's evidence for ``pair``: the candidates for the relative pose ``first_from_second`` of two lone
    markers measured in it (each combination of their plausible solutions, :func:`_plausible`, and the planar
    one when they share a plane, :func:`_planar_candidate`), and which of the pair's modes the two markers'
    eight corners fit jointly (:func:`_joint_fit` within ``[groups] agree_px``; see :meth:`Pair.observe`)."""
    rotations, translations, planar = [], [], []
    for mine in _plausible(first, config.filter):
        ra, ta = mine.pose.rotation, mine.pose.tvec
        for theirs in _plausible(second, config.filter):
            rotations.append(ra.T @ theirs.pose.rotation)
            translations.append(ra.T @ (theirs.pose.tvec - ta))
            planar.append(False)
    in_plane = _planar_candidate(first, second, camera)
    if in_plane is not None:  # (both markers in one plane: a candidate the planar flip has no part in)
        rotations.append(in_plane.rotation)
        translations.append(in_plane.tvec)
        planar.append(True)
    image = np.concatenate([first.corners_in_image.reshape(4, 2), second.corners_in_image.reshape(4, 2)])
    square = marker_corners_in_marker(second.length_m)

    starts = [h.pose for h in first.hypotheses]

    def fits(mode: Mode) -> bool:
        points = np.concatenate([first.points_in_target, square @ mode.rotation.T + mode.translation])
        return bool(np.any(_joint_fit_rms(points, image, starts, camera) <= config.groups.agree_px))

    pair.observe(np.stack(rotations), np.stack(translations), np.array(planar), fits)


def _planar_candidate(first: MarkerPose, second: MarkerPose, camera: CameraModel) -> Pose | None:
    """``first_from_second`` if both markers lie in one plane: the second's corners taken into the first's
    plane through the homography of the first's four corners (unique: the planar flip is a choice made only
    when that homography is split into a rotation and a translation), and a square of the second's side
    fitted to them (in-plane turn and shift). None when they do not form such a square (not one plane)."""
    pixels = np.concatenate([first.corners_in_image.reshape(4, 2), second.corners_in_image.reshape(4, 2)])
    undistorted = pixels.astype(np.float64)
    if camera.dist_or_none is not None:  # (the homography holds between undistorted points)
        k = camera.camera_matrix
        undistorted = cv2.undistortPoints(pixels.reshape(-1, 1, 2), k, camera.dist_or_none, P=k).reshape(-1, 2)
    square_first = marker_corners_in_marker(first.length_m)[:, :2]
    try:
        homography = cv2.getPerspectiveTransform(undistorted[:4].astype(np.float32), square_first.astype(np.float32))
    except cv2.error:
        return None
    points = cv2.perspectiveTransform(undistorted[4:].reshape(-1, 1, 2), homography).reshape(4, 2)
    square = marker_corners_in_marker(second.length_m)[:, :2]
    centre = points.mean(axis=0)
    u, _, vt = np.linalg.svd((square - square.mean(axis=0)).T @ (points - centre))
    turn = (u @ vt).T
    if np.linalg.det(turn) < 0:
        return None  # a mirrored square: not the second marker seen in the first's plane
    residual = float(np.sqrt(np.mean(np.sum((square @ turn.T + centre - points) ** 2, axis=1))))
    if not np.isfinite(residual) or residual > _PLANAR_FIT * second.length_m:
        return None
    rotation = np.eye(3)
    rotation[:2, :2] = turn
    return Pose.from_matrix(rotation, np.array([centre[0], centre[1], 0.0]))


def _plausible(solved: MarkerPose, config: FilterConfig) -> tuple:
    """A marker's solutions that this frame leaves possible: both, unless the frame alone decides its flip
    (:func:`~ar_anchor.track.filtering.decided_alone`): then a flipped candidate would only vote for a wrong
    relative rotation."""
    return solved.hypotheses[:1] if decided_alone(solved.hypotheses, config) else solved.hypotheses


def _near(mode: Mode, rotation: np.ndarray, translation: np.ndarray) -> bool:
    cosine = (float(np.vdot(mode.rotation, rotation)) - 1.0) / 2.0
    near_turn = math.degrees(math.acos(min(1.0, max(-1.0, cosine)))) < _NEW_MODE_DEG
    return near_turn and float(np.linalg.norm(mode.translation - translation)) < _NEW_MODE_M


def _joint_fit_rms(points: np.ndarray, image: np.ndarray, starts: list[Pose], camera: CameraModel) -> np.ndarray:
    """The RMS reprojection errors (one per start pose) of the camera pose refined by Levenberg-Marquardt
    from each of ``starts`` on ``points`` (N, 3) and ``image`` (N, 2); NaN (no fit) for a start that puts a
    point behind the camera. The pose stage's compiled polish (:func:`~ar_anchor.track.marker_poses.refine_poses`),
    all starts in one call: 32 us for two starts against 113 us a start for ``solvePnPRefineLM`` (8 points).
    OpenCV's where the polish is not compiled (its numpy version is slower still). Both reach the same fit.
    """
    if compiled_refine() is None or distortion12(camera.dist_or_none) is None:
        return np.array([_opencv_joint_fit_rms(start, points, image, camera) for start in starts])
    count = len(starts)
    rotations = np.stack([start.rotation for start in starts])
    tvecs = np.stack([start.tvec for start in starts])
    obj = np.broadcast_to(points, (count, *points.shape))
    img = np.broadcast_to(image, (count, *image.shape))
    return refine_poses(rotations, tvecs, obj, img, camera.camera_matrix, camera.dist_or_none)[2]


def _opencv_joint_fit_rms(start: Pose, points: np.ndarray, image: np.ndarray, camera: CameraModel) -> float:
    """``solvePnPRefineLM`` from ``start``: the refined pose's RMS reprojection error (inf when it fails)."""
    rvec, tvec = start.rvec.reshape(3, 1).copy(), start.tvec.reshape(3, 1).copy()
    try:
        rvec, tvec = cv2.solvePnPRefineLM(points, image, camera.camera_matrix, camera.dist_or_none, rvec, tvec)
    except cv2.error:
        return math.inf
    pose = Pose(rvec.ravel(), tvec.ravel())
    return reprojection_rms(pose, points, image, camera) if pose.is_finite() else math.inf
