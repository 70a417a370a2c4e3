"""A :class:`~.sheet.MarkerSheet` laid out on pages (mm, y down from the page's top edge).

The layout reads a sheet through :class:`Sheet`, the few fields and methods it needs, so that ``sheet.py``
(whose ``MarkerSheet.pages`` calls this module) is not imported here.

Lone markers fill cells (marker, quiet zone of at least one marker cell, two caption lines) in
rows and columns, as many per page as fit, each cell with cut marks; a board is one cell centred
on a portrait page, or on a landscape one when it does not fit in portrait. Nothing is scaled: a
sheet that does not fit is an :class:`~ar_anchor.errors.InputError`. Every page gets a header
(title, print note, config file) and the 100 mm scale-check ruler.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

from ...errors import InputError
from .page import PAPERS, Fill, MarkerItem, Page, Rect, Text, marker_bits, mm_text, text_width

__all__ = ["PRINT_NOTE", "RULER_MM", "Sheet", "board_origin", "sheet_pages"]


class Sheet(Protocol):
    """What the layout reads of a sheet (:class:`~.sheet.MarkerSheet` has it all). Lengths in mm."""

    kind: str
    dictionary: str
    ids: tuple[int, ...]
    marker_mm: float
    cols: int
    rows: int
    gap_mm: float
    square_mm: float
    legacy: bool
    name: str
    paper: str

    @property
    def board_size_mm(self) -> tuple[float, float]: ...

    @property
    def quiet_mm(self) -> float: ...

    def cv_board(self) -> cv2.aruco.Board: ...

    def stem(self, fmt: str = "pdf", dpi: int = 300) -> str: ...

    def command(self, fmt: str = "pdf", dpi: int = 300) -> str: ...

    def title(self) -> str: ...


MARGIN = 8.0  # page edge to anything printed
MARK_GAP = 1.0  # cut marks start this far outside the cut box ...
MARK_LEN = 3.0  # ... and are this long
MARK_WIDTH = 0.15
MARK_SPACE = MARK_GAP + MARK_LEN + 0.5  # room kept free for cut marks around every cut box
GUTTER = 2 * MARK_SPACE  # between two cut boxes
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


def sheet_pages(sheet: Sheet, fmt: str = "pdf", dpi: int = 300) -> list[Page]:
    """The sheet's pages (see :meth:`MarkerSheet.pages`)."""
    pages = _single_pages(sheet) if sheet.kind == "single" else [_board_page(sheet)]
    for number, page in enumerate(pages, start=1):
        _decorate(sheet, page, number, len(pages), fmt, dpi)
    return pages


def _single_pages(sheet: Sheet) -> list[Page]:
    width, height = PAPERS[sheet.paper]
    left, top, right, bottom = _content_area(width, height)
    side, quiet = sheet.marker_mm, sheet.quiet_mm
    caption_width = max(text_width(line, CAPTION_SIZE) for line in _caption(sheet, max(sheet.ids)))
    cell_w = max(side + 2 * quiet, caption_width + 2.0)
    cell_h = side + 2 * quiet + CAPTION_HEIGHT
    across = int((right - left + GUTTER + 1e-9) // (cell_w + GUTTER))
    down = int((bottom - top + GUTTER + 1e-9) // (cell_h + GUTTER))
    if across < 1 or down < 1:
        raise InputError(
            f"--size-mm: a {mm_text(side)} mm marker needs {cell_w:.1f} x {cell_h:.1f} mm with its quiet zone and "
            f"caption, but {sheet.paper} paper has {right - left:.1f} x {bottom - top:.1f} mm for it "
            "(sheets are printed at 100 %, never scaled down)"
        )
    per_page = across * down
    chunks = [sheet.ids[i : i + per_page] for i in range(0, len(sheet.ids), per_page)]
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
                MarkerItem(marker_id, mx, my, side, marker_bits(sheet.dictionary, marker_id), sheet.dictionary)
            )
            for line_no, line in enumerate(_caption(sheet, marker_id)):
                baseline = my + side + quiet + 1.2 + CAPTION_LINE * (line_no + 0.8)
                page.items.append(Text(bx + cell_w / 2, baseline, line, CAPTION_SIZE, "center"))
            page.items.append(Fill(tuple(_cut_marks(bx, by, cell_w, cell_h)), "cut-marks"))
        pages.append(page)
    return pages


def _caption(sheet: Sheet, marker_id: int | None = None) -> list[str]:
    if sheet.kind == "single":
        return [sheet.dictionary, f"id {marker_id}, {mm_text(sheet.marker_mm)} mm"]
    width, height = sheet.board_size_mm
    ids = f"ids {sheet.ids[0]}-{sheet.ids[-1]}"
    if sheet.kind == "grid":
        return [
            f"grid board '{sheet.name}': {sheet.dictionary}, {sheet.cols}x{sheet.rows} markers, {ids}",
            f"marker {mm_text(sheet.marker_mm)} mm, gap {mm_text(sheet.gap_mm)} mm, "
            f"board {mm_text(width)} x {mm_text(height)} mm",
        ]
    return [
        f"ChArUco board '{sheet.name}': {sheet.dictionary}, {sheet.cols}x{sheet.rows} squares, {ids}"
        + (", legacy pattern" if sheet.legacy else ""),
        f"square {mm_text(sheet.square_mm)} mm, marker {mm_text(sheet.marker_mm)} mm, "
        f"board {mm_text(width)} x {mm_text(height)} mm",
    ]


def _board_page(sheet: Sheet) -> Page:
    board_w, board_h = sheet.board_size_mm
    quiet = sheet.quiet_mm
    caption = _caption(sheet)
    box_w = max(board_w + 2 * quiet, max(text_width(line, CAPTION_SIZE) for line in caption) + 2.0)
    box_h = board_h + 2 * quiet + CAPTION_HEIGHT
    portrait = PAPERS[sheet.paper]
    for width, height in (portrait, portrait[::-1]):
        left, top, right, bottom = _content_area(width, height)
        if box_w <= right - left + 1e-9 and box_h <= bottom - top + 1e-9:
            break
    else:
        left, top, right, bottom = _content_area(*portrait)
        options = "--cols/--rows/" + ("--size-mm/--gap-mm" if sheet.kind == "grid" else "--square-mm")
        raise InputError(
            f"{options}: the {sheet.cols}x{sheet.rows} {sheet.kind} board is "
            f"{mm_text(board_w)} x {mm_text(board_h)} mm "
            f"({box_w:.1f} x {box_h:.1f} mm with its quiet zone and caption), but {sheet.paper} paper has "
            f"{right - left:.1f} x {bottom - top:.1f} mm for it (portrait or landscape); sheets are printed "
            "at 100 %, never scaled down"
        )
    page = Page(width, height)
    bx = (left + right) / 2 - box_w / 2
    by = (top + bottom) / 2 - box_h / 2
    ox, oy = bx + (box_w - board_w) / 2, by + quiet  # the board's top-left corner
    board = sheet.cv_board()
    corners = np.asarray(board.getObjPoints(), dtype=np.float64).reshape(-1, 4, 3)
    board_ids = [int(i) for i in np.asarray(board.getIds()).ravel()]
    if sheet.kind == "charuco":
        centres = corners[:, :, :2].mean(axis=1)
        white = {(int(cx // sheet.square_mm), int(cy // sheet.square_mm)) for cx, cy in centres}
        black = tuple(
            (ox + col * sheet.square_mm, oy + row * sheet.square_mm, sheet.square_mm, sheet.square_mm)
            for row in range(sheet.rows)
            for col in range(sheet.cols)
            if (col, row) not in white
        )
        page.items.append(Fill(black, "chessboard"))
    for marker_id, corner in zip(board_ids, corners):
        x, y = corner[0, 0], corner[0, 1]
        side = corner[1, 0] - corner[0, 0]
        page.items.append(
            MarkerItem(marker_id, ox + x, oy + y, side, marker_bits(sheet.dictionary, marker_id), sheet.dictionary)
        )
    for line_no, line in enumerate(caption):
        baseline = oy + board_h + quiet + 1.2 + CAPTION_LINE * (line_no + 0.8)
        page.items.append(Text(bx + box_w / 2, baseline, line, CAPTION_SIZE, "center"))
    page.items.append(Fill(tuple(_cut_marks(bx, by, box_w, box_h)), "cut-marks"))
    return page


def board_origin(sheet: Sheet) -> tuple[float, float]:
    """Where the board's top-left corner (OpenCV's board frame origin) lies on its page."""
    page = sheet_pages(sheet)[0]
    marker = page.markers[0]
    corner = np.asarray(sheet.cv_board().getObjPoints()[0], dtype=np.float64).reshape(4, 3)[0]
    return (marker.x - corner[0], marker.y - corner[1])


def _decorate(sheet: Sheet, page: Page, number: int, count: int, fmt: str, dpi: int) -> None:
    """Header (title, print note, config file) and the 100 mm scale-check ruler."""
    width, height = page.width, page.height
    right = width - MARGIN
    page_text = f"page {number}/{count}"
    title = f"ar-anchor markers: {sheet.title()}"
    room = right - MARGIN - text_width(page_text, NOTE_SIZE) - 4.0
    page.items += [
        Text(MARGIN, MARGIN + 3.0, title, _fit(title, TITLE_SIZE, room)),
        Text(right, MARGIN + 3.0, page_text, NOTE_SIZE, "right"),
    ]
    note = f"{PRINT_NOTE} The bar at the bottom must measure {RULER_MM:g} mm."
    config = f"Tracker config: {sheet.stem(fmt, dpi)}.toml (made by: {sheet.command(fmt, dpi)})"
    for line_no, line in enumerate((note, config)):
        page.items.append(Text(MARGIN, MARGIN + 7.3 + 3.6 * line_no, line, _fit(line, NOTE_SIZE, right - MARGIN)))
    page.items += _ruler(width, height - MARGIN - FOOTER_HEIGHT)


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


def _fit(text: str, size: float, room: float) -> float:
    """The font size, shrunk if needed so the line fits ``room`` mm (text only; never marker geometry)."""
    width = text_width(text, size)
    return size if width <= room else size * room / width
