"""Camera intrinsics: the pinhole matrix K, lens distortion and the image size they belong to.

A :class:`CameraModel` is read from a camera file (:meth:`CameraModel.from_yaml`: OpenCV FileStorage YAML, XML
or JSON, ROS ``camera_info`` YAML, PhotonVision calibration JSON; the formats and their readers are in
:mod:`.files`) and written as OpenCV YAML (:meth:`CameraModel.to_yaml`).

Without any file, :meth:`CameraModel.assumed` is the pinhole a focal length (or a field of view) gives.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import CameraError, OutputError
from .files import opencv_path_problem, read_camera_file

__all__ = ["CameraModel", "focal_from_hfov", "hfov_from_focal"]

log = logging.getLogger(__name__)

_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)

# A camera matrix that cannot be a real camera's is refused, one that is odd is used with a warning:
_FOCAL_RANGE = (0.01, 1000.0)  # fx, fy in image sides (max(width, height)): 179 deg to 0.06 deg of view
_CENTRE_SLACK = 0.5  # the principal point within [-0.5, 1.5] x the image size (warned outside the image)
_SKEW_REFUSED = 0.1  # |K[0][1]| above this x fx is refused (OpenCV's model has no skew and ignores it) ...
_SKEW_WARNED = 1e-6  # ... and above this x fx warned about


def focal_from_hfov(width: int, hfov_deg: float) -> float:
    """The focal length (pixels) of a pinhole whose ``width``-pixel image spans ``hfov_deg`` degrees across."""
    return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def hfov_from_focal(width: int, focal_px: float) -> float:
    """The horizontal field of view (degrees) of a pinhole of focal length ``focal_px`` (pixels), ``width`` wide."""
    return math.degrees(2.0 * math.atan2(width / 2.0, focal_px))


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
    def assumed(
        cls, width: int, height: int, *, focal_px: float | None = None, hfov_deg: float | None = None
    ) -> CameraModel:
        """The pinhole a camera without a calibration is taken for: principal point at the image centre, no
        distortion, fx = fy = ``focal_px``, or ``(width / 2) / tan(hfov_deg / 2)`` from the horizontal field of
        view ``hfov_deg`` (degrees) of a ``width`` x ``height`` image; exactly one of the two is given."""
        if (focal_px is None) == (hfov_deg is None):
            raise ValueError("give exactly one of focal_px and hfov_deg")
        if focal_px is None:
            focal_px = focal_from_hfov(width, hfov_deg)
        return cls.from_fov(width, height, float(focal_px))

    @classmethod
    def default_synthetic(cls) -> CameraModel:
        """The camera of ``configs/camera_synthetic.yml``: 1280x720, fx = fy = 1000 px, no distortion."""
        return cls.from_fov(1280, 720, 1000.0)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> CameraModel:
        """Read a camera file (OpenCV FileStorage YAML, XML or JSON; ROS camera_info YAML; PhotonVision calibration
        JSON); raise :class:`CameraError` naming the file."""
        values = read_camera_file(Path(path))
        try:
            camera = cls(values.matrix, values.dist, values.width, values.height)
            camera.check_plausible()
        except CameraError as err:
            raise CameraError(f"{values.where}: {err}") from err
        if values.photonvision:
            log.info("%s: %dx%d, fx %.1f px", values.where, camera.width, camera.height, camera.camera_matrix[0, 0])
        return camera

    def to_yaml(self, path: str | os.PathLike[str], **extra: str | float | int | np.ndarray) -> None:
        """Write the OpenCV FileStorage YAML that :meth:`from_yaml` reads (extra scalars and matrices appended)."""
        problem = opencv_path_problem(path)
        if problem is not None:
            raise OutputError(f"{path}: cannot write ({problem})")
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

    def check_plausible(self) -> None:
        """Refuse (:class:`CameraError`) intrinsics no real camera has, warn about odd ones.

        Refused: a focal length outside 0.01 to 1000 image sides (checked before anything is computed
        from it), a principal point far outside the image (beyond half an image size), a skew
        ``K[0][1]`` above a tenth of fx (OpenCV's model has no skew: it ignores it), and distortion
        that folds the image (the lens model turns back on itself before the image's edge, so that two
        directions land on one pixel). Warned: a principal point outside the image, a small skew.
        """
        k, (width, height) = self.camera_matrix, self.size
        fx, fy, skew, cx, cy = k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]
        low, high = (factor * max(width, height) for factor in _FOCAL_RANGE)
        for name, focal in (("fx", fx), ("fy", fy)):
            if not low <= focal <= high:
                raise CameraError(
                    f"camera_matrix: {name} = {focal:g} px is no focal length for a {width}x{height} image "
                    f"(expected {low:g} to {high:g} px)"
                )
        slack_x, slack_y = _CENTRE_SLACK * width, _CENTRE_SLACK * height
        centre = f"principal point (cx, cy) = ({cx:g}, {cy:g})"
        if not (-slack_x <= cx <= width + slack_x and -slack_y <= cy <= height + slack_y):
            raise CameraError(
                f"camera_matrix: {centre} lies far outside the {width}x{height} image (a mistyped value, or the "
                "calibration of another image size?)"
            )
        if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
            log.warning(
                "camera_matrix: %s lies outside the %dx%d image (a cropped image's calibration?)", centre, width, height
            )
        if abs(skew) > _SKEW_REFUSED * fx:
            raise CameraError(f"camera_matrix: skew K[0][1] = {skew:g}: OpenCV's camera model has none (expected 0)")
        if abs(skew) > _SKEW_WARNED * fx:
            log.warning("camera_matrix: skew K[0][1] = %g is ignored: OpenCV's camera model has none", skew)
        fold = _distortion_fold(self)
        if fold is not None:
            raise CameraError(
                f"distortion_coefficients fold the image: the lens model turns back on itself near pixel "
                f"({fold[0]:.0f}, {fold[1]:.0f}), inside the {width}x{height} image (not a usable calibration)"
            )

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

    def project_rays(self, rays: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of normalised image points (N, 2) (``x / z, y / z``) through the distortion model: what
        :meth:`project` gives for ``(x, y, 1)``, in numpy (a 1280x720 image's rays: 25-40 ms against 0.3-0.9 s
        for ``cv2.projectPoints``, which also computes the Jacobians); OpenCV's own for a tilted sensor."""
        rays = np.asarray(rays, dtype=np.float64).reshape(-1, 2)
        d = np.zeros(14)
        d[: self.dist_coeffs.size] = self.dist_coeffs
        if np.any(d[12:] != 0.0):
            return self.project(np.column_stack([rays, np.ones(len(rays))]))
        xd, yd = _distort(rays[:, 0], rays[:, 1], d)
        k = self.camera_matrix
        return np.column_stack([k[0, 0] * xd + k[0, 2], k[1, 1] * yd + k[1, 2]])  # (no skew: as OpenCV)


def _distort(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of normalised image points (radial, rational, tangential, thin prism; the
    14-coefficient model's sensor tilt is left out: a projective map, it folds nothing)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return xd, yd


def _distortion_fold(camera: CameraModel, rays: int = 72, samples: int = 800) -> tuple[float, float] | None:
    """Where (pixels) the distortion model folds inside the image, or None when it does not.

    Walks ``rays`` directions out from the principal point, from a millionth of the focal length to ten
    focal lengths off-axis (84 deg), and looks at the Jacobian of the undistorted-to-distorted map: where
    its determinant is not positive the map folds. Only the part of each ray before its distorted point
    leaves the image counts (beyond it, a polynomial's turn is outside the calibrated field and harmless).
    """
    if not camera.has_distortion:
        return None
    d = np.zeros(14)
    d[: camera.dist_coeffs.size] = camera.dist_coeffs
    k, (width, height) = camera.camera_matrix, camera.size
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)[:, None]
    radii = np.geomspace(1e-6, 10.0, samples)[None, :]
    x, y = radii * np.cos(angles), radii * np.sin(angles)
    h = radii * 1e-5
    with np.errstate(all="ignore"):
        xd, yd = _distort(x, y, d)
        dx_x, dy_x = (a - b for a, b in zip(_distort(x + h, y, d), _distort(x - h, y, d)))
        dx_y, dy_y = (a - b for a, b in zip(_distort(x, y + h, d), _distort(x, y - h, d)))
        det = dx_x * dy_y - dx_y * dy_x
        u, v = fx * xd + cx, fy * yd + cy
        inside = (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
        folded = ~(det > 0) | ~np.isfinite(u) | ~np.isfinite(v)
    # each ray up to (not including) its first sample outside the image
    before_exit = np.cumprod(inside, axis=1).astype(bool)
    bad = folded & before_exit
    if not bad.any():
        return None
    ray, sample = np.argwhere(bad)[0]
    previous = max(sample - 1, 0)
    return float(u[ray, previous]), float(v[ray, previous])
