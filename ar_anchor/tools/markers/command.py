"""``ar-anchor markers``: the options to a :class:`~.sheet.MarkerSheet`, the sheet to files.

:func:`sheet_from_args` refuses options that do not belong to the kind of sheet asked for and
names the missing ones; :func:`write_sheet` renders everything before writing anything (the sheet
files and the ``<stem>.toml`` tracker config snippet); :func:`run_markers` prints the paths.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path

from ...config import implausible_length_hint
from ...errors import InputError, OutputError, printable
from ...run.outputs import prepare_out_dir
from ...run.paths import OutDirLock
from ...run.written import WrittenFiles, refuse_theirs
from .draw import FORMATS, render_pdf, render_png, render_svg
from .layout import RULER_MM
from .sheet import MarkerSheet, parse_ids

__all__ = ["run_markers", "sheet_from_args", "write_sheet"]

log = logging.getLogger(__name__)


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
    files = [*zip(names, blobs), (f"{stem}.toml", config)]
    created = not out.exists()
    out = prepare_out_dir(out)
    try:
        with OutDirLock(out):  # one run per output folder, as for every command
            return _write_files(out, files)
    except InputError:
        if created:  # refused before anything was written: no empty folder left behind
            with suppress(OSError):
                out.rmdir()
        raise


def _same_content(path: Path, blob: bytes) -> bool:
    """Is ``path`` a regular file holding exactly ``blob`` (replacing it loses nothing)?"""
    try:
        if path.is_symlink() or not path.is_file() or path.stat().st_size != len(blob):
            return False
        return path.read_bytes() == blob
    except OSError:
        return False


def _write_files(out: Path, files: list[tuple[str, bytes]]) -> list[Path]:
    """Write ``files`` (name, bytes) into ``out``, replacing only files markers wrote there (listed in
    ``.ar-anchor-markers.json``) or that hold the same bytes: any other file in the way refuses the whole sheet
    before anything is written."""
    manifest = WrittenFiles(out, "markers")
    theirs = [name for name, blob in files if name in manifest.theirs([name]) and not _same_content(out / name, blob)]
    refuse_theirs(out, theirs, not_written_by="ar-anchor markers did not write", writer="the sheet")
    written = []
    try:
        for name, blob in files:
            path = out / name
            try:
                path.write_bytes(blob)
            except OSError as err:
                raise OutputError(f"{printable(path)}: cannot write ({err.strerror or err})") from None
            manifest.record(name)
            written.append(path)
            log.info("wrote %s (%d bytes)", path, len(blob))
    finally:
        manifest.save()
    return written


def _flag(dest: str) -> str:
    """The option that sets ``dest``, as messages name it (a length: its canonical name, ``--marker-length``)."""
    return _LENGTHS[dest][0] if dest in _LENGTHS else f"--{dest.replace('_', '-')}"


def _given(args: argparse.Namespace, name: str) -> bool:
    value = getattr(args, name, None)
    return value not in (None, False)


# the lengths markers reads in millimetres: their canonical option (a bare number in metres, as everywhere) and
# the millimetre alias the sheet's messages name
_LENGTHS = {
    "size_mm": ("--marker-length", "--size-mm", "a marker"),
    "square_mm": ("--square-length", "--square-mm", "a square"),
}


def _typed_flag(args: argparse.Namespace, dest: str) -> str | None:
    """The flag the user typed for the length in ``dest`` (``--marker-length`` or ``--size-mm``), if recorded."""
    return (getattr(args, "length_flags", None) or {}).get(dest)


def sheet_from_args(args: argparse.Namespace) -> MarkerSheet:
    """The sheet the ``markers`` options ask for; missing or misplaced options are InputErrors, naming each
    length by the flag the user typed (``--marker-length`` or its millimetre alias ``--size-mm``)."""
    for dest, (canonical, _alias, what) in _LENGTHS.items():
        value_mm = getattr(args, dest, None)
        if value_mm is not None and _typed_flag(args, dest) == canonical:
            hint = implausible_length_hint(value_mm / 1000.0, canonical, what)
            if hint is not None:  # a bare number is metres here: 50 is most likely 50 mm
                raise InputError(hint)
    with _as_typed(args):
        return _sheet_from_args(args)


@contextmanager
def _as_typed(args: argparse.Namespace) -> Iterator[None]:
    """An :class:`InputError` inside names each length by the flag the user typed (the sheet's messages name
    the millimetre aliases, ``--size-mm``; the user may have typed ``--marker-length``)."""
    try:
        yield
    except InputError as err:
        message = str(err)
        for dest, (_canonical, alias, _what) in _LENGTHS.items():
            typed = _typed_flag(args, dest)
            if typed is not None and typed != alias:
                message = message.replace(alias, typed)
        if message == str(err):
            raise
        raise InputError(message) from None


def _sheet_from_args(args: argparse.Namespace) -> MarkerSheet:
    board = getattr(args, "board", None)
    paper = getattr(args, "paper", "a4")
    dictionary = getattr(args, "dictionary", "DICT_4X4_50")
    first_id = getattr(args, "first_id", 0) or 0
    name = getattr(args, "name", None)

    def refuse(options: Sequence[str], mode: str) -> None:
        for option in options:
            if _given(args, option):
                raise InputError(f"{_typed_flag(args, option) or _flag(option)}: not used with {mode}")

    def require(options: Sequence[str], mode: str) -> None:
        missing = [_flag(o) for o in options if getattr(args, o, None) is None]
        if missing:
            raise InputError(f"{', '.join(missing)}: required with {mode}")

    if board is None:
        if getattr(args, "ids", None) is None:
            raise InputError("--ids: nothing to print; give --ids and --marker-length for single markers, or --board")
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
    placed = {"first_id": first_id, "name": name or board, "paper": paper}  # what either board takes alike
    if board == "grid":
        refuse(("square_mm", "legacy"), mode)
        require(("cols", "rows", "size_mm", "gap_mm"), mode)
        return MarkerSheet.grid(dictionary, args.cols, args.rows, args.size_mm, args.gap_mm, **placed)
    refuse(("gap_mm",), mode)
    require(("cols", "rows", "square_mm", "size_mm"), mode)
    legacy = bool(getattr(args, "legacy", False))
    return MarkerSheet.charuco(dictionary, args.cols, args.rows, args.square_mm, args.size_mm, legacy=legacy, **placed)


def run_markers(args: argparse.Namespace) -> int:
    """``ar-anchor markers``: write the sheet and its config snippet, print their paths; 0 on success."""
    sheet = sheet_from_args(args)
    fmt = getattr(args, "format", "pdf")
    dpi = getattr(args, "dpi", 300)
    out = getattr(args, "out", None) or Path("markers")
    with _as_typed(args):
        paths = write_sheet(sheet, out, fmt, dpi)
    if not getattr(args, "quiet", False):
        print(f"print at 100 % / actual size (no scaling) and check the {RULER_MM:g} mm bar before use")
        print("outputs: " + ", ".join(printable(path) for path in paths))  # the last line: every file written
    return 0
