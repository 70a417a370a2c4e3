"""A rolling shutter undone (``[pose] rolling_shutter_s``): each frame's corners taken back to the time of its
first row, from each corner's image velocity since the frame before (:class:`RollingShutter`).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..config import TrackerConfig
from ..sources.base import Frame
from .detection import MarkerDetections

__all__ = ["RollingShutter"]

log = logging.getLogger(__name__)


class RollingShutter:
    """One stream's rolling-shutter correction: :meth:`to_first_row` for each new frame, in order; it keeps
    the corners of the frame before (:attr:`previous`; :meth:`forget` after a cut)."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.previous: tuple[int, dict[int, np.ndarray]] | None = None  # (time, corners by marker id)
        self._warned = False

    def to_first_row(self, detections: MarkerDetections, frame: Frame) -> MarkerDetections:
        """``detections`` with every corner taken back to the frame's first-row time, for a rolling shutter
        (``[pose] rolling_shutter_s``, the readout time from the first row to the last; 0: unchanged). A
        corner on row ``y`` was exposed ``y / height * readout`` after the first row, while the camera moved:
        each corner moves back by its image velocity (its shift since the last frame processed, over the
        time between them: per corner, since a turning marker's corners move apart) times that delay. A
        marker not seen in that frame, one whose corners did not move as one square (:func:`_jumped`: a
        detection that jumped, whose velocity would be made of the jump), the first frame, or one after a
        gap of more than ``restart_gap_s`` is left as detected. Without this, a hand-held camera's pose is
        a mix of moments that varies with its motion: sheared markers, and the main jitter of a joint
        pose far away (docs/tracking-and-states.md)."""
        readout = self.config.pose.rolling_shutter_s
        now = {int(i): c.copy() for i, c in zip(detections.ids.tolist(), detections.corners)}
        previous, self.previous = self.previous, (frame.timestamp_ns, now)
        if readout <= 0 or previous is None or not now:
            return detections
        then_ns, before = previous
        dt = (frame.timestamp_ns - then_ns) * 1e-9
        if not 0 < dt <= max(self.config.filter.restart_gap_s, 1e-9):
            return detections
        if readout > dt * 1.05 and not self._warned:  # a camera reads its frame out within the frame
            self._warned = True
            log.warning(
                "[pose] rolling_shutter_s = %g s is longer than the time between frames (%.3g s): no camera reads "
                "out slower than its frame rate; is it the readout of this camera, in seconds?",
                readout,
                dt,
            )
        height = frame.image.shape[0]
        corners = detections.corners.copy()
        for k, marker_id in enumerate(detections.ids.tolist()):
            earlier = before.get(int(marker_id))
            if earlier is None:
                continue
            if _jumped(earlier, corners[k]):
                continue  # not the same square moved: a detection that jumped (this one or the last)
            velocity = (corners[k] - earlier) / dt  # px/s, per corner (a turning marker's corners move apart)
            delay = corners[k][:, 1:2] / height * readout  # s after the first row, per corner
            corners[k] = corners[k] - velocity * delay
        return dataclasses.replace(detections, corners=corners)

    def forget(self) -> None:
        """Forget the frame before: the next frame's corners are left as detected."""
        self.previous = None


_JUMP_SHARE = 0.05  # corners that moved this share of the marker's side (at least 1 px) otherwise than ...


def _jumped(before: np.ndarray, now: np.ndarray) -> bool:
    """Did a marker's corners (4, 2) move from ``before`` to ``now`` otherwise than one square turned,
    scaled and shifted in the image (a similarity fitted by least squares), by more than
    :data:`_JUMP_SHARE` of its side or 1 px? Then one of the two detections jumped (or is not finite)."""
    z0 = before[:, 0] + 1j * before[:, 1]
    z1 = now[:, 0] + 1j * now[:, 1]
    c0, c1 = z0.mean(), z1.mean()
    spread = float(np.sum(np.abs(z0 - c0) ** 2))
    if not spread > 0 or not np.all(np.isfinite(z1)):
        return True
    a = np.sum((z1 - c1) * np.conj(z0 - c0)) / spread
    off = float(np.abs(z1 - (a * (z0 - c0) + c1)).max())
    side = float(np.abs(np.diff(np.append(z1, z1[0]))).mean())
    return not off <= max(1.0, _JUMP_SHARE * side)
