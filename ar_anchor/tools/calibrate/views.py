"""ChArUco views: the board (:class:`CharucoSpec`), detection and sharpness of each frame
(:class:`ViewDetector`, :func:`edge_width_px`), and which views to keep: sharp, distinct, covering
the image (:func:`select_views` for files and videos, :class:`OnlineSelector` for devices).

A view that is not kept becomes a :class:`Rejection` whose ``reason`` is a key of :data:`REASONS`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ...config import canonical_dictionary, dictionary_id
from ...errors import ConfigError, InputError

__all__ = [
    "REASONS",
    "CharucoSpec",
    "OnlineSelector",
    "Rejection",
    "View",
    "ViewDetector",
    "blur_threshold_px",
    "edge_width_px",
    "is_duplicate",
    "jpeg_preview",
    "reason_counts",
    "select_views",
]

MIN_CORNERS = 6  # at least this many chessboard corners per view ...
MIN_CORNER_FRACTION = 0.25  # ... and at least this fraction of the board's corners
BLUR_FLOOR_PX = 1.8  # edge width (Gaussian sigma, px) always accepted
BLUR_RATIO = 1.6  # ... and accepted up to this multiple of the sharp reference
BLUR_REFERENCE_PERCENTILE = 25.0  # the sharp reference: this percentile of the detected views' widths
DUPLICATE_FRACTION = 0.02  # of the image diagonal: mean shift of shared corners below it = same view
MIN_INTERVAL_S = 0.5  # devices: kept views at least this far apart in time
SELECTION_GRID = (16, 12)  # cells across, down (coverage-greedy selection)
PREVIEW_MAX_SIDE = 1024  # recording images are scaled down to this longer side

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
        cls,
        charuco: str,
        square_m: float,
        marker_m: float,
        dictionary: str,
        legacy: bool = False,
        *,
        options: tuple[str, str] = ("--square-m", "--marker-m"),
    ) -> CharucoSpec:
        """Validate the command-line description; :class:`InputError` names the option at fault (the lengths':
        ``options``, the flags the user typed for the square and the marker)."""
        square_option, marker_option = options
        text = str(charuco).strip().lower()
        parts = text.split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise InputError(f"--charuco: expected squares across x down such as 5x7, got {charuco!r}")
        cols, rows = (int(p) for p in parts)
        if cols < 2 or rows < 2:
            raise InputError(f"--charuco: a board needs at least 2x2 squares, got {charuco!r}")
        for option, value in ((square_option, square_m), (marker_option, marker_m)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{option}: must be a length > 0 in metres, got {value!r}")
        if marker_m >= square_m:
            raise InputError(
                f"{marker_option}: the marker ({marker_m:g} m) must be smaller than the square "
                f"({square_option} {square_m:g} m)"
            )
        try:
            canonical = canonical_dictionary(dictionary)
        except ConfigError as err:
            raise InputError(f"--dictionary: {err}") from None
        dict_id = dictionary_id(canonical)
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
        """The OpenCV ChArUco board (lengths in metres)."""
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
        """The board's view in ``image``, or why it is rejected (no board, too few corners, corners on one line)."""
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
            preview, scale = jpeg_preview(image)
        return View(name, frame, points, ids, width, preview, scale)


def jpeg_preview(image: np.ndarray) -> tuple[bytes, float]:
    """A JPEG of ``image`` for the recording, its longer side at most ``PREVIEW_MAX_SIDE``: (bytes, scale)."""
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
        duplicate = _duplicate_of(sharp[best], [sharp[k] for k in kept], image_size)
        if duplicate is not None:
            rejections.append(duplicate)
            continue
        kept.append(best)
        seen += cells[best]
    for index in remaining:
        duplicate = _duplicate_of(sharp[index], [sharp[k] for k in kept], image_size)
        rejections.append(duplicate or Rejection(sharp[index].name, sharp[index].frame, "surplus", f"{max_views} kept"))
    return sorted((sharp[k] for k in kept), key=lambda v: v.frame), rejections


def _duplicate_of(view: View, kept: Sequence[View], image_size: tuple[int, int]) -> Rejection | None:
    """The rejection of ``view`` as a near-copy of the first of ``kept`` it duplicates, or None."""
    for other in kept:
        same, shift = is_duplicate(view, other, image_size)
        if same:
            return Rejection(view.name, view.frame, "duplicate", f"of {other.name}, {shift:.1f} px apart")
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
        duplicate = _duplicate_of(view, self.kept, self.image_size)
        if duplicate is not None:
            return duplicate
        if now_s - self._last_kept_s < MIN_INTERVAL_S:
            return Rejection(view.name, view.frame, "", "too soon after the last kept view")
        self.kept.append(view)
        self._last_kept_s = now_s
        return None

    @property
    def full(self) -> bool:
        return len(self.kept) >= self.max_views


def reason_counts(rejections: Iterable[Rejection]) -> str:
    """``"1 no board, 2 blurry"``: the rejections counted by reason, in the order of :data:`REASONS`."""
    counts: dict[str, int] = {}
    for rejection in rejections:
        counts[rejection.reason] = counts.get(rejection.reason, 0) + 1
    return ", ".join(f"{counts[r]} {REASONS[r]}" for r in REASONS if counts.get(r))
