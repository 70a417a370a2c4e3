"""Hints for a user's likely first mistakes, found while a run goes on (:class:`RunHints`).

Two mistakes make a run succeed silently with nothing useful in it:

- **the wrong dictionary**: no marker of the configured dictionary in the first frames (30 frames or
  one second of the stream, or the whole run when it is shorter). Then, once, a few of those frames
  are probed for the other predefined dictionaries (:func:`~ar_anchor.track.dictionary_probe.probe_dictionaries`)
  and one warning names the one found and the flag to use. A run that finds a marker in its first
  frames stops looking at once: it keeps no frame and probes nothing. The probe takes at most
  :data:`PROBE_BUDGET_S` (plus one detection), and always runs while the run's interrupt guard is on (a
  run shorter than the window probes at its end, before its outputs close: :meth:`RunHints.end_of_stream`),
  so a Ctrl-C or SIGTERM meanwhile ends the run as interrupted, ``summary.json`` saying so.
- **a marker length in millimetres**: poses hundreds of metres away. The first pose beyond
  :data:`FAR_M` is named once, with the marker length it was solved with.

The hint also goes into ``summary.json`` (``dictionary_hint``), for the end-of-run summary line,
unless a marker of the configured dictionary turned up after all.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import cv2
import numpy as np

from ..config import TrackerConfig
from ..sources.base import Frame
from ..track.dictionary_probe import DictionaryGuess, probe_dictionaries
from ..track.results import FrameResult

__all__ = ["FAR_M", "PROBE_BUDGET_S", "WINDOW_FRAMES", "WINDOW_S", "RunHints", "dictionary_hint_text"]

log = logging.getLogger(__name__)

WINDOW_FRAMES = 30  # the first frames in which no marker of the configured dictionary means a hint ...
WINDOW_S = 1.0  # ... or the first second of the stream, whichever ends first
PROBE_BUDGET_S = 5.0  # the dictionary probe starts no detection after this (a 1080p frame of squares: 6 s each)
FAR_M = 100.0  # a pose farther than this from the camera is named once: a length in millimetres?
_SHOWN_IDS = 8


def dictionary_hint_text(guess: DictionaryGuess) -> str:
    """``they hold DICT_X markers (ids 1, 3, ...): use --dictionary DICT_X``."""
    ids = ", ".join(str(i) for i in guess.ids[:_SHOWN_IDS]) + (", ..." if len(guess.ids) > _SHOWN_IDS else "")
    return f"they hold {guess.dictionary} markers (ids {ids}): use --dictionary {guess.dictionary}"


class RunHints:
    """Watches a run's frames for the mistakes in the module doc: call :meth:`after_frame` with each
    tracked frame and :meth:`finish` when the run ends (its dict goes into ``summary.json``)."""

    def __init__(self, config: TrackerConfig) -> None:
        self._config = config
        self._watching = True  # no marker of the configured dictionary yet, within the window
        self._frames = 0
        self._first_ns: int | None = None
        self._kept: dict[str, np.ndarray] = {}  # first, middle and latest image of the window
        self._far_named = False
        self.dictionary_hint: str | None = None  # for the summary; None again if markers turn up later

    def after_frame(self, frame: Frame, result: FrameResult) -> None:
        """Look at one tracked frame (cheap: once a marker was found, two comparisons)."""
        if self._watching:
            self._watch(frame, result)
        elif self.dictionary_hint is not None and len(result.detections):
            self.dictionary_hint = None  # the configured dictionary's markers turned up after all
        if not self._far_named and result.targets:
            self._name_far_pose(result)

    def end_of_stream(self) -> None:
        """The stream ended by itself: probe now if it was shorter than the window. Seconds at most
        (:data:`PROBE_BUDGET_S`): call it while the run's interrupt guard is on, not after (a signal
        meanwhile is the run's interrupt, and ``summary.json`` says so)."""
        if self._watching and self._frames:
            self._probe()

    def finish(self, *, probe: bool = True) -> dict[str, Any]:
        """The run ended: probe now if it was shorter than the window and not probed yet (``probe``: it
        completed; an interrupted or failed run ends at once; a run calls :meth:`end_of_stream` first, inside
        its guard); what goes into ``summary.json``."""
        if probe:
            self.end_of_stream()
        self._kept.clear()
        return {} if self.dictionary_hint is None else {"dictionary_hint": self.dictionary_hint}

    def _watch(self, frame: Frame, result: FrameResult) -> None:
        if len(result.detections):
            self._watching = False
            self._kept.clear()
            return
        self._frames += 1
        if self._first_ns is None:
            self._first_ns = frame.timestamp_ns
            self._kept["first"] = frame.image
        if self._frames == WINDOW_FRAMES // 2:
            self._kept["middle"] = frame.image
        self._kept["latest"] = frame.image
        if self._frames >= WINDOW_FRAMES or frame.timestamp_ns - self._first_ns >= WINDOW_S * 1e9:
            self._probe()

    def _probe(self) -> None:
        """Probe the kept frames (latest first: the first frames of a video are often empty) once."""
        self._watching = False
        images = [self._kept[name] for name in ("latest", "middle", "first") if name in self._kept]
        self._kept.clear()
        configured = self._config.detector.dictionary
        log.info("no %s marker in the first %d frames: probing the other dictionaries", configured, self._frames)
        try:
            guess = probe_dictionaries(images, self._config.detector, budget_s=PROBE_BUDGET_S)
        except cv2.error as err:  # a hint that cannot be had is no reason to fail the run
            log.debug("dictionary probe failed: %s", err)
            return
        if guess is None:
            log.info("no %s marker in the first %d frames, nor one of another dictionary", configured, self._frames)
            return
        self.dictionary_hint = dictionary_hint_text(guess)
        log.warning("no %s marker in the first %d frames; %s", configured, self._frames, self.dictionary_hint)

    def _name_far_pose(self, result: FrameResult) -> None:
        for target in result.targets.values():
            distance = float(np.linalg.norm(target.pose.tvec))
            if math.isfinite(distance) and distance > FAR_M:
                self._far_named = True
                log.warning(
                    "%s is %.0f m from the camera (frame %d): is its size right? it is taken as %g m "
                    "(--marker-length, [markers] length_m or its board's marker_length_m); did you give millimetres?",
                    target.target,
                    distance,
                    result.index,
                    target.length_m,
                )
                return
