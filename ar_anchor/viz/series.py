"""Per-frame values sent in batches: each frame's scalars, poses and other archetypes (points, lines...)
kept, and sent every N frames, one call per entity.

A per-frame ``rr.log`` of every plotted number (each target's reprojection error, ambiguity, flip evidence;
every stage's time), of every target's pose and of the scene's other entities is a hundred calls a frame
with a dozen targets, each paid in the output thread that shares the GIL with the tracker (a call costs
50-150 us of Python and rerun's chunk building; sending N frames' rows in one costs about what one frame's
does). :class:`SeriesBuffer` keeps the values with the frame they belong to and sends each entity's values
of the last ``every`` frames in one ``send_columns``: the recording holds every frame's value at that
frame's ``frame`` and ``time`` (a pose or archetype also on ``log_time``, which ``rr.log`` stamps each call
with: the wall clock when its frame was logged), and a live viewer sees them up to ``every`` frames late
(poses and archetypes are sent on their own frame instead where a viewer watches: ``at_once``). Rerun
orders data by their time, not by when they arrive, so a clear logged meanwhile (a target gone) still
applies from its own frame on; only where the clear's time is that of a value kept (frames at the same
time) does the order of arrival decide, and those values are sent before it (:meth:`SeriesBuffer.clearing`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Collection
from typing import Any

import numpy as np

from .sinks import Recording

__all__ = ["SeriesBuffer"]


class SeriesBuffer:
    """Scalars of many series, poses and other archetypes of many entities (entity paths) at the current
    frame, sent every ``every`` frames.

    :meth:`at` sets the frame (its ``frame`` sequence number and ``time`` in seconds) that :meth:`add`,
    :meth:`transform` and :meth:`log` file values under; :meth:`flush` sends what is kept (also done by
    :meth:`at` once ``every`` frames are kept, and due before the recording's file changes or closes).

    ``at_once``: the poses and archetypes are sent on their own frame instead (one call per entity and
    frame, as ``rr.log``; the scalars stay in batches), for a recording a viewer watches live: there a pose
    or detection kept back would be drawn on an image up to ``every`` frames newer (the AR overlay trailing
    its marker).
    """

    def __init__(self, recording: Recording, every: int, *, at_once: bool = False) -> None:
        self.recording = recording
        self.every = max(1, int(every))
        self.at_once = at_once
        self._frames: list[int] = []  # the frames kept, in order
        self._seconds: list[float] = []
        self._log_ns: list[int] = []  # the wall clock when each frame was logged (rerun's ``log_time``)
        self._series: dict[str, tuple[list[int], list[float]]] = {}  # entity -> (row of each value, values)
        self._poses: dict[str, tuple[list[int], list[np.ndarray], list[np.ndarray]]] = {}  # -> rows, t, R
        self._rows: dict[str, tuple[list[int], list[Any]]] = {}  # entity -> (rows, each row's component arrays)

    def at(self, frame: int, seconds: float) -> None:
        """The frame the next values belong to; the kept frames are sent first when there are ``every``."""
        if len(self._frames) >= self.every:
            self.flush()
        self._frames.append(int(frame))
        self._seconds.append(float(seconds))
        self._log_ns.append(time.time_ns())

    def add(self, entity: str, value: float | None) -> None:
        """One point of the series ``entity`` at the current frame; None and non-finite values are skipped."""
        if value is None or not math.isfinite(value) or not self._frames:
            return
        kept = self._series.get(entity)
        if kept is None:
            kept = self._series[entity] = ([], [])
        kept[0].append(len(self._frames) - 1)
        kept[1].append(float(value))

    def transform(self, entity: str, translation: np.ndarray, rotation: np.ndarray) -> None:
        """``entity``'s ``Transform3D`` (``translation``, 3x3 ``rotation``) at the current frame."""
        if not self._frames:
            return
        if self.at_once:
            self.recording.transform(entity, translation, rotation)
            return
        rows, translations, rotations = self._poses.setdefault(entity, ([], [], []))
        rows.append(len(self._frames) - 1)
        translations.append(translation)
        rotations.append(rotation)

    def log(self, entity: str, data: Any) -> None:
        """The archetype ``data`` (e.g. ``rr.Points2D``) at ``entity`` on the current frame, as ``rr.log`` logs
        it. An entity whose rows change components is sent before the row that changes them."""
        if self.at_once or not self._frames:
            self.recording.log(entity, data)
            return
        cells = self.recording.component_arrays(data)
        kept = self._rows.get(entity)
        if kept is not None and [d.component for d, _ in kept[1][-1]] != [d.component for d, _ in cells]:
            self.flush([entity])
        rows, rows_cells = self._rows.setdefault(entity, ([], []))
        rows.append(len(self._frames) - 1)
        rows_cells.append(cells)

    def clearing(self, entities: Collection[str], *, recursive: bool = False) -> None:
        """``entities`` (and, ``recursive``, those under them) are cleared at the current frame: their kept
        values are sent first if a kept frame is not before it on a timeline (rerun breaks a tie of times by
        arrival, and the clear was logged after them); otherwise they stay kept, the clear applying from its
        own time on whenever they arrive."""
        frames, seconds = self._frames, self._seconds
        if any(frame >= frames[-1] for frame in frames[:-1]) or any(s >= seconds[-1] for s in seconds[:-1]):
            cleared = set(entities)
            if recursive:
                prefixes = tuple(f"{entity}/" for entity in entities)
                kept = [*self._series, *self._poses, *self._rows]
                cleared.update(entity for entity in kept if entity.startswith(prefixes))
            self.flush(cleared)

    def flush(self, entities: Collection[str] | None = None) -> None:
        """Send the kept values (one call per entity; entities with values at the same frames share their
        time columns): of every entity, and start afresh; or, given ``entities``, of those only."""
        frames, seconds, log_ns = self._frames, self._seconds, self._log_ns
        if entities is None:
            series, poses, rows_of = self._series, self._poses, self._rows
            self._frames, self._seconds, self._log_ns = [], [], []
            self._series, self._poses, self._rows = {}, {}, {}
        else:
            series = {entity: self._series.pop(entity) for entity in entities if entity in self._series}
            poses = {entity: self._poses.pop(entity) for entity in entities if entity in self._poses}
            rows_of = {entity: self._rows.pop(entity) for entity in entities if entity in self._rows}
        indexes: dict[tuple[tuple[int, ...], bool], Any] = {}  # the rows of an entity (+ log_time) -> time columns

        def times(rows: list[int], logged: bool) -> Any:
            key = (tuple(rows), logged)
            if key not in indexes:
                indexes[key] = self.recording.time_columns(
                    frames=[frames[row] for row in rows],
                    seconds=[seconds[row] for row in rows],
                    log_ns=[log_ns[row] for row in rows] if logged else None,
                )
            return indexes[key]

        for entity, (rows, values) in series.items():
            self.recording.scalar_columns(entity, values, times(rows, False))
        for entity, (rows, translations, rotations) in poses.items():
            self.recording.transform_columns(entity, translations, rotations, times(rows, True))
        for entity, (rows, cells) in rows_of.items():
            self.recording.rows_columns(entity, cells, times(rows, True))
