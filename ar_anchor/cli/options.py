"""What the commands share: argument types, option groups, the tracker config with its command-line
overrides, and the camera scaled to the source."""

from __future__ import annotations

import argparse
import logging
import math
import re
import time
from pathlib import Path
from typing import Any

from ..units import length_option as length  # the argparse type of every length option


def base_parser() -> tuple[argparse.ArgumentParser, Any]:
    """The ``ar-anchor`` parser with the common options and no command yet: the parser and its subparsers, to
    which the commands add theirs (:func:`~.main.build_parser` every command; a batch task ``replay`` alone)."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="ar-anchor",
        description="Real-time fiducial-marker AR tracker (ArUco + IPPE + rerun).",
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"ar-anchor {__version__}")
    add_common_options(parser, defaults=True)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    return parser, commands


def int_at_least(minimum: int):
    """An argparse type: an integer ``>= minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


def float_above(minimum: float, *, inclusive: bool):
    """An argparse type: a finite number ``> minimum`` (``>=`` when ``inclusive``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and (value >= minimum if inclusive else value > minimum)):
            raise argparse.ArgumentTypeError(f"must be a number {'>=' if inclusive else '>'} {minimum:g}, got {text!r}")
        return value

    return parse


positive_float = float_above(0.0, inclusive=False)
non_negative_float = float_above(0.0, inclusive=True)


class SameLength(argparse.Action):
    """Stores a length option and its aliases into one ``dest`` (``--marker-length`` and ``--size-mm``); a second
    alias given in the same command is refused, naming both. ``namespace.length_flags[dest]`` keeps the flag
    the user typed, for messages."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, option=None):
        flags = dict(getattr(namespace, "length_flags", None) or {})
        previous = flags.get(self.dest)
        if previous is not None and previous != option:
            parser.error(f"argument {option}: the same length as {previous}: give one of them")
        flags[self.dest] = option
        namespace.length_flags = flags
        setattr(namespace, self.dest, values)


def output_path(text: str) -> Path:
    """An argparse type: a path to write to. An empty one is refused (it would mean the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("empty path (give the folder or file to write, e.g. runs/first)")
    return Path(text)


def float_in(low: float, high: float):
    """A number in [low, high]."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"must be a number in [{low:g}, {high:g}], got {text!r}")
        return value

    return parse


def viewer_url(text: str) -> str:
    """A rerun viewer's gRPC address: rerun+http(s)://host:port/proxy (or rerun://, rerun+https://)."""
    from urllib.parse import urlparse

    parsed = urlparse(text)
    if parsed.scheme not in ("rerun", "rerun+http", "rerun+https") or not parsed.hostname:
        raise argparse.ArgumentTypeError(
            f"expected a rerun viewer URL such as rerun+http://127.0.0.1:9876/proxy, got {text!r}"
        )
    try:
        parsed.port  # noqa: B018 - raises ValueError on a malformed port
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad port in {text!r}") from None
    return text


_CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def camera_name(text: str) -> str:
    """An argparse type: a camera's name, one entity path part (``cameras/<name>/`` in the recording):
    1-64 ASCII letters, digits, ``_`` and ``-``, starting with a letter or digit."""
    if not _CAMERA_NAME.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"expected a camera name such as left or cam_2 (1-64 letters, digits, _ and -, starting with a "
            f"letter or digit: one part of the recording's entity paths), got {text!r}"
        )
    return text


def recording_id(text: str) -> str:
    """An argparse type: a rerun recording id, any non-empty string."""
    if not text:
        raise argparse.ArgumentTypeError("empty recording id (give the id every camera's process shares, e.g. lab)")
    return text


def add_common_options(parser: argparse.ArgumentParser, *, defaults: bool) -> None:
    """-v / -q, accepted before and after the command name (the command's copy sets no default,
    so ``ar-anchor -q demo`` is not undone by the subparser)."""
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0 if defaults else argparse.SUPPRESS,
        help="more log output (-vv for debug)",
    )
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=False if defaults else argparse.SUPPRESS,
        help="no progress bar or summary table",
    )


def add_command(commands: Any, name: str, help_text: str, description: str) -> argparse.ArgumentParser:
    """A subparser ``name`` under ``commands``, with the common options (-v / -q)."""
    parser = commands.add_parser(name, help=help_text, description=description, allow_abbrev=False)
    add_common_options(parser, defaults=False)
    return parser


def add_run_options(parser: argparse.ArgumentParser, name: str, *, spawn: bool = True) -> None:
    """--max-frames, --out and (optionally) --spawn, shared by the commands that run the tracker."""
    parser.add_argument("--max-frames", type=int_at_least(1), default=None, help="stop after N frames")
    parser.add_argument(
        "--out", type=output_path, default=None, help=f"output directory (default recordings/{name}-<time>/)"
    )
    parser.add_argument(
        "--video-out",
        type=output_path,
        default=None,
        metavar="FILE",
        help="also write the annotated video (overlays drawn) to FILE: .mp4/.mov/.mkv (H.264) or .avi (MJPG)",
    )
    parser.add_argument(
        "--no-overlay",
        action="store_true",
        help="do not draw overlays into the recording (faster); --video-out still does",
    )
    parser.add_argument(
        "--no-recording",
        action="store_true",
        help="write no rerun recording: poses.csv and summary.json only (and --video-out when given)",
    )
    if spawn:
        add_viewer_options(parser)


def add_viewer_options(parser: argparse.ArgumentParser) -> None:
    """--spawn (a viewer of this run's own), --connect [URL] (a running one, checked before the run) or
    --serve [--serve-port PORT] (a web viewer on 127.0.0.1: :func:`ar_anchor.cli.view.serve_run`)."""
    viewer = parser.add_mutually_exclusive_group()
    viewer.add_argument(
        "--spawn",
        action="store_true",
        help="also stream to a rerun viewer it starts (its own, on a free port: a running viewer is not reused)",
    )
    viewer.add_argument(
        "--connect",
        metavar="URL",
        nargs="?",
        type=viewer_url,
        const="rerun+http://127.0.0.1:9876/proxy",
        default=None,
        help="stream to a running viewer (default rerun+http://127.0.0.1:9876/proxy, the local one); "
        "the run does not start when none listens there",
    )
    viewer.add_argument(
        "--serve",
        action="store_true",
        help="also stream to a web viewer it serves on 127.0.0.1 (no display needed: open the URL it prints "
        "in a browser); after the run it keeps serving the recording until Ctrl-C. 127.0.0.1 keeps other "
        "machines out, not other users: any process on this machine can connect, watch the run and write "
        "entries into its view (rerun's servers have no authentication)",
    )
    parser.add_argument(
        "--serve-port",
        type=int_at_least(0),
        default=None,
        metavar="PORT",
        help="--serve: the web viewer's HTTP port (default 9090, or a free one when taken)",
    )


def add_camera_options(parser: argparse.ArgumentParser) -> None:
    """--recording-id and --name: several processes, one per camera, streaming into one recording (see
    :mod:`ar_anchor.viz.recorder` and docs/outputs-and-viewer.md, "Several cameras into one viewer")."""
    parser.add_argument(
        "--recording-id",
        type=recording_id,
        default=None,
        metavar="ID",
        help="the rerun recording id: every process given the same ID is one recording, in a viewer they all "
        "stream to (--connect) and in their recording.rrd files opened together or merged (default: a new id)",
    )
    parser.add_argument(
        "--name",
        dest="camera_name",
        type=camera_name,
        default=None,
        metavar="NAME",
        help="this camera's name: its entities go under cameras/NAME/ in the recording (give each camera's "
        "process its own); with --recording-id no viewer layout is sent (the viewer lays out every camera)",
    )


def add_marker_length(parser: argparse.ArgumentParser, help: str, *, required: bool = False) -> None:
    """``--marker-length LENGTH``: a marker's side as every command spells it (a bare number is metres)."""
    parser.add_argument(
        "--marker-length", type=length("m"), default=None, required=required, metavar="LENGTH", help=help
    )


def add_tracker_options(parser: argparse.ArgumentParser) -> None:
    """--config, --dictionary, --marker-length and --no-filter: the tracker config and its overrides."""
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="tracker TOML (default: configs/default.toml values: lone markers, no boards; "
        "demo and live --device synthetic: configs/demo.toml)",
    )
    parser.add_argument(
        "--dictionary",
        default=None,
        help="override [detector] dictionary, e.g. DICT_ARUCO_ORIGINAL, 4x4_50 or tag36h11",
    )
    add_marker_length(
        parser, "override [markers] length_m: marker side, e.g. 50mm, 5cm or 0.05 (a bare number is metres)"
    )
    parser.add_argument(
        "--no-filter",
        action="store_true",
        help="the raw per-frame pipeline: lower-error IPPE solution, no flip resolution or smoothing",
    )
    parser.add_argument(
        "--learn-groups",
        action="store_true",
        help="[groups] learn: markers whose relative pose holds over frames and viewpoints are solved together "
        "as a learned board, board:group-N (see docs/tracking-and-states.md)",
    )


def a_number(text: str) -> float:
    """An argparse type: any number (its range is checked where the value is used, in one line naming the option)."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def add_assumed_camera_options(parser: argparse.ArgumentParser) -> None:
    """--focal-px and --hfov-deg: a camera without a calibration file, taken for an ideal pinhole."""
    parser.add_argument(
        "--focal-px",
        type=a_number,
        default=None,
        metavar="F",
        help="no calibration file: take the camera for a pinhole of focal length F pixels (fx = fy = F, principal "
        "point at the image centre, no lens distortion), at the source's resolution; distances are approximate",
    )
    parser.add_argument(
        "--hfov-deg",
        type=a_number,
        default=None,
        metavar="A",
        help="no calibration file: as --focal-px, the focal length from the horizontal field of view, A degrees "
        "across the image: F = (width / 2) / tan(A / 2)",
    )


# An assumed focal length whose pinhole would see more than this across is refused: no lens a pinhole without
# distortion describes, and the likely slip is a focal length in millimetres (4 mm: a view 179 deg wide)
MAX_ASSUMED_HFOV_DEG = 150.0
# Wider than this, an assumed pinhole is warned about: a wide lens's distortion is large at the edges
WIDE_ASSUMED_HFOV_DEG = 100.0


def assumed_camera_option(args: argparse.Namespace) -> str | None:
    """``--focal-px F`` or ``--hfov-deg A`` as given (None when neither is); :class:`~ar_anchor.errors.InputError`
    when both are, or either with ``--camera``."""
    from ..errors import InputError

    focal, hfov = getattr(args, "focal_px", None), getattr(args, "hfov_deg", None)
    if focal is not None and hfov is not None:
        raise InputError("--focal-px and --hfov-deg: give one of them (both set the focal length)")
    if focal is not None and not (math.isfinite(focal) and focal > 0):
        raise InputError(f"--focal-px {focal:g}: must be a focal length in pixels, > 0")
    if hfov is not None and not (math.isfinite(hfov) and 1.0 < hfov < 179.0):
        raise InputError(
            f"--hfov-deg {hfov:g}: must be a horizontal field of view between 1 and 179 degrees (a pinhole sees "
            "less than 180)"
        )
    option = f"--focal-px {focal:g}" if focal is not None else f"--hfov-deg {hfov:g}" if hfov is not None else None
    if option is not None and getattr(args, "camera", None) is not None:
        raise InputError(
            f"{option.split()[0]} with --camera: give one (--camera is the camera's calibration; "
            f"{option.split()[0]} an assumed focal length for a camera without one)"
        )
    return option


def assumed_camera(args: argparse.Namespace, resolution: tuple[int, int], *, warn: bool = True) -> Any:
    """The pinhole ``--focal-px`` or ``--hfov-deg`` describe at the source's ``resolution`` (width, height), with
    one warning line that distances are approximate (``warn``; else an info line); None when neither is given.
    A focal length no camera of that image width has is a :class:`~ar_anchor.errors.CameraError` naming the
    option, with a hint."""
    from ..camera import CameraModel, hfov_from_focal
    from ..errors import CameraError

    option = assumed_camera_option(args)
    if option is None:
        return None
    width, height = resolution
    focal, hfov = getattr(args, "focal_px", None), getattr(args, "hfov_deg", None)
    if focal is not None:
        hfov = hfov_from_focal(width, focal)
        seen = f"{option}: a focal length of {focal:g} px would see {hfov:.3g} deg across these {width}x{height} images"
        if hfov > MAX_ASSUMED_HFOV_DEG:
            raise CameraError(
                f"{seen}: did you give millimetres? In pixels it is the focal length in mm x the image width in px / "
                "the sensor width in mm; or give the field of view, --hfov-deg"
            )
        if hfov < 1.0:
            sixty = width / 2 / math.tan(math.radians(30.0))
            raise CameraError(f"{seen} (less than 1 deg): a typo? (a 60 deg view is --focal-px {sixty:.0f})")
    camera = CameraModel.assumed(width, height, focal_px=focal, hfov_deg=None if focal is not None else hfov)
    try:
        camera.check_plausible()
    except CameraError as err:
        raise CameraError(f"{option}: {err}") from None
    wide = (
        f"; a view {hfov:.0f} deg wide: a wide lens's distortion, not modelled, bends the edges"
        if hfov > WIDE_ASSUMED_HFOV_DEG
        else ""
    )
    logging.getLogger("ar_anchor.cli").log(
        logging.WARNING if warn else logging.INFO,
        "no calibration: %s taken for a pinhole (fx = fy = %.1f px at %dx%d, principal point at the image "
        "centre, no lens distortion): distances are approximate%s",
        option,
        camera.camera_matrix[0, 0],
        width,
        height,
        wide,
    )
    return camera


def default_out(name: str) -> Path:
    """``recordings/<name>-<YYYYmmdd-HHMMSS>``: a run's output directory when --out is not given."""
    return Path("recordings") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def run_options(args: argparse.Namespace, name: str, **specific: Any):  # noqa: ANN201
    """The :class:`~ar_anchor.run.options.RunOptions` every run command takes from its options (frames,
    viewer, annotated video, overlays, --recording-id and --name when the command has them), the recording
    named ``ar_anchor <name>`` (shared: ``ar_anchor <ID>``, the same in every process), plus ``specific``."""
    from ..errors import InputError
    from ..run.options import RunOptions

    if getattr(args, "serve_port", None) is not None and not getattr(args, "serve", False):
        raise InputError("--serve-port is the port of --serve's web viewer: give --serve too")
    if args.no_recording:
        viewer = next((f for f in ("spawn", "connect", "serve") if getattr(args, f, None)), None)
        if viewer is not None:
            raise InputError(f"--no-recording writes no recording for --{viewer}'s viewer to show: give one of them")
    shared_id = getattr(args, "recording_id", None)
    return RunOptions(
        max_frames=args.max_frames,
        spawn=args.spawn,
        connect=args.connect,
        recording_name=f"ar_anchor {shared_id if shared_id is not None else name}",
        recording_id=shared_id,
        camera_name=getattr(args, "camera_name", None),
        video_out=args.video_out,
        overlays=not args.no_overlay,
        recording=not args.no_recording,
        **specific,
    )


def load_tracker_config(args: argparse.Namespace, *, demo: bool = False):  # noqa: ANN202
    """``--config`` (or the built-in defaults; ``demo``: the demo scene's) with the command-line overrides."""
    from ..config import ConfigValueError, implausible_length_hint, load_config
    from ..errors import ConfigError

    config = load_config(args.config, demo=demo)
    length = getattr(args, "marker_length", None)
    if length is not None and (hint := implausible_length_hint(length, "--marker-length")):
        logging.getLogger("ar_anchor.cli").warning(hint)
    try:
        return config.with_overrides(
            dictionary=getattr(args, "dictionary", None),
            marker_length_m=getattr(args, "marker_length", None),
            filter_enabled=False if getattr(args, "no_filter", False) else None,
            learn_groups=True if getattr(args, "learn_groups", False) else None,
        )
    except ConfigValueError as err:  # the library names the key; the user typed a flag
        flag = _OVERRIDE_FLAGS.get(err.key)
        if flag is None:
            raise
        raise ConfigError(f"{flag}: {err.problem}") from None


_OVERRIDE_FLAGS = {"dictionary": "--dictionary", "length_m": "--marker-length"}


def camera_for_source(camera: Any, resolution: tuple[int, int], option: str, *, frames_from: Any = None) -> Any:
    """``camera`` scaled to the source's ``resolution`` (width, height; pixels); errors name ``option``, and
    ``frames_from`` (the image whose size the frames have, in an image folder) when given."""
    from ..errors import CameraError, printable

    try:
        return camera.scaled_to(*resolution)
    except CameraError as err:
        where = f" (the size of {printable(frames_from)})" if frames_from is not None else ""
        hint = "; a camera without its calibration: --focal-px F or --hfov-deg A instead, for approximate distances"
        raise CameraError(f"{option}: {err}{where}{hint}") from None
