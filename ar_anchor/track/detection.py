"""Marker detection: ``cv2.aruco.ArucoDetector`` limited to the configured dictionary."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import CORNER_REFINEMENTS, DetectorConfig, dictionary_id
from .corners import refine_corners_by_edges

__all__ = ["FAST_MIN_SIDE_PX", "Detector", "MarkerDetections", "Region", "mean_side", "plan_regions"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MarkerDetections:
    """Markers found in one image, as parallel arrays.

    Attributes
    ----------
    ids : (N,) int32 marker ids.
    corners : (N, 4, 2) float64 pixel coordinates, TL, TR, BR, BL (pixel centres at integers).
    duplicated : (M,) int32 ids seen more than once in the image, dropped (not in ``ids``): which marker
        is which cannot be told, so none of them is used.
    """

    ids: np.ndarray
    corners: np.ndarray
    duplicated: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int32).reshape(-1)
        corners = np.asarray(self.corners, dtype=np.float64).reshape(-1, 4, 2)
        if len(ids) != len(corners):
            raise ValueError(f"MarkerDetections: {len(ids)} ids but {len(corners)} corner sets")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners", corners)
        object.__setattr__(self, "duplicated", np.asarray(self.duplicated, dtype=np.int32).reshape(-1))

    @classmethod
    def empty(cls) -> MarkerDetections:
        return cls(np.zeros(0, np.int32), np.zeros((0, 4, 2)))

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Region:
    """A rectangle of the image to search, ``[x0, x1) x [y0, y1)`` pixels, at ``scale`` (<= 1)."""

    x0: int
    y0: int
    x1: int
    y1: int
    scale: float = 1.0
    cell_px: float = 10.0  # the expected width of a marker cell in the searched (scaled) image


def plan_regions(
    previous: dict[int, np.ndarray],
    before: dict[int, np.ndarray],
    size: tuple[int, int],
    margin: float,
    target_side_px: float = 80.0,
    cells: int = 6,
) -> list[Region]:
    """Search regions for the next frame from the markers' last corners (``previous``, id -> (4, 2)),
    moved on by their last motion (``before``: the frame before), grown by ``margin`` marker sides
    and by that motion, clipped to the image, and merged where they overlap. A region's scale shrinks
    its markers to about ``target_side_px`` when they are at least a third larger (never enlarges).
    ``cells``: marker cells per side, border included (for the regions' expected cell size)."""
    width, height = size
    boxes: list[list[float]] = []  # x0, y0, x1, y1, smallest side
    for marker_id, corners in previous.items():
        corners = np.asarray(corners, np.float64)
        motion = corners.mean(axis=0) - before[marker_id].mean(axis=0) if marker_id in before else np.zeros(2)
        side = float(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1).mean())
        grow = margin * side + float(np.abs(motion).max()) + 8.0
        lo, hi = corners.min(axis=0) + motion - grow, corners.max(axis=0) + motion + grow
        boxes.append([lo[0], lo[1], hi[0], hi[1], side])
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]), min(a[4], b[4])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    regions = []
    for x0, y0, x1, y1, side in boxes:
        x0, y0 = max(int(np.floor(x0)), 0), max(int(np.floor(y0)), 0)
        x1, y1 = min(int(np.ceil(x1)) + 1, width), min(int(np.ceil(y1)) + 1, height)
        if x1 - x0 >= 8 and y1 - y0 >= 8:
            scale = target_side_px / max(side, 1.0)
            scale = scale if scale < 0.75 else 1.0  # shrinking a little saves nothing
            regions.append(Region(x0, y0, x1, y1, scale, side * scale / cells))
    return regions


# OpenCV's Aruco3 search (useAruco3Detection, no downscaling) keeps candidates whose sides are at least
# minSideLengthCanonicalImg pixels (32) and thresholds the image once: on chessboard.avi (18 markers of 33-60 px)
# it finds exactly the markers the three-window search finds in every frame, in a sixth of the time; it finds
# no marker of 32 px and every one of 40 px and more (synthetic 4x4 markers, blurred and noisy, 640-1920 px wide).
# It is used only while every marker known is at least FAST_MIN_SIDE_PX (a margin for a marker seen smaller
# in the next frame); see MarkerSearch._detect (search.py).
_FAST_CANONICAL_SIDE_PX = 32
FAST_MIN_SIDE_PX = 40.0


def _derived_parameters(params: cv2.aruco.DetectorParameters, **changes: object) -> cv2.aruco.DetectorParameters:
    """OpenCV's defaults with ``params``' refinement, perimeter limit and bit reading, then ``changes``."""
    derived = cv2.aruco.DetectorParameters()
    for name in (
        "cornerRefinementMethod",
        "relativeCornerRefinmentWinSize",
        "minMarkerPerimeterRate",
        "perspectiveRemoveIgnoredMarginPerCell",
        "perspectiveRemovePixelPerCell",
    ):
        if hasattr(params, name):
            setattr(derived, name, getattr(params, name))
    for name, value in changes.items():
        setattr(derived, name, value)
    return derived


def _fast_parameters(params: cv2.aruco.DetectorParameters) -> cv2.aruco.DetectorParameters:
    """The Aruco3 variant of ``params``, without downscaling (sides are measured in the image's pixels)."""
    return _derived_parameters(
        params,
        useAruco3Detection=True,
        minSideLengthCanonicalImg=_FAST_CANONICAL_SIDE_PX,
        minMarkerLengthRatioOriginalImg=0.0,
    )


def mean_side(corners: np.ndarray) -> float:
    """The mean side length, in pixels, of a marker's corners (4, 2): a quarter of its perimeter."""
    corners = np.asarray(corners, np.float64).reshape(4, 2)
    return float(np.sqrt(((np.roll(corners, -1, axis=0) - corners) ** 2).sum(axis=1)).mean())


class Detector:
    """Find markers of one dictionary, with sub-pixel corners fitted to the markers' edges by default
    (:mod:`ar_anchor.track.corners`; ``corner_refinement`` selects OpenCV's methods instead)."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self.dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(config.dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = CORNER_REFINEMENTS[config.corner_refinement]
        # subpix: window relative to a marker cell (OpenCV's default 0.3). On far markers its corners
        # keep a bias of a few tenths of a pixel whatever the window, hence the "edges" default
        self._edges = config.corner_refinement == "edges"
        self.cells = int(self.dictionary.markerSize) + 2  # marker cells per side, border included
        if hasattr(params, "relativeCornerRefinmentWinSize"):
            params.relativeCornerRefinmentWinSize = config.refinement_window
        params.minMarkerPerimeterRate = config.min_perimeter_rate
        # Reading the bits of far markers (cells of about 3 px): OpenCV's defaults (margin 0.13, 4 px per
        # cell) lose a 20 px 4x4 marker entirely at some sub-pixel phases (bench boards at 3 m, 4.5 m).
        # Margin 0.25 with 6 px per cell reads them at every distance of that bench and still finds all
        # 24 markers of the real aruco_testdata board photo and the same markers in its video.
        params.perspectiveRemoveIgnoredMarginPerCell = config.cell_margin
        params.perspectiveRemovePixelPerCell = 6
        self.parameters = params
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, params)
        self._fast_detector: cv2.aruco.ArucoDetector | None = None  # built on the first fast search
        self._region_detectors: dict[tuple[int, float], cv2.aruco.ArucoDetector] = {}
        self._warned_duplicates: set[int] = set()
        self.rejected: tuple[np.ndarray, ...] = ()  # the last image's rejected candidates

    def detect(self, image: np.ndarray, camera: CameraModel | None = None, fast: bool = False) -> MarkerDetections:
        """Detect markers in a BGR or grey image. Markers whose id appears twice are dropped (ambiguous).

        ``camera`` (optional) lets the edge refinement fit the markers' sides in the undistorted image.
        ``fast``: OpenCV's Aruco3 search (one threshold, candidates of at least :data:`FAST_MIN_SIDE_PX`),
        several times cheaper where markers are big; it cannot find smaller markers.
        """
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if fast and self._fast_detector is None:
            self._fast_detector = cv2.aruco.ArucoDetector(self.dictionary, _fast_parameters(self.parameters))
        corners, ids, rejected = (self._fast_detector if fast else self._detector).detectMarkers(grey)
        self.rejected = rejected
        if ids is None or len(ids) == 0:
            return MarkerDetections.empty()
        detections = self._clean(ids, corners)
        if self._edges:
            k, dist = (None, None) if camera is None else (camera.camera_matrix, camera.dist_or_none)
            detections = MarkerDetections(
                detections.ids,
                refine_corners_by_edges(grey, detections.corners, self.cells, k, dist),
                detections.duplicated,
            )
        return detections

    def detect_regions(
        self, image: np.ndarray, regions: list[Region], camera: CameraModel | None = None, thorough: bool = False
    ) -> MarkerDetections:
        """Detect markers only inside ``regions`` (ROI tracking), each searched at its own scale.

        A region's crop is searched by the same detector, shrunk first when ``region.scale < 1``
        (big markers need no full resolution to be found); corners map back to full-image pixels
        exactly (pixel centres at integers: ``full = (p + 0.5) / scale - 0.5 + origin``), and the
        edge refinement then runs on the region's full-resolution pixels, so ROI corners are as
        accurate as full-frame ones. Only the regions are converted to grey. A marker found in two
        overlapping regions at the same place counts once. ``thorough``: every region searched once, at
        full scale, as the full-frame search does (three threshold windows).
        """
        found_ids: list[np.ndarray] = []
        found_corners: list[np.ndarray] = []
        rejected: list[np.ndarray] = []
        k, dist = (None, None) if camera is None else (camera.camera_matrix, camera.dist_or_none)
        # the smallest marker perimeter a full-frame search accepts, in pixels: a crop's own fraction of its
        # size would accept far smaller candidates (many more contours to look at, none a full-frame search keeps)
        min_perimeter_px = self.parameters.minMarkerPerimeterRate * max(image.shape[:2])
        for region in regions:
            crop = image[region.y0 : region.y1, region.x0 : region.x1]
            if crop.shape[0] < 8 or crop.shape[1] < 8:
                continue
            grey = crop if crop.ndim == 2 else cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)  # only the region's pixels
            if region.scale < 1.0 and not thorough:
                size = (max(8, round(grey.shape[1] * region.scale)), max(8, round(grey.shape[0] * region.scale)))
                # bilinear is 7x cheaper than area averaging and good enough to find a marker shrunk by up to
                # half (its corners are refined at full resolution afterwards); below that it would alias
                shrink = cv2.INTER_LINEAR if region.scale >= 0.5 else cv2.INTER_AREA
                search = cv2.resize(grey, size, interpolation=shrink)
            else:
                search = grey
            origin = np.array([region.x0, region.y0], np.float64)
            rate = min_perimeter_px * search.shape[1] / grey.shape[1] / max(search.shape[:2])
            cell_px = 0.0 if thorough else region.cell_px  # (below 8 px: the three windows)
            corners, ids, candidates = self._region_detector(cell_px, rate).detectMarkers(search)
            if (ids is None or not len(ids)) and not thorough:
                # the one threshold window, or shrinking (e.g. sides bent by a strong lens), can lose a
                # marker: look again with the full-frame detector at full scale
                search = grey
                rate = min_perimeter_px / max(grey.shape[:2])
                corners, ids, candidates = self._region_detector(0.0, rate).detectMarkers(grey)
            factors = (search.shape[1] / grey.shape[1], search.shape[0] / grey.shape[0])

            def to_crop(points: np.ndarray, factors: tuple[float, float] = factors) -> np.ndarray:
                points = np.asarray(points, np.float64).reshape(-1, 4, 2)
                return (points + 0.5) / np.asarray(factors) - 0.5

            if ids is not None and len(ids):
                local = to_crop(np.asarray(corners))
                if self._edges:  # refined at full resolution, on the region's own pixels
                    shifted = None
                    if k is not None:
                        shifted = k.copy()
                        shifted[:2, 2] -= origin
                    local = refine_corners_by_edges(grey, local, self.cells, shifted, dist)
                found_ids.append(np.asarray(ids).reshape(-1))
                found_corners.append(local + origin)
            rejected.extend((to_crop(c) + origin).astype(np.float32).reshape(1, 4, 2) for c in candidates)
        self.rejected = tuple(rejected)
        if not found_ids:
            return MarkerDetections.empty()
        ids = np.concatenate(found_ids)
        corners = np.concatenate(found_corners)
        keep = np.ones(len(ids), bool)
        for i in range(len(ids)):  # the same marker seen from two overlapping regions: keep the first
            for j in range(i):
                if keep[j] and ids[j] == ids[i] and np.abs(corners[j] - corners[i]).max() < 2.0:
                    keep[i] = False
                    break
        return self._clean(ids[keep], corners[keep])

    def _region_detector(self, cell_px: float, perimeter_rate: float) -> cv2.aruco.ArucoDetector:
        """A detector for a region whose marker cells are about ``cell_px`` wide (after its scale): for
        cells of 8 px and more, the full-frame detector's parameters but one adaptive-threshold window
        (23 px, two to three cells) instead of the three sizes a full-frame search must try, since the
        marker's size is known (a third less time); for smaller cells, the full-frame detector's three.
        ``perimeter_rate``: the region's ``minMarkerPerimeterRate`` (the full frame's smallest perimeter
        in pixels, as a fraction of the searched image's larger side)."""
        # small cells: one window can outline a far marker a pixel or two off (the edge fit cannot
        # move a small marker's corners that far), so the full-frame detector's three windows it is
        window = 23 if cell_px >= 8.0 else 0
        rate = float(min(max(perimeter_rate, 1e-3), 4.0))
        rate = float(f"{rate:.2g}")  # a few detectors serve every region size
        key = (window, rate)
        detector = self._region_detectors.get(key)
        if detector is None:
            if len(self._region_detectors) >= 64:
                self._region_detectors.clear()
            changes: dict[str, object] = {"minMarkerPerimeterRate": rate}
            if window:
                changes.update(adaptiveThreshWinSizeMin=window, adaptiveThreshWinSizeMax=window)
            detector = cv2.aruco.ArucoDetector(self.dictionary, _derived_parameters(self.parameters, **changes))
            self._region_detectors[key] = detector
        return detector

    def recover(
        self,
        image: np.ndarray,
        detections: MarkerDetections,
        board: cv2.aruco.Board,
        camera_matrix: np.ndarray,
        dist: np.ndarray | None,
    ) -> MarkerDetections:
        """Look again for ``board``'s missing markers among the last :meth:`detect` call's rejected
        candidates, where the detected ones say they should be (``refineDetectedMarkers``)."""
        board_ids = set(np.asarray(board.getIds()).reshape(-1).tolist())
        seen = board_ids & set(detections.ids.tolist())
        if not seen or seen == board_ids or not getattr(self, "rejected", None):
            return detections
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners = [c.reshape(1, 4, 2).astype(np.float32) for c in detections.corners]
        ids = detections.ids.reshape(-1, 1).astype(np.int32)
        try:
            corners, ids, rejected, _ = self._detector.refineDetectedMarkers(
                grey, board, corners, ids, self.rejected, camera_matrix, dist
            )
        except cv2.error as err:
            log.debug("refineDetectedMarkers failed: %s", str(err).strip().splitlines()[-1])
            return detections
        self.rejected = rejected
        if ids is None or len(ids) <= len(detections):
            return detections
        recovered = self._clean(ids, corners)
        if self._edges:
            new = ~np.isin(recovered.ids, detections.ids)
            refined = recovered.corners.copy()
            refined[new] = refine_corners_by_edges(grey, refined[new], self.cells, camera_matrix, dist)
            recovered = MarkerDetections(recovered.ids, refined, recovered.duplicated)
        return recovered

    def _clean(self, ids: np.ndarray, corners: np.ndarray) -> MarkerDetections:
        ids = np.asarray(ids).reshape(-1)
        corners = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
        unique, counts = np.unique(ids, return_counts=True)
        duplicated = unique[counts > 1]
        if duplicated.size:
            new = set(duplicated.tolist()) - self._warned_duplicates
            if new:
                log.warning("marker id(s) %s seen more than once in one frame: ignored while duplicated", sorted(new))
                self._warned_duplicates |= new
            keep = ~np.isin(ids, duplicated)
            ids, corners = ids[keep], corners[keep]
        order = np.argsort(ids, kind="stable")
        return MarkerDetections(ids[order], corners[order], duplicated)
