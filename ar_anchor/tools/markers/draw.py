"""Laid-out pages to files: PDF (fpdf2, vector), SVG (one document per page, user units = mm) and PNG.

PDF: one multi-page file, ``/PrintScaling /None``, a fixed creation date (``SOURCE_DATE_EPOCH``
wins) so the same command writes the same bytes. PNG: numpy/cv2 at ``dpi``, a pHYs chunk with
the DPI, marker module edges on whole pixels (:func:`rasterise_page`).
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Iterable
from datetime import datetime, timezone
from typing import TYPE_CHECKING
from xml.sax.saxutils import escape

import cv2
import numpy as np

from ... import __version__
from ...errors import InputError, OutputError
from .layout import PRINT_NOTE
from .page import MM_PER_INCH, PAPERS, Fill, MarkerItem, Page, Rect, mm_text, text_width

if TYPE_CHECKING:
    from .sheet import MarkerSheet

__all__ = ["FORMATS", "MAX_DPI", "rasterise_page", "render_pdf", "render_png", "render_svg"]

FORMATS = ("pdf", "svg", "png")
MAX_DPI = 2400  # beyond any printer; an A4 page is then 20k x 28k px (560 MB), and 10x more would exhaust memory

# PDF creation date: fixed, so a command reproduces its sheet byte for byte (SOURCE_DATE_EPOCH wins)
_FIXED_DATE = datetime(2000, 1, 1, tzinfo=timezone.utc)


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
            room = text_width(item.text, item.size) * scale  # never wider than the layout's Helvetica line
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
            f"--dpi: at {dpi} dpi a module of the {mm_text(sheet.marker_mm)} mm markers is {module_px:.2f} px "
            "(at least 2 px are needed); raise --dpi"
        )
    return [_png_with_dpi(rasterise_page(page, dpi), dpi) for page in sheet.pages("png", dpi)]
