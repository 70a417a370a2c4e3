"""Which predefined ArUco dictionary the markers in a few images belong to (:func:`probe_dictionaries`).

A run that finds no marker of its configured dictionary in its first frames asks this once, so that it
can say which dictionary the markers are of, and the flag to use (:mod:`ar_anchor.run.hints`).

OpenCV's dictionaries come in families whose smaller members are prefixes of the largest one
(``DICT_4X4_50`` holds the first 50 codes of ``DICT_4X4_100``, ``_250`` and ``_1000``): one detection
with the largest member of each family finds the markers of all of them, and the answer names the
smallest member that holds every id found. Families are told apart by how many markers each finds;
the probe reads bits strictly (no erroneous border bits, no error correction) so that texture or the
markers of another family seldom decode by chance.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..config import DetectorConfig, dictionary_id, dictionary_names

__all__ = ["DictionaryGuess", "dictionary_families", "probe_dictionaries"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DictionaryGuess:
    """The dictionary that explains most of the markers found: its canonical name, the distinct ids
    found (sorted) and how many markers it found over all the images probed."""

    dictionary: str
    ids: tuple[int, ...]
    markers: int


@functools.cache
def dictionary_families() -> tuple[tuple[str, ...], ...]:
    """OpenCV's predefined dictionaries grouped into families, each from its smallest member to its
    largest, every member a prefix of the next (``DICT_4X4_50`` ... ``DICT_4X4_1000``)."""
    codes = {name: cv2.aruco.getPredefinedDictionary(dictionary_id(name)).bytesList for name in dictionary_names()}

    def prefix(small: str, big: str) -> bool:
        a, b = codes[small], codes[big]
        return a.shape[0] < b.shape[0] and a.shape[1:] == b.shape[1:] and bool(np.array_equal(b[: a.shape[0]], a))

    families: list[tuple[str, ...]] = []
    for name in sorted(codes, key=lambda n: (-codes[n].shape[0], n)):  # largest first: the roots
        if any(prefix(name, family[-1]) for family in families):
            continue
        members = [other for other in codes if other == name or prefix(other, name)]
        families.append(tuple(sorted(members, key=lambda n: codes[n].shape[0])))
    return tuple(sorted(families, key=lambda family: family[-1]))


def _strict_parameters(config: DetectorConfig) -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # ids only: corners need no refining
    params.minMarkerPerimeterRate = config.min_perimeter_rate
    params.perspectiveRemoveIgnoredMarginPerCell = config.cell_margin
    params.perspectiveRemovePixelPerCell = 6
    params.maxErroneousBitsInBorderRate = 0.0
    params.errorCorrectionRate = 0.0
    return params


def probe_dictionaries(
    images: list[np.ndarray], config: DetectorConfig, *, budget_s: float | None = None
) -> DictionaryGuess | None:
    """The dictionary whose markers ``images`` (BGR or grey) hold, other than ``config.dictionary``;
    None when no family finds a marker, or when the best answer is the configured dictionary itself.

    The images are probed in turn until one holds markers of some family (the rest are not looked at):
    in it, the family that finds the most markers wins (ties: the first in name order), and its
    smallest member that holds every id found is named. Costs one detection per family (ten) and image
    probed: about 0.1-0.5 s per image of a textured 640x480 scene, most of it in the 1000-marker
    dictionaries, which match every candidate square against all their codes; a 1080p image full of
    square candidates that decode to nothing, 6 s. ``budget_s``: no detection starts once that much time
    has gone (the answer is then the best found so far; said at INFO), so the probe ends within about
    ``budget_s`` plus one detection.
    """
    params = _strict_parameters(config)
    detectors = [
        (family, cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary_id(family[-1])), params))
        for family in dictionary_families()
    ]
    best: tuple[int, tuple[str, ...], list[int]] | None = None
    deadline = None if budget_s is None else time.monotonic() + budget_s
    for number, image in enumerate(images):
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        for done, (family, detector) in enumerate(detectors):
            if deadline is not None and time.monotonic() > deadline:
                log.info(
                    "dictionary probe stopped after %g s (image %d of %d, %d of %d families looked at)",
                    budget_s,
                    number + 1,
                    len(images),
                    done,
                    len(detectors),
                )
                return _named(best, config)
            _corners, ids, _rejected = detector.detectMarkers(grey)
            found = [] if ids is None else [int(i) for i in np.asarray(ids).reshape(-1)]
            if found and (best is None or len(found) > best[0]):
                best = (len(found), family, found)
        if best is not None:
            break
    return _named(best, config)


def _named(best: tuple[int, tuple[str, ...], list[int]] | None, config: DetectorConfig) -> DictionaryGuess | None:
    """The guess for the family that found the most markers (its smallest member holding every id found)."""
    if best is None:
        return None
    count, family, found = best
    largest = max(found)
    name = next(n for n in family if cv2.aruco.getPredefinedDictionary(dictionary_id(n)).bytesList.shape[0] > largest)
    if name.upper() == config.dictionary.upper():
        return None
    return DictionaryGuess(name, tuple(sorted(set(found))), count)
