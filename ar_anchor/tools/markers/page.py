"""The page model of a marker sheet: what is printed where, in mm (y down from the page's top edge).

A :class:`Page` holds :class:`MarkerItem` (one ArUco marker, drawn from its dictionary's bit
matrix), :class:`Fill` (black rectangles filled together as one shape: chessboard, cut marks,
ruler) and :class:`Text` items. :func:`marker_rects` turns a marker's modules into exact
rectangles; :func:`text_width` gives Helvetica's width of a line (the layout and the PNG renderer
agree on it). Nothing here knows about sheets or file formats.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...config import dictionary_id

__all__ = [
    "MM_PER_INCH",
    "PAPERS",
    "Fill",
    "MarkerItem",
    "Page",
    "Rect",
    "Text",
    "marker_bits",
    "marker_rects",
    "mm_text",
    "text_width",
]

PAPERS: dict[str, tuple[float, float]] = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}  # portrait, mm
MM_PER_INCH = 25.4


Rect = tuple[float, float, float, float]  # x, y, width, height in mm; y down from the page's top edge


@dataclass(frozen=True)
class MarkerItem:
    """One ArUco marker: its black square's top-left corner at (x, y), side ``side`` mm.

    ``bits``: the module grid with its one-module black border, rows top to bottom, True = black.
    """

    marker_id: int
    x: float
    y: float
    side: float
    bits: tuple[tuple[bool, ...], ...]
    dictionary: str = ""

    @property
    def modules(self) -> int:
        return len(self.bits)

    def rects(self) -> list[Rect]:
        return marker_rects(self.bits, self.x, self.y, self.side)


@dataclass(frozen=True)
class Fill:
    """Black rectangles filled together as one shape (``tag`` says what they are)."""

    rects: tuple[Rect, ...]
    tag: str = ""


@dataclass(frozen=True)
class Text:
    """One line of text; ``y`` is its baseline, ``size`` the font size (em) in mm."""

    x: float
    y: float
    text: str
    size: float
    align: str = "left"  # left | center | right


@dataclass
class Page:
    """One page, ``width`` x ``height`` mm (landscape when wider than high), and what is printed on it."""

    width: float
    height: float
    items: list[MarkerItem | Fill | Text] = field(default_factory=list)

    @property
    def landscape(self) -> bool:
        return self.width > self.height

    @property
    def markers(self) -> list[MarkerItem]:
        return [item for item in self.items if isinstance(item, MarkerItem)]

    def fills(self, tag: str) -> list[Fill]:
        return [item for item in self.items if isinstance(item, Fill) and item.tag == tag]


def marker_bits(dictionary: str, marker_id: int) -> tuple[tuple[bool, ...], ...]:
    """The module grid of one marker, border included (``markerSize + 2`` square), True = black."""
    cv_dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(dictionary))
    modules = int(cv_dictionary.markerSize) + 2
    image = cv2.aruco.generateImageMarker(cv_dictionary, int(marker_id), modules, borderBits=1)
    return tuple(tuple(bool(v == 0) for v in row) for row in np.asarray(image))


def marker_rects(bits: Sequence[Sequence[bool]], x: float, y: float, side: float) -> list[Rect]:
    """The black modules of ``bits`` as rectangles: horizontal runs, merged downwards while the same run
    continues. Module edges are at ``x + k * side / n`` (exact, never accumulated)."""
    n = len(bits)
    edge = [k * side / n for k in range(n + 1)]
    edge[n] = side
    open_runs: dict[tuple[int, int], int] = {}  # (c0, c1) -> first row
    rects: list[Rect] = []

    def close(c0: int, c1: int, r0: int, r1: int) -> None:
        rects.append((x + edge[c0], y + edge[r0], edge[c1] - edge[c0], edge[r1] - edge[r0]))

    for r in range(n + 1):
        runs: set[tuple[int, int]] = set()
        if r < n:
            c = 0
            while c < n:
                if bits[r][c]:
                    c0 = c
                    while c < n and bits[r][c]:
                        c += 1
                    runs.add((c0, c))
                else:
                    c += 1
        for run in sorted(set(open_runs) - runs):
            close(run[0], run[1], open_runs.pop(run), r)
        for run in sorted(runs - set(open_runs)):
            open_runs[run] = r
    return rects


def mm_text(value: float) -> str:
    """A length in mm as written in names, captions and messages: ``50``, ``22.5``."""
    return f"{value:g}"


def text_width(text: str, size: float) -> float:
    """Width in mm of ``text`` in Helvetica at font size ``size`` mm (fpdf2's metrics; else an estimate)."""
    try:
        from fpdf.fonts import CORE_FONTS_CHARWIDTHS

        widths = CORE_FONTS_CHARWIDTHS["helvetica"]
        return sum(widths.get(ch, 600) for ch in text) * size / 1000.0
    except (ImportError, KeyError):  # pragma: no cover - fpdf2 missing
        return 0.6 * size * len(text)
