"""Camera intrinsics: the pinhole matrix K, lens distortion and the image size they belong to.

Files are OpenCV FileStorage YAML with the keys OpenCV's calibration sample writes:
``camera_matrix`` (3x3), ``distortion_coefficients`` (1xN, N in 4, 5, 8, 12, 14),
``image_width``, ``image_height``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .errors import CameraError

__all__ = ["CameraModel"]

log = logging.getLogger(__name__)

_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


@dataclass(frozen=True)
class CameraModel:
    """Calibrated camera.

    Attributes
    ----------
    camera_matrix : (3, 3) float64, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels, with pixel
        centres at integer coordinates (OpenCV's convention).
    dist_coeffs : (N,) float64, OpenCV distortion (k1, k2, p1, p2[, k3[, ...]]); empty for none.
    width, height : image size in pixels the intrinsics were calibrated at.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        matrix = np.asarray(self.camera_matrix, dtype=np.float64)
        if matrix.shape != (3, 3):
            raise CameraError(f"camera_matrix: expected 3x3, got shape {matrix.shape}")
        if not np.all(np.isfinite(matrix)):
            raise CameraError("camera_matrix: contains non-finite values")
        fx, fy = matrix[0, 0], matrix[1, 1]
        if fx <= 0 or fy <= 0:
            raise CameraError(f"camera_matrix: focal lengths must be > 0, got fx={fx:g}, fy={fy:g}")
        if not np.allclose(matrix[2], [0.0, 0.0, 1.0]) or matrix[1, 0] != 0.0:
            raise CameraError("camera_matrix: last row must be [0, 0, 1] and K[1][0] must be 0")
        dist = np.asarray(self.dist_coeffs, dtype=np.float64).reshape(-1)
        if dist.size not in _DIST_LENGTHS:
            raise CameraError(f"distortion_coefficients: expected 4, 5, 8, 12 or 14 values (or none), got {dist.size}")
        if not np.all(np.isfinite(dist)):
            raise CameraError("distortion_coefficients: contains non-finite values")
        if not (isinstance(self.width, (int, np.integer)) and isinstance(self.height, (int, np.integer))):
            raise CameraError("image_width/image_height: must be integers")
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        matrix.flags.writeable = False
        dist.flags.writeable = False
        object.__setattr__(self, "camera_matrix", matrix)
        object.__setattr__(self, "dist_coeffs", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_fov(cls, width: int, height: int, fx: float, fy: float | None = None) -> CameraModel:
        """Ideal pinhole camera, principal point at the image centre ((W-1)/2, (H-1)/2)."""
        fy = fx if fy is None else fy
        matrix = np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(matrix, np.zeros(0), width, height)

    @classmethod
    def default_synthetic(cls) -> CameraModel:
        """The camera of ``configs/camera_synthetic.yml``: 1280x720, fx = fy = 1000 px, no distortion."""
        return cls.from_fov(1280, 720, 1000.0)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> CameraModel:
        """Read an OpenCV FileStorage YAML camera file; raise :class:`CameraError` naming the file."""
        path = Path(path)
        if not path.is_file():
            raise CameraError(f"camera file {path}: not found")
        try:
            text = path.read_bytes()
        except OSError as err:
            raise CameraError(f"camera file {path}: cannot read ({err.strerror})") from err
        if not text.strip():
            raise CameraError(f"camera file {path}: file is empty")
        try:
            storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as err:  # OpenCV 5's binding wraps parse errors in SystemError
            raise CameraError(f"camera file {path}: not valid OpenCV YAML/XML ({_first_line(err)})") from None
        try:
            if not storage.isOpened():
                raise CameraError(f"camera file {path}: cannot be parsed as OpenCV FileStorage")
            if not storage.root().isMap():
                raise CameraError(f"camera file {path}: expected key: value pairs at the top level")
            matrix = _read_mat(storage, "camera_matrix", path, required=True)
            dist = _read_mat(storage, "distortion_coefficients", path, required=False)
            width = _read_int(storage, "image_width", path)
            height = _read_int(storage, "image_height", path)
        except (cv2.error, SystemError) as err:
            raise CameraError(f"camera file {path}: unreadable content ({_first_line(err)})") from None
        finally:
            storage.release()
        if matrix is not None and matrix.size == 9:
            matrix = matrix.reshape(3, 3)
        try:
            return cls(matrix, np.zeros(0) if dist is None else dist, width, height)
        except CameraError as err:
            raise CameraError(f"camera file {path}: {err}") from err

    def to_yaml(self, path: str | os.PathLike[str], **extra: str | float | int) -> None:
        """Write the OpenCV FileStorage YAML that :meth:`from_yaml` reads (extra scalars appended)."""
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        try:
            storage.write("image_width", self.width)
            storage.write("image_height", self.height)
            storage.write("camera_matrix", np.array(self.camera_matrix))
            dist = self.dist_coeffs if self.dist_coeffs.size else np.zeros(5)
            storage.write("distortion_coefficients", np.array(dist).reshape(1, -1))
            for key, value in extra.items():
                storage.write(key, value)
        finally:
            storage.release()

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    @property
    def has_distortion(self) -> bool:
        return bool(self.dist_coeffs.size and np.any(self.dist_coeffs != 0.0))

    @property
    def dist_or_none(self) -> np.ndarray | None:
        """Distortion for OpenCV calls (None when there is none)."""
        return self.dist_coeffs if self.has_distortion else None

    def scaled_to(self, width: int, height: int, *, warn: bool = True) -> CameraModel:
        """Intrinsics for the same lens at another resolution (pixel-centre convention kept).

        Logs a warning (calibrate at the resolution you track at when you can). A different aspect
        ratio is a :class:`CameraError`: the stream is then cropped or stretched in a way the
        calibration cannot know.
        """
        if (width, height) == self.size:
            return self
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise CameraError(
                f"camera calibrated at {self.width}x{self.height} (aspect {self.width / self.height:.3f}) cannot be "
                f"used for {width}x{height} frames (aspect {width / height:.3f}): calibrate at this resolution"
            )
        log.log(
            logging.WARNING if warn else logging.DEBUG,
            "camera calibrated at %dx%d used at %dx%d: scaling intrinsics by %.4g",
            self.width,
            self.height,
            width,
            height,
            sx,
        )
        k = np.array(self.camera_matrix)
        k[0, 0] *= sx
        k[0, 1] *= sx
        k[1, 1] *= sy
        k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
        k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
        return CameraModel(k, self.dist_coeffs, width, height)

    def project(self, points_in_camera: np.ndarray) -> np.ndarray:
        """Project camera-frame points (N, 3) to pixels (N, 2) through the distortion model."""
        points = np.asarray(points_in_camera, dtype=np.float64).reshape(-1, 3)
        if points.size == 0:
            return np.zeros((0, 2))
        pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), self.camera_matrix, self.dist_or_none)
        return pixels.reshape(-1, 2)


def _first_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


def _read_mat(storage: cv2.FileStorage, key: str, path: Path, *, required: bool) -> np.ndarray | None:
    node = storage.getNode(key)
    if node.empty() or node.isNone():
        if required:
            raise CameraError(f"camera file {path}: missing '{key}'")
        return None
    if node.isSeq():
        values = [node.at(i).real() for i in range(node.size())]
        return np.asarray(values, dtype=np.float64)
    if not node.isMap():
        raise CameraError(f"camera file {path}: '{key}' is not an OpenCV matrix (!!opencv-matrix)")
    mat = node.mat()
    if mat is None:
        raise CameraError(f"camera file {path}: '{key}' is not an OpenCV matrix (!!opencv-matrix)")
    return np.asarray(mat, dtype=np.float64)


def _read_int(storage: cv2.FileStorage, key: str, path: Path) -> int:
    node = storage.getNode(key)
    if node.empty() or node.isNone():
        raise CameraError(f"camera file {path}: missing '{key}'")
    if not (node.isInt() or node.isReal()):
        raise CameraError(f"camera file {path}: '{key}' must be a number")
    value = node.real()
    if not np.isfinite(value) or value != int(value) or value <= 0:
        raise CameraError(f"camera file {path}: '{key}' must be a positive integer, got {value:g}")
    return int(value)
