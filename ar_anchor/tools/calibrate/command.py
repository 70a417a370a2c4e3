"""``ar-anchor calibrate``: check the options, calibrate, write the camera YAML and the recording,
print the report."""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from contextlib import ExitStack
from pathlib import Path

from ...config import BoardConfig, canonical_dictionary, implausible_length_hint, load_config
from ...errors import ArAnchorError, ConfigError, InputError, SourceError, printable
from ...run.outputs import prepare_out_file_folder
from ...run.paths import OutDirLock, check_paths, spec_inputs
from ...sources.open import is_device
from .gather import calibrate_source
from .recording import CalibrationRecording
from .report import format_report, write_camera_yaml
from .views import CharucoSpec

__all__ = ["charuco_spec", "read_board_file", "run_calibrate"]

log = logging.getLogger(__name__)


_NEEDS_CHARUCO = "calibrate needs a ChArUco board (print one with ar-anchor markers --board charuco)"


def read_board_file(path: Path) -> BoardConfig:
    """The ChArUco board of ``path``, the tracker config ``ar-anchor markers --board charuco`` writes beside the
    sheet (any tracker config with one ChArUco board). :class:`InputError` naming ``--board`` for a file with
    no ChArUco board (a grid board's, a single markers sheet's), several, or ids not from 0."""
    try:
        config = load_config(path)
    except ConfigError as err:
        raise ConfigError(f"--board: {err}") from None
    where = f"--board {printable(path)}"
    boards = [board for board in config.boards if board.kind == "charuco"]
    if not boards:
        kinds = sorted({board.kind for board in config.boards})
        found = f"a {' and a '.join(kinds)} board" if kinds else "no [[boards]] table (single markers?)"
        raise InputError(f"{where}: {found}; {_NEEDS_CHARUCO}")
    if len(boards) > 1:
        names = ", ".join(board.name for board in boards)
        raise InputError(f"{where}: {len(boards)} ChArUco boards ({names}); calibrate takes a file with one")
    board = boards[0]
    if board.marker_ids != tuple(range(len(board.marker_ids))):
        raise InputError(
            f"{where}: board '{board.name}' has ids {board.marker_ids[0]}..{board.marker_ids[-1]}; calibrate reads "
            "ChArUco boards whose ids run from 0 (ar-anchor markers --board charuco --first-id 0)"
        )
    return board


def charuco_spec(args: argparse.Namespace) -> CharucoSpec:
    """The board to calibrate with: from ``--board FILE.toml`` (the long options, when also given, must agree
    with it) or from ``--charuco``, the square and marker lengths and ``--dictionary``; errors name the flags."""
    flags = getattr(args, "length_flags", None) or {}
    square_flag, marker_flag = flags.get("square_m", "--square-length"), flags.get("marker_m", "--marker-length")
    given = {
        "--charuco": getattr(args, "charuco", None),
        square_flag: getattr(args, "square_m", None),
        marker_flag: getattr(args, "marker_m", None),
        "--dictionary": getattr(args, "dictionary", None),
        "--legacy": getattr(args, "legacy", None),
    }
    for flag, value in ((square_flag, given[square_flag]), (marker_flag, given[marker_flag])):
        what = "a square" if flag == square_flag else "a marker"
        if value is not None and (hint := implausible_length_hint(value, flag, what)):
            log.warning("%s", hint)
    board_file = getattr(args, "board", None)
    if board_file is None:
        missing = [flag for flag, value in given.items() if value is None and flag != "--legacy"]
        if missing:
            raise InputError(
                f"{', '.join(missing)}: required, or --board FILE.toml (the board file ar-anchor markers wrote "
                "beside the sheet)"
            )
        values = given
    else:
        board = read_board_file(Path(board_file))
        values = {
            "--charuco": f"{board.cols}x{board.rows}",
            square_flag: board.square_length_m,
            marker_flag: board.marker_length_m,
            "--dictionary": board.dictionary,
            "--legacy": board.legacy,
        }
        for flag, value in given.items():
            if value is not None and not _same(flag, value, values[flag]):
                said, typed = (f"{v:g} m" if isinstance(v, float) else v for v in (values[flag], value))
                raise InputError(
                    f"--board {printable(board_file)} and {flag} disagree: the board file says {said}, "
                    f"{flag} says {typed}; give one of them"
                )
    return CharucoSpec.parse(
        values["--charuco"],
        values[square_flag],
        values[marker_flag],
        values["--dictionary"],
        bool(values["--legacy"]),
        options=(square_flag, marker_flag),
    )


def _same(flag: str, given: object, board: object) -> bool:
    """Does a long option's value say what the board file says (``9X6`` is ``9x6``, ``6x6_250`` is
    ``DICT_6X6_250``, lengths to 1e-9)?"""
    if isinstance(board, bool):
        return bool(given) == board
    if isinstance(board, float):
        return math.isclose(float(given), board, rel_tol=1e-9)  # type: ignore[arg-type]
    if flag == "--dictionary":
        try:
            return canonical_dictionary(str(given)) == board
        except ConfigError as err:
            raise InputError(f"--dictionary: {err}") from None
    return str(given).strip().lower().replace(" ", "") == str(board)


def _check_paths(out: Path, rrd: Path, source: str) -> None:
    """Neither output (``--out``, ``--rrd``, or the temporary files they are written through) may be an input
    file of ``source`` or the other output (:class:`InputError` naming both)."""
    outputs = [("--out", out), ("--rrd", rrd)]
    outputs += [("--out", out.with_name(f".{out.name}.{os.getpid()}.tmp.yml"))]
    outputs += [("--rrd", rrd.with_name(f".{rrd.name}.{os.getpid()}.tmp"))]
    check_paths(outputs, [] if is_device(source) else spec_inputs(source))


_APPLICATION = b"ar_anchor_calibrate"  # the recording's application id, in the head of every .rrd it writes


def _written_by_calibrate(rrd: Path) -> bool:
    """Is ``rrd`` a recording an earlier ``ar-anchor calibrate`` wrote (a rerun file whose head names its
    application id)? A link, a folder or anything else is not."""
    if rrd.is_symlink() or not rrd.is_file():
        return False
    try:
        with rrd.open("rb") as handle:
            head = handle.read(4096)
    except OSError:
        return False
    return head.startswith(b"RRF") and _APPLICATION in head


def _check_rrd_is_ours(rrd: Path, out: Path, given: bool) -> None:
    """The recording replaces only a recording calibrate wrote (:class:`InputError` naming the option)."""
    if (rrd.exists() or rrd.is_symlink()) and not _written_by_calibrate(rrd):
        option = f"--rrd {printable(rrd)}" if given else f"--out {printable(out)}"
        hint = "give another --rrd" if given else "give --rrd elsewhere"
        raise InputError(
            f"{option}: would overwrite {printable(rrd)} (the recording), which ar-anchor calibrate did not write: "
            f"move that file or {hint}"
        )


def run_calibrate(args: argparse.Namespace) -> int:
    """``ar-anchor calibrate``: calibrate, write ``--out`` and the recording, print the report."""
    spec = charuco_spec(args)
    out = Path(args.out)
    quiet = bool(getattr(args, "quiet", False))
    if out.is_dir():
        raise InputError(f"--out {out}: is a directory (give the camera YAML file to write)")
    if out.suffix.lower() == ".rrd":
        raise InputError(f"--out {out}: the camera file must be YAML, e.g. camera.yml")
    prepare_out_file_folder(out)
    rrd = Path(args.rrd) if getattr(args, "rrd", None) is not None else out.with_suffix(".rrd")
    if rrd.is_dir():
        raise InputError(f"--rrd {printable(rrd)}: is a directory (give the .rrd file to write)")
    source = str(args.source)
    if not is_device(source) and not any(ch in source for ch in "*?[") and not Path(source).exists():
        raise SourceError(f"{source}: not found (expected an image folder or glob, a video file, or a device)")
    _check_paths(out, rrd, source)
    _check_rrd_is_ours(rrd, out, getattr(args, "rrd", None) is not None)
    prepare_out_file_folder(rrd, "--rrd")
    with ExitStack() as locks:  # one run per output folder, as for every command (--out's, and --rrd's)
        locks.enter_context(OutDirLock(out.parent, "--out"))
        if os.path.abspath(rrd.parent) != os.path.abspath(out.parent):
            locks.enter_context(OutDirLock(rrd.parent, "--rrd"))
        return _calibrate(args, spec, source, out, rrd, quiet)


def _calibrate(args: argparse.Namespace, spec: CharucoSpec, source: str, out: Path, rrd: Path, quiet: bool) -> int:
    def progress(message: str) -> None:
        if not quiet:
            print(f"ar-anchor: {message}", file=sys.stderr, flush=True)

    recording = CalibrationRecording(rrd, spawn=bool(getattr(args, "spawn", False)))
    succeeded = False
    try:
        try:
            report = calibrate_source(
                source,
                spec,
                max_views=args.max_views,
                min_views=args.min_views,
                duration_s=getattr(args, "duration_s", 60.0) or 60.0,
                width=getattr(args, "width", None),
                height=getattr(args, "height", None),
                fps=getattr(args, "fps", None),
                previews=True,
                progress=progress,
                on_keep=recording.live_view,
            )
        except ArAnchorError as err:
            recording.event(f"calibration failed: {err}", warn=True)
            raise
        for rejection in report.rejections:
            recording.event(str(rejection), frame=rejection.frame, warn=True)
        recording.result(report)
        write_camera_yaml(out, report)
        succeeded = True
    finally:
        recording.close(keep=succeeded)
    if quiet:  # (otherwise the report ends with them: said once)
        for warning in report.warnings:
            log.warning("%s", warning)
    else:
        print(format_report(report))
    k = report.camera.camera_matrix
    print(
        f"camera: {out} (fx {k[0, 0]:.1f} fy {k[1, 1]:.1f} cx {k[0, 2]:.1f} cy {k[1, 2]:.1f}, "
        f"RMS {report.result.rms:.3f} px, {len(report.views)} views); recording: {rrd}"
    )
    return 0
