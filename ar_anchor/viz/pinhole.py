"""The viewer's pinhole for a camera: the matrix that maps the camera frame onto a logged image
(:func:`image_from_camera`), and what the viewer's projected overlay misses for want of lens distortion.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from ..camera import CameraModel


def image_from_camera(camera: CameraModel, scale: float = 1.0) -> np.ndarray:
    """The viewer's pinhole matrix for an image of ``camera`` logged at ``scale``: ``camera_matrix`` with the
    principal point half a pixel further (OpenCV puts pixel centres at integers, rerun pixel corners) and
    scaled, so that it maps a point in the camera frame to where it is on the logged image (lens
    distortion aside: the viewer has none)."""
    to_rerun = np.diag([scale, scale, 1.0]) @ np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    return to_rerun @ np.asarray(camera.camera_matrix, np.float64)


def _distortion_note(camera: CameraModel) -> str | None:
    """What the viewer's projected overlay misses (its pinhole has no distortion): how far a point on the
    image's border is from where an undistorted camera sees it, at most; None for a camera without
    distortion."""
    if not camera.has_distortion:
        return None
    width, height = camera.width, camera.height
    edge = np.linspace(0.0, 1.0, 33)
    border = np.concatenate(
        [np.c_[edge * (width - 1), np.zeros_like(edge)], np.c_[edge * (width - 1), np.full_like(edge, height - 1)]]
        + [np.c_[np.zeros_like(edge), edge * (height - 1)], np.c_[np.full_like(edge, width - 1), edge * (height - 1)]]
    )
    matrix = np.asarray(camera.camera_matrix, np.float64)
    ideal = cv2.undistortPoints(border.reshape(-1, 1, 2), matrix, camera.dist_or_none, P=matrix).reshape(-1, 2)
    offsets = np.linalg.norm(ideal - border, axis=1)
    offsets = offsets[np.isfinite(offsets)]
    worst = float(offsets.max()) if offsets.size else float("nan")
    return (
        f"camera view: the viewer projects the 3D overlay without lens distortion (its pinhole has none): up to "
        f"{worst:.1f} px off at the image's edges, exact at its centre; the image and the 2D detections are "
        "the camera's own (distorted) pixels"
    )
