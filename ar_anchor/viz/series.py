"""Time series sent in batches: each frame's scalars kept, and sent every N frames, one call per series.

A per-frame ``rr.log`` of every plotted number (each target's reprojection error, ambiguity, flip evidence;
every stage's time) is a hundred calls a frame with a dozen targets, each paid in the output thread that
shares the GIL with the tracker. :class:`SeriesBuffer` keeps the values with the frame they belong to and
sends each series' values of the last ``every`` frames in one ``send_columns``: the plots hold every frame's
value, and a live viewer sees them up to ``every`` frames late. Rerun orders data by their time, not by
when they arrive, so a clear logged meanwhile (a target gone) still applies from its own frame on.
"""

from __future__ import annotations

import math
from typing import Any

from .sinks import Recording

__all__ = ["SeriesBuffer"]


class SeriesBuffer:
    """Scalars of many series (entity paths) at the current frame, sent every ``every`` frames.

    :meth:`at` sets the frame (its ``frame`` sequence number and ``time`` in seconds) that :meth:`add`
    files values under; :meth:`flush` sends what is kept (also done by :meth:`at` once ``every`` frames
    are kept, and due before the recording's file changes or closes).
    """

    def __init__(self, recording: Recording, every: int) -> None:
        self.recording = recording
        self.every = max(1, int(every))
        self._frames: list[int] = []  # the frames kept, in order
        self._seconds: list[float] = []
        self._series: dict[str, tuple[list[int], list[float]]] = {}  # entity -> (row of each value, values)

    def at(self, frame: int, seconds: float) -> None:
        """The frame the next values belong to; the kept frames are sent first when there are ``every``."""
        if len(self._frames) >= self.every:
            self.flush()
        self._frames.append(int(frame))
        self._seconds.append(float(seconds))

    def add(self, entity: str, value: float | None) -> None:
        """One point of the series ``entity`` at the current frame; None and non-finite values are skipped."""
        if value is None or not math.isfinite(value) or not self._frames:
            return
        rows, values = self._series.setdefault(entity, ([], []))
        rows.append(len(self._frames) - 1)
        values.append(float(value))

    def flush(self) -> None:
        """Send every series' kept values (one call each; series with values at the same frames share their
        time columns) and start afresh."""
        frames, seconds, series = self._frames, self._seconds, self._series
        self._frames, self._seconds, self._series = [], [], {}
        indexes: dict[tuple[int, ...], Any] = {}  # the rows of a series -> its time columns
        for entity, (rows, values) in series.items():
            key = tuple(rows)
            if key not in indexes:
                indexes[key] = self.recording.time_columns(
                    frames=[frames[row] for row in rows], seconds=[seconds[row] for row in rows]
                )
            self.recording.scalar_columns(entity, values, indexes[key])
