"""``ar-anchor calibrate``: camera calibration from ChArUco views (image folder or glob, video, device).

Pipeline
--------
1. **Detect** every considered frame with ``cv2.aruco.CharucoDetector.detectBoard``. A view needs
   at least ``max(6, 25 %)`` of the board's chessboard corners, spread over two rows and two columns.
2. **Sharpness**: :func:`edge_width_px` estimates the blur of the board's edges, in pixels (the sigma
   of a Gaussian edge): ``contrast / (sqrt(2 pi) * peak derivative)``, with the derivative taken
   along each of the board's two axes as seen in the image (all ChArUco edges are parallel to one of
   them) and the worse axis kept, so motion blur along either axis counts. It does not depend on
   the board's size in the image or on its contrast (sharp renders and photos measure 0.8-1.1 px).
   A view is *blurry* when its width exceeds ``max(1.8 px, 1.6 x the 25th percentile`` of the
   widths of all detected views) -- relative to the sharpest quarter, so a soft lens is not
   rejected wholesale and a clip that is mostly motion-blurred still has a sharp reference.
3. **Distinct views**: a view *duplicates* a kept one when they share at least half of their corners,
   the mean displacement of the shared corners is below 2 % of the image diagonal, and the corner
   counts are within ``max(2, 15 %)`` of each other.
4. **Selection** (files): all sharp views compete for ``--max-views`` places, greedily by coverage:
   each pick maximises ``sum(1 / (1 + n))`` over the cells of a 16x12 grid its corners touch (``n``:
   kept views already touching that cell), so views adding unseen image regions come first.
   Videos are sampled (every ``k``-th frame, at most about ``10 x --max-views`` candidates).
   Devices keep views online: a frame is kept when it is sharp (against the running reference),
   distinct from every kept view and at least 0.5 s (capture time) after the last kept one, until ``--max-views``
   views or ``--duration-s`` (Ctrl-C stops the capture and calibrates with what was kept).
5. **Calibration**: ``cv2.calibrateCameraExtended`` on ``CharucoBoard.matchImagePoints`` points,
   5-parameter distortion (k1, k2, p1, p2, k3). The model falls back to ``CALIB_FIX_K3`` only when
   the 5-parameter fit fails, or its radial polynomial folds over (stops increasing) before the
   image corners -- *not* merely because there are few views: with OpenCV's four tutorial views,
   fixing k3 moves fx from 457 to 326 px at the same RMS (k3 trades off against the focal length
   when corners stay near the centre), 28 % away from OpenCV's own calibration of them.
6. **Outliers**: views whose RMS reprojection error exceeds ``max(3 x median, median + 0.5 px)`` are
   dropped, worst first, never below ``--min-views``, and the camera is calibrated once more.
7. **Coverage**: an 8x6 grid of image cells; a warning when fewer than half hold a corner, when the
   outer third of a side holds none, or when no corner reaches that side's outermost cells.

Outputs: the OpenCV YAML camera file (``camera_matrix``, ``distortion_coefficients``,
``image_width``, ``image_height``, ``rms``, ``date``, ``board``, ``views``, ``coverage``, ``model``),
written atomically, and a rerun recording (entity tree below).

Rerun entity tree (timelines ``view``: position in the selection, ``frame``: source frame index):
``views/image`` each selected view (JPEG) with ``corners`` (detected) and ``reprojected``;
``metrics/view_error_px/first_fit|final`` per-view RMS; ``coverage`` the heat map with all corners;
``events`` rejections and the report (TextLog).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import dictionary_id, dictionary_names
from ..errors import ArAnchorError, ConfigError, InputError, OutputError, SourceError

__all__ = [
    "CalibrationReport",
    "CalibrationResult",
    "CharucoSpec",
    "Coverage",
    "Rejection",
    "View",
    "ViewDetector",
    "calibrate_source",
    "calibrate_views",
    "coverage_of",
    "edge_width_px",
    "format_report",
    "is_duplicate",
    "run_calibrate",
    "select_views",
    "write_camera_yaml",
]

log = logging.getLogger(__name__)

MIN_CORNERS = 6  # at least this many chessboard corners per view ...
MIN_CORNER_FRACTION = 0.25  # ... and at least this fraction of the board's corners
BLUR_FLOOR_PX = 1.8  # edge width (Gaussian sigma, px) always accepted
BLUR_RATIO = 1.6  # ... and accepted up to this multiple of the sharp reference
BLUR_REFERENCE_PERCENTILE = 25.0  # the sharp reference: this percentile of the detected views' widths
DUPLICATE_FRACTION = 0.02  # of the image diagonal: mean shift of shared corners below it = same view
MIN_INTERVAL_S = 0.5  # devices: kept views at least this far apart in time
CANDIDATES_PER_VIEW = 10  # videos: consider about this many frames per wanted view
OUTLIER_FACTOR = 3.0  # per-view RMS above max(factor x median, median + margin) is an outlier
OUTLIER_MARGIN_PX = 0.5
COVERAGE_GRID = (8, 6)  # cells across, down (report)
SELECTION_GRID = (16, 12)  # cells across, down (coverage-greedy selection)
PREVIEW_MAX_SIDE = 1024  # recording images are scaled down to this longer side
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)

REASONS = {
    "no board": "no board",
    "few corners": "too few corners",
    "blur": "blurry",
    "duplicate": "duplicate",
    "outlier": "outlier",
    "surplus": "over --max-views",
}


# ---------------------------------------------------------------------------- board


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board: ``cols`` x ``rows`` chessboard squares, markers from ``dictionary``."""

    cols: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str
    legacy: bool = False

    @classmethod
    def parse(
        cls, charuco: str, square_m: float, marker_m: float, dictionary: str, legacy: bool = False
    ) -> CharucoSpec:
        """Validate the command-line description; :class:`InputError` names the option at fault."""
        text = str(charuco).strip().lower()
        parts = text.split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise InputError(f"--charuco: expected squares across x down such as 5x7, got {charuco!r}")
        cols, rows = (int(p) for p in parts)
        if cols < 2 or rows < 2:
            raise InputError(f"--charuco: a board needs at least 2x2 squares, got {charuco!r}")
        for option, value in (("--square-m", square_m), ("--marker-m", marker_m)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{option}: must be a length > 0 in metres, got {value!r}")
        if marker_m >= square_m:
            raise InputError(
                f"--marker-m: the marker ({marker_m:g} m) must be smaller than the square (--square-m {square_m:g} m)"
            )
        try:
            dict_id = dictionary_id(dictionary)
        except ConfigError as err:
            raise InputError(f"--dictionary: {err}") from None
        canonical = next((n for n in dictionary_names() if int(getattr(cv2.aruco, n)) == dict_id), str(dictionary))
        spec = cls(cols, rows, float(square_m), float(marker_m), canonical, bool(legacy))
        available = cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0]
        if spec.marker_count > available:
            raise InputError(
                f"--dictionary: {canonical} has {available} markers, a {cols}x{rows} ChArUco board needs "
                f"{spec.marker_count}: use a larger dictionary or check --charuco"
            )
        return spec

    @property
    def corner_count(self) -> int:
        return (self.cols - 1) * (self.rows - 1)

    @property
    def marker_count(self) -> int:
        return self.cols * self.rows // 2

    @property
    def min_corners(self) -> int:
        """Fewest chessboard corners a view must show: ``max(6, 25 %)`` of the board's."""
        return max(MIN_CORNERS, math.ceil(MIN_CORNER_FRACTION * self.corner_count))

    def build(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)
        board.setLegacyPattern(self.legacy)
        return board

    def describe(self) -> str:
        """``charuco 5x7 square 0.04 marker 0.02 DICT_6X6_250 legacy=false`` (the YAML's ``board``)."""
        return (
            f"charuco {self.cols}x{self.rows} square {self.square_m:g} marker {self.marker_m:g} "
            f"{self.dictionary} legacy={'true' if self.legacy else 'false'}"
        )


# ---------------------------------------------------------------------------- views


@dataclass(frozen=True)
class View:
    """One detected board view.

    corners : (N, 2) float64 chessboard corners, pixels (OpenCV centres at integers).
    ids : (N,) int chessboard corner ids (row-major over the board's inner corners).
    edge_width_px : estimated blur of the board's edges (Gaussian sigma, px); see :func:`edge_width_px`.
    preview : JPEG of the frame scaled by ``preview_scale`` (for the recording), or empty.
    """

    name: str
    frame: int
    corners: np.ndarray
    ids: np.ndarray
    edge_width_px: float
    preview: bytes = b""
    preview_scale: float = 1.0

    @property
    def count(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Rejection:
    """A view that was not used, and why (``reason`` is a key of :data:`REASONS`)."""

    name: str
    frame: int
    reason: str
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.name}: {REASONS.get(self.reason, self.reason)}" + (f" ({self.detail})" if self.detail else "")


def edge_width_px(grey: np.ndarray, corners: np.ndarray, ids: np.ndarray, cols: int) -> float:
    """Blur of the board's edges, in pixels (the sigma of a Gaussian-blurred step edge).

    Inside the convex hull of the detected corners: ``contrast / (sqrt(2 pi) * peak)``, where the
    contrast is the 5-95 % grey-level range and the peak is the 99.5th percentile of the directional
    derivative along each board axis (mean direction of neighbouring corners in the image); the
    larger of the two axes' widths is returned. Independent of scale and contrast; a sharp image
    measures about 0.8-1 px, a Gaussian blur of sigma s about ``sqrt(s^2 + 0.8^2)``.
    """
    points = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(ids).reshape(-1)
    hull = cv2.convexHull(points.astype(np.float32)).reshape(-1, 2)
    x, y, w, h = cv2.boundingRect(hull)
    x, y = max(x - 1, 0), max(y - 1, 0)
    w, h = min(w + 2, grey.shape[1] - x), min(h + 2, grey.shape[0] - y)
    if w < 4 or h < 4:
        return math.inf
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull - [x, y]).astype(np.int32), 255)
    inside = mask > 0
    if inside.sum() < 64:
        return math.inf
    region = grey[y : y + h, x : x + w].astype(np.float32)
    low, high = np.percentile(region[inside], [5.0, 95.0])
    contrast = float(high - low)
    if contrast <= 1.0:
        return math.inf
    gx = cv2.Sobel(region, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)[inside]
    gy = cv2.Sobel(region, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)[inside]
    widths = []
    for axis in _board_axes(points, ids, cols):
        peak = float(np.percentile(np.abs(gx * axis[0] + gy * axis[1]), 99.5))
        widths.append(contrast / (math.sqrt(2.0 * math.pi) * peak) if peak > 0 else math.inf)
    if not widths:  # cannot happen for a view with corners on two rows and columns; be safe
        peak = float(np.percentile(np.hypot(gx, gy), 99.5))
        widths.append(contrast / (math.sqrt(2.0 * math.pi) * peak) if peak > 0 else math.inf)
    return float(max(widths))


def _board_axes(points: np.ndarray, ids: np.ndarray, cols: int) -> list[np.ndarray]:
    """Mean image direction of the board's x and y axes (unit vectors) from neighbouring corners."""
    per_row = cols - 1
    position = {int(i): p for i, p in zip(ids, points)}
    axes = []
    for step in (1, per_row):
        steps = [
            position[i + step] - position[i]
            for i in position
            if i + step in position and (step != 1 or i % per_row != per_row - 1)
        ]
        steps = [s / n for s in steps if (n := np.linalg.norm(s)) > 1e-9]
        if steps:
            mean = np.mean(steps, axis=0)
            if np.linalg.norm(mean) > 1e-9:
                axes.append(mean / np.linalg.norm(mean))
    return axes


class ViewDetector:
    """Detects the board in frames and measures each view (corners, ids, sharpness)."""

    def __init__(self, spec: CharucoSpec, *, previews: bool = False) -> None:
        self.spec = spec
        self.board = spec.build()
        self.detector = cv2.aruco.CharucoDetector(self.board)
        self.previews = previews
        self.markers_seen = 0  # frames in which markers of the dictionary were found

    def detect(self, image: np.ndarray, name: str, frame: int) -> View | Rejection:
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _marker_corners, marker_ids = self.detector.detectBoard(grey)
        if marker_ids is not None and len(marker_ids):
            self.markers_seen += 1
        count = 0 if ids is None else len(ids)
        if count == 0:
            found = 0 if marker_ids is None else len(marker_ids)
            detail = f"{found} marker(s), no chessboard corner" if found else ""
            return Rejection(name, frame, "no board", detail)
        points = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        ids = np.asarray(ids, dtype=np.int32).reshape(-1)
        need = self.spec.min_corners
        if count < need:
            return Rejection(name, frame, "few corners", f"{count} < {need}")
        per_row = self.spec.cols - 1
        if len(set((ids // per_row).tolist())) < 2 or len(set((ids % per_row).tolist())) < 2:
            return Rejection(name, frame, "few corners", f"{count} corners on one line")
        width = edge_width_px(grey, points, ids, self.spec.cols)
        preview, scale = b"", 1.0
        if self.previews:
            preview, scale = _jpeg_preview(image)
        return View(name, frame, points, ids, width, preview, scale)


def _jpeg_preview(image: np.ndarray) -> tuple[bytes, float]:
    scale = min(1.0, PREVIEW_MAX_SIDE / max(image.shape[:2]))
    if scale < 1.0:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return (jpeg.tobytes() if ok else b""), scale


def blur_threshold_px(widths: Iterable[float]) -> float:
    """Largest accepted edge width: ``max(1.8 px, 1.6 x the 25th percentile of widths)``."""
    finite = [w for w in widths if math.isfinite(w)]
    if not finite:
        return BLUR_FLOOR_PX
    return max(BLUR_FLOOR_PX, BLUR_RATIO * float(np.percentile(finite, BLUR_REFERENCE_PERCENTILE)))


def is_duplicate(a: View, b: View, image_size: tuple[int, int]) -> tuple[bool, float]:
    """(is ``a`` a near-copy of ``b``, mean shift of their shared corners in px)."""
    shared, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    if len(shared) == 0:
        return False, math.inf
    shift = float(np.linalg.norm(a.corners[ia] - b.corners[ib], axis=1).mean())
    if len(shared) < 0.5 * min(a.count, b.count):
        return False, shift
    similar_count = abs(a.count - b.count) <= max(2, 0.15 * max(a.count, b.count))
    return similar_count and shift < DUPLICATE_FRACTION * math.hypot(*image_size), shift


def _cells(view: View, image_size: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """Boolean (cells,) mask of the grid cells holding a corner of ``view``."""
    width, height = image_size
    gx = np.clip(((view.corners[:, 0] + 0.5) * grid[0] / width).astype(int), 0, grid[0] - 1)
    gy = np.clip(((view.corners[:, 1] + 0.5) * grid[1] / height).astype(int), 0, grid[1] - 1)
    mask = np.zeros(grid[0] * grid[1], bool)
    mask[gy * grid[0] + gx] = True
    return mask


def select_views(
    candidates: Sequence[View], image_size: tuple[int, int], max_views: int
) -> tuple[list[View], list[Rejection]]:
    """Drop blurry views, then pick up to ``max_views`` distinct ones, greedily by image coverage.

    Returns the kept views in frame order and a rejection for every other candidate.
    """
    rejections: list[Rejection] = []
    threshold = blur_threshold_px(v.edge_width_px for v in candidates)
    sharp = []
    for view in candidates:
        if view.edge_width_px > threshold:
            rejections.append(
                Rejection(view.name, view.frame, "blur", f"edge width {view.edge_width_px:.2f} px > {threshold:.2f} px")
            )
        else:
            sharp.append(view)
    if not sharp:
        return [], rejections
    cells = np.array([_cells(v, image_size, SELECTION_GRID) for v in sharp], dtype=np.float64)
    # ties: more corners, then sharper, then earlier
    tie = np.array([v.count * 1e-3 - v.edge_width_px * 1e-5 - v.frame * 1e-12 for v in sharp])
    seen = np.zeros(cells.shape[1])
    remaining = list(range(len(sharp)))
    kept: list[int] = []
    while remaining and len(kept) < max_views:
        scores = cells[remaining] @ (1.0 / (1.0 + seen)) + tie[remaining]
        best = remaining.pop(int(np.argmax(scores)))
        duplicate = _first_duplicate(sharp[best], [sharp[k] for k in kept], image_size)
        if duplicate is not None:
            other, shift = duplicate
            rejections.append(
                Rejection(sharp[best].name, sharp[best].frame, "duplicate", f"of {other.name}, {shift:.1f} px apart")
            )
            continue
        kept.append(best)
        seen += cells[best]
    for index in remaining:
        duplicate = _first_duplicate(sharp[index], [sharp[k] for k in kept], image_size)
        if duplicate is not None:
            other, shift = duplicate
            rejections.append(
                Rejection(sharp[index].name, sharp[index].frame, "duplicate", f"of {other.name}, {shift:.1f} px apart")
            )
        else:
            rejections.append(Rejection(sharp[index].name, sharp[index].frame, "surplus", f"{max_views} kept"))
    return sorted((sharp[k] for k in kept), key=lambda v: v.frame), rejections


def _first_duplicate(view: View, kept: Sequence[View], image_size: tuple[int, int]) -> tuple[View, float] | None:
    for other in kept:
        same, shift = is_duplicate(view, other, image_size)
        if same:
            return other, shift
    return None


class OnlineSelector:
    """Keeps views as they arrive (devices): sharp, distinct, and spaced in time."""

    def __init__(self, image_size: tuple[int, int], max_views: int) -> None:
        self.image_size = image_size
        self.max_views = max_views
        self.kept: list[View] = []
        self.widths: list[float] = []
        self._last_kept_s = -math.inf

    def offer(self, view: View, now_s: float) -> Rejection | None:
        """None when ``view`` (captured at ``now_s``) is kept, else why not; a view merely too soon
        after the last kept one is not a rejection: ``Rejection(reason="")``."""
        self.widths.append(view.edge_width_px)
        threshold = blur_threshold_px(self.widths)
        if view.edge_width_px > threshold:
            return Rejection(
                view.name, view.frame, "blur", f"edge width {view.edge_width_px:.2f} px > {threshold:.2f} px"
            )
        duplicate = _first_duplicate(view, self.kept, self.image_size)
        if duplicate is not None:
            other, shift = duplicate
            return Rejection(view.name, view.frame, "duplicate", f"of {other.name}, {shift:.1f} px apart")
        if now_s - self._last_kept_s < MIN_INTERVAL_S:
            return Rejection(view.name, view.frame, "", "too soon after the last kept view")
        self.kept.append(view)
        self._last_kept_s = now_s
        return None

    @property
    def full(self) -> bool:
        return len(self.kept) >= self.max_views


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


def _radial_folds(camera_matrix: np.ndarray, dist: np.ndarray, image_size: tuple[int, int]) -> bool:
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
    if full is not None and not _radial_folds(full[1], full[2], image_size):
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


def is_device(source: str) -> bool:
    """``/dev/videoN`` or a bare camera index."""
    text = str(source).strip()
    return text.isdigit() or text.startswith("/dev/video")


Progress = Callable[[str], None]


def _gather_files(
    source: str, detector: ViewDetector, max_views: int, progress: Progress | None
) -> tuple[list[View], list[Rejection], int, tuple[int, int], int]:
    """Detect in the (sampled) frames of a folder, glob or video: (views, rejections, considered, size, step)."""
    from ..sources import open_source
    from ..sources.files import ImageFolderSource

    try:
        opened = open_source(source, live=False)
    except SourceError as err:
        message = str(err)
        raise SourceError(message if source in message else f"{source}: {message}") from None
    views: list[View] = []
    rejections: list[Rejection] = []
    considered = 0
    with opened as frames:
        is_folder = isinstance(frames, ImageFolderSource)
        count = frames.info.frame_count
        step = 1 if is_folder or not count else max(1, math.ceil(count / (CANDIDATES_PER_VIEW * max_views)))
        if step > 1:
            log.info("%s: %d frames, considering one in %d", source, count, step)
        size = frames.resolution
        last_report = time.monotonic()
        for frame in frames:
            if frame.index % step:
                continue
            considered += 1
            name = frames.files[frame.index].name if is_folder else f"frame {frame.index}"
            found = detector.detect(frame.image, name, frame.index)
            (views if isinstance(found, View) else rejections).append(found)
            if progress is not None and time.monotonic() - last_report > 2.0:
                last_report = time.monotonic()
                total = f"/{math.ceil(count / step)}" if count else ""
                progress(f"considered {considered}{total} frames, board in {len(views)}")
    return views, rejections, considered, size, step


def _gather_device(
    source: str,
    detector: ViewDetector,
    *,
    max_views: int,
    duration_s: float,
    width: int | None,
    height: int | None,
    fps: float | None,
    progress: Progress | None,
    on_keep: Callable[[View, np.ndarray], None] | None = None,
    grabber: object | None = None,
) -> tuple[list[View], list[Rejection], int, tuple[int, int]]:
    """Capture from a device until ``max_views`` distinct sharp views or ``duration_s`` (or Ctrl-C)."""
    from ..sources.live import LiveSource, WebcamGrabber

    if grabber is None:
        grabber = WebcamGrabber(source.strip(), width=width, height=height, fps=fps)
    try:
        live = LiveSource(grabber, queue_size=1, reconnect_s=2.0, stall_s=5.0)  # type: ignore[arg-type]
    except SourceError as err:  # the grabber names the live command's --device option: this one's is SOURCE
        raise SourceError(str(err).removeprefix("--device ")) from None
    size = live.resolution
    selector = OnlineSelector(size, max_views)
    rejections: list[Rejection] = []
    considered = 0
    start = time.monotonic()
    last_status = start
    if progress is not None:
        progress(
            f"{source}: capturing at {size[0]}x{size[1]} for up to {duration_s:g} s or {max_views} views; "
            "move the board over the whole image, tilted 20-50 degrees (Ctrl-C: stop and calibrate)"
        )
    try:
        with live:
            first_ns: int | None = None
            for frame in live:
                now = time.monotonic() - start
                if now > duration_s:
                    break
                first_ns = frame.timestamp_ns if first_ns is None else first_ns
                considered += 1
                found = detector.detect(frame.image, f"frame {frame.index}", frame.index)
                if isinstance(found, View):
                    why = selector.offer(found, (frame.timestamp_ns - first_ns) * 1e-9)
                    if why is None:
                        if on_keep is not None:
                            on_keep(found, frame.image)
                        if progress is not None:
                            progress(
                                f"view {len(selector.kept)}/{max_views} kept: frame {frame.index}, "
                                f"{found.count} corners, edge width {found.edge_width_px:.2f} px ({now:.0f} s)"
                            )
                        if selector.full:
                            break
                    elif why.reason:
                        rejections.append(why)
                    else:
                        considered -= 1  # merely too soon: not a considered view
                else:
                    rejections.append(found)
                if progress is not None and time.monotonic() - last_status > 5.0:
                    last_status = time.monotonic()
                    progress(
                        f"{now:.0f} s: {len(selector.kept)}/{max_views} views kept, {considered} frames considered"
                    )
    except KeyboardInterrupt:
        if progress is not None:
            progress("capture stopped (Ctrl-C): calibrating with the views kept so far")
    return list(selector.kept), rejections, considered, size


def calibrate_source(
    source: str,
    spec: CharucoSpec,
    *,
    max_views: int = 40,
    min_views: int = 6,
    duration_s: float = 60.0,
    width: int | None = None,
    height: int | None = None,
    fps: float | None = None,
    previews: bool = False,
    progress: Progress | None = None,
    on_keep: Callable[[View, np.ndarray], None] | None = None,
    grabber: object | None = None,
) -> CalibrationReport:
    """Calibrate a camera from the ChArUco views in ``source`` (folder, glob, video or device).

    ``previews``: keep a JPEG of each view (for the recording). ``progress``: called with one-line
    progress messages. ``grabber``: a device stand-in (tests); ``on_keep``: called for each view a
    device keeps, with its frame.
    """
    if max_views < min_views:
        raise InputError(f"--max-views ({max_views}) must be at least --min-views ({min_views})")
    started = time.monotonic()
    detector = ViewDetector(spec, previews=previews)
    step = 1
    if grabber is not None or is_device(source):
        views, rejections, considered, size = _gather_device(
            source,
            detector,
            max_views=max_views,
            duration_s=duration_s,
            width=width,
            height=height,
            fps=fps,
            progress=progress,
            on_keep=on_keep,
            grabber=grabber,
        )
        kept = views
    else:
        views, rejections, considered, size, step = _gather_files(source, detector, max_views, progress)
        kept, more = select_views(views, size, max_views)
        rejections += more
    rejections.sort(key=lambda r: r.frame)
    for rejection in rejections:
        log.log(logging.DEBUG if rejection.reason == "no board" else logging.INFO, "rejected %s", rejection)
    if considered == 0:
        raise SourceError(f"{source}: no frame could be read")
    if not views:
        hint = (
            f" (markers of {spec.dictionary} were seen in {detector.markers_seen} view(s) but never as this board)"
            if detector.markers_seen
            else ""
        )
        raise InputError(
            f"no ChArUco board ({spec.describe()}) found in any of the {considered} view(s) of {source}{hint}; "
            "check --charuco/--dictionary/--legacy"
        )
    if len(kept) < min_views:
        raise InputError(
            f"only {len(kept)} usable view(s) of {considered} considered in {source}, --min-views is {min_views} "
            f"(rejected: {_reason_counts(rejections) or 'none'}); add views of the whole board, sharp and from "
            "different angles"
        )
    result = calibrate_views(spec, kept, size, min_views=min_views)
    coverage = coverage_of(result.views, size)
    warnings = list(coverage.warnings)
    fx, fy = result.camera.camera_matrix[0, 0], result.camera.camera_matrix[1, 1]
    sfx, sfy = result.std[0], result.std[1]
    if math.isfinite(sfx) and math.isfinite(sfy) and max(sfx / fx, sfy / fy) > 0.01:
        warnings.append(
            f"focal length poorly constrained (fx +- {sfx / fx:.1%}, fy +- {sfy / fy:.1%}): add views with the board "
            "tilted 20-50 degrees, near the image corners"
        )
    if result.rms > 1.0:
        warnings.append(f"RMS reprojection error {result.rms:.2f} px is high (expect < 0.5 px): check the board spec")
    return CalibrationReport(
        source=str(source),
        spec=spec,
        image_size=(int(size[0]), int(size[1])),
        considered=considered,
        rejections=tuple(rejections),
        result=result,
        coverage=coverage,
        warnings=tuple(warnings),
        seconds=time.monotonic() - started,
        frame_step=step,
    )


def _reason_counts(rejections: Iterable[Rejection]) -> str:
    counts: dict[str, int] = {}
    for rejection in rejections:
        counts[rejection.reason] = counts.get(rejection.reason, 0) + 1
    return ", ".join(f"{counts[r]} {REASONS[r]}" for r in REASONS if counts.get(r))


# ---------------------------------------------------------------------------- outputs


def write_camera_yaml(path: str | os.PathLike[str], report: CalibrationReport) -> None:
    """Write the camera YAML atomically (temporary file beside it, read back, then renamed)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"--out {path}: is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"--out {path}: cannot create its folder ({err.strerror})") from None
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp.yml")
    result = report.result
    try:
        try:
            report.camera.to_yaml(
                temporary,
                rms=float(result.rms),
                date=_dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                board=report.spec.describe(),
                views=len(result.views),
                coverage=round(report.coverage.fraction, 4),
                model=result.model,
            )
        except (cv2.error, SystemError, OSError) as err:
            raise OutputError(f"--out {path}: cannot write ({_first_line(err)})") from None
        if not temporary.is_file():
            raise OutputError(f"--out {path}: cannot write")
        try:
            CameraModel.from_yaml(temporary)
        except InputError as err:  # our own file must read back
            raise OutputError(f"--out {path}: written file does not read back ({err})") from None
        try:
            os.replace(temporary, path)
        except OSError as err:
            raise OutputError(f"--out {path}: cannot write ({err.strerror})") from None
    finally:
        if temporary.exists():
            temporary.unlink(missing_ok=True)


def _first_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


def format_report(report: CalibrationReport) -> str:
    """The terminal report: views, intrinsics, distortion, errors, coverage, warnings."""
    result = report.result
    camera = report.camera
    k = camera.camera_matrix
    std = result.std
    rejected = report.all_rejections
    lines = [
        f"calibrate {report.source}: {report.considered} view(s) considered"
        + (f" (one frame in {report.frame_step})" if report.frame_step > 1 else "")
        + f", {len(result.views)} used, {len(rejected)} rejected"
        + (f" ({_reason_counts(rejected)})" if rejected else ""),
    ]
    shown = [r for r in rejected if r.reason != "no board" or len(rejected) <= 12]
    for rejection in shown[:12]:
        lines.append(f"  rejected {rejection}")
    if len(shown) > 12:
        lines.append(f"  ... and {len(shown) - 12} more")
    elif len(shown) < len(rejected):
        lines.append(f"  ... and {len(rejected) - len(shown)} view(s) without the board")

    def pm(value: float, sigma: float, digits: int) -> str:
        return f"{value:.{digits}f}" + (f" +-{sigma:.{digits}f}" if math.isfinite(sigma) else "")

    lines.append(
        f"camera {camera.width}x{camera.height}: fx {pm(k[0, 0], std[0], 2)}  fy {pm(k[1, 1], std[1], 2)}  "
        f"cx {pm(k[0, 2], std[2], 2)}  cy {pm(k[1, 2], std[3], 2)} px"
    )
    names = ("k1", "k2", "p1", "p2", "k3")
    dist = camera.dist_coeffs
    lines.append(
        "distortion "
        + "  ".join(f"{n} {dist[i]:+.5f}" for i, n in enumerate(names) if i < dist.size)
        + f"  ({result.model})"
    )
    errors = np.asarray(result.errors_px)
    worst = int(np.argmax(errors))
    lines.append(
        f"RMS {result.rms:.3f} px"
        + (f" (first fit {result.first_rms:.3f} px on {len(result.first_views)} views)" if result.dropped else "")
        + f"; per view median {np.median(errors):.3f}, max {errors[worst]:.3f} ({result.views[worst].name})"
    )
    per_view = [f"{e:.2f}" for e in errors]
    for start in range(0, len(per_view), 16):
        lines.append(("  per-view px: " if start == 0 else "               ") + " ".join(per_view[start : start + 16]))
    coverage = report.coverage
    rows, cols = coverage.counts.shape
    lines.append(
        f"coverage {np.count_nonzero(coverage.counts)}/{coverage.counts.size} cells ({coverage.fraction:.0%}) "
        f"of a {cols}x{rows} grid, corners per cell:"
    )
    lines.extend("  " + line for line in coverage.heat_map().splitlines())
    for warning in report.warnings:
        lines.append(f"warning: {warning}")
    lines.append(f"({report.seconds:.1f} s)")
    return "\n".join(lines)


class _Recording:
    """The calibration's rerun recording (``.rrd`` file and/or a spawned viewer).

    The file is written beside its final name and renamed there by :meth:`close` when the
    calibration succeeded (``keep``); a failed run leaves no recording behind.
    """

    def __init__(self, rrd_path: Path | None, *, spawn: bool) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        from ..viz.recorder import spawn_local_viewer

        self.rr = rr
        self.rec = rr.RecordingStream("ar_anchor_calibrate")
        self.path = rrd_path
        self.partial = None if rrd_path is None else rrd_path.with_name(f".{rrd_path.name}.{os.getpid()}.tmp.rrd")
        sinks: list[object] = []
        if rrd_path is not None and self.partial is not None:
            try:
                rrd_path.parent.mkdir(parents=True, exist_ok=True)
                if rrd_path.is_dir():
                    raise IsADirectoryError(21, "is a directory")
                self.partial.touch()
            except OSError as err:
                raise OutputError(f"--rrd {rrd_path}: cannot write ({err.strerror})") from None
            sinks.append(rr.FileSink(str(self.partial)))
        if spawn and (url := spawn_local_viewer()) is not None:
            sinks.append(rr.GrpcSink(url))
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin="views", name="Views"),
                    rrb.TextLogView(origin="events", name="Events"),
                    row_shares=[3, 1],
                ),
                rrb.Vertical(
                    rrb.Spatial2DView(origin="coverage", name="Coverage"),
                    rrb.TimeSeriesView(origin="metrics/view_error_px", name="Per-view RMS error (px)"),
                ),
                column_shares=[3, 2],
            ),
            collapse_panels=True,
        )
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=blueprint)
        self.rec.send_recording_name("ar-anchor calibrate")

    def event(self, text: str, *, frame: int | None = None, warn: bool = False) -> None:
        rr = self.rr
        if frame is not None:
            self.rec.set_time("frame", sequence=int(frame))
        level = rr.TextLogLevel.WARN if warn else rr.TextLogLevel.INFO
        self.rec.log("events", rr.TextLog(text, level=level), static=frame is None)

    def live_view(self, view: View, image: np.ndarray) -> None:
        """A view a device just kept (on the ``frame`` timeline), so the viewer shows progress."""
        rr = self.rr
        self.rec.set_time("frame", sequence=int(view.frame))
        preview, scale = (view.preview, view.preview_scale) if view.preview else _jpeg_preview(image)
        self.rec.log("views/image", rr.EncodedImage(contents=preview, media_type="image/jpeg"))
        self.rec.log(
            "views/image/corners", rr.Points2D((view.corners + 0.5) * scale, radii=2.0, colors=[(40, 220, 80)])
        )

    def result(self, report: CalibrationReport) -> None:
        rr = self.rr
        result = report.result
        final = {id(v): i for i, v in enumerate(result.views)}
        for position, (view, first_error) in enumerate(zip(result.first_views, result.first_errors_px)):
            self.rec.set_time("view", sequence=position)
            self.rec.set_time("frame", sequence=int(view.frame))
            scale = view.preview_scale
            if view.preview:
                self.rec.log("views/image", rr.EncodedImage(contents=view.preview, media_type="image/jpeg"))
            self.rec.log(
                "views/image/corners",
                rr.Points2D((view.corners + 0.5) * scale, radii=2.0, colors=[(40, 220, 80)]),
            )
            self.rec.log("metrics/view_error_px/first_fit", rr.Scalars(first_error))
            index = final.get(id(view))
            if index is not None:
                self.rec.log("metrics/view_error_px/final", rr.Scalars(result.errors_px[index]))
                if index < len(result.reprojected):
                    self.rec.log(
                        "views/image/reprojected",
                        rr.Points2D((result.reprojected[index] + 0.5) * scale, radii=1.0, colors=[(255, 60, 60)]),
                    )
                text = f"view {position}: {view.name}, {view.count} corners, {result.errors_px[index]:.3f} px"
                self.rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.INFO))
            else:
                self.rec.log("views/image/reprojected", rr.Clear(recursive=False))
                why = next((d for d in result.dropped if d.name == view.name and d.frame == view.frame), None)
                self.rec.log("events", rr.TextLog(f"view {position}: {why or view.name}", level=rr.TextLogLevel.WARN))
        self._coverage(report)
        for line in format_report(report).splitlines():
            self.rec.log("events", rr.TextLog(line, level=rr.TextLogLevel.INFO), static=False)

    def _coverage(self, report: CalibrationReport) -> None:
        rr = self.rr
        width, height = report.image_size
        counts = report.coverage.counts.astype(np.float64)
        level = np.log1p(counts) / max(np.log1p(counts.max()), 1e-9)
        colours = cv2.applyColorMap(np.round(level * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        colours[counts == 0] = (40, 40, 40)
        scale = min(1.0, 640.0 / width)
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        image = cv2.resize(colours, size, interpolation=cv2.INTER_NEAREST)
        ok, png = cv2.imencode(".png", image)
        if ok:
            self.rec.log("coverage", rr.EncodedImage(contents=png.tobytes(), media_type="image/png"), static=True)
        corners = np.concatenate([v.corners for v in report.result.views])
        self.rec.log(
            "coverage/corners", rr.Points2D((corners + 0.5) * scale, radii=1.0, colors=[(255, 255, 255)]), static=True
        )

    def close(self, *, keep: bool) -> None:
        try:
            self.rec.flush(timeout_sec=10.0)
        finally:
            self.rec.disconnect()
            if self.partial is not None and self.path is not None and self.partial.exists():
                if keep:
                    try:
                        os.replace(self.partial, self.path)
                    except OSError as err:
                        self.partial.unlink(missing_ok=True)
                        raise OutputError(f"--rrd {self.path}: cannot write ({err.strerror})") from None
                else:
                    self.partial.unlink(missing_ok=True)


def run_calibrate(args: argparse.Namespace) -> int:
    """``ar-anchor calibrate``: calibrate, write ``--out`` and the recording, print the report."""
    spec = CharucoSpec.parse(args.charuco, args.square_m, args.marker_m, args.dictionary, args.legacy)
    out = Path(args.out)
    quiet = bool(getattr(args, "quiet", False))
    if out.is_dir():
        raise InputError(f"--out {out}: is a directory (give the camera YAML file to write)")
    if out.suffix.lower() == ".rrd":
        raise InputError(f"--out {out}: the camera file must be YAML, e.g. camera.yml")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"--out {out}: cannot create its folder ({err.strerror})") from None
    if not os.access(out.parent, os.W_OK):
        raise OutputError(f"--out {out}: folder {out.parent} is not writable")
    rrd = Path(args.rrd) if getattr(args, "rrd", None) is not None else out.with_suffix(".rrd")
    source = str(args.source)
    if not is_device(source) and not any(ch in source for ch in "*?[") and not Path(source).exists():
        raise SourceError(f"{source}: not found (expected an image folder or glob, a video file, or a device)")

    def progress(message: str) -> None:
        if not quiet:
            print(f"ar-anchor: {message}", file=sys.stderr, flush=True)

    recording = _Recording(rrd, spawn=bool(getattr(args, "spawn", False)))
    succeeded = False
    try:
        try:
            report = calibrate_source(
                source,
                spec,
                max_views=args.max_views,
                min_views=args.min_views,
                duration_s=getattr(args, "duration_s", 60.0) or 60.0,
                width=getattr(args, "width", None),
                height=getattr(args, "height", None),
                fps=getattr(args, "fps", None),
                previews=True,
                progress=progress,
                on_keep=recording.live_view,
            )
        except ArAnchorError as err:
            recording.event(f"calibration failed: {err}", warn=True)
            raise
        for rejection in report.rejections:
            recording.event(str(rejection), frame=rejection.frame, warn=True)
        recording.result(report)
        write_camera_yaml(out, report)
        succeeded = True
    finally:
        recording.close(keep=succeeded)
    for warning in report.warnings:
        log.warning("%s", warning)
    if not quiet:
        print(format_report(report))
    k = report.camera.camera_matrix
    print(
        f"camera: {out} (fx {k[0, 0]:.1f} fy {k[1, 1]:.1f} cx {k[0, 2]:.1f} cy {k[1, 2]:.1f}, "
        f"RMS {report.result.rms:.3f} px, {len(report.views)} views); recording: {rrd}"
    )
    return 0
