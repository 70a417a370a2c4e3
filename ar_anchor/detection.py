"""Marker detection: ``cv2.aruco.ArucoDetector`` limited to the configured dictionary."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import CameraModel
from .config import CORNER_REFINEMENTS, DetectorConfig, dictionary_id
from .corners import refine_corners_by_edges

__all__ = ["Detector", "MarkerDetections"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MarkerDetections:
    """Markers found in one image, as parallel arrays.

    Attributes
    ----------
    ids : (N,) int32 marker ids.
    corners : (N, 4, 2) float64 pixel coordinates, TL, TR, BR, BL (pixel centres at integers).
    """

    ids: np.ndarray
    corners: np.ndarray

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int32).reshape(-1)
        corners = np.asarray(self.corners, dtype=np.float64).reshape(-1, 4, 2)
        if len(ids) != len(corners):
            raise ValueError(f"MarkerDetections: {len(ids)} ids but {len(corners)} corner sets")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners", corners)

    @classmethod
    def empty(cls) -> MarkerDetections:
        return cls(np.zeros(0, np.int32), np.zeros((0, 4, 2)))

    def __len__(self) -> int:
        return len(self.ids)


class Detector:
    """Find markers of one dictionary, with sub-pixel corners fitted to the markers' edges by default
    (:mod:`ar_anchor.corners`; ``corner_refinement`` selects OpenCV's methods instead)."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self.dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(config.dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = CORNER_REFINEMENTS[config.corner_refinement]
        # subpix: window relative to a marker cell (OpenCV's default 0.3). On far markers its corners
        # keep a bias of a few tenths of a pixel whatever the window, hence the "edges" default
        self._edges = config.corner_refinement == "edges"
        self._cells = int(self.dictionary.markerSize) + 2
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
        self._warned_duplicates: set[int] = set()
        self.rejected: tuple[np.ndarray, ...] = ()  # the last image's rejected candidates

    def detect(self, image: np.ndarray, camera: CameraModel | None = None) -> MarkerDetections:
        """Detect markers in a BGR or grey image. Markers whose id appears twice are dropped (ambiguous).

        ``camera`` (optional) lets the edge refinement fit the markers' sides in the undistorted image.
        """
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, rejected = self._detector.detectMarkers(grey)
        self.rejected = rejected
        if ids is None or len(ids) == 0:
            return MarkerDetections.empty()
        detections = self._clean(ids, corners)
        if self._edges:
            k, dist = (None, None) if camera is None else (camera.camera_matrix, camera.dist_or_none)
            detections = MarkerDetections(
                detections.ids, refine_corners_by_edges(grey, detections.corners, self._cells, k, dist)
            )
        return detections

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
            refined[new] = refine_corners_by_edges(grey, refined[new], self._cells, camera_matrix, dist)
            recovered = MarkerDetections(recovered.ids, refined)
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
        return MarkerDetections(ids[order], corners[order])
