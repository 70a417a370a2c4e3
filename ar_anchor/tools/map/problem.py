"""The map problem: the observations with the cameras, the marker square and each frame's corners in normalised
image coordinates precomputed, and what initialisation and bundle adjustment share."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...camera import CameraModel
from ...geometry import Pose, marker_corners_in_marker
from .model import FrameObservations

HUBER_PX = 1.0  # the robust loss's scale

Progress = Callable[[str], None]


@dataclass
class Problem:
    """The observations with what every step needs precomputed: the cameras, the marker square, and each
    frame's corners undistorted to normalised image coordinates (for fast vectorised scoring)."""

    frames: list[FrameObservations]
    cameras: list[CameraModel]  # per input
    length_m: float
    square: np.ndarray = field(init=False)
    normalised: list[np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.square = marker_corners_in_marker(self.length_m)
        self.normalised = []
        for frame in self.frames:
            camera = self.camera(frame)
            points = cv2.undistortPoints(
                frame.corners.reshape(-1, 1, 2),
                camera.camera_matrix,
                camera.dist_or_none,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
            )
            self.normalised.append(points.reshape(-1, 4, 2))

    def camera(self, frame: FrameObservations) -> CameraModel:
        """The camera ``frame`` was seen by."""
        return self.cameras[frame.source]

    def focal(self, frame: FrameObservations) -> float:
        """The mean focal length (pixels) of ``frame``'s camera."""
        k = self.camera(frame).camera_matrix
        return float(0.5 * (k[0, 0] + k[1, 1]))


def rotations(poses: Sequence[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations and (N, 3) translations of ``poses``."""
    return np.stack([p.rotation for p in poses]), np.stack([p.tvec for p in poses])
