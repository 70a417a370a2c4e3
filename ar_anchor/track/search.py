"""Where each frame's markers are looked for (:class:`MarkerSearch`, the detection stage of
:meth:`Tracker.detect <ar_anchor.track.tracker.Tracker.detect>`): whether the frame repeats the last one's content
or is motion-blurred, and its markers, found in regions around where they were (ROI tracking) or in the whole
frame (the fast search for big markers, or the thorough one). It holds detection state only (where markers were,
the last frame's fingerprint, the typical sharpness), so it may run a frame ahead of the rest (:mod:`.ahead`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import TrackerConfig
from ..sources.base import Frame
from .detection import FAST_MIN_SIDE_PX, Detector, MarkerDetections, mean_side, plan_regions
from .pose import BoardSolver
from .results import DetectedFrame

__all__ = ["MarkerSearch"]

_MOST_OF_THE_FRAME = 0.4  # regions covering more than this share of the frame: a fast whole-frame search instead
_REPEAT_PX = 0.25  # corners that moved less than this (every one) are a repeated frame's


class MarkerSearch:
    """One stream's detection stage (see the module doc): :meth:`look` at each frame, in order; :meth:`reset`
    after a cut. ``detector`` finds the markers, in the whole frame or in regions."""

    _BLUR_RATIO = 0.6  # a frame this much less sharp than usual is motion-blurred

    def __init__(self, config: TrackerConfig, detector: Detector) -> None:
        self.config = config
        self.detector = detector
        # ROI tracking state: the last two frames' corners per marker id
        self._last_corners: dict[int, np.ndarray] = {}
        self._before_corners: dict[int, np.ndarray] = {}
        self._fingerprint: np.ndarray | None = None  # every 4th pixel of the last frame (repeats)
        self._sharpness: float | None = None  # typical variance of the fingerprint's Laplacian (blur)
        self._detail = math.nan  # this frame's fine-scale contrast (see FrameResult.detail)
        self._last_observed: MarkerDetections | None = None  # the last new frame's markers (repeats)
        self._seen: dict[int, tuple[np.ndarray, int]] = {}  # marker id -> (last corners, when)
        self._frames_since_full = 0
        self._frames_since_thorough = 0  # frames since the last thorough full-frame search (see _search_whole_frame)
        self._last_size: tuple[int, int] | None = None

    def look(self, frame: Frame, camera: CameraModel, board_solvers: Sequence[BoardSolver] = ()) -> DetectedFrame:
        """The detection stage of one frame (``camera``: the calibration at its size): whether it repeats the last
        new frame (:meth:`_repeats`, and the same markers at the same corners) or is motion-blurred (:meth:`_blurred`),
        and its markers (:meth:`_detect`), those of ``board_solvers``' boards recovered when ``[pose]
        recover_markers`` asks."""
        fingerprint = _every_4th_pixel(frame.image)
        candidate = self._last_observed is not None and self._repeats(fingerprint)
        blurred = self._blurred(fingerprint)
        t0 = time.perf_counter()
        detections = self._detect(frame.image, camera, frame.timestamp_ns, blurred)
        if candidate and self._last_observed is not None and _same_corners(detections, self._last_observed):
            detect_ms = (time.perf_counter() - t0) * 1e3
            return DetectedFrame(frame, camera, detections, blurred, self._detail, True, detect_ms)
        if self.config.pose.recover_markers:
            for solver in board_solvers:
                detections = self.detector.recover(
                    frame.image, detections, solver.cv_board, camera.camera_matrix, camera.dist_or_none
                )
        self._fingerprint, self._last_observed = fingerprint, detections
        return DetectedFrame(frame, camera, detections, blurred, self._detail, False, (time.perf_counter() - t0) * 1e3)

    def _detect(
        self, image: np.ndarray, camera: CameraModel, timestamp_ns: int, blurred: bool = False
    ) -> MarkerDetections:
        """Full-frame detection, or ROI tracking between full-frame searches (``[detector] roi``).

        Regions are searched only while every marker seen in the last ``[filter] memory_s`` was seen in
        the previous frame too. The whole frame is searched on the first frame, every ``roi_full_every``
        frames, after a frame size change, in every frame while a recently seen marker is missing (a
        marker lost to one blurred frame is looked for everywhere until it is back or forgotten), and
        again in the same frame whenever a region search misses a marker the previous frame had. So ROI
        tracking never finds fewer of the known markers than full-frame detection; a marker never seen
        before is found within ``roi_full_every`` frames. ``blurred``: the frame is motion-blurred (see
        :meth:`_blurred`), so it is not given the fast whole-frame search.
        """
        settings = self.config.detector
        size = (image.shape[1], image.shape[0])
        memory_ns = int(self.config.filter.memory_s * 1e9)
        self._seen = {i: seen for i, seen in self._seen.items() if timestamp_ns - seen[1] <= memory_ns}
        missing = any(i not in self._last_corners for i in self._seen)
        full = (
            not settings.roi
            or not self._last_corners
            or missing
            or self._frames_since_full + 1 >= settings.roi_full_every
            or size != self._last_size
        )
        detections = None
        if not full:
            moving = {i: c for i, c in self._before_corners.items() if i in self._last_corners}
            regions = plan_regions(self._last_corners, moving, size, settings.roi_margin, cells=self.detector.cells)
            area = sum((r.x1 - r.x0) * (r.y1 - r.y0) for r in regions)
            if area <= _MOST_OF_THE_FRAME * size[0] * size[1] or not self._fast_allowed(size, blurred):
                detections = self.detector.detect_regions(image, regions, camera)
                if not set(self._last_corners) <= set(detections.ids.tolist()):
                    detections = None  # a marker was missed: search everywhere
            # (else regions as large as most of the frame: the fast whole-frame search costs less)
        if detections is None:
            detections = self._search_whole_frame(image, camera, size, blurred)
            self._frames_since_full = 0
        else:
            self._frames_since_full += 1
            if self.config.detector.fast_search:
                self._frames_since_thorough += 1
        self._last_size = size
        self._before_corners = self._last_corners
        self._last_corners = {int(i): c for i, c in zip(detections.ids, detections.corners)}
        for marker_id, corners in self._last_corners.items():
            if self.config.tracks_marker(marker_id):  # (a stray id of no interest is not searched for)
                self._seen[marker_id] = (corners, timestamp_ns)
        return detections

    def _search_whole_frame(
        self, image: np.ndarray, camera: CameraModel, size: tuple[int, int], blurred: bool
    ) -> MarkerDetections:
        """A full-frame search: the fast one (:meth:`Detector.detect` ``fast``: big markers only) while ROI
        tracking may use it, else the thorough one, which finds markers of any size.

        Fast only while every marker seen in the last ``memory_s`` was at least ``FAST_MIN_SIDE_PX`` on its
        last sighting, on a frame of the same size that is not motion-blurred (one threshold can outline a
        smeared marker, corners many pixels off, that the thorough search rejects), and never for
        ``roi_full_every`` frames in a row (``[detector] fast_search``, off by default: see
        docs/architecture.md). A marker the previous frame had that the fast search misses is looked for
        again, thoroughly, in its region (as ROI tracking does). So no marker the previous frame had is
        lost, and a marker never seen before (or a small one coming back) is found within
        ``roi_full_every`` frames.
        """
        settings = self.config.detector
        if not self._fast_allowed(size, blurred):
            self._frames_since_thorough = 0
            return self.detector.detect(image, camera)
        self._frames_since_thorough += 1
        detections = self.detector.detect(image, camera, fast=True)
        found = set(detections.ids.tolist())
        lost = {i: c for i, c in self._last_corners.items() if i not in found}
        if not lost:
            return detections
        # (mostly markers really gone this frame, blurred or hidden: a region each costs little to make sure)
        rejected = self.detector.rejected
        moving = {i: c for i, c in self._before_corners.items() if i in lost}
        regions = plan_regions(lost, moving, size, settings.roi_margin, cells=self.detector.cells)
        again = self.detector.detect_regions(image, regions, camera, thorough=True)
        self.detector.rejected = (*rejected, *self.detector.rejected)
        new = ~np.isin(again.ids, detections.ids)
        if not new.any():
            return detections
        return MarkerDetections(
            np.concatenate([detections.ids, again.ids[new]]),
            np.concatenate([detections.corners, again.corners[new]]),
            np.union1d(detections.duplicated, again.duplicated),
        )

    def _fast_allowed(self, size: tuple[int, int], blurred: bool) -> bool:
        """May the next whole-frame search be the fast one (see :meth:`_search_whole_frame`)?"""
        settings = self.config.detector
        return (
            settings.roi
            and settings.fast_search
            and not blurred
            and size == self._last_size
            and bool(self._seen)
            and self._frames_since_thorough + 1 < settings.roi_full_every
            and all(mean_side(corners) >= FAST_MIN_SIDE_PX for corners, _ in self._seen.values())
        )

    def _blurred(self, fingerprint: np.ndarray) -> bool:
        """Is this frame motion-blurred (a quick turn), not merely missing a marker? Sharpness is the
        Laplacian's variance of every 4th pixel over that of a half-size copy: blur takes the fine scale
        away first, while removing content (a marker out of view) lowers both alike. Blurred: below
        ``_BLUR_RATIO`` of its running typical value."""
        grey = cv2.cvtColor(fingerprint, cv2.COLOR_BGR2GRAY) if fingerprint.ndim == 3 else fingerprint
        grey = grey.astype(np.float32)
        self._detail = float(cv2.Laplacian(grey, cv2.CV_32F).var())
        coarse = float(cv2.Laplacian(cv2.pyrDown(grey), cv2.CV_32F).var()) if min(grey.shape[:2]) >= 16 else 0.0
        if coarse <= 1e-6:
            return False
        sharpness = self._detail / coarse
        typical = self._sharpness
        blurred = typical is not None and sharpness < self._BLUR_RATIO * typical
        if not blurred:
            self._sharpness = sharpness if typical is None else 0.9 * typical + 0.1 * sharpness
        return blurred

    def _repeats(self, fingerprint: np.ndarray) -> bool:
        """Might this be the last tracked frame's content again: every 4th pixel the same to within
        ``[filter] repeat_grey`` grey levels on average (a repeated frame re-encoded by a lossy codec is
        not bit-identical)? It is a repeat only if it also shows the same markers at the same corners
        (``_REPEAT_PX``): a slowly moving real video differs as little in its pixels, but not there."""
        previous = self._fingerprint
        if previous is None or previous.shape != fingerprint.shape:
            return False
        tolerance = self.config.filter.repeat_grey
        if tolerance <= 0:
            return bool(np.array_equal(previous, fingerprint))
        return float(cv2.absdiff(previous, fingerprint).mean()) < tolerance

    def reset(self) -> None:
        """Forget where markers were, repeats and sharpness: the next frame is looked at as by a new search."""
        self._fingerprint = self._last_observed = None
        self._sharpness = None
        self._last_corners, self._before_corners, self._seen = {}, {}, {}
        self._frames_since_full = self._frames_since_thorough = 0
        self._last_size = None


def _every_4th_pixel(image: np.ndarray) -> np.ndarray:
    """``image[::4, ::4]``, contiguous: by OpenCV's nearest-neighbour resize where that picks the same pixels
    (sides divisible by 4: a third of numpy's strided copy's time, without the GIL), else by numpy."""
    height, width = image.shape[:2]
    if height % 4 or width % 4 or height < 4 or width < 4:
        return np.ascontiguousarray(image[::4, ::4])
    return cv2.resize(image, (width // 4, height // 4), interpolation=cv2.INTER_NEAREST)


def _same_corners(now: MarkerDetections, before: MarkerDetections) -> bool:
    """Does every marker found now sit where it was found before (each corner within ``_REPEAT_PX``)?
    (A marker the repeat lost to compression noise changes nothing; one found only now does.)"""
    if len(now.ids) == 0:
        return False
    where = {int(i): c for i, c in zip(before.ids, before.corners)}
    return all(
        int(i) in where and float(np.abs(c - where[int(i)]).max()) < _REPEAT_PX for i, c in zip(now.ids, now.corners)
    )
