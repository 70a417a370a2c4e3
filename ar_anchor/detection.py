"""Marker detection: ``cv2.aruco.ArucoDetector`` limited to the configured dictionary."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .config import CORNER_REFINEMENTS, DetectorConfig, dictionary_id

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
    """Find markers of one dictionary, with sub-pixel corner refinement by default."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self.dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(config.dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = CORNER_REFINEMENTS[config.corner_refinement]
        # sub-pixel window relative to a marker cell (OpenCV's default 0.3). On far markers the corners
        # keep a bias of a few tenths of a pixel either way; measured on the stability benchmark, a
        # larger window helps some geometries and hurts others, so the default stays OpenCV's
        if hasattr(params, "relativeCornerRefinmentWinSize"):
            params.relativeCornerRefinmentWinSize = config.refinement_window
        params.minMarkerPerimeterRate = config.min_perimeter_rate
        self.parameters = params
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, params)
        self._warned_duplicates: set[int] = set()
        self.rejected: tuple[np.ndarray, ...] = ()  # the last image's rejected candidates

    def detect(self, image: np.ndarray) -> MarkerDetections:
        """Detect markers in a BGR or grey image. Markers whose id appears twice are dropped (ambiguous)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, rejected = self._detector.detectMarkers(grey)
        self.rejected = rejected
        if ids is None or len(ids) == 0:
            return MarkerDetections.empty()
        return self._clean(ids, corners)

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
        return self._clean(ids, corners)

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
