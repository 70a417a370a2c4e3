"""What to print: :class:`MarkerSheet` (lone markers, a grid board or a ChArUco board), validated.

The constructors check every option and name the one at fault (:class:`~ar_anchor.errors.InputError`);
the sheet then knows its ids, sizes, OpenCV board, file stem, the ``ar-anchor markers`` command
that prints it and the tracker config snippet for it. Its pages come from :mod:`.layout`.
Also here: ``--ids`` parsing (:func:`parse_ids`) and formatting (:func:`format_ids`).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ...config import canonical_dictionary as config_canonical_dictionary
from ...config import dictionary_id, dictionary_size
from ...errors import ConfigError, InputError
from .layout import board_origin, sheet_pages
from .page import PAPERS, Page, mm_text

__all__ = ["MAX_BOARD_CELLS", "MIN_MARKER_MM", "MIN_QUIET_MM", "MarkerSheet", "format_ids", "parse_ids"]

log = logging.getLogger(__name__)

MAX_BOARD_CELLS = 100  # the tracker config accepts at most 100 columns / rows
MIN_MARKER_MM = 1.0  # a marker's black square; smaller ones do not print (nor get detected)
MIN_QUIET_MM = 3.0  # quiet zone around a marker or board: one marker cell, at least this


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


def canonical_dictionary(name: str, option: str = "--dictionary") -> str:
    """The dictionary's canonical name (``DICT_4X4_50``) for any spelling the config accepts."""
    try:
        return config_canonical_dictionary(name)
    except ConfigError as err:
        raise InputError(f"{option}: {err}") from None


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
        """One marker per id (``ids``: a list or text such as ``0-3,7``), ``size_mm`` across."""
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
        """A ``cols`` x ``rows`` grid board of ``size_mm`` markers ``gap_mm`` apart, ids from ``first_id``."""
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
            "grid", dictionary, ids, float(size_mm), gap_mm=float(gap_mm), **_board_fields(cols, rows, name, paper)
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
        """A ``cols`` x ``rows`` ChArUco board: ``square_mm`` squares, ``marker_mm`` markers, ids from ``first_id``."""
        dictionary = canonical_dictionary(dictionary)
        _check_count("--cols", cols, 2)
        _check_count("--rows", rows, 2)
        _check_length("--square-mm", square_mm)
        _check_length("--size-mm", marker_mm, MIN_MARKER_MM)
        if marker_mm >= square_mm:
            raise InputError(
                f"--size-mm: the marker ({mm_text(marker_mm)} mm) must be smaller than the chessboard square "
                f"(--square-mm {mm_text(square_mm)} mm)"
            )
        ids = _board_ids(dictionary, first_id, (cols * rows) // 2, f"a {cols}x{rows} ChArUco board")
        return cls(
            "charuco",
            dictionary,
            ids,
            float(marker_mm),
            square_mm=float(square_mm),
            legacy=bool(legacy),
            **_board_fields(cols, rows, name, paper),
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
            stem = f"{self.dictionary}_ids{ids}_{mm_text(self.marker_mm)}mm"
        else:
            prefix = self.name or self.kind
            ids = f"ids{self.ids[0]}-{self.ids[-1]}"
            stem = f"{prefix}_{self.cols}x{self.rows}_{self.dictionary}_{ids}_"
            if self.kind == "grid":
                stem += f"{mm_text(self.marker_mm)}mm_gap{mm_text(self.gap_mm)}mm"
            else:
                stem += f"sq{mm_text(self.square_mm)}mm_m{mm_text(self.marker_mm)}mm" + (
                    "_legacy" if self.legacy else ""
                )
        if self.paper != "a4":
            stem += f"_{self.paper}"
        if fmt == "png":
            stem += f"_{int(dpi)}dpi"
        return stem

    def command(self, fmt: str = "pdf", dpi: int = 300) -> str:
        """The ``ar-anchor markers`` command line that prints this sheet (without --out)."""
        parts = ["ar-anchor markers", f"--dictionary {self.dictionary}"]
        if self.kind == "single":
            parts += [f"--ids {format_ids(self.ids)}", f"--marker-length {mm_text(self.marker_mm)}mm"]
        else:
            parts += [f"--board {self.kind}", f"--cols {self.cols}", f"--rows {self.rows}"]
            if self.kind == "grid":
                parts += [f"--marker-length {mm_text(self.marker_mm)}mm", f"--gap-mm {mm_text(self.gap_mm)}"]
            else:
                parts += [
                    f"--square-length {mm_text(self.square_mm)}mm",
                    f"--marker-length {mm_text(self.marker_mm)}mm",
                ]
                parts += ["--legacy"] if self.legacy else []
            parts += [f"--first-id {self.first_id}"] if self.first_id else []
            parts += [f"--name {self.name}"] if self.name != self.kind else []
        parts += [f"--paper {self.paper}"] if self.paper != "a4" else []
        parts += [f"--format {fmt}"] if fmt != "pdf" else []
        parts += [f"--dpi {dpi}"] if fmt == "png" and dpi != 300 else []
        return " ".join(parts)

    def title(self) -> str:
        if self.kind == "single":
            return f"{self.dictionary}, ids {format_ids(self.ids)}, {mm_text(self.marker_mm)} mm markers"
        width, height = self.board_size_mm
        return (
            f"{'grid' if self.kind == 'grid' else 'ChArUco'} board '{self.name}', {self.dictionary}, "
            f"{self.cols}x{self.rows}, {mm_text(width)} x {mm_text(height)} mm"
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
        return sheet_pages(self, fmt, dpi)

    def board_origin_mm(self) -> tuple[float, float]:
        """Where the board's top-left corner (OpenCV's board frame origin) lies on its page."""
        return board_origin(self)


def _metres(mm: float) -> str:
    return repr(float(mm) / 1000.0)


def _check_length(option: str, value: float | None, minimum: float = 0.0) -> None:
    if value is None or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise InputError(f"{option}: must be a length in mm > 0, got {value!r}")
    if value < minimum:
        slip = value * 1000 >= minimum  # metres given to a millimetre option: today's hint, in the other direction
        hint = f"; did you give metres? {value:g} m is {option} {value * 1000:g} (or {value:g}m)" if slip else ""
        raise InputError(f"{option}: must be at least {minimum:g} mm (nothing smaller prints), got {value!r}{hint}")


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


def _board_fields(cols: int, rows: int, name: str, paper: str) -> dict[str, Any]:
    """The fields a grid and a ChArUco sheet share: their cells, and their name and paper, checked."""
    return {"cols": int(cols), "rows": int(rows), "name": _check_name(name), "paper": _check_paper(paper)}


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
