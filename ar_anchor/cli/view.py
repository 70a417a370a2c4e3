"""`ar-anchor view`: open recordings in the rerun viewer, native or (``--web``) in a browser.

The viewer is the ``rerun`` program of rerun-sdk, started with a fixed command line
(:mod:`ar_anchor.viz.viewer`): natively it is a window of its own, and this command waits until it is
closed; with ``--web`` it serves the web viewer and the recordings on 127.0.0.1 (two ports: the page over
HTTP, the recordings over gRPC) until Ctrl-C. Another address only with ``--bind``, and with a warning:
rerun's servers have no authentication.

127.0.0.1 keeps other machines out, not other users: any process on this machine, of any user (and of any
container sharing its network), can connect to both ports, read every recording served and log entries
into them (the gRPC server is a proxy that takes data from any logging SDK). rerun 0.41 offers no token
and no private (Unix) socket for its viewer servers, so nothing narrower can be asked of it; this is said
next to the options (:data:`LOCAL_ONLY_RISK`).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

from ..errors import EXIT_INTERRUPTED, EXIT_OK, ArAnchorError, InputError, printable
from .options import add_command, float_in

log = logging.getLogger(__name__)

# what 127.0.0.1 means, in the --help of --web, --bind and --serve (rerun 0.41's servers take no token)
LOCAL_ONLY_RISK = (
    "127.0.0.1 keeps other machines out, not other users: any process on this machine can connect, read the "
    "recordings served and write entries into them (rerun's servers have no authentication)"
)

SCREENSHOT_OPTIONS = ("frame", "layout", "size", "timeout", "chromium")  # given without --screenshot: refused
_RRD_MAGIC = b"RRF"  # an .rrd (or .rbl) file starts with RRF and a format digit


#: What ``--layout`` shows, for the help (``ar_anchor.viz.screenshot.LAYOUT_NAMES`` builds them; not imported
#: here: ``--help`` loads no viewer code).
LAYOUTS = {
    "full": "the run's own layout: the AR overlay, the 3D scene, the plots and the events",
    "overlay": "the AR overlay view alone: the camera image with the 3D world projected onto it",
    "camera": "the camera view alone: the image and its 2D detections",
    "3d": "the 3D scene alone",
}


def port_number(text: str) -> int:
    """An argparse type: a TCP port, 1-65535 (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port in 0-65535 (0: a free one), got {port}")
    return port


def bind_address(text: str) -> str:
    """An argparse type: an IP address to listen on (``localhost`` allowed)."""
    import ipaddress

    if text == "localhost":
        return "127.0.0.1"
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an IP address such as 127.0.0.1, got {text!r}") from None


def add_parser(commands: Any) -> None:
    """The ``view`` command's options."""
    view = add_command(
        commands,
        "view",
        "open recordings in the rerun viewer: a window, or --web in a browser (headless machines)",
        "Open RECORDING (.rrd files, or a run's output directory: its recording*.rrd parts) in the native "
        "rerun viewer, which needs a display, and wait until its window is closed. --web serves the web "
        "viewer on 127.0.0.1 instead and prints the URL to open; it serves until Ctrl-C. Over SSH, forward "
        "both ports it prints (e.g. ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876 HOST). --screenshot "
        "writes a PNG of the web viewer at one frame instead (headless Chromium, no display needed).",
    )
    view.add_argument(
        "recordings",
        nargs="+",
        metavar="RECORDING",
        help="a .rrd file (e.g. OUT/recording*.rrd: all parts of a long run) or a run's output directory",
    )
    view.add_argument(
        "--web",
        action="store_true",
        help="serve the web viewer for a browser instead of a window, on --bind (default 127.0.0.1). "
        + LOCAL_ONLY_RISK,
    )
    view.add_argument(
        "--port",
        type=port_number,
        default=None,
        help="--web: the web viewer's HTTP port, the one in the URL (default 9090, or a free one when taken)",
    )
    view.add_argument(
        "--grpc-port",
        type=port_number,
        default=None,
        help="the viewer's gRPC port, where the page reads the recordings (default 9876, or a free one when taken)",
    )
    view.add_argument(
        "--bind",
        type=bind_address,
        default="127.0.0.1",
        metavar="ADDRESS",
        help="address the viewer listens on (default 127.0.0.1: this machine's processes only, every user's: "
        "any of them can read the recordings and write entries into them). Any other address shows the "
        "recordings, unauthenticated, to whoever reaches it on the network",
    )
    _add_screenshot_options(view)
    view.set_defaults(func=cmd_view)


def _add_screenshot_options(view: Any) -> None:
    """``view``'s screenshot options, in a group of their own."""
    shot = view.add_argument_group(
        "screenshot",
        "a PNG of the web viewer showing the recording (every part of a split run) at one frame, taken in headless "
        "Chromium (apt install chromium); about a minute. Exit 2 when Chromium is missing or --frame is not in "
        "the recording, 1 when the viewer did not show that frame",
    )
    shot.add_argument("--screenshot", type=Path, metavar="OUT.png", help="write the screenshot to OUT.png and exit")
    shot.add_argument(
        "--frame",
        type=int,
        default=None,
        metavar="N",
        help="--screenshot: the frame to show (the `frame` timeline; default its middle)",
    )
    shot.add_argument(
        "--layout",
        choices=tuple(LAYOUTS),
        default=None,
        help="--screenshot: what the viewer shows: "
        + "; ".join(f"{name}: {what}" for name, what in LAYOUTS.items())
        + " (default full)",
    )
    shot.add_argument(
        "--size",
        type=window_size,
        default=None,
        metavar="WxH",
        help="--screenshot: the browser window in pixels (default 1600x900)",
    )
    shot.add_argument(
        "--timeout",
        type=float_in(1.0, 86400.0),
        default=None,
        metavar="S",
        help="--screenshot: seconds the viewer gets to load and show the frame (default 300)",
    )
    shot.add_argument(
        "--chromium", metavar="PATH", help="--screenshot: the Chromium binary (default: chromium on PATH)"
    )


def window_size(text: str) -> tuple[int, int]:
    """An argparse type: ``WIDTHxHEIGHT`` in pixels, each 200-8000."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1600x900, got {text!r}") from None
    if not (200 <= width <= 8000 and 200 <= height <= 8000):
        raise argparse.ArgumentTypeError(f"width and height must be 200-8000 pixels, got {text!r}")
    return width, height


def _part_number(path: Path) -> tuple[int, str]:
    """recording.rrd first, then recording.part2.rrd, part3, ... part10 (not as text sorts them)."""
    match = re.fullmatch(r"recording\.part(\d+)\.rrd", path.name)
    return (int(match.group(1)) if match else 1, path.name)


def recording_files(names: list[str]) -> list[Path]:
    """The files to open for ``names``: each an .rrd file, or a directory meaning its ``recording*.rrd``
    parts in order. InputError naming the first one that is missing, unreadable or not a recording."""
    files: list[Path] = []
    for name in names:
        path = Path(name)
        if path.is_dir():
            parts = sorted(path.glob("recording*.rrd"), key=_part_number)
            if not parts:
                made = " (the run was made with --no-recording)" if _made_without_recording(path) else ""
                raise InputError(f"{printable(name)}: no recording (recording*.rrd) in this directory{made}")
        else:
            parts = [path]
        for part in parts:
            _check_recording(part)
            if part not in files:
                files.append(part)
    return files


def _check_recording(path: Path) -> None:
    """InputError unless ``path`` is a readable regular file that starts as a recording does. Opened without
    blocking and typed before it is read: a named pipe (which would block ``open`` until a writer came, for
    ever), a socket or a device is refused by what it is."""
    import stat

    from ..sources.checks import file_kind

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise InputError(f"{printable(path)}: no such file") from None
    except OSError as err:
        raise InputError(f"{printable(path)}: cannot read ({err.strerror or err})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise InputError(f"{printable(path)}: is {file_kind(mode)}, not a rerun recording (.rrd)")
        head = os.read(fd, 4)
    except OSError as err:
        raise InputError(f"{printable(path)}: cannot read ({err.strerror or err})") from None
    finally:
        os.close(fd)
    if not head.startswith(_RRD_MAGIC):
        raise InputError(f"{printable(path)}: not a rerun recording (.rrd)")


def cmd_view(args: argparse.Namespace) -> int:
    """``ar-anchor view RECORDING...``: show the recordings until the window closes or Ctrl-C; the exit code."""
    from ..viz.viewer import is_loopback, open_native_viewer, serve_web_viewer, stop_process

    files = recording_files(args.recordings)
    if getattr(args, "screenshot", None) is not None:
        return screenshot(args, files)
    shot_options = [name for name in SCREENSHOT_OPTIONS if getattr(args, name, None) is not None]
    if shot_options:
        raise InputError(f"--{shot_options[0]} is --screenshot's: give --screenshot OUT.png too")
    if not is_loopback(args.bind):
        log.warning(
            "--bind %s: the viewer and the recordings are open to the network here, with no authentication",
            args.bind,
        )
    if not args.web:
        if args.port is not None:
            raise InputError("--port is the web viewer's: give --web too (the native viewer's port is --grpc-port)")
        process = open_native_viewer(files, bind=args.bind, port=args.grpc_port)
        try:
            status = process.wait()
        except KeyboardInterrupt:
            stop_process(process)
            print("ar-anchor: interrupted; viewer closed", file=sys.stderr)
            return EXIT_INTERRUPTED
        if status != 0:
            raise ArAnchorError(f"the rerun viewer exited with status {status} (-vv shows its output)")
        return EXIT_OK
    viewer = serve_web_viewer(files, bind=args.bind, web_port=args.port, grpc_port=args.grpc_port)
    try:
        print(f"view: open {viewer.url}", flush=True)
        if not args.quiet:
            print(f"view: serving {len(files)} recording(s) on {args.bind} until Ctrl-C", file=sys.stderr, flush=True)
        status = viewer.wait()
    except KeyboardInterrupt:
        print("ar-anchor: interrupted; web viewer stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        viewer.stop()
    raise ArAnchorError(f"the rerun web viewer exited on its own (status {status}; -vv shows its output)")


def screenshot(args: argparse.Namespace, files: list[Path]) -> int:
    """``view --screenshot OUT.png``: the web viewer showing ``files`` at ``--frame`` in ``--layout``, as a PNG."""
    from ..errors import OutputError
    from ..viz.screenshot import encode_png, require_chromium, take_screenshot

    if args.web:
        raise InputError("--screenshot and --web: give one (--screenshot takes its own viewer, closed after the shot)")
    out = args.screenshot
    if out.suffix.lower() != ".png":
        raise InputError(f"--screenshot {printable(out)}: the screenshot is a PNG: name it OUT.png")
    if out.is_dir():
        raise InputError(f"--screenshot {printable(out)}: is a directory: name the PNG to write")
    require_chromium(args.chromium)
    say = (lambda line: print(f"view: {line}", file=sys.stderr, flush=True)) if not args.quiet else None
    if say is not None:
        say(f"{len(files)} file(s): {', '.join(printable(f.name) for f in files)}; layout {args.layout or 'full'}")
    layout = args.layout or "full"
    shot = take_screenshot(
        files,
        frame=args.frame,
        layout=layout,
        size=args.size or (1600, 900),
        timeout_s=args.timeout or 300.0,
        chromium=args.chromium,
        say=say,
    )
    png = encode_png(shot.image)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(png)
    except OSError as err:
        raise OutputError(f"--screenshot {printable(out)}: cannot write ({err.strerror or err})") from None
    print(f"screenshot: {printable(out)} (frame {shot.frame} of {shot.frames[0]}..{shot.frames[1]}, {layout} layout)")
    return EXIT_OK


def serve_run(args: argparse.Namespace) -> int:
    """A run command with ``--serve``: a web viewer on 127.0.0.1 (its URL printed first) that the run
    streams to (as ``--connect`` to it), besides its files. After a run that ended by itself the viewer
    keeps serving the recording until Ctrl-C, and the exit code is the run's; a run that fails or is
    interrupted takes the viewer with it."""
    from ..viz.viewer import serve_web_viewer

    viewer = serve_web_viewer(web_port=args.serve_port, grpc_port=None, options=("--serve-port", "--serve"))
    try:
        print(f"{args.command}: watch the run at {viewer.url}", flush=True)
        args.connect = viewer.grpc_url
        code = int(args.func(args))
        print(
            f"{args.command}: the run ended; the web viewer keeps serving it at {viewer.url} until Ctrl-C",
            file=sys.stderr,
            flush=True,
        )
        try:
            viewer.wait()
        except KeyboardInterrupt:
            print("ar-anchor: web viewer stopped", file=sys.stderr)
            return code
        log.warning("the web viewer exited on its own")
        return code
    finally:
        viewer.stop()


def _made_without_recording(folder: Path) -> bool:
    """Does ``folder``'s ``summary.json`` say its run wrote no recording (``--no-recording``)?"""
    import json

    try:
        summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and summary.get("recording") is False
