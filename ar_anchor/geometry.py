"""Rigid-body geometry in OpenCV's conventions.

A :class:`Pose` is ``b_from_a``: it maps points expressed in frame ``a`` into frame ``b``
(``X_b = R X_a + t``). The tracker's main pose is ``camera_from_target``: ``t`` is the target
origin seen from the camera, *not* the camera position; the camera centre in the target frame
is ``C = -R^T t`` (:meth:`Pose.camera_centre`). Rotations travel as Rodrigues vectors
(``rvec``, axis * angle in radians), metres throughout.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "Pose",
    "angle_between_deg",
    "look_at",
    "marker_corners_in_marker",
    "matrix_from_rvec",
    "mean_rotation",
    "pose_errors",
    "rvec_from_matrix",
    "transform_points",
]


def _as_vec3(value: object, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"{name}: expected 3 values, got shape {np.shape(value)}")
    return arr


def matrix_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector (3,) -> rotation matrix (3, 3)."""
    rotation, _ = cv2.Rodrigues(_as_vec3(rvec, "rvec"))
    return rotation


def rvec_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> Rodrigues vector (3,) with norm in [0, pi].

    A quaternion-based log map (Shepperd's method, as scipy's ``Rotation.from_matrix``, in plain
    numpy: it runs several times per target and frame): ``cv2.Rodrigues`` rounds rotations below
    about 1e-5 rad to exactly zero, which would lose small increments when poses are composed.
    """
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"rotation: expected shape (3, 3), got {m.shape}")
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m.tolist()  # plain floats: several times faster here
    if not all(map(math.isfinite, (m00, m01, m02, m10, m11, m12, m20, m21, m22))):
        return np.full(3, np.nan)
    trace = m00 + m11 + m22
    diagonal = (m00, m11, m22, trace)
    largest = diagonal.index(max(diagonal))
    if largest == 3:
        q = (m21 - m12, m02 - m20, m10 - m01, 1.0 + trace)
    elif largest == 0:
        q = (1.0 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12)
    elif largest == 1:
        q = (m01 + m10, 1.0 + m11 - m00 - m22, m12 + m21, m02 - m20)
    else:
        q = (m02 + m20, m12 + m21, 1.0 + m22 - m00 - m11, m10 - m01)
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = -1.0 if q[3] < 0 else 1.0
    x, y, z, w = (sign * v / norm for v in q)
    sine = math.sqrt(x * x + y * y + z * z)
    if sine < 1e-12:
        return np.array([2.0 * x / w, 2.0 * y / w, 2.0 * z / w])  # the small-angle limit of angle * vector / sine
    factor = 2.0 * math.atan2(sine, w) / sine
    return np.array([factor * x, factor * y, factor * z])


def vector_norm(vector: np.ndarray) -> float:
    """Euclidean length of a short 1-D vector (``np.linalg.norm`` costs several times more on 3 entries)."""
    return math.sqrt(float(np.dot(vector, vector)))


def angle_between_deg(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Geodesic angle in degrees between two rotation matrices (0..180)."""
    trace = float(np.vdot(rotation_a, rotation_b))  # trace(A^T B), the sum of the element-wise products
    return math.degrees(math.acos(min(1.0, max(-1.0, (trace - 1.0) / 2.0))))


def mean_rotation(rotations: Sequence[np.ndarray]) -> np.ndarray:
    """The chordal mean of 3x3 rotation matrices (the SVD projection of their sum onto the rotations)."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    mean = u @ vt
    if np.linalg.det(mean) < 0:
        mean = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return mean


def pose_errors(estimate: Pose, truth: Pose) -> tuple[float, float]:
    """(rotation error in degrees, translation error in % of the true distance) of ``estimate``."""
    rotation = angle_between_deg(estimate.rotation, truth.rotation)
    return rotation, 100.0 * float(np.linalg.norm(estimate.tvec - truth.tvec) / np.linalg.norm(truth.tvec))


def marker_corners_in_marker(length_m: float) -> np.ndarray:
    """Corners TL, TR, BR, BL of a square marker in its own frame, shape (4, 3).

    The marker frame is centred, x right, y up, z toward the viewer; this order is the one
    ``SOLVEPNP_IPPE_SQUARE`` requires: ``(-h, h, 0), (h, h, 0), (h, -h, 0), (-h, -h, 0)``, h = side / 2.
    """
    h = length_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def transform_points(rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``X' = R X + t`` to points of shape (N, 3)."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(rotation).T + np.asarray(translation)


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``b_from_a`` stored as Rodrigues vector and translation (metres).

    Attributes
    ----------
    rvec : (3,) float64, axis-angle rotation, radians.
    tvec : (3,) float64, translation, metres.
    """

    rvec: np.ndarray
    tvec: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "rvec", _as_vec3(self.rvec, "rvec"))
        object.__setattr__(self, "tvec", _as_vec3(self.tvec, "tvec"))
        self.rvec.flags.writeable = False
        self.tvec.flags.writeable = False

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.zeros(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, rotation: np.ndarray, translation: np.ndarray) -> Pose:
        return cls(rvec_from_matrix(rotation), translation)

    @functools.cached_property
    def rotation(self) -> np.ndarray:
        """Rotation matrix R (3, 3), read-only (computed once: poses are asked for it many times a frame)."""
        rotation = matrix_from_rvec(self.rvec)
        rotation.flags.writeable = False
        return rotation

    def as_homogeneous(self) -> np.ndarray:
        """4x4 matrix [[R, t], [0, 1]]."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.tvec
        return matrix

    def inverse(self) -> Pose:
        """``a_from_b`` for this ``b_from_a``: R^T, -R^T t."""
        rotation_t = self.rotation.T
        return Pose.from_matrix(rotation_t, -rotation_t @ self.tvec)

    def camera_centre(self) -> np.ndarray:
        """For a ``camera_from_target`` pose: the camera centre in target coordinates, ``-R^T t``."""
        return -self.rotation.T @ self.tvec

    def compose(self, other: Pose) -> Pose:
        """``c_from_a = self (c_from_b) ∘ other (b_from_a)``."""
        rotation = self.rotation
        return Pose.from_matrix(rotation @ other.rotation, rotation @ other.tvec + self.tvec)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (N, 3) from frame a to frame b."""
        return transform_points(self.rotation, self.tvec, points)

    def is_finite(self) -> bool:
        return bool(np.isfinite(self.rvec).all() and np.isfinite(self.tvec).all())


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 1.0, 0.0)) -> Pose:
    """``camera_from_world`` for an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image.
    """
    eye = _as_vec3(eye, "eye")
    target = _as_vec3(target, "target")
    forward = target - eye
    norm = np.linalg.norm(forward)
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z_axis = forward / norm
    x_axis = np.cross(z_axis, _as_vec3(up, "up"))
    if np.linalg.norm(x_axis) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    world_from_camera_rotation = np.column_stack([x_axis, y_axis, z_axis])
    rotation = world_from_camera_rotation.T
    return Pose.from_matrix(rotation, -rotation @ eye)
