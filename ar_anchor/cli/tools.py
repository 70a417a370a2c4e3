"""The tools around the tracker: `ar-anchor markers`, `ar-anchor calibrate`, `ar-anchor study`, `ar-anchor map`."""

from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import InputError
from .options import SameLength, add_command, add_marker_length, int_at_least, length, positive_float


def add_parsers(commands: Any) -> None:
    """The ``markers``, ``calibrate``, ``study`` and ``map`` commands' options."""
    add_markers_parser(commands)
    add_calibrate_parser(commands)
    add_study_parser(commands)
    add_map_parser(commands)


def add_length_option(
    parser: argparse.ArgumentParser,
    option: str,
    alias: str,
    *,
    dest: str,
    kind: Callable[[str], float],
    alias_kind: Callable[[str], float],
    help: str,
    alias_help: str,
) -> None:
    """A length option and its older alias, one after the other: one destination, each its own type (a bare
    number's unit), and given both, they must agree (:class:`~.options.SameLength`)."""
    parser.add_argument(option, dest=dest, action=SameLength, type=kind, default=None, metavar="LENGTH", help=help)
    parser.add_argument(
        alias, dest=dest, action=SameLength, type=alias_kind, default=None, metavar="LENGTH", help=alias_help
    )


def add_markers_parser(commands: Any) -> None:
    """The ``markers`` command's options."""
    markers = add_command(
        commands,
        "markers",
        "printable marker sheets (PDF, SVG, PNG) at exact size, with the matching tracker config",
        "Single markers (--ids), grid boards (--board grid) or ChArUco boards (--board charuco) as PDF "
        "(exact physical size, scale ruler, cut marks, caption), SVG or PNG at --dpi; a TOML snippet "
        "beside each sheet configures the tracker for exactly what was printed.",
    )
    markers.add_argument(
        "--dictionary",
        default="DICT_4X4_50",
        help="cv2.aruco dictionary, e.g. 4x4_50 or tag36h11 (default DICT_4X4_50)",
    )
    markers.add_argument("--ids", default=None, help="single markers: ids, e.g. 0-3 or 0,5,7 or 0-3,9")
    add_length_option(
        markers,
        "--marker-length",
        "--size-mm",
        dest="size_mm",
        kind=length("m", to="mm"),
        alias_kind=length("mm"),
        help="marker side (the black square), e.g. 50mm or 5cm (a bare number is metres)",
        alias_help="the same as --marker-length, a bare number in mm",
    )
    markers.add_argument("--board", choices=("grid", "charuco"), default=None, help="print a board instead")
    markers.add_argument("--cols", type=int_at_least(1), default=None, help="board: markers (grid) or squares across")
    markers.add_argument("--rows", type=int_at_least(1), default=None, help="board: markers (grid) or squares down")
    markers.add_argument(
        "--gap-mm",
        type=length("mm"),
        default=None,
        metavar="LENGTH",
        help="grid: gap between markers, e.g. 10mm or 1cm (a bare number is mm)",
    )
    add_length_option(
        markers,
        "--square-length",
        "--square-mm",
        dest="square_mm",
        kind=length("m", to="mm"),
        alias_kind=length("mm"),
        help="charuco: chessboard square side, e.g. 30mm or 3cm (a bare number is metres)",
        alias_help="the same as --square-length, a bare number in mm",
    )
    markers.add_argument("--first-id", type=int_at_least(0), default=0, help="board: id of its first marker")
    markers.add_argument("--legacy", action="store_true", help="charuco: the legacy (pre-4.6) pattern")
    markers.add_argument("--name", default=None, help="board name in the config snippet (default: grid/charuco)")
    markers.add_argument("--format", choices=("pdf", "svg", "png"), default="pdf", help="output format (default pdf)")
    markers.add_argument("--dpi", type=int_at_least(50), default=300, help="png: dots per inch (default 300)")
    markers.add_argument("--paper", choices=("a4", "letter"), default="a4", help="pdf/svg page size (default a4)")
    markers.add_argument("--out", type=Path, default=Path("markers"), help="output directory (default markers/)")
    markers.set_defaults(func=cmd_markers)


def add_calibrate_parser(commands: Any) -> None:
    """The ``calibrate`` command's options."""
    calibrate = add_command(
        commands,
        "calibrate",
        "calibrate a camera from ChArUco views (image folder, video, or a live device)",
        "Detect a ChArUco board in SOURCE (a folder or glob of images, a video file, or a device such as "
        "/dev/video0), keep sharp and distinct views, calibrate, drop outlier views, report per-view "
        "error and image coverage, and write the OpenCV YAML camera file every other command reads.",
    )
    calibrate.add_argument("source", metavar="SOURCE", help="image folder or glob, video file, or device")
    calibrate.add_argument(
        "--board",
        type=Path,
        default=None,
        metavar="FILE.toml",
        help="the board's TOML, as `ar-anchor markers --board charuco` wrote it beside the sheet: squares, "
        "lengths, dictionary and legacy pattern from it (then the options below are not needed; given, they must "
        "agree with it)",
    )
    calibrate.add_argument("--charuco", default=None, metavar="CxR", help="board squares across x down, e.g. 5x7")
    add_length_option(
        calibrate,
        "--square-length",
        "--square-m",
        dest="square_m",
        kind=length("m"),
        alias_kind=length("m"),
        help="chessboard square side, e.g. 30mm or 3cm (a bare number is metres)",
        alias_help="the same as --square-length (its older name)",
    )
    add_length_option(
        calibrate,
        "--marker-length",
        "--marker-m",
        dest="marker_m",
        kind=length("m"),
        alias_kind=length("m"),
        help="marker side, e.g. 22mm (a bare number is metres)",
        alias_help="the same as --marker-length (its older name)",
    )
    calibrate.add_argument(
        "--dictionary", default=None, help="cv2.aruco dictionary of the board's markers, e.g. 6x6_250 or DICT_6X6_250"
    )
    calibrate.add_argument(
        "--legacy", action="store_true", default=None, help="the board uses the legacy (pre-4.6) pattern"
    )
    calibrate.add_argument("--out", type=Path, required=True, help="camera YAML file to write")
    calibrate.add_argument("--max-views", type=int_at_least(3), default=40, help="views used at most (default 40)")
    calibrate.add_argument("--min-views", type=int_at_least(3), default=6, help="views needed at least (default 6)")
    calibrate.add_argument(
        "--rrd", type=Path, default=None, help="rerun recording of the calibration (default: beside --out)"
    )
    calibrate.add_argument("--spawn", action="store_true", help="also stream to a rerun viewer it starts")
    calibrate.add_argument("--fps", type=positive_float, default=None, help="device: frames per second to ask for")
    calibrate.add_argument("--width", type=int_at_least(1), default=None, help="device: frame width to ask for")
    calibrate.add_argument("--height", type=int_at_least(1), default=None, help="device: frame height to ask for")
    calibrate.add_argument(
        "--duration-s", type=positive_float, default=60.0, help="device: stop capturing after this long (default 60)"
    )
    calibrate.set_defaults(func=cmd_calibrate)


def add_study_parser(commands: Any) -> None:
    """The ``study`` command's options (:mod:`ar_anchor.tools.study.options`)."""
    study = add_command(
        commands,
        "study",
        "reproduce the PnP textbook's experiments: outliers, ransac, jitter",
        "Each study writes NAME.png, NAME.md, NAME.json and NAME.rrd to --out (default recordings/study/).",
    )
    from ..tools.study.options import configure_parser as configure_study

    configure_study(study)
    study.set_defaults(func=cmd_study)


def add_map_parser(commands: Any) -> None:
    """The ``map`` command's options."""
    mapper = add_command(
        commands,
        "map",
        "learn a map of markers that sit rigidly together (a sheet, a wall, a room) from videos",
        "Detect the markers in VIDEO (video files, image folders or globs), place them from the reference "
        "marker (the most seen, or --origin) robustly to the planar flip, and bundle-adjust every frame's "
        "camera pose and every marker's pose. Writes --out (the ArUco marker map YAML, or our layout TOML "
        "when it ends in .toml; the other format beside it), <stem>_report.md and <stem>.rrd; the map is "
        'then a [[boards]] kind = "custom" board of the tracker config.',
    )
    mapper.add_argument("sources", nargs="+", metavar="VIDEO", help="video file, image folder or quoted glob")
    mapper.add_argument("--camera", type=Path, required=True, help="camera YAML of the camera that filmed VIDEO")
    mapper.add_argument("--dictionary", required=True, help="cv2.aruco dictionary of the markers, e.g. DICT_4X4_50")
    add_marker_length(mapper, "side of each marker's black square, e.g. 50mm (a bare number is metres)", required=True)
    mapper.add_argument("--out", type=Path, required=True, help="layout file to write: layout.yml or layout.toml")
    mapper.add_argument("--origin", type=int_at_least(0), default=None, help="marker id of the map frame")
    mapper.add_argument("--step", type=int_at_least(1), default=1, help="search one frame in N (default 1: all)")
    mapper.add_argument("--max-frames", type=int_at_least(1), default=None, help="search at most N frames in all")
    mapper.add_argument("--rrd", type=Path, default=None, help="rerun recording of the map (default: beside --out)")
    mapper.add_argument("--spawn", action="store_true", help="also show the map in a rerun viewer it starts")
    mapper.set_defaults(func=cmd_map)


def cmd_study(args: argparse.Namespace) -> int:
    """``ar-anchor study``: run the chosen PnP studies; the exit code."""
    if importlib.util.find_spec("matplotlib") is None:
        raise InputError(
            "ar-anchor study draws its figures with matplotlib, which is not installed: "
            "pip install 'ar-anchor[study]' (or pip install matplotlib)"
        )
    from ..tools.study.command import run_study

    return run_study(args)


def cmd_markers(args: argparse.Namespace) -> int:
    """``ar-anchor markers``: write printable marker sheets; the exit code."""
    from ..tools.markers import run_markers

    return run_markers(args)


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``ar-anchor calibrate``: calibrate a camera from ChArUco views; the exit code."""
    from ..tools.calibrate import run_calibrate

    return run_calibrate(args)


def cmd_map(args: argparse.Namespace) -> int:
    """``ar-anchor map``: learn a marker map from videos; the exit code."""
    from ..tools.map import run_map

    return run_map(args)
