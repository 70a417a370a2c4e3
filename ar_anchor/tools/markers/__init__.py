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

Modules: :mod:`.page` (the page model: items, marker modules, font metrics), :mod:`.sheet`
(:class:`MarkerSheet`: what to print, validated; ids; file names; the tracker config snippet),
:mod:`.layout` (sheets laid out on pages: cells, captions, header, cut marks, the ruler),
:mod:`.draw` (PDF, SVG and PNG from laid-out pages) and :mod:`.command` (``ar-anchor markers``:
options to a sheet, files written).
"""

from __future__ import annotations

from .command import run_markers, sheet_from_args, write_sheet
from .draw import FORMATS, rasterise_page, render_pdf, render_png, render_svg
from .page import PAPERS, Fill, MarkerItem, Page, Text, marker_bits, marker_rects
from .sheet import MarkerSheet, parse_ids

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
