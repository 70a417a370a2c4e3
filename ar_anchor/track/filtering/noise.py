"""Measurement noise: the corner noise, estimated online from the residuals, and the pose covariance it
implies through the projection Jacobian (see the package doc)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ...camera import CameraModel
from ...config import FilterConfig
from ...geometry import Pose
from ..pose import BoardPose, MarkerPose

__all__ = ["CornerNoise", "pose_covariance", "unit_covariances_of", "unit_pose_covariances"]

_EYE3, _EYE6 = np.eye(3), np.eye(6)


def pose_covariance(
    pose: Pose, points_in_target: np.ndarray, camera: CameraModel, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of (rotation error, translation) implied by isotropic corner noise ``sigma_px``.

    Linearises the pinhole projection at ``pose`` with the rotation perturbed on the right
    (``R exp(dtheta)``, the filter's error convention): ``Sigma = sigma^2 (J^T J)^-1``. Returns the
    3x3 rotation block (rad^2, body frame) and the 3x3 translation block (m^2, camera frame).
    """
    points = np.asarray(points_in_target, dtype=np.float64).reshape(1, -1, 3)
    unit = unit_pose_covariances(pose.rotation[None], pose.tvec[None], points, camera)[0]
    covariance = sigma_px**2 * unit
    return covariance[:3, :3], covariance[3:, 3:]


def unit_pose_covariances(
    rotations: np.ndarray, translations: np.ndarray, points_in_target: np.ndarray, camera: CameraModel
) -> np.ndarray:
    """:func:`pose_covariance`'s full 6x6 matrices at a corner noise of one pixel, for K poses at once:
    ``rotations`` (K, 3, 3), ``translations`` (K, 3), each pose's points (K, N, 3). Returns (K, 6, 6)."""
    fx, fy = camera.camera_matrix[0, 0], camera.camera_matrix[1, 1]
    points = np.asarray(points_in_target, dtype=np.float64)
    poses, count = points.shape[:2]
    in_camera = points @ rotations.transpose(0, 2, 1) + translations[:, None, :]  # (K, N, 3)
    x, y, z = in_camera[..., 0], in_camera[..., 1], in_camera[..., 2]
    d_pixel_d_cam = np.zeros((poses, count, 2, 3))  # the pinhole projection's Jacobian at each point
    d_pixel_d_cam[..., 0, 0] = fx / z
    d_pixel_d_cam[..., 0, 2] = -fx * x / z**2
    d_pixel_d_cam[..., 1, 1] = fy / z
    d_pixel_d_cam[..., 1, 2] = -fy * y / z**2
    px, py, pz = points[..., 0], points[..., 1], points[..., 2]
    skew = np.zeros((poses, count, 3, 3))  # [p]_x per point
    skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -pz, py, -px
    skew[..., 1, 0], skew[..., 2, 0], skew[..., 2, 1] = pz, -py, px
    d_rotation = -rotations[:, None] @ skew  # (K, N, 3, 3)
    d_cam = np.concatenate([d_rotation, np.broadcast_to(_EYE3, d_rotation.shape)], axis=3)  # (K, N, 3, 6)
    jacobian = (d_pixel_d_cam @ d_cam).reshape(poses, 2 * count, 6)
    information = jacobian.transpose(0, 2, 1) @ jacobian
    trace = np.trace(information, axis1=1, axis2=2)
    information += _EYE6 * (1e-9 * trace)[:, None, None]  # keep it invertible at degenerate views
    return np.linalg.inv(information)


# 4 corners (8 coordinates), 6 pose parameters: E[RMS^2] = sigma^2 (8 - 6) / 4, so sigma = RMS * sqrt(2)
_RESIDUAL_TO_SIGMA = math.sqrt(2.0)


class CornerNoise:
    """One target's corner noise and this frame's pose covariances (each pose is asked for several times)."""

    _OUTLIER_RATIO = 2.5  # a frame with this many times the usual residual is not vouched for ...
    _OUTLIER_MIN_PX = 0.15  # ... if that residual is above this (below it, a fit is good by any standard)

    def __init__(self, config: FilterConfig, points_in_target: np.ndarray) -> None:
        self.config = config
        self.points = np.asarray(points_in_target, dtype=np.float64)
        self.sigma_px = config.corner_noise_px  # the slow estimate
        self.frame_sigma_px = config.corner_noise_px  # this frame's: the larger of the slow one and its own
        self.outlier = False  # this frame's residual is far above the track's usual one
        self._usual_px: float | None = None
        self._covariances: dict[int, tuple[Pose, tuple[np.ndarray, np.ndarray]]] = {}  # this frame's, by pose
        self._unit: Mapping[int, tuple[Pose, np.ndarray]] = {}  # this frame's at one pixel of noise, by pose

    def new_frame(self, unit: Mapping[int, tuple[Pose, np.ndarray]] | None = None) -> None:
        """A new frame: ``unit``, this frame's poses' covariances at one pixel of corner noise (id(pose) ->
        (pose, 6x6)), computed for all targets at once (:func:`unit_pose_covariances`), where known."""
        self._covariances.clear()
        self._unit = unit or {}

    def covariance(self, pose: Pose, camera: CameraModel) -> tuple[np.ndarray, ...]:
        """:func:`pose_covariance` of one of this frame's poses at this frame's corner noise."""
        cached = self._covariances.get(id(pose))
        if cached is None or cached[0] is not pose:
            unit = self._unit.get(id(pose))
            if unit is not None and unit[0] is pose:
                covariance = self.frame_sigma_px**2 * unit[1]
                blocks = (covariance[:3, :3], covariance[3:, 3:])
            else:
                blocks = pose_covariance(pose, self.points, camera, self.frame_sigma_px)
            cached = self._covariances[id(pose)] = (pose, blocks)
        return cached[1]

    def observe(self, measurement: MarkerPose | BoardPose) -> None:
        """Take this frame's measurement: its points and its residual. The corner noise is a slow estimate
        from the residuals, and this frame's own (a blurred frame's residuals are larger): its measurement is
        trusted by the larger of the two. A frame whose residual is ``_OUTLIER_RATIO`` times the track's
        usual one and above ``_OUTLIER_MIN_PX`` (motion blur, rolling shutter, a partly hidden marker) may
        be off by more than its noise says: it is an :attr:`outlier`, not vouched for."""
        self.points = np.asarray(measurement.points_in_target, dtype=np.float64)
        estimate = measurement.best.reproj_px * _RESIDUAL_TO_SIGMA
        usual = self._usual_px
        self.outlier = (
            usual is not None
            and estimate > self._OUTLIER_RATIO * max(usual, self.config.corner_noise_px)
            and measurement.best.reproj_px > self._OUTLIER_MIN_PX
        )
        if not self.outlier:  # the usual residual, slowly, from the frames that are not outliers
            self._usual_px = estimate if usual is None else 0.95 * usual + 0.05 * estimate
        self.sigma_px = max(self.config.corner_noise_px, 0.9 * self.sigma_px + 0.1 * estimate)
        self.frame_sigma_px = max(self.sigma_px, estimate)


def unit_covariances_of(
    measurements: Sequence[MarkerPose | BoardPose], camera: CameraModel
) -> dict[int, tuple[Pose, np.ndarray]]:
    """Every solution's covariance at one pixel of corner noise (id(pose) -> (pose, 6x6)), batched over the
    targets of a frame whose solutions have the same number of points (every lone marker: four)."""
    groups: dict[int, list[tuple[Pose, np.ndarray]]] = {}
    for measurement in measurements:
        points = np.asarray(measurement.points_in_target, dtype=np.float64).reshape(-1, 3)
        for hypothesis in measurement.hypotheses:
            groups.setdefault(len(points), []).append((hypothesis.pose, points))
    unit: dict[int, tuple[Pose, np.ndarray]] = {}
    for members in groups.values():
        rotations = np.stack([pose.rotation for pose, _ in members])
        translations = np.stack([pose.tvec for pose, _ in members])
        covariances = unit_pose_covariances(rotations, translations, np.stack([p for _, p in members]), camera)
        unit.update((id(pose), (pose, covariance)) for (pose, _), covariance in zip(members, covariances))
    return unit
