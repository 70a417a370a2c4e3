"""The calibration proper: ``cv2.calibrateCameraExtended`` on the kept views, the distortion model
(k3 fixed only when the 5-parameter fit fails or folds over inside the image), outlier views
dropped and the camera calibrated again (:func:`calibrate_views`), and the image coverage of the
corners used (:func:`coverage_of`). :class:`CalibrationReport` is a whole run's outcome.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...camera import CameraModel
from ...errors import ArAnchorError, InputError
from .views import CharucoSpec, Rejection, View

__all__ = [
    "CalibrationReport",
    "CalibrationResult",
    "Coverage",
    "calibrate_views",
    "coverage_of",
    "radial_folds",
]

log = logging.getLogger(__name__)

OUTLIER_FACTOR = 3.0  # per-view RMS above max(factor x median, median + margin) is an outlier
OUTLIER_MARGIN_PX = 0.5
COVERAGE_GRID = (8, 6)  # cells across, down (report)
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


# ---------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration and the views it used.

    views : the views used by the final fit; ``errors_px`` their RMS reprojection errors (same order).
    first_views, first_errors_px : the first fit's views and errors (before outliers were dropped).
    dropped : the outlier views (a :class:`Rejection` each).
    std : standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3 (NaN when unknown).
    """

    camera: CameraModel
    rms: float
    views: tuple[View, ...]
    errors_px: tuple[float, ...]
    first_views: tuple[View, ...]
    first_errors_px: tuple[float, ...]
    first_rms: float
    dropped: tuple[Rejection, ...]
    flags: int
    std: tuple[float, ...]
    model: str
    reprojected: tuple[np.ndarray, ...] = field(default=(), repr=False)


def _points(board: cv2.aruco.CharucoBoard, views: Sequence[View]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    objects, images = [], []
    for view in views:
        obj, img = board.matchImagePoints(
            view.corners.reshape(-1, 1, 2).astype(np.float32), view.ids.reshape(-1, 1).astype(np.int32)
        )
        objects.append(np.asarray(obj, np.float32).reshape(-1, 1, 3))
        images.append(np.asarray(img, np.float32).reshape(-1, 1, 2))
    return objects, images


def radial_folds(camera_matrix: np.ndarray, dist: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Does the radial polynomial stop increasing before it reaches the image's corners?"""
    k = np.zeros(5)
    k[: min(5, dist.size)] = dist.reshape(-1)[:5]
    k1, k2, _p1, _p2, k3 = k
    width, height = image_size
    fx, fy, cx, cy = camera_matrix[0, 0], camera_matrix[1, 1], camera_matrix[0, 2], camera_matrix[1, 2]
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    reach = float(np.max(np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy)))
    r = np.linspace(0.0, 5.0, 5001)
    r2 = r * r
    distorted = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3
    beyond = np.nonzero(distorted >= reach)[0]
    if beyond.size == 0:
        return True  # never reaches the corners: folds (or flattens) inside the image
    return bool(np.any(slope[: beyond[0] + 1] <= 0))


def _fit(
    board: cv2.aruco.CharucoBoard, views: Sequence[View], image_size: tuple[int, int], flags: int
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]] | None:
    """One ``calibrateCameraExtended`` run: (rms, K, dist, per-view errors, std, reprojections) or None."""
    objects, images = _points(board, views)
    try:
        rms, matrix, dist, rvecs, tvecs, std, _std_extrinsics, per_view = cv2.calibrateCameraExtended(
            objects, images, image_size, None, None, flags=flags, criteria=_CRITERIA
        )
    except cv2.error as err:
        log.info("calibration with flags %d failed: %s", flags, str(err).strip().splitlines()[-1])
        return None
    matrix, dist = np.asarray(matrix, np.float64), np.asarray(dist, np.float64).reshape(-1)
    per_view = np.asarray(per_view, np.float64).reshape(-1)
    if not (
        np.isfinite(rms)
        and np.all(np.isfinite(matrix))
        and np.all(np.isfinite(dist))
        and np.all(np.isfinite(per_view))
        and matrix[0, 0] > 0
        and matrix[1, 1] > 0
        and -0.5 <= matrix[0, 2] <= image_size[0] - 0.5
        and -0.5 <= matrix[1, 2] <= image_size[1] - 0.5
    ):
        log.info("calibration with flags %d gave an unusable result (rms %s, K %s)", flags, rms, matrix.tolist())
        return None
    reprojected = [
        cv2.projectPoints(obj, rvec, tvec, matrix, dist)[0].reshape(-1, 2)
        for obj, rvec, tvec in zip(objects, rvecs, tvecs)
    ]
    return float(rms), matrix, dist, per_view, np.asarray(std, np.float64).reshape(-1), reprojected


def _calibrate_once(
    board: cv2.aruco.CharucoBoard, views: Sequence[View], image_size: tuple[int, int]
) -> tuple[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]], int, str]:
    """The 5-parameter model, or k3 fixed when that fit fails or folds over inside the image."""
    full = _fit(board, views, image_size, 0)
    if full is not None and not radial_folds(full[1], full[2], image_size):
        return full, 0, "k1 k2 p1 p2 k3"
    reason = "failed" if full is None else "folds over inside the image"
    log.warning("the 5-parameter distortion fit %s: calibrating again with k3 fixed at 0", reason)
    fixed = _fit(board, views, image_size, cv2.CALIB_FIX_K3)
    if fixed is None:
        raise ArAnchorError(
            f"calibration failed on {len(views)} views (no finite, plausible camera): add views with the board "
            "tilted 20-50 degrees and covering the image"
        )
    return fixed, cv2.CALIB_FIX_K3, "k1 k2 p1 p2 (k3 fixed at 0)"


def calibrate_views(
    spec: CharucoSpec, views: Sequence[View], image_size: tuple[int, int], *, min_views: int = 6
) -> CalibrationResult:
    """Calibrate from ``views``, drop outlier views (never below ``min_views``) and calibrate again."""
    if len(views) < max(min_views, 1):
        raise InputError(f"{len(views)} usable view(s), --min-views is {min_views}")
    board = spec.build()
    (rms, matrix, dist, errors, std, reprojected), flags, model = _calibrate_once(board, views, image_size)
    first = (tuple(views), tuple(float(e) for e in errors), rms)
    median = float(np.median(errors))
    limit = max(OUTLIER_FACTOR * median, median + OUTLIER_MARGIN_PX)
    worst_first = sorted((i for i in range(len(views)) if errors[i] > limit), key=lambda i: -errors[i])
    drop = worst_first[: max(len(views) - min_views, 0)]
    dropped = tuple(
        Rejection(views[i].name, views[i].frame, "outlier", f"{errors[i]:.2f} px > {limit:.2f} px") for i in drop
    )
    if len(worst_first) > len(drop):
        log.warning(
            "%d outlier view(s) kept: dropping them would leave fewer than --min-views %d",
            len(worst_first) - len(drop),
            min_views,
        )
    if drop:
        views = [v for i, v in enumerate(views) if i not in set(drop)]
        (rms, matrix, dist, errors, std, reprojected), flags, model = _calibrate_once(board, views, image_size)
    padded = np.full(9, np.nan)
    padded[: min(9, std.size)] = std[:9]
    if flags & cv2.CALIB_FIX_K3:
        padded[8] = np.nan
    camera = CameraModel(matrix, dist[:5] if dist.size >= 5 else dist, int(image_size[0]), int(image_size[1]))
    return CalibrationResult(
        camera=camera,
        rms=float(rms),
        views=tuple(views),
        errors_px=tuple(float(e) for e in errors),
        first_views=first[0],
        first_errors_px=first[1],
        first_rms=first[2],
        dropped=dropped,
        flags=flags,
        std=tuple(float(s) for s in padded),
        model=model,
        reprojected=tuple(reprojected),
    )


# ---------------------------------------------------------------------------- coverage


@dataclass(frozen=True)
class Coverage:
    """Corners per cell of a coarse image grid (rows, cols) and the warnings it gives."""

    counts: np.ndarray
    image_size: tuple[int, int]
    warnings: tuple[str, ...]

    @property
    def fraction(self) -> float:
        return float(np.count_nonzero(self.counts)) / self.counts.size

    def heat_map(self) -> str:
        """The grid as text, two characters per cell (blank: no corner; denser: more corners)."""
        shades = ".:-=+*#%@"
        top = max(int(self.counts.max()), 1)
        lines = ["+" + "--" * self.counts.shape[1] + "+"]
        for row in self.counts:
            cells = []
            for count in row:
                if count == 0:
                    cells.append("  ")
                else:
                    level = math.log1p(count) / math.log1p(top)
                    cells.append(shades[min(len(shades) - 1, int(level * (len(shades) - 1) + 0.5))] * 2)
            lines.append("|" + "".join(cells) + "|")
        lines.append(lines[0])
        return "\n".join(lines)


def coverage_of(views: Sequence[View], image_size: tuple[int, int], grid: tuple[int, int] = COVERAGE_GRID) -> Coverage:
    """Which cells of a ``grid`` (across, down) hold corners, with warnings for poor coverage."""
    width, height = image_size
    cols, rows = grid
    counts = np.zeros((rows, cols), np.int64)
    points = np.concatenate([v.corners for v in views]) if views else np.zeros((0, 2))
    if len(points):
        gx = np.clip(((points[:, 0] + 0.5) * cols / width).astype(int), 0, cols - 1)
        gy = np.clip(((points[:, 1] + 0.5) * rows / height).astype(int), 0, rows - 1)
        np.add.at(counts, (gy, gx), 1)
    warnings = []
    fraction = float(np.count_nonzero(counts)) / counts.size
    if fraction < 0.5:
        warnings.append(
            f"corners cover only {fraction:.0%} of the image ({np.count_nonzero(counts)}/{counts.size} cells): "
            "move the board over the whole image, corners included"
        )
    sides = {
        "left": (points[:, 0] < width / 3, counts[:, 0]),
        "right": (points[:, 0] > 2 * width / 3, counts[:, -1]),
        "top": (points[:, 1] < height / 3, counts[0, :]),
        "bottom": (points[:, 1] > 2 * height / 3, counts[-1, :]),
    }
    no_third = [side for side, (third, _edge) in sides.items() if not np.any(third)]
    if no_third:
        warnings.append(
            f"no corner in the outer third of the image on the {', '.join(no_third)}: distortion there is a guess"
        )
    no_edge = [side for side, (third, edge) in sides.items() if np.any(third) and not np.any(edge)]
    if no_edge:
        warnings.append(
            f"corners never reach the {', '.join(no_edge)} edge cells: distortion near the border is extrapolated"
        )
    return Coverage(counts, (int(width), int(height)), tuple(warnings))


# ---------------------------------------------------------------------------- whole runs


@dataclass(frozen=True)
class CalibrationReport:
    """Everything a calibration run found: what was considered, kept, rejected, and the result."""

    source: str
    spec: CharucoSpec
    image_size: tuple[int, int]
    considered: int
    rejections: tuple[Rejection, ...]
    result: CalibrationResult
    coverage: Coverage
    warnings: tuple[str, ...]
    seconds: float
    frame_step: int = 1

    @property
    def camera(self) -> CameraModel:
        return self.result.camera

    @property
    def views(self) -> tuple[View, ...]:
        return self.result.views

    def rejected(self, reason: str) -> list[Rejection]:
        return [r for r in self.all_rejections if r.reason == reason]

    @property
    def all_rejections(self) -> tuple[Rejection, ...]:
        return self.rejections + self.result.dropped
