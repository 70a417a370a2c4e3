"""``ar-anchor markers``: printable marker sheets at exact physical size, with the matching tracker config.

Three kinds of sheet (:class:`MarkerSheet`):

* ``single``: lone markers (``--ids`` at ``--size-mm``), as many per page as fit, each with a white quiet
  zone of at least one marker cell, a caption (dictionary, id, side) and cut marks; more pages as needed.
* ``grid``: one ``cv2.aruco.GridBoard`` (ids row-major from ``--first-id``), placed from the board's own
  ``getObjPoints()``.
* ``charuco``: one ``cv2.aruco.CharucoBoard`` (``setLegacyPattern(--legacy)``), chessboard and markers
  placed from the board's ``getObjPoints()`` (black squares are the squares without a marker).

Geometry is exact: every marker is drawn as vector rectangles computed from the dictionary's bit
matrix (``generateImageMarker`` with one border bit, one pixel per module), module edges at
``x + k * side / (markerSize + 2)`` (never accumulated), all black rectangles of a marker filled as one
path (no hairline seams between modules). Nothing is ever scaled to fit: a sheet that does not fit the
paper is an :class:`~ar_anchor.errors.InputError` naming the options and the sizes. Every PDF/SVG page
carries a 100 mm scale-check bar with mm/cm ticks and a "print at 100 %" line; a board that does not
fit in portrait is laid out on a landscape page.

Formats: ``pdf`` (fpdf2, one multi-page file, ``/PrintScaling /None`` viewer preference, fixed creation
date so the same command writes the same bytes), ``svg`` (plain XML, user units = mm, one file per
page) and ``png`` (numpy/cv2 at ``--dpi``, one file per page, the DPI in the file name and in a pHYs
chunk; marker module edges on whole pixels, see :func:`rasterise_page`).

Files, written to ``--out`` (see :meth:`MarkerSheet.stem`)::

    <stem>.pdf | <stem>.svg | <stem>.png        one page
    <stem>_p1.svg, <stem>_p2.svg, ...           svg/png with several pages
    <stem>.toml                                 tracker config snippet for exactly what was printed

    single:   DICT_4X4_50_ids0-3+9_50mm
    grid:     grid_2x2_DICT_4X4_50_ids10-13_40mm_gap20mm
    charuco:  charuco_5x7_DICT_6X6_250_ids0-16_sq40mm_m20mm[_legacy]
    suffixes: _letter (letter paper), _<dpi>dpi (png); a board's leading kind is its --name (default
              "grid" / "charuco"); ids of lone markers are ranges joined by "+", or
              <first>-<last>_<count>markers when that would be longer than 40 characters
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from xml.sax.saxutils import escape

import cv2
import numpy as np

from .. import __version__
from ..config import dictionary_id, dictionary_names, dictionary_size
from ..errors import ConfigError, InputError, OutputError
from ..run.outputs import prepare_out_dir

__all__ = [
    "FORMATS",
    "PAPERS",
    "Fill",
    "MarkerItem",
    "MarkerSheet",
    "Page",
    "Text",
    "marker_bits",
    "marker_rects",
    "parse_ids",
    "rasterise_page",
    "render_pdf",
    "render_png",
    "render_svg",
    "run_markers",
    "sheet_from_args",
    "write_sheet",
]

log = logging.getLogger(__name__)

PAPERS: dict[str, tuple[float, float]] = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}  # portrait, mm
FORMATS = ("pdf", "svg", "png")
MM_PER_INCH = 25.4
MAX_BOARD_CELLS = 100  # the tracker config accepts at most 100 columns / rows
MIN_MARKER_MM = 1.0  # a marker's black square; smaller ones do not print (nor get detected)
MAX_DPI = 2400  # beyond any printer; an A4 page is then 20k x 28k px (560 MB), and 10x more would exhaust memory

# ---------------------------------------------------------------------------- page layout (mm)

MARGIN = 8.0  # page edge to anything printed
MARK_GAP = 1.0  # cut marks start this far outside the cut box ...
MARK_LEN = 3.0  # ... and are this long
MARK_WIDTH = 0.15
MARK_SPACE = MARK_GAP + MARK_LEN + 0.5  # room kept free for cut marks around every cut box
GUTTER = 2 * MARK_SPACE  # between two cut boxes
MIN_QUIET_MM = 3.0  # quiet zone around a marker or board: one marker cell, at least this
TITLE_SIZE = 3.5  # font sizes (em) in mm
NOTE_SIZE = 2.6
CAPTION_SIZE = 2.8
CAPTION_LINE = 3.6
CAPTION_HEIGHT = 1.2 + 2 * CAPTION_LINE  # two caption lines below a quiet zone
HEADER_BOTTOM = MARGIN + 12.5  # three header lines
FOOTER_HEIGHT = 14.0  # the scale-check ruler
RULER_MM = 100.0
RULER_BAR = 1.2  # thickness of the 100 mm bar
TICK_WIDTH = 0.15
PRINT_NOTE = "Print at 100 % / actual size, no scaling (turn off 'fit to page')."
RULER_NOTE = "this bar must measure 100 mm"

# PDF creation date: fixed, so a command reproduces its sheet byte for byte (SOURCE_DATE_EPOCH wins)
_FIXED_DATE = datetime(2000, 1, 1, tzinfo=timezone.utc)


# ---------------------------------------------------------------------------- drawing primitives


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


# ---------------------------------------------------------------------------- ids, names


def parse_ids(text: str, option: str = "--ids") -> tuple[int, ...]:
    """``"0-3,9"`` -> ``(0, 1, 2, 3, 9)``: comma-separated ids and inclusive ranges, sorted; duplicates,
    empty items and reversed ranges are errors."""
    if text is None or not str(text).strip():
        raise InputError(f"{option}: no ids given (e.g. 0-3 or 0,5,7 or 0-3,9)")
    ids: list[int] = []
    for item in str(text).split(","):
        item = item.strip()
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", item)
        if not match:
            raise InputError(f"{option}: cannot read {item!r} in {text!r} (expected ids and ranges, e.g. 0-3,9)")
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        if last < first:
            raise InputError(f"{option}: range {item!r} runs backwards")
        if last - first > 100_000:
            raise InputError(f"{option}: range {item!r} is too long")
        ids.extend(range(first, last + 1))
    seen: set[int] = set()
    for marker_id in ids:
        if marker_id in seen:
            raise InputError(f"{option}: id {marker_id} is listed twice in {text!r}")
        seen.add(marker_id)
    return tuple(sorted(ids))


def format_ids(ids: Iterable[int], sep: str = ",") -> str:
    """``(0, 1, 2, 3, 9)`` -> ``"0-3,9"``."""
    ids = sorted(ids)
    parts: list[str] = []
    start = prev = None
    for marker_id in [*ids, None]:
        if start is not None and (marker_id is None or marker_id != prev + 1):
            parts.append(str(start) if start == prev else f"{start}-{prev}")
            start = None
        if marker_id is not None and start is None:
            start = marker_id
        prev = marker_id
    return sep.join(parts)


def _mm(value: float) -> str:
    return f"{value:g}"


def canonical_dictionary(name: str, option: str = "--dictionary") -> str:
    try:
        wanted = dictionary_id(name)
    except ConfigError as err:
        raise InputError(f"{option}: {err}") from None
    return next(n for n in dictionary_names() if dictionary_id(n) == wanted)


# ---------------------------------------------------------------------------- the sheet


@dataclass(frozen=True)
class MarkerSheet:
    """What to print. Build with :meth:`single`, :meth:`grid` or :meth:`charuco` (they validate, with
    messages naming the command-line option at fault). Lengths in mm."""

    kind: str  # single | grid | charuco
    dictionary: str
    ids: tuple[int, ...]
    marker_mm: float
    cols: int = 0
    rows: int = 0
    gap_mm: float = 0.0
    square_mm: float = 0.0
    legacy: bool = False
    name: str = ""
    paper: str = "a4"

    # ------------------------------------------------------------------ constructors

    @classmethod
    def single(cls, dictionary: str, ids: Iterable[int] | str, size_mm: float, *, paper: str = "a4") -> MarkerSheet:
        dictionary = canonical_dictionary(dictionary)
        ids = parse_ids(ids) if isinstance(ids, str) else tuple(sorted(int(i) for i in ids))
        if not ids:
            raise InputError("--ids: no ids given")
        if len(set(ids)) != len(ids):
            raise InputError(f"--ids: ids must be unique, got {list(ids)}")
        _check_length("--size-mm", size_mm, MIN_MARKER_MM)
        _check_ids("--ids", dictionary, ids)
        return cls("single", dictionary, ids, float(size_mm), paper=_check_paper(paper))

    @classmethod
    def grid(
        cls,
        dictionary: str,
        cols: int,
        rows: int,
        size_mm: float,
        gap_mm: float,
        *,
        first_id: int = 0,
        name: str = "grid",
        paper: str = "a4",
    ) -> MarkerSheet:
        dictionary = canonical_dictionary(dictionary)
        _check_count("--cols", cols, 1)
        _check_count("--rows", rows, 1)
        _check_length("--size-mm", size_mm, MIN_MARKER_MM)
        _check_length("--gap-mm", gap_mm)
        ids = _board_ids(dictionary, first_id, cols * rows, f"a {cols}x{rows} grid board")
        module = size_mm / (cv2.aruco.getPredefinedDictionary(dictionary_id(dictionary)).markerSize + 2)
        if cols * rows > 1 and gap_mm < 0.7 * module:
            log.warning(
                "--gap-mm: %g mm is less than 70 %% of a marker cell (%.3g mm); OpenCV advises a wider gap "
                "for stable board detection",
                gap_mm,
                module,
            )
        return cls(
            "grid",
            dictionary,
            ids,
            float(size_mm),
            cols=int(cols),
            rows=int(rows),
            gap_mm=float(gap_mm),
            name=_check_name(name),
            paper=_check_paper(paper),
        )

    @classmethod
    def charuco(
        cls,
        dictionary: str,
        cols: int,
        rows: int,
        square_mm: float,
        marker_mm: float,
        *,
        first_id: int = 0,
        legacy: bool = False,
        name: str = "charuco",
        paper: str = "a4",
    ) -> MarkerSheet:
        dictionary = canonical_dictionary(dictionary)
        _check_count("--cols", cols, 2)
        _check_count("--rows", rows, 2)
        _check_length("--square-mm", square_mm)
        _check_length("--size-mm", marker_mm, MIN_MARKER_MM)
        if marker_mm >= square_mm:
            raise InputError(
                f"--size-mm: the marker ({_mm(marker_mm)} mm) must be smaller than the chessboard square "
                f"(--square-mm {_mm(square_mm)} mm)"
            )
        ids = _board_ids(dictionary, first_id, (cols * rows) // 2, f"a {cols}x{rows} ChArUco board")
        return cls(
            "charuco",
            dictionary,
            ids,
            float(marker_mm),
            cols=int(cols),
            rows=int(rows),
            square_mm=float(square_mm),
            legacy=bool(legacy),
            name=_check_name(name),
            paper=_check_paper(paper),
        )

    # ------------------------------------------------------------------ properties

    @property
    def first_id(self) -> int:
        return self.ids[0]

    @property
    def modules(self) -> int:
        """Modules across one marker, border included."""
        return int(cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary)).markerSize) + 2

    @property
    def module_mm(self) -> float:
        return self.marker_mm / self.modules

    @property
    def board_size_mm(self) -> tuple[float, float]:
        if self.kind == "grid":
            return (
                self.cols * self.marker_mm + (self.cols - 1) * self.gap_mm,
                self.rows * self.marker_mm + (self.rows - 1) * self.gap_mm,
            )
        if self.kind == "charuco":
            return (self.cols * self.square_mm, self.rows * self.square_mm)
        raise ValueError("single markers have no board")

    @property
    def quiet_mm(self) -> float:
        """White margin kept around every marker / the board: one marker cell, at least MIN_QUIET_MM."""
        return max(self.module_mm, MIN_QUIET_MM)

    def cv_board(self) -> cv2.aruco.Board:
        """The OpenCV board, in mm (grid and charuco sheets)."""
        cv_dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary))
        ids = np.array(self.ids, dtype=np.int32)
        if self.kind == "grid":
            return cv2.aruco.GridBoard((self.cols, self.rows), self.marker_mm, self.gap_mm, cv_dictionary, ids)
        if self.kind == "charuco":
            board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm, cv_dictionary, ids)
            board.setLegacyPattern(self.legacy)
            return board
        raise ValueError("single markers have no board")

    def stem(self, fmt: str = "pdf", dpi: int = 300) -> str:
        """File name without extension (see the module docstring)."""
        if self.kind == "single":
            ids = format_ids(self.ids, "+")
            if len(ids) > 40:
                ids = f"{self.ids[0]}-{self.ids[-1]}_{len(self.ids)}markers"
            stem = f"{self.dictionary}_ids{ids}_{_mm(self.marker_mm)}mm"
        else:
            prefix = self.name or self.kind
            ids = f"ids{self.ids[0]}-{self.ids[-1]}"
            stem = f"{prefix}_{self.cols}x{self.rows}_{self.dictionary}_{ids}_"
            if self.kind == "grid":
                stem += f"{_mm(self.marker_mm)}mm_gap{_mm(self.gap_mm)}mm"
            else:
                stem += f"sq{_mm(self.square_mm)}mm_m{_mm(self.marker_mm)}mm" + ("_legacy" if self.legacy else "")
        if self.paper != "a4":
            stem += f"_{self.paper}"
        if fmt == "png":
            stem += f"_{int(dpi)}dpi"
        return stem

    def command(self, fmt: str = "pdf", dpi: int = 300) -> str:
        """The ``ar-anchor markers`` command line that prints this sheet (without --out)."""
        parts = ["ar-anchor markers", f"--dictionary {self.dictionary}"]
        if self.kind == "single":
            parts += [f"--ids {format_ids(self.ids)}", f"--size-mm {_mm(self.marker_mm)}"]
        else:
            parts += [f"--board {self.kind}", f"--cols {self.cols}", f"--rows {self.rows}"]
            if self.kind == "grid":
                parts += [f"--size-mm {_mm(self.marker_mm)}", f"--gap-mm {_mm(self.gap_mm)}"]
            else:
                parts += [f"--square-mm {_mm(self.square_mm)}", f"--size-mm {_mm(self.marker_mm)}"]
                parts += ["--legacy"] if self.legacy else []
            parts += [f"--first-id {self.first_id}"] if self.first_id else []
            parts += [f"--name {self.name}"] if self.name != self.kind else []
        parts += [f"--paper {self.paper}"] if self.paper != "a4" else []
        parts += [f"--format {fmt}"] if fmt != "pdf" else []
        parts += [f"--dpi {dpi}"] if fmt == "png" and dpi != 300 else []
        return " ".join(parts)

    def title(self) -> str:
        if self.kind == "single":
            return f"{self.dictionary}, ids {format_ids(self.ids)}, {_mm(self.marker_mm)} mm markers"
        width, height = self.board_size_mm
        return (
            f"{'grid' if self.kind == 'grid' else 'ChArUco'} board '{self.name}', {self.dictionary}, "
            f"{self.cols}x{self.rows}, {_mm(width)} x {_mm(height)} mm"
        )

    # ------------------------------------------------------------------ tracker config

    def config_toml(self, files: Sequence[str] = (), fmt: str = "pdf", dpi: int = 300) -> str:
        """A tracker config snippet (``ar_anchor.config.load_config`` reads it) for what this sheet prints."""
        lines = [
            f"# ar-anchor tracker config for {', '.join(files) if files else 'a marker sheet'}",
            f"# made by: {self.command(fmt, dpi)}",
            "# Lengths are the printed sizes. Print at 100 % / actual size and check the sheet's 100 mm bar;",
            "# if it is off, measure the black squares and put the measured sizes here.",
            "# Use this file as --config, or copy its tables into your own config.",
            "",
            "[detector]",
            f'dictionary = "{self.dictionary}"',
            "",
        ]
        if self.kind == "single":
            lines += [
                "[markers]",
                f"length_m = {_metres(self.marker_mm)}",
                f"ids = [{', '.join(str(i) for i in self.ids)}]",
            ]
        elif self.kind == "grid":
            lines += [
                "[[boards]]",
                f'name = "{self.name}"',
                'kind = "grid"',
                f"cols = {self.cols}",
                f"rows = {self.rows}",
                f"marker_length_m = {_metres(self.marker_mm)}",
                f"separation_m = {_metres(self.gap_mm)}",
                f"first_id = {self.first_id}",
            ]
        else:
            lines += [
                "[[boards]]",
                f'name = "{self.name}"',
                'kind = "charuco"',
                f"squares_x = {self.cols}",
                f"squares_y = {self.rows}",
                f"square_length_m = {_metres(self.square_mm)}",
                f"marker_length_m = {_metres(self.marker_mm)}",
                f"legacy = {'true' if self.legacy else 'false'}",
                f"first_id = {self.first_id}",
            ]
        return "\n".join(lines) + "\n"

    # ------------------------------------------------------------------ layout

    def pages(self, fmt: str = "pdf", dpi: int = 300) -> list[Page]:
        """The laid-out pages (raises :class:`InputError` when the sheet does not fit the paper); ``fmt`` and
        ``dpi`` only change the header's file name and command."""
        pages = self._single_pages() if self.kind == "single" else [self._board_page()]
        for number, page in enumerate(pages, start=1):
            self._decorate(page, number, len(pages), fmt, dpi)
        return pages

    def _single_pages(self) -> list[Page]:
        width, height = PAPERS[self.paper]
        left, top, right, bottom = _content_area(width, height)
        side, quiet = self.marker_mm, self.quiet_mm
        caption_width = max(_text_width(line, CAPTION_SIZE) for line in self._caption(max(self.ids)))
        cell_w = max(side + 2 * quiet, caption_width + 2.0)
        cell_h = side + 2 * quiet + CAPTION_HEIGHT
        across = int((right - left + GUTTER + 1e-9) // (cell_w + GUTTER))
        down = int((bottom - top + GUTTER + 1e-9) // (cell_h + GUTTER))
        if across < 1 or down < 1:
            raise InputError(
                f"--size-mm: a {_mm(side)} mm marker needs {cell_w:.1f} x {cell_h:.1f} mm with its quiet zone and "
                f"caption, but {self.paper} paper has {right - left:.1f} x {bottom - top:.1f} mm for it "
                "(sheets are printed at 100 %, never scaled down)"
            )
        per_page = across * down
        chunks = [self.ids[i : i + per_page] for i in range(0, len(self.ids), per_page)]
        pages = []
        for chunk in chunks:
            page = Page(width, height)
            used = min(across, len(chunk))
            x0 = (left + right) / 2 - (used * cell_w + (used - 1) * GUTTER) / 2
            for index, marker_id in enumerate(chunk):
                row, col = divmod(index, across)
                bx, by = x0 + col * (cell_w + GUTTER), top + row * (cell_h + GUTTER)
                mx, my = bx + (cell_w - side) / 2, by + quiet
                page.items.append(
                    MarkerItem(marker_id, mx, my, side, marker_bits(self.dictionary, marker_id), self.dictionary)
                )
                for line_no, line in enumerate(self._caption(marker_id)):
                    baseline = my + side + quiet + 1.2 + CAPTION_LINE * (line_no + 0.8)
                    page.items.append(Text(bx + cell_w / 2, baseline, line, CAPTION_SIZE, "center"))
                page.items.append(Fill(tuple(_cut_marks(bx, by, cell_w, cell_h)), "cut-marks"))
            pages.append(page)
        return pages

    def _caption(self, marker_id: int | None = None) -> list[str]:
        if self.kind == "single":
            return [self.dictionary, f"id {marker_id}, {_mm(self.marker_mm)} mm"]
        width, height = self.board_size_mm
        ids = f"ids {self.ids[0]}-{self.ids[-1]}"
        if self.kind == "grid":
            return [
                f"grid board '{self.name}': {self.dictionary}, {self.cols}x{self.rows} markers, {ids}",
                f"marker {_mm(self.marker_mm)} mm, gap {_mm(self.gap_mm)} mm, board {_mm(width)} x {_mm(height)} mm",
            ]
        return [
            f"ChArUco board '{self.name}': {self.dictionary}, {self.cols}x{self.rows} squares, {ids}"
            + (", legacy pattern" if self.legacy else ""),
            f"square {_mm(self.square_mm)} mm, marker {_mm(self.marker_mm)} mm, board {_mm(width)} x {_mm(height)} mm",
        ]

    def _board_page(self) -> Page:
        board_w, board_h = self.board_size_mm
        quiet = self.quiet_mm
        caption = self._caption()
        box_w = max(board_w + 2 * quiet, max(_text_width(line, CAPTION_SIZE) for line in caption) + 2.0)
        box_h = board_h + 2 * quiet + CAPTION_HEIGHT
        portrait = PAPERS[self.paper]
        for width, height in (portrait, portrait[::-1]):
            left, top, right, bottom = _content_area(width, height)
            if box_w <= right - left + 1e-9 and box_h <= bottom - top + 1e-9:
                break
        else:
            left, top, right, bottom = _content_area(*portrait)
            options = "--cols/--rows/" + ("--size-mm/--gap-mm" if self.kind == "grid" else "--square-mm")
            raise InputError(
                f"{options}: the {self.cols}x{self.rows} {self.kind} board is {_mm(board_w)} x {_mm(board_h)} mm "
                f"({box_w:.1f} x {box_h:.1f} mm with its quiet zone and caption), but {self.paper} paper has "
                f"{right - left:.1f} x {bottom - top:.1f} mm for it (portrait or landscape); sheets are printed "
                "at 100 %, never scaled down"
            )
        page = Page(width, height)
        bx = (left + right) / 2 - box_w / 2
        by = (top + bottom) / 2 - box_h / 2
        ox, oy = bx + (box_w - board_w) / 2, by + quiet  # the board's top-left corner
        board = self.cv_board()
        corners = np.asarray(board.getObjPoints(), dtype=np.float64).reshape(-1, 4, 3)
        board_ids = [int(i) for i in np.asarray(board.getIds()).ravel()]
        if self.kind == "charuco":
            centres = corners[:, :, :2].mean(axis=1)
            white = {(int(cx // self.square_mm), int(cy // self.square_mm)) for cx, cy in centres}
            black = tuple(
                (ox + col * self.square_mm, oy + row * self.square_mm, self.square_mm, self.square_mm)
                for row in range(self.rows)
                for col in range(self.cols)
                if (col, row) not in white
            )
            page.items.append(Fill(black, "chessboard"))
        for marker_id, corner in zip(board_ids, corners):
            x, y = corner[0, 0], corner[0, 1]
            side = corner[1, 0] - corner[0, 0]
            page.items.append(
                MarkerItem(marker_id, ox + x, oy + y, side, marker_bits(self.dictionary, marker_id), self.dictionary)
            )
        for line_no, line in enumerate(caption):
            baseline = oy + board_h + quiet + 1.2 + CAPTION_LINE * (line_no + 0.8)
            page.items.append(Text(bx + box_w / 2, baseline, line, CAPTION_SIZE, "center"))
        page.items.append(Fill(tuple(_cut_marks(bx, by, box_w, box_h)), "cut-marks"))
        return page

    def board_origin_mm(self) -> tuple[float, float]:
        """Where the board's top-left corner (OpenCV's board frame origin) lies on its page."""
        page = self.pages()[0]
        marker = page.markers[0]
        corner = np.asarray(self.cv_board().getObjPoints()[0], dtype=np.float64).reshape(4, 3)[0]
        return (marker.x - corner[0], marker.y - corner[1])

    def _decorate(self, page: Page, number: int, count: int, fmt: str, dpi: int) -> None:
        """Header (title, print note, config file) and the 100 mm scale-check ruler."""
        width, height = page.width, page.height
        right = width - MARGIN
        page_text = f"page {number}/{count}"
        title = f"ar-anchor markers: {self.title()}"
        room = right - MARGIN - _text_width(page_text, NOTE_SIZE) - 4.0
        page.items += [
            Text(MARGIN, MARGIN + 3.0, title, _fit(title, TITLE_SIZE, room)),
            Text(right, MARGIN + 3.0, page_text, NOTE_SIZE, "right"),
        ]
        note = f"{PRINT_NOTE} The bar at the bottom must measure {RULER_MM:g} mm."
        config = f"Tracker config: {self.stem(fmt, dpi)}.toml (made by: {self.command(fmt, dpi)})"
        for line_no, line in enumerate((note, config)):
            page.items.append(Text(MARGIN, MARGIN + 7.3 + 3.6 * line_no, line, _fit(line, NOTE_SIZE, right - MARGIN)))
        page.items += _ruler(width, height - MARGIN - FOOTER_HEIGHT)


def _metres(mm: float) -> str:
    return repr(float(mm) / 1000.0)


def _check_length(option: str, value: float | None, minimum: float = 0.0) -> None:
    if value is None or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise InputError(f"{option}: must be a length in mm > 0, got {value!r}")
    if value < minimum:
        raise InputError(f"{option}: must be at least {minimum:g} mm (nothing smaller prints), got {value!r}")


def _check_count(option: str, value: int | None, minimum: int) -> None:
    if value is None or not isinstance(value, int) or not minimum <= value <= MAX_BOARD_CELLS:
        raise InputError(f"{option}: must be an integer in [{minimum}, {MAX_BOARD_CELLS}], got {value!r}")


def _check_paper(paper: str) -> str:
    if paper not in PAPERS:
        raise InputError(f"--paper: must be one of {', '.join(PAPERS)}, got {paper!r}")
    return paper


def _check_name(name: str) -> str:
    if not name or not name.replace("_", "").replace("-", "").isalnum() or not name.isascii():
        raise InputError(f"--name: letters, digits, '-' and '_' only, got {name!r}")
    return name


def _check_ids(option: str, dictionary: str, ids: Sequence[int]) -> None:
    size = dictionary_size(dictionary)
    bad = [i for i in ids if not 0 <= i < size]
    if bad:
        shown = ", ".join(map(str, bad[:5])) + (", ..." if len(bad) > 5 else "")
        raise InputError(f"{option}: ids {shown} are outside {dictionary} (ids 0..{size - 1})")


def _board_ids(dictionary: str, first_id: int, count: int, what: str) -> tuple[int, ...]:
    size = dictionary_size(dictionary)
    if not isinstance(first_id, int) or first_id < 0:
        raise InputError(f"--first-id: must be an integer >= 0, got {first_id!r}")
    if first_id + count > size:
        raise InputError(
            f"--first-id: {what} needs {count} ids, {first_id}..{first_id + count - 1}, "
            f"but {dictionary} has ids 0..{size - 1}"
        )
    return tuple(range(first_id, first_id + count))


def _content_area(width: float, height: float) -> tuple[float, float, float, float]:
    """left, top, right, bottom of the area for cut boxes (cut marks fit around it)."""
    return (
        MARGIN + MARK_SPACE,
        HEADER_BOTTOM + MARK_SPACE,
        width - MARGIN - MARK_SPACE,
        height - MARGIN - FOOTER_HEIGHT - MARK_SPACE,
    )


def _cut_marks(x: float, y: float, w: float, h: float) -> list[Rect]:
    """Crop marks: the cut box's edges continued outside each corner, MARK_GAP away from it."""
    t, near, far = MARK_WIDTH, MARK_GAP, MARK_GAP + MARK_LEN
    rects = []
    for cx, sx in ((x, -1), (x + w, 1)):
        for cy, sy in ((y, -1), (y + h, 1)):
            hx = cx + near if sx > 0 else cx - far
            rects.append((hx, cy - t / 2, MARK_LEN, t))  # horizontal, along the top/bottom edge
            vy = cy + near if sy > 0 else cy - far
            rects.append((cx - t / 2, vy, t, MARK_LEN))  # vertical, along the left/right edge
    return rects


def _ruler(width: float, top: float) -> list[MarkerItem | Fill | Text]:
    """The scale check: a RULER_MM bar (its ends are exact), mm/5 mm/cm ticks below it, cm labels."""
    x0 = (width - RULER_MM) / 2
    bar_y = top + 5.0
    ticks = []
    for k in range(int(RULER_MM) + 1):
        length = 3.2 if k % 10 == 0 else 2.0 if k % 5 == 0 else 1.2
        tx = min(max(x0 + k - TICK_WIDTH / 2, x0), x0 + RULER_MM - TICK_WIDTH)
        ticks.append((tx, bar_y + RULER_BAR, TICK_WIDTH, length))
    items: list[MarkerItem | Fill | Text] = [
        Text(width / 2, top + 3.2, f"{RULER_NOTE} - {PRINT_NOTE}", NOTE_SIZE, "center"),
        Fill(((x0, bar_y, RULER_MM, RULER_BAR),), "ruler-bar"),
        Fill(tuple(ticks), "ruler-ticks"),
    ]
    for cm in range(int(RULER_MM) // 10 + 1):
        label = f"{cm} cm" if cm in (0, int(RULER_MM) // 10) else str(cm)
        items.append(Text(x0 + 10 * cm, bar_y + RULER_BAR + 3.2 + 2.6, label, 2.4, "center"))
    return items


def _text_width(text: str, size: float) -> float:
    """Width in mm of ``text`` in Helvetica at font size ``size`` mm (fpdf2's metrics; else an estimate)."""
    try:
        from fpdf.fonts import CORE_FONTS_CHARWIDTHS

        widths = CORE_FONTS_CHARWIDTHS["helvetica"]
        return sum(widths.get(ch, 600) for ch in text) * size / 1000.0
    except (ImportError, KeyError):  # pragma: no cover - fpdf2 missing
        return 0.6 * size * len(text)


def _fit(text: str, size: float, room: float) -> float:
    """The font size, shrunk if needed so the line fits ``room`` mm (text only; never marker geometry)."""
    width = _text_width(text, size)
    return size if width <= room else size * room / width


# ---------------------------------------------------------------------------- PDF


def _creation_date() -> datetime:
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "")
    if epoch.isdigit():
        return datetime.fromtimestamp(int(epoch), tz=timezone.utc)
    return _FIXED_DATE


def render_pdf(sheet: MarkerSheet) -> bytes:
    """The sheet as one PDF (all pages), vector only: markers, chessboard, ticks and marks are filled
    paths, text is Helvetica."""
    pages = sheet.pages()
    try:
        from fpdf import FPDF, ViewerPreferences
        from fpdf.enums import PathPaintRule
    except ImportError:
        raise OutputError("--format pdf: needs the fpdf2 package (pip install 'fpdf2>=2.7')") from None

    pdf = FPDF(unit="mm", format=PAPERS[sheet.paper])
    pdf.set_auto_page_break(False)
    pdf.set_margins(0, 0, 0)
    pdf.set_creation_date(_creation_date())
    pdf.set_title(f"ar-anchor markers: {sheet.title()}")
    pdf.set_subject(f"{PRINT_NOTE} {sheet.command()}")
    pdf.set_creator(f"ar-anchor {__version__}")
    pdf.viewer_preferences = ViewerPreferences(print_scaling="None")
    pdf.set_text_color(0)

    def fill(rects: Iterable[Rect]) -> None:
        with pdf.new_path(paint_rule=PathPaintRule.FILL_NONZERO) as path:
            path.style.fill_color = "#000000"
            for x, y, w, h in rects:
                path.move_to(x, y)
                path.line_to(x + w, y)
                path.line_to(x + w, y + h)
                path.line_to(x, y + h)
                path.close()

    for page in pages:
        pdf.add_page(orientation="L" if page.landscape else "P")
        for item in page.items:
            if isinstance(item, MarkerItem):
                fill(item.rects())
            elif isinstance(item, Fill):
                fill(item.rects)
            else:
                pdf.set_font("helvetica", size=item.size / MM_PER_INCH * 72.0)
                width = pdf.get_string_width(item.text)
                x = item.x - {"left": 0.0, "center": width / 2, "right": width}[item.align]
                pdf.text(x, item.y, item.text)
    return bytes(pdf.output())


# ---------------------------------------------------------------------------- SVG


def _num(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _path_data(rects: Iterable[Rect]) -> str:
    return " ".join(f"M{_num(x)} {_num(y)}h{_num(w)}v{_num(h)}h{_num(-w)}z" for x, y, w, h in rects)


def render_svg(sheet: MarkerSheet) -> list[str]:
    """One SVG document per page; user units are mm (``viewBox`` = the page in mm)."""
    documents = []
    pages = sheet.pages("svg")
    for number, page in enumerate(pages, start=1):
        w, h = _num(page.width), _num(page.height)
        lines = [
            '<?xml version="1.0" encoding="UTF-8"?>',
            f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{w}mm" height="{h}mm" '
            f'viewBox="0 0 {w} {h}">',
            f"<title>{escape(f'ar-anchor markers: {sheet.title()} (page {number}/{len(pages)})')}</title>",
            f"<desc>{escape(PRINT_NOTE + ' ' + sheet.command('svg'))}</desc>",
            f'<rect x="0" y="0" width="{w}" height="{h}" fill="#ffffff"/>',
        ]
        for item in page.items:
            if isinstance(item, MarkerItem):
                lines.append(
                    f'<path class="marker" data-dictionary="{item.dictionary}" data-id="{item.marker_id}" '
                    f'data-side-mm="{_num(item.side)}" fill="#000000" d="{_path_data(item.rects())}"/>'
                )
            elif isinstance(item, Fill):
                lines.append(f'<path class="{item.tag}" fill="#000000" d="{_path_data(item.rects)}"/>')
            else:
                anchor = {"left": "start", "center": "middle", "right": "end"}[item.align]
                lines.append(
                    f'<text x="{_num(item.x)}" y="{_num(item.y)}" font-family="Helvetica, Arial, sans-serif" '
                    f'font-size="{_num(item.size)}" text-anchor="{anchor}" fill="#000000">{escape(item.text)}</text>'
                )
        lines.append("</svg>")
        documents.append("\n".join(lines) + "\n")
    return documents


# ---------------------------------------------------------------------------- PNG


def _px(value: float) -> int:
    """Pixel edge nearest to ``value`` (halves round up, so shifting by whole pixels commutes with rounding)."""
    return math.floor(value + 0.5)


def _marker_edges(start_mm: float, side_mm: float, modules: int, scale: float) -> list[int]:
    """Pixel edges of a marker's modules along one axis. Whole-pixel modules when that keeps the side
    within half a pixel of the exact ``side_mm * scale`` (centred on the exact position); otherwise every
    edge is the rounded exact position (each edge within half a pixel, the side within 1 px, no
    accumulated error)."""
    exact = side_mm * scale
    module = _px(exact / modules)
    if module >= 1 and abs(module * modules - exact) <= 0.5:
        first = _px((start_mm + side_mm / 2) * scale - module * modules / 2)
        return [first + k * module for k in range(modules + 1)]
    return [_px((start_mm + k * side_mm / modules) * scale) for k in range(modules + 1)]


_HERSHEY = cv2.FONT_HERSHEY_SIMPLEX


def rasterise_page(page: Page, dpi: int) -> np.ndarray:
    """The page as an 8-bit grey image at ``dpi`` (px = mm / 25.4 * dpi), white paper, black ink."""
    scale = dpi / MM_PER_INCH
    image = np.full((_px(page.height * scale), _px(page.width * scale)), 255, dtype=np.uint8)

    def fill(x: float, y: float, w: float, h: float) -> None:
        x0, y0 = _px(x * scale), _px(y * scale)
        x1, y1 = max(_px((x + w) * scale), x0 + 1), max(_px((y + h) * scale), y0 + 1)
        image[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = 0

    for item in page.items:
        if isinstance(item, MarkerItem):
            xs = _marker_edges(item.x, item.side, item.modules, scale)
            ys = _marker_edges(item.y, item.side, item.modules, scale)
            for r, row in enumerate(item.bits):
                for c, black in enumerate(row):
                    if black:
                        image[ys[r] : ys[r + 1], xs[c] : xs[c + 1]] = 0
        elif isinstance(item, Fill):
            for rect in item.rects:
                fill(*rect)
        else:
            (_, unit_h), _ = cv2.getTextSize("H", _HERSHEY, 1.0, 1)
            font_scale = 0.72 * item.size * scale / unit_h  # Helvetica's cap height is 0.72 em
            thickness = max(1, round(font_scale * 1.6))
            (text_w, _), _ = cv2.getTextSize(item.text, _HERSHEY, font_scale, thickness)
            room = _text_width(item.text, item.size) * scale  # never wider than the layout's Helvetica line
            if text_w > room > 0:
                font_scale *= room / text_w
                thickness = max(1, round(font_scale * 1.6))
                (text_w, _), _ = cv2.getTextSize(item.text, _HERSHEY, font_scale, thickness)
            x = item.x * scale - {"left": 0.0, "center": text_w / 2, "right": text_w}[item.align]
            cv2.putText(
                image, item.text, (_px(x), _px(item.y * scale)), _HERSHEY, font_scale, 0, thickness, cv2.LINE_AA
            )
    return image


def _png_with_dpi(image: np.ndarray, dpi: int) -> bytes:
    """PNG bytes (cv2) with a pHYs chunk (pixels per metre) inserted after IHDR."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - cv2 always encodes uint8 images
        raise OutputError("cannot encode PNG")
    data = encoded.tobytes()
    ihdr_end = 8 + 8 + 13 + 4  # signature, IHDR length+type, IHDR data, CRC
    per_metre = round(dpi / 0.0254)
    payload = b"pHYs" + struct.pack(">IIB", per_metre, per_metre, 1)
    chunk = struct.pack(">I", 9) + payload + struct.pack(">I", zlib.crc32(payload) & 0xFFFFFFFF)
    return data[:ihdr_end] + chunk + data[ihdr_end:]


def render_png(sheet: MarkerSheet, dpi: int = 300) -> list[bytes]:
    """One PNG per page at ``dpi`` (pHYs set). Markers' modules are at least 2 px, else an InputError."""
    if not isinstance(dpi, int) or not 1 <= dpi <= MAX_DPI:
        raise InputError(f"--dpi: must be an integer in [1, {MAX_DPI}], got {dpi!r}")
    module_px = sheet.module_mm / MM_PER_INCH * dpi
    if module_px < 2.0:
        raise InputError(
            f"--dpi: at {dpi} dpi a module of the {_mm(sheet.marker_mm)} mm markers is {module_px:.2f} px "
            "(at least 2 px are needed); raise --dpi"
        )
    return [_png_with_dpi(rasterise_page(page, dpi), dpi) for page in sheet.pages("png", dpi)]


# ---------------------------------------------------------------------------- files and the command


def write_sheet(sheet: MarkerSheet, out: str | os.PathLike[str], fmt: str = "pdf", dpi: int = 300) -> list[Path]:
    """Render and write the sheet (``<stem>.<fmt>`` or ``<stem>_p<N>.<fmt>``) and its ``<stem>.toml``;
    returns the written paths, sheet files first. Everything is rendered before anything is written."""
    if fmt not in FORMATS:
        raise InputError(f"--format: must be one of {', '.join(FORMATS)}, got {fmt!r}")
    out = Path(out)
    stem = sheet.stem(fmt, dpi)
    if fmt == "pdf":
        blobs = [render_pdf(sheet)]
    elif fmt == "svg":
        blobs = [doc.encode("utf-8") for doc in render_svg(sheet)]
    else:
        blobs = render_png(sheet, dpi)
    names = [f"{stem}.{fmt}"] if len(blobs) == 1 else [f"{stem}_p{n}.{fmt}" for n in range(1, len(blobs) + 1)]
    config = sheet.config_toml(names, fmt, dpi).encode("utf-8")
    prepare_out_dir(out)
    written = []
    for name, blob in [*zip(names, blobs), (f"{stem}.toml", config)]:
        path = out / name
        try:
            path.write_bytes(blob)
        except OSError as err:
            raise OutputError(f"{path}: cannot write ({err.strerror or err})") from None
        written.append(path)
        log.info("wrote %s (%d bytes)", path, len(blob))
    return written


def _given(args: argparse.Namespace, name: str) -> bool:
    value = getattr(args, name, None)
    return value not in (None, False)


def sheet_from_args(args: argparse.Namespace) -> MarkerSheet:
    """The sheet the ``markers`` options ask for; missing or misplaced options are InputErrors."""
    board = getattr(args, "board", None)
    paper = getattr(args, "paper", "a4")
    dictionary = getattr(args, "dictionary", "DICT_4X4_50")
    first_id = getattr(args, "first_id", 0) or 0
    name = getattr(args, "name", None)

    def refuse(options: Sequence[str], mode: str) -> None:
        for option in options:
            if _given(args, option):
                raise InputError(f"--{option.replace('_', '-')}: not used with {mode}")

    def require(options: Sequence[str], mode: str) -> None:
        missing = [f"--{o.replace('_', '-')}" for o in options if getattr(args, o, None) is None]
        if missing:
            raise InputError(f"{', '.join(missing)}: required with {mode}")

    if board is None:
        if getattr(args, "ids", None) is None:
            raise InputError("--ids: nothing to print; give --ids and --size-mm for single markers, or --board")
        mode = "single markers (--ids)"
        refuse(("cols", "rows", "gap_mm", "square_mm", "legacy", "name"), mode)
        if first_id:
            raise InputError(f"--first-id: not used with {mode}")
        require(("size_mm",), mode)
        return MarkerSheet.single(dictionary, parse_ids(args.ids), args.size_mm, paper=paper)
    if board not in ("grid", "charuco"):
        raise InputError(f"--board: must be grid or charuco, got {board!r}")
    mode = f"--board {board}"
    if _given(args, "ids"):
        raise InputError(f"--ids: not used with {mode} (a board's ids run from --first-id)")
    if board == "grid":
        refuse(("square_mm", "legacy"), mode)
        require(("cols", "rows", "size_mm", "gap_mm"), mode)
        return MarkerSheet.grid(
            dictionary,
            args.cols,
            args.rows,
            args.size_mm,
            args.gap_mm,
            first_id=first_id,
            name=name or "grid",
            paper=paper,
        )
    refuse(("gap_mm",), mode)
    require(("cols", "rows", "square_mm", "size_mm"), mode)
    return MarkerSheet.charuco(
        dictionary,
        args.cols,
        args.rows,
        args.square_mm,
        args.size_mm,
        first_id=first_id,
        legacy=bool(getattr(args, "legacy", False)),
        name=name or "charuco",
        paper=paper,
    )


def run_markers(args: argparse.Namespace) -> int:
    """``ar-anchor markers``: write the sheet and its config snippet, print their paths; 0 on success."""
    sheet = sheet_from_args(args)
    fmt = getattr(args, "format", "pdf")
    dpi = getattr(args, "dpi", 300)
    out = getattr(args, "out", None) or Path("markers")
    paths = write_sheet(sheet, out, fmt, dpi)
    if not getattr(args, "quiet", False):
        for path in paths:
            print(f"wrote {path}")
        print(f"print at 100 % / actual size (no scaling) and check the {RULER_MM:g} mm bar before use")
    return 0
