"""The calibration proper: ``cv2.calibrateCameraExtended`` on the kept views, the distortion model
(k3 fixed only when the 5-parameter fit fails or folds over inside the image), outlier views
dropped and the camera calibrated again (:func:`calibrate_views`), and the image coverage of the
corners used (:func:`coverage_of`). :class:`CalibrationReport` is a whole run's outcome.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np

from ...camera import CameraModel
from ...errors import ArAnchorError, InputError
from .views import CharucoSpec, Rejection, View

__all__ = [
    "CalibrationReport",
    "CalibrationResult",
    "Coverage",
    "Uncertainty",
    "bootstrap_uncertainty",
    "calibrate_views",
    "coverage_of",
    "orientation_spread_deg",
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
    std : OpenCV's standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3 (NaN when unknown), from
        the residuals alone as if every corner's error were independent: optimistic for real views
        (see :func:`bootstrap_uncertainty` for one that covers reality).
    orientation_spread_deg : the largest angle between two used views' board normals.
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
    orientation_spread_deg: float = 0.0


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


class _Fit(NamedTuple):
    """One ``calibrateCameraExtended`` run's outcome."""

    rms: float
    matrix: np.ndarray
    dist: np.ndarray
    errors: np.ndarray  # (views,) RMS reprojection error of each view, px
    std: np.ndarray  # OpenCV's stdDeviationsIntrinsics (fx fy cx cy k1 k2 p1 p2 k3 ...)
    reprojected: list[np.ndarray]
    normals: np.ndarray  # (views, 3) the board's normal in the camera frame, unit vectors


def _plausible(rms: float, matrix: np.ndarray, dist: np.ndarray, image_size: tuple[int, int]) -> bool:
    """A finite camera with positive focal lengths and its principal point inside the image."""
    return bool(
        np.isfinite(rms)
        and np.all(np.isfinite(matrix))
        and np.all(np.isfinite(dist))
        and matrix[0, 0] > 0
        and matrix[1, 1] > 0
        and -0.5 <= matrix[0, 2] <= image_size[0] - 0.5
        and -0.5 <= matrix[1, 2] <= image_size[1] - 0.5
    )


def _fit(
    board: cv2.aruco.CharucoBoard,
    views: Sequence[View],
    image_size: tuple[int, int],
    flags: int,
    points: tuple[list[np.ndarray], list[np.ndarray]] | None = None,
) -> _Fit | None:
    """One ``calibrateCameraExtended`` run (on ``points`` when given, else on the views'), or None
    when it fails or gives no plausible camera."""
    objects, images = points if points is not None else _points(board, views)
    try:
        rms, matrix, dist, rvecs, tvecs, std, _std_extrinsics, per_view = cv2.calibrateCameraExtended(
            objects, images, image_size, None, None, flags=flags, criteria=_CRITERIA
        )
    except cv2.error as err:
        log.info("calibration with flags %d failed: %s", flags, str(err).strip().splitlines()[-1])
        return None
    matrix, dist = np.asarray(matrix, np.float64), np.asarray(dist, np.float64).reshape(-1)
    per_view = np.asarray(per_view, np.float64).reshape(-1)
    if not (_plausible(rms, matrix, dist, image_size) and np.all(np.isfinite(per_view))):
        log.info("calibration with flags %d gave an unusable result (rms %s, K %s)", flags, rms, matrix.tolist())
        return None
    reprojected = [
        cv2.projectPoints(obj, rvec, tvec, matrix, dist)[0].reshape(-1, 2)
        for obj, rvec, tvec in zip(objects, rvecs, tvecs)
    ]
    normals = np.array([cv2.Rodrigues(rvec)[0][:, 2] for rvec in rvecs], np.float64).reshape(-1, 3)
    std = np.asarray(std, np.float64).reshape(-1)
    return _Fit(float(rms), matrix, dist, per_view, std, reprojected, normals)


def _calibrate_once(
    board: cv2.aruco.CharucoBoard, views: Sequence[View], image_size: tuple[int, int]
) -> tuple[_Fit, int, str]:
    """The 5-parameter model, or k3 fixed when that fit fails or folds over inside the image."""
    full = _fit(board, views, image_size, 0)
    if full is not None and not radial_folds(full.matrix, full.dist, image_size):
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


def orientation_spread_deg(normals: np.ndarray) -> float:
    """The largest angle between two views' board normals, in degrees (0 for one view): how different
    the board's orientations are. Views of parallel boards cannot separate the focal length from the
    distance, however many there are."""
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    if len(normals) < 2:
        return 0.0
    cosines = np.clip(normals @ normals.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def calibrate_views(
    spec: CharucoSpec, views: Sequence[View], image_size: tuple[int, int], *, min_views: int = 6
) -> CalibrationResult:
    """Calibrate from ``views``, drop outlier views (never below ``min_views``) and calibrate again."""
    if len(views) < max(min_views, 1):
        raise InputError(f"{len(views)} usable view(s), --min-views is {min_views}")
    board = spec.build()
    fit, flags, model = _calibrate_once(board, views, image_size)
    errors = fit.errors
    first = (tuple(views), tuple(float(e) for e in errors), fit.rms)
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
        fit, flags, model = _calibrate_once(board, views, image_size)
    rms, matrix, dist, errors, std = fit.rms, fit.matrix, fit.dist, fit.errors, fit.std
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
        reprojected=tuple(fit.reprojected),
        orientation_spread_deg=orientation_spread_deg(fit.normals),
    )


# ---------------------------------------------------------------------------- uncertainty

BOOTSTRAP_RESAMPLES = 100  # calibrations on views drawn with replacement ...
BOOTSTRAP_BUDGET_S = 15.0  # ... stopped early after this long (the report says how many ran)
BOOTSTRAP_SEED = 0  # the same views give the same resamples, hence the same uncertainty
MIN_TRUSTED_VIEWS = 8  # fewer views: their spread says little about the truth
MIN_ORIENTATION_SPREAD_DEG = 15.0  # board normals all closer than this: focal length and distance trade off
MAX_FAILED_FRACTION = 0.1  # more resampled calibrations failing: the views barely constrain the camera
MIN_RESAMPLES = 20  # fewer ran (time budget, failures): the spread itself is a guess
PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Uncertainty:
    """How far the calibration may be from the truth: one standard deviation per parameter.

    std : of fx, fy, cx, cy (px), k1, k2, p1, p2, k3 (NaN for a parameter held fixed): per parameter the
        larger of ``bootstrap_std`` and OpenCV's own estimate (:attr:`CalibrationResult.std`).
    bootstrap_std : the standard deviation of the parameters over calibrations on views drawn with
        replacement from the ``n`` used ones, times ``sqrt(n / (n - 1))`` (the plug-in bootstrap's bias for
        n samples; NaN when fewer than two calibrations succeeded).
    planned, ran, failed : resampled calibrations wanted, run (fewer when the time budget ran out), and
        failed (no plausible camera); ``views`` the views resampled.
    distrust : the reasons not to trust the uncertainty itself (empty: none known).
    """

    std: tuple[float, ...]
    bootstrap_std: tuple[float, ...]
    planned: int
    ran: int
    failed: int
    views: int
    seconds: float
    distrust: tuple[str, ...]

    def describe(self, *, timed: bool = False) -> str:
        """One line: how the uncertainty was estimated (``timed``: with the bootstrap's duration)."""
        if self.ran - self.failed < 2:
            why = (
                f"{self.views} view(s): too few to resample"
                if not self.planned
                else f"{self.ran - self.failed} of {self.planned} calibrations on resampled views succeeded"
            )
            return f"OpenCV's estimate from the residuals ({why})"
        duration = f", {self.seconds:.1f} s" if timed else ""
        return (
            f"the larger of the spread over {self.ran - self.failed} calibrations on resampled views "
            f"(of {self.views}{duration}) and OpenCV's estimate from the residuals"
        )


def _resample(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` view indices drawn with replacement, naming at least three distinct views (two views
    of a plane leave the calibration underdetermined: such draws are drawn again)."""
    need = min(3, count)
    while True:
        picks = rng.integers(0, count, count)
        if len(np.unique(picks)) >= need:
            return np.sort(picks)


def _parameters(matrix: np.ndarray, dist: np.ndarray, flags: int) -> np.ndarray:
    values = np.full(len(PARAMETERS), np.nan)
    values[:4] = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    coefficients = dist.reshape(-1)[:5]
    values[4 : 4 + coefficients.size] = coefficients
    if flags & cv2.CALIB_FIX_K3:
        values[8] = np.nan
    return values


def _start(result: CalibrationResult) -> tuple[np.ndarray, np.ndarray]:
    """Where each resample's calibration starts: at the calibration itself, not at OpenCV's own guess (the same
    minimum in fewer iterations; on 12 rendered view sets 14-27 % faster, every deviation the same to 6 digits)."""
    dist = np.zeros(5)
    dist[: min(5, result.camera.dist_coeffs.size)] = result.camera.dist_coeffs.reshape(-1)[:5]
    return np.asarray(result.camera.camera_matrix, np.float64), dist


def bootstrap_uncertainty(
    spec: CharucoSpec,
    result: CalibrationResult,
    image_size: tuple[int, int],
    *,
    resamples: int = BOOTSTRAP_RESAMPLES,
    budget_s: float = BOOTSTRAP_BUDGET_S,
    seed: int = BOOTSTRAP_SEED,
    progress: Callable[[str], None] | None = None,
) -> Uncertainty:
    """The calibration's uncertainty from a bootstrap over its views.

    ``resamples`` times, as many views as were used are drawn with replacement (a fixed ``seed``: the
    same views give the same answer) and the camera is calibrated on them with the same model; the
    standard deviation of each parameter over these calibrations is its uncertainty. Unlike OpenCV's
    estimate, which treats every corner's error as independent, it counts what varies from view to
    view (a board not quite flat, rolling shutter, blur, a view that pulls the focal length) and how
    much the result depends on which views were taken. Stops after ``budget_s`` seconds; ``progress``
    gets a line every two seconds and one at the end.
    """
    started = time.monotonic()
    views = result.views
    count = len(views)
    board = spec.build()
    objects, images = _points(board, views)
    rng = np.random.default_rng(seed)
    start_matrix, start_dist = _start(result)
    samples: list[np.ndarray] = []
    ran = failed = 0
    planned = resamples if count >= 3 else 0
    last_report = started
    for _ in range(planned):
        if time.monotonic() - started >= budget_s:
            break
        picks = _resample(rng, count)
        ran += 1
        try:
            rms, matrix, dist, _rvecs, _tvecs = cv2.calibrateCamera(
                [objects[i] for i in picks],
                [images[i] for i in picks],
                image_size,
                start_matrix.copy(),
                start_dist.copy(),
                flags=result.flags | cv2.CALIB_USE_INTRINSIC_GUESS,
                criteria=_CRITERIA,
            )
        except cv2.error:
            failed += 1
            continue
        matrix, dist = np.asarray(matrix, np.float64), np.asarray(dist, np.float64).reshape(-1)
        if not _plausible(rms, matrix, dist, image_size):
            failed += 1
            continue
        samples.append(_parameters(matrix, dist, result.flags))
        if progress is not None and time.monotonic() - last_report > 2.0:
            last_report = time.monotonic()
            progress(f"uncertainty: {ran}/{planned} resampled calibrations ({last_report - started:.0f} s)")
    seconds = time.monotonic() - started
    if progress is not None and planned:
        stopped = f", stopped at the {budget_s:g} s budget" if ran < planned else ""
        progress(f"uncertainty: {ran}/{planned} resampled calibrations of {count} views ({seconds:.1f} s{stopped})")
    bootstrap = np.full(len(PARAMETERS), np.nan)
    if len(samples) >= 2:  # resampling n views underestimates the variance by (n - 1) / n
        bootstrap = np.std(samples, axis=0, ddof=1) * math.sqrt(count / (count - 1))
    opencv = np.asarray(result.std, np.float64)
    std = np.where(np.isnan(bootstrap), opencv, np.fmax(bootstrap, opencv))
    if result.flags & cv2.CALIB_FIX_K3:
        std[8] = np.nan
    distrust = _distrust(result, count, planned, ran, failed, seconds)
    return Uncertainty(
        std=tuple(float(v) for v in std),
        bootstrap_std=tuple(float(v) for v in bootstrap),
        planned=planned,
        ran=ran,
        failed=failed,
        views=count,
        seconds=seconds,
        distrust=tuple(distrust),
    )


def _distrust(result: CalibrationResult, count: int, planned: int, ran: int, failed: int, seconds: float) -> list[str]:
    """Why the uncertainty is not to be trusted (too few views, too alike, resamples failing); empty: it is."""
    distrust = []
    if count < MIN_TRUSTED_VIEWS:
        distrust.append(f"only {count} view(s) (at least {MIN_TRUSTED_VIEWS} are needed to estimate it)")
    if count >= 2 and result.orientation_spread_deg < MIN_ORIENTATION_SPREAD_DEG:
        distrust.append(
            f"the board's orientations differ by at most {result.orientation_spread_deg:.0f} degrees "
            f"(less than {MIN_ORIENTATION_SPREAD_DEG:g})"
        )
    if ran and failed > MAX_FAILED_FRACTION * ran:
        distrust.append(f"{failed} of {ran} calibrations on resampled views failed")
    if planned and ran - failed < MIN_RESAMPLES:
        distrust.append(f"only {ran - failed} calibrations on resampled views succeeded in {seconds:.0f} s")
    return distrust


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
    uncertainty: Uncertainty | None = None

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
