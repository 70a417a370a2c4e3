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
        self.parameters = params
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, params)
        self._warned_duplicates: set[int] = set()

    def detect(self, image: np.ndarray) -> MarkerDetections:
        """Detect markers in a BGR or grey image. Markers whose id appears twice are dropped (ambiguous)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _rejected = self._detector.detectMarkers(grey)
        if ids is None or len(ids) == 0:
            return MarkerDetections.empty()
        ids = ids.reshape(-1)
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
