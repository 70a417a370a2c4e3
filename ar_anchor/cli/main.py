"""``ar-anchor``: the command-line front. It parses options and wires source, tracker and outputs.

Exit codes: 0 success; 1 run-time failure (outputs written so far stay valid); 2 bad input or
usage (config, camera file, option); 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import ArAnchorError, InputError

__all__ = ["main"]

log = logging.getLogger("ar_anchor")

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


# ---------------------------------------------------------------------------- argument types


def _int_at_least(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


def _float_above(minimum: float, *, inclusive: bool):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and (value >= minimum if inclusive else value > minimum)):
            raise argparse.ArgumentTypeError(f"must be a number {'>=' if inclusive else '>'} {minimum:g}, got {text!r}")
        return value

    return parse


_positive_float = _float_above(0.0, inclusive=False)
_non_negative_float = _float_above(0.0, inclusive=True)


def _float_in(low: float, high: float):
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


def _viewer_url(text: str) -> str:
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


# ---------------------------------------------------------------------------- parser


def _add_common_options(parser: argparse.ArgumentParser, *, defaults: bool) -> None:
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


def _add_command(commands: Any, name: str, help_text: str, description: str) -> argparse.ArgumentParser:
    parser = commands.add_parser(name, help=help_text, description=description, allow_abbrev=False)
    _add_common_options(parser, defaults=False)
    return parser


def _add_run_options(parser: argparse.ArgumentParser, name: str, *, spawn: bool = True) -> None:
    """--max-frames, --out and (optionally) --spawn, shared by the commands that run the tracker."""
    parser.add_argument("--max-frames", type=_int_at_least(1), default=None, help="stop after N frames")
    parser.add_argument("--out", type=Path, default=None, help=f"output directory (default recordings/{name}-<time>/)")
    parser.add_argument(
        "--video-out",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the annotated video (overlays drawn) to FILE: .mp4/.mov/.mkv (H.264) or .avi (MJPG)",
    )
    parser.add_argument(
        "--no-overlay",
        action="store_true",
        help="do not draw overlays into the recording (faster); --video-out still does",
    )
    if spawn:
        parser.add_argument("--spawn", action="store_true", help="also stream to a rerun viewer it starts")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ar-anchor",
        description="Real-time fiducial-marker AR tracker (ArUco + IPPE + rerun).",
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"ar-anchor {__version__}")
    _add_common_options(parser, defaults=True)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    demo = _add_command(
        commands,
        "demo",
        "track a built-in synthetic scene with exact ground truth (no camera needed)",
        "Render a synthetic scene (lone markers and a 2x2 board, the camera sweeping from near "
        "to far), track it, and write poses.csv, summary.json and recording.rrd.",
    )
    demo.add_argument("--frames", type=_int_at_least(1), default=300, help="frames to render (default 300)")
    demo.add_argument("--seed", type=_int_at_least(0), default=0, help="seed of scene texture and noise (default 0)")
    demo.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera YAML to render with (default: configs/camera_synthetic.yml values)",
    )
    _add_tracker_options(demo)
    demo.add_argument(
        "--trajectory",
        choices=("sweep", "orbit", "static"),
        default="sweep",
        help="camera path (default sweep: near to far)",
    )
    demo.add_argument(
        "--near", type=_float_in(0.02, 100.0), default=0.35, help="nearest camera distance, metres (0.02-100)"
    )
    demo.add_argument(
        "--far", type=_float_in(0.02, 100.0), default=3.0, help="farthest camera distance, metres (0.02-100)"
    )
    demo.add_argument(
        "--noise", type=_float_in(0.0, 100.0), default=2.0, help="sensor noise sigma, grey levels (0-100)"
    )
    demo.add_argument("--blur", type=_float_in(0.0, 50.0), default=0.6, help="optical blur sigma, pixels (0-50)")
    _add_run_options(demo, "demo")
    demo.set_defaults(func=cmd_demo)

    replay = _add_command(
        commands,
        "replay",
        "track a video file, an image folder or a glob of images",
        "Track every frame of a video file (container timestamps), an image folder or a glob "
        "(natural order, --fps timestamps) and write poses.csv, summary.json and recording.rrd.",
    )
    replay.add_argument(
        "source", metavar="SOURCE", help="video file, image folder, or a quoted glob such as 'shots/*.png'"
    )
    replay.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera YAML (default: camera.yml beside SOURCE, as `live --record` writes it)",
    )
    _add_tracker_options(replay)
    replay.add_argument("--fps", type=_positive_float, default=30.0, help="frame rate of image folders (default 30)")
    _add_run_options(replay, "replay")
    replay.set_defaults(func=cmd_replay)

    live = _add_command(
        commands,
        "live",
        "track a V4L2 webcam (or --device synthetic) live; view it in rerun",
        "Track a live camera. The live view is the rerun viewer (--spawn, or --connect to a running "
        "one); outputs are written as the run goes and finalised on Ctrl-C.",
    )
    live.add_argument(
        "--device",
        default="/dev/video0",
        help="V4L2 device path or index, or 'synthetic' for the demo scene in real time (default /dev/video0)",
    )
    live.add_argument("--camera", type=Path, default=None, help="camera YAML (required for a real camera)")
    _add_tracker_options(live)
    live.add_argument("--width", type=_int_at_least(1), default=None, help="requested frame width")
    live.add_argument("--height", type=_int_at_least(1), default=None, help="requested frame height")
    live.add_argument("--fps", type=_positive_float, default=None, help="requested frame rate (synthetic: 30)")
    live.add_argument("--fourcc", default="MJPG", help="requested pixel format (default MJPG, when offered)")
    live.add_argument(
        "--queue",
        type=_int_at_least(1),
        default=1,
        help="frames waiting for the tracker at most; older ones are dropped (default 1: newest only)",
    )
    live.add_argument(
        "--reconnect-s",
        type=_non_negative_float,
        default=5.0,
        help="keep trying to reopen a vanished device this long (default 5 s)",
    )
    live.add_argument(
        "--stall-s",
        type=_positive_float,
        default=10.0,
        help="end the run when no frame arrives for this long (default 10 s)",
    )
    live.add_argument("--seed", type=_int_at_least(0), default=0, help="synthetic device: scene seed")
    live.add_argument(
        "--record",
        action="store_true",
        help="also save the processed frames losslessly (raw.mkv + timestamps) for frame-exact replay",
    )
    _add_run_options(live, "live", spawn=False)
    viewer = live.add_mutually_exclusive_group()
    viewer.add_argument("--spawn", action="store_true", help="start a rerun viewer and stream to it")
    viewer.add_argument(
        "--connect",
        metavar="URL",
        type=_viewer_url,
        default=None,
        help="stream to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy",
    )
    live.set_defaults(func=cmd_live)

    bench = _add_command(
        commands,
        "bench",
        "benchmarks on synthetic ground truth (and real video without it: real)",
        "stability: raw per-frame IPPE vs. the tracker over a grid of synthetic scenarios "
        "(flips, errors, jitter, lag, time to commit), written as markdown and JSON.",
    )
    bench.add_argument(
        "name",
        choices=("stability", "boards", "overlay", "speed", "run", "real"),
        help="stability: raw vs tracker; boards: lone marker vs a board; overlay: drawing cost vs triangles; "
        "speed: per-stage times and accuracy of the tracker (full frame, ROI) vs a plain OpenCV loop; "
        "run: ar-anchor replay fps, live latency and memory over a long live run, at 1080p; "
        "real: relative-pose consistency of markers on one rigid sheet in a real video (tracker, its raw "
        "per-frame pick, plain OpenCV), default chessboard.avi from $AR_ANCHOR_REALDATA",
    )
    bench.add_argument("--video", type=Path, default=None, help="real: the video (default: chessboard.avi)")
    bench.add_argument(
        "--camera", type=Path, default=None, help="real: its calibration (default: camera.yml or intrinsics.yml by it)"
    )
    bench.add_argument("--dictionary", default=None, help="real: override [detector] dictionary")
    bench.add_argument(
        "--marker-length", type=_positive_float, default=None, help="real: override [markers] length_m (metres)"
    )
    bench.add_argument(
        "--layout", type=Path, default=None, help="real: printed marker map (ArUco YAML or TOML): also score vs. it"
    )
    bench.add_argument("--quick", action="store_true", help="half the scenarios, shorter clips")
    bench.add_argument(
        "--minutes",
        type=_non_negative_float,
        default=None,
        help="run: length of the live run whose memory is watched (default 10; 0: skip; --quick: 0)",
    )
    bench.add_argument("--config", type=Path, default=None, help="tracker TOML (default: configs/default.toml values)")
    bench.add_argument(
        "--out", type=Path, default=Path("bench") / "results", help="output directory (default bench/results)"
    )
    bench.set_defaults(func=cmd_bench)

    markers = _add_command(
        commands,
        "markers",
        "printable marker sheets (PDF, SVG, PNG) at exact size, with the matching tracker config",
        "Single markers (--ids), grid boards (--board grid) or ChArUco boards (--board charuco) as PDF "
        "(exact physical size, scale ruler, cut marks, caption), SVG or PNG at --dpi; a TOML snippet "
        "beside each sheet configures the tracker for exactly what was printed.",
    )
    markers.add_argument("--dictionary", default="DICT_4X4_50", help="cv2.aruco dictionary (default DICT_4X4_50)")
    markers.add_argument("--ids", default=None, help="single markers: ids, e.g. 0-3 or 0,5,7 or 0-3,9")
    markers.add_argument("--size-mm", type=_positive_float, default=None, help="marker side in mm (the black square)")
    markers.add_argument("--board", choices=("grid", "charuco"), default=None, help="print a board instead")
    markers.add_argument("--cols", type=_int_at_least(1), default=None, help="board: markers (grid) or squares across")
    markers.add_argument("--rows", type=_int_at_least(1), default=None, help="board: markers (grid) or squares down")
    markers.add_argument("--gap-mm", type=_positive_float, default=None, help="grid: gap between markers in mm")
    markers.add_argument("--square-mm", type=_positive_float, default=None, help="charuco: chessboard square in mm")
    markers.add_argument("--first-id", type=_int_at_least(0), default=0, help="board: id of its first marker")
    markers.add_argument("--legacy", action="store_true", help="charuco: the legacy (pre-4.6) pattern")
    markers.add_argument("--name", default=None, help="board name in the config snippet (default: grid/charuco)")
    markers.add_argument("--format", choices=("pdf", "svg", "png"), default="pdf", help="output format (default pdf)")
    markers.add_argument("--dpi", type=_int_at_least(50), default=300, help="png: dots per inch (default 300)")
    markers.add_argument("--paper", choices=("a4", "letter"), default="a4", help="pdf/svg page size (default a4)")
    markers.add_argument("--out", type=Path, default=Path("markers"), help="output directory (default markers/)")
    markers.set_defaults(func=cmd_markers)

    calibrate = _add_command(
        commands,
        "calibrate",
        "calibrate a camera from ChArUco views (image folder, video, or a live device)",
        "Detect a ChArUco board in SOURCE (a folder or glob of images, a video file, or a device such as "
        "/dev/video0), keep sharp and distinct views, calibrate, drop outlier views, report per-view "
        "error and image coverage, and write the OpenCV YAML camera file every other command reads.",
    )
    calibrate.add_argument("source", metavar="SOURCE", help="image folder or glob, video file, or device")
    calibrate.add_argument("--charuco", required=True, metavar="CxR", help="board squares across x down, e.g. 5x7")
    calibrate.add_argument("--square-m", type=_positive_float, required=True, help="chessboard square side, metres")
    calibrate.add_argument("--marker-m", type=_positive_float, required=True, help="marker side, metres")
    calibrate.add_argument("--dictionary", required=True, help="cv2.aruco dictionary of the board's markers")
    calibrate.add_argument("--legacy", action="store_true", help="the board uses the legacy (pre-4.6) pattern")
    calibrate.add_argument("--out", type=Path, required=True, help="camera YAML file to write")
    calibrate.add_argument("--max-views", type=_int_at_least(3), default=40, help="views used at most (default 40)")
    calibrate.add_argument("--min-views", type=_int_at_least(3), default=6, help="views needed at least (default 6)")
    calibrate.add_argument(
        "--rrd", type=Path, default=None, help="rerun recording of the calibration (default: beside --out)"
    )
    calibrate.add_argument("--spawn", action="store_true", help="also stream to a rerun viewer it starts")
    calibrate.add_argument("--fps", type=_positive_float, default=None, help="device: frames per second to ask for")
    calibrate.add_argument("--width", type=_int_at_least(1), default=None, help="device: frame width to ask for")
    calibrate.add_argument("--height", type=_int_at_least(1), default=None, help="device: frame height to ask for")
    calibrate.add_argument(
        "--duration-s", type=_positive_float, default=60.0, help="device: stop capturing after this long (default 60)"
    )
    calibrate.set_defaults(func=cmd_calibrate)
    study = _add_command(
        commands,
        "study",
        "reproduce the PnP textbook's experiments: outliers, ransac, jitter",
        "Each study writes NAME.png, NAME.md, NAME.json and NAME.rrd to --out (default recordings/study/).",
    )
    from ..tools.study.options import configure_parser as configure_study

    configure_study(study)
    study.set_defaults(func=cmd_study)
    return parser


def _add_tracker_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="tracker TOML (default: configs/default.toml values: lone markers, no boards; "
        "demo and live --device synthetic: configs/demo.toml)",
    )
    parser.add_argument("--dictionary", default=None, help="override [detector] dictionary, e.g. DICT_ARUCO_ORIGINAL")
    parser.add_argument(
        "--marker-length", type=_positive_float, default=None, help="override [markers] length_m: marker side in metres"
    )
    parser.add_argument(
        "--no-filter",
        action="store_true",
        help="the raw per-frame pipeline: lower-error IPPE solution, no flip resolution or smoothing",
    )


# ---------------------------------------------------------------------------- commands


def _default_out(name: str) -> Path:
    return Path("recordings") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


class _Progress:
    """A tqdm bar on a terminal (frames, fps, ETA), nothing otherwise."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(desc=desc, unit="frame", leave=False, dynamic_ncols=True)

    def __call__(self, done: int, total: int | None, _result: object = None) -> None:
        if self.bar is None:
            return
        if total is not None and self.bar.total != total:
            self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class _LiveStatus:
    """One status line for live runs, rewritten about twice a second on a terminal."""

    def __init__(self, enabled: bool, stats: Any) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.stats = stats
        self.start = time.monotonic()
        self.last = 0.0
        self.latency_ms = 0.0

    def __call__(self, done: int, _total: int | None, result: Any = None) -> None:
        if result is not None and result.latency_ms:
            self.latency_ms = (
                0.9 * self.latency_ms + 0.1 * sum(result.latency_ms.values())
                if done > 1
                else sum(result.latency_ms.values())
            )
        now = time.monotonic()
        if not self.enabled or now - self.last < 0.5:
            return
        self.last = now
        elapsed = now - self.start
        counts = self.stats.as_dict()
        tracked = 0 if result is None else sum(1 for t in result.targets.values() if t.measured)
        sys.stderr.write(
            f"\rlive {elapsed:6.1f} s | {done} frames, {done / max(elapsed, 1e-9):5.1f} fps | "
            f"dropped {counts['dropped_queue']} | targets {tracked} | tracker {self.latency_ms:5.1f} ms   "
        )
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def _load_tracker_config(args: argparse.Namespace, *, demo: bool = False):  # noqa: ANN202
    """``--config`` (or the built-in defaults; ``demo``: the demo scene's) with the command-line overrides."""
    from ..config import load_config

    config = load_config(args.config, demo=demo)
    return config.with_overrides(
        dictionary=getattr(args, "dictionary", None),
        marker_length_m=getattr(args, "marker_length", None),
        filter_enabled=False if getattr(args, "no_filter", False) else None,
    )


def _camera_for_source(camera: Any, resolution: tuple[int, int], option: str) -> Any:
    from ..errors import CameraError

    try:
        return camera.scaled_to(*resolution)
    except CameraError as err:
        raise CameraError(f"{option}: {err}") from None


def _finish(args: argparse.Namespace, outputs: Any) -> int:
    if not args.quiet:
        print(format_summary(outputs.summary))
    files = "poses.csv, summary.json, recording.rrd" + (", raw.mkv" if outputs.raw_video else "")
    print(f"outputs: {outputs.out_dir}/ ({files})")
    video = outputs.summary.get("video_out")
    if video:
        print(f"annotated video: {video['path']} ({video['frames']} frames)")
    status = outputs.summary.get("status")
    return EXIT_OK if status == "completed" else EXIT_FAILURE


def cmd_demo(args: argparse.Namespace) -> int:
    from ..camera import CameraModel
    from ..errors import SourceError
    from ..run.loop import run_session
    from ..run.options import RunOptions
    from ..sources.synthetic import SyntheticSource
    from ..synthetic import Trajectory, demo_scene
    from ..track.tracker import Tracker

    config = _load_tracker_config(args, demo=True)
    camera = CameraModel.from_yaml(args.camera) if args.camera else CameraModel.default_synthetic()
    if args.trajectory == "sweep" and args.far < args.near:
        raise InputError(f"--far {args.far} must not be below --near {args.near}")
    trajectory = Trajectory(kind=args.trajectory, near_m=args.near, far_m=args.far, look_at=(-0.01, 0.0, 0.0))
    try:
        scene = demo_scene(
            config,
            camera,
            frames=args.frames,
            seed=args.seed,
            trajectory=trajectory,
            noise_sigma=args.noise,
            blur_sigma=args.blur,
        )
    except SourceError as err:
        raise SourceError(f"--camera {args.camera}: {err}") from None
    options = RunOptions(
        max_frames=args.max_frames,
        spawn=args.spawn,
        recording_name="ar_anchor demo",
        video_out=args.video_out,
        overlays=not args.no_overlay,
        extra_summary={"command": "demo", "seed": args.seed, "trajectory": args.trajectory},
    )
    progress = _Progress(not args.quiet, "demo")
    try:
        with SyntheticSource(scene) as source:
            outputs = run_session(
                source, Tracker(config, camera), args.out or _default_out("demo"), options, progress=progress
            )
    finally:
        progress.close()
    return _finish(args, outputs)


def _replay_camera(args: argparse.Namespace) -> Path:
    """``--camera``, or the ``camera.yml`` beside the source (as ``live --record`` leaves it)."""
    from ..errors import CameraError

    if args.camera is not None:
        return args.camera
    beside = Path(args.source).parent / "camera.yml"
    if not beside.is_file():
        raise CameraError(
            f"--camera FILE is required: the calibration of the camera that took {args.source} (none found at {beside})"
        )
    log.warning("using %s, found beside the source", beside)
    return beside


def cmd_replay(args: argparse.Namespace) -> int:
    from ..camera import CameraModel
    from ..run.loop import run_session
    from ..run.options import RunOptions
    from ..sources import open_source
    from ..track.tracker import Tracker

    config = _load_tracker_config(args)
    with open_source(args.source, live=False, fps=args.fps) as source:
        camera_path = _replay_camera(args)
        camera = _camera_for_source(CameraModel.from_yaml(camera_path), source.resolution, f"--camera {camera_path}")
        options = RunOptions(
            max_frames=args.max_frames,
            spawn=args.spawn,
            recording_name=f"ar_anchor replay {args.source}",
            video_out=args.video_out,
            overlays=not args.no_overlay,
            record_fps=source.info.fps or 30.0,
            extra_summary={"command": "replay", "source": str(args.source)},
        )
        progress = _Progress(not args.quiet, "replay")
        try:
            outputs = run_session(
                source,
                Tracker(config, camera),
                args.out or _default_out("replay"),
                options,
                progress=progress,
                summary_extras=lambda: {"source_ended_early": source.info.ended_early},
            )
        finally:
            progress.close()
    code = _finish(args, outputs)
    if source.info.ended_early:
        print(
            f"ar-anchor: error: {args.source}: the stream ended early (damaged or truncated file); outputs cover "
            f"the {outputs.summary['frames']} frames read before that",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    return code


def _synthetic_camera_scene(args: argparse.Namespace, config: Any) -> Any:
    """What ``live --device synthetic`` shows: the demo scene through ``--camera`` (default the synthetic
    camera) at ``--width``/``--height``, at ``--fps`` (default 30)."""
    from ..camera import CameraModel
    from ..errors import CameraError, SourceError
    from ..sources.live import CLIP_FRAMES
    from ..sources.open import live_demo_scene

    camera = CameraModel.from_yaml(args.camera) if args.camera else CameraModel.default_synthetic()
    if args.width or args.height:
        size = (args.width or camera.width, args.height or camera.height)
        try:
            camera = camera.scaled_to(*size, warn=False)  # the size asked for: no warning
        except CameraError as err:
            raise CameraError(f"--width/--height: {err}") from None
    try:
        scene = live_demo_scene(config, camera, fps=args.fps or 30.0, seed=args.seed)
    except SourceError as err:
        raise SourceError(f"--camera {args.camera}: {err}") from None
    if not args.quiet:
        count = min(CLIP_FRAMES, scene.frames)
        print(f"live: rendering the synthetic camera's {count} frames ...", file=sys.stderr, flush=True)
    return scene


def _print_live_counts(stats: dict[str, Any]) -> None:
    print(
        f"live: {stats['captured']} frames captured, {stats['delivered']} tracked, {stats['dropped_queue']} "
        f"dropped (tracker busy), {stats['dropped_non_monotonic']} dropped (timestamps)"
        + (f"; ended: {stats['ended_because']}" if stats["ended_because"] else "")
    )


def cmd_live(args: argparse.Namespace) -> int:
    from ..camera import CameraModel
    from ..errors import CameraError
    from ..run.loop import run_session
    from ..run.options import RunOptions
    from ..sources.open import SYNTHETIC, DeviceSettings, open_source
    from ..track.tracker import Tracker

    config = _load_tracker_config(args, demo=args.device == SYNTHETIC)
    scene = _synthetic_camera_scene(args, config) if args.device == SYNTHETIC else None
    device = DeviceSettings(
        width=args.width,
        height=args.height,
        fourcc=args.fourcc,
        queue_size=args.queue,
        reconnect_s=args.reconnect_s,
        stall_s=args.stall_s,
    )
    source = open_source(args.device, live=True, fps=args.fps, device=device, scene=scene)
    try:
        if args.camera is None and source.camera is None:
            raise CameraError("--camera FILE is required for a real camera (its calibration: see the README)")
        camera_file = CameraModel.from_yaml(args.camera) if args.camera else source.camera
        camera = _camera_for_source(camera_file, source.resolution, f"--camera {args.camera}")
        out_dir = args.out or _default_out("live")
        options = RunOptions(
            max_frames=args.max_frames,
            spawn=args.spawn,
            connect=args.connect,
            recording_name=f"ar_anchor live {args.device}",
            record_raw=args.record,
            record_fps=source.info.fps or 30.0,
            video_out=args.video_out,
            overlays=not args.no_overlay,
            extra_summary={"command": "live", "device": str(args.device), "granted": dict(source.grabber.granted)},
            output_queue=3,  # live: a late logger skips frames rather than holding many (6 MB each at 1080p)
        )
        if args.record:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            camera.to_yaml(Path(out_dir) / "camera.yml")  # so `ar-anchor replay OUT/raw.mkv` finds it
        status = _LiveStatus(not args.quiet, source.stats)
        try:
            with source:
                outputs = run_session(
                    source,
                    Tracker(config, camera),
                    out_dir,
                    options,
                    progress=status,
                    summary_extras=lambda: {"live": source.stats.as_dict()},
                )
        finally:
            status.close()
    finally:
        source.close()
    if not args.quiet:
        _print_live_counts(source.stats.as_dict())
    return _finish(args, outputs)


def cmd_bench(args: argparse.Namespace) -> int:
    from ..bench.boards import write_board_report
    from ..bench.overlay import write_overlay_report
    from ..bench.stability import write_stability_report
    from ..config import load_config
    from ..run.outputs import prepare_out_dir

    config = load_config(args.config)
    real = None
    if args.name == "real":  # its data files are checked (exit 2) before anything is written
        from ..bench.real import real_inputs

        real = real_inputs(args.video, args.camera, args.dictionary, args.marker_length, args.layout)
    prepare_out_dir(args.out)  # before minutes of work, not after
    command = f"ar-anchor bench {args.name}" + (" --quick" if args.quick else "")

    def progress(i: int, total: int, name: str) -> None:
        if not args.quiet:
            print(f"[{i + 1}/{total}] {name}", file=sys.stderr, flush=True)

    if real is not None:
        from ..bench.real import real_summary, write_real_report

        for option in ("video", "camera", "dictionary", "marker_length", "layout", "config"):
            if getattr(args, option) is not None:
                command += f" --{option.replace('_', '-')} {getattr(args, option)}"
        config = _load_tracker_config(  # as ar-anchor replay builds it
            argparse.Namespace(config=args.config, dictionary=real.dictionary, marker_length=real.marker_length_m)
        )

        video_name = real.video.name

        def frames(done: int, total: int | None) -> None:
            if done % 50 == 0 or done == total:
                progress(done - 1, total or done, f"frames of {video_name}")

        print(real_summary(write_real_report(args.out, real, config, command=command, progress=frames)))
    elif args.name == "run":
        from ..bench.run import write_run_report

        if args.minutes is not None:
            command += f" --minutes {args.minutes:g}"
        write_run_report(args.out, quick=args.quick, minutes=args.minutes, progress=progress, command=command)
    elif args.name == "speed":
        from ..bench.speed import write_speed_report

        write_speed_report(args.out, quick=args.quick, progress=progress, command=command)
    elif args.name == "overlay":
        write_overlay_report(args.out, frames=30 if args.quick else 60, progress=progress, command=command)
    elif args.name == "boards":
        frames = 60 if args.quick else 150
        write_board_report(args.out, config=config, frames=frames, progress=progress, command=command)
    else:
        write_stability_report(args.out, quick=args.quick, config=config, progress=progress, command=command)
    print(f"results: {args.out / (args.name + '.md')} and {args.out / (args.name + '.json')}")
    return EXIT_OK


def cmd_study(args: argparse.Namespace) -> int:
    from ..tools.study.command import run_study

    return run_study(args)


def cmd_markers(args: argparse.Namespace) -> int:
    from ..tools.markers import run_markers

    return run_markers(args)


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ..tools.calibrate import run_calibrate

    return run_calibrate(args)


def format_summary(summary: dict[str, Any]) -> str:
    """The run's summary as a small fixed-width table."""
    fps = summary.get("fps")
    lines = [
        f"{summary['frames']} frames in {summary['wall_time_s']:.1f} s ({fps:.1f} fps)"
        if fps
        else f"{summary['frames']} frames",
        f"markers found in {summary['frames_with_markers']} of {summary['frames']} frames, "
        f"a pose in {summary['frames_with_pose']}",
    ]
    truth = summary.get("ground_truth")
    header = f"{'target':<12} {'detected':>9} {'tracked/ambig/pred':>18}"
    if truth:
        header += f" {'in view':>8} {'rate':>6} {'rot med/p95 deg':>17} {'trans med/p95 %':>17}"
    lines.append(header)
    lines.append("-" * len(header))
    for name, entry in summary["targets"].items():
        states = entry.get("states", {})
        state_text = f"{states.get('tracked', 0)}/{states.get('ambiguous', 0)}/{states.get('predicted', 0)}"
        row = f"{name:<12} {entry['frames_measured']:>9} {state_text:>18}"
        if truth:
            rate = entry.get("detection_rate_in_view")
            rot, trans = entry["rotation_error_deg"], entry["translation_error_pct"]

            def pair(d: dict[str, float | None]) -> str:
                return "-" if d["median"] is None else f"{d['median']:.2f} / {d['p95']:.2f}"

            row += f" {entry['frames_in_view']:>8} {'-' if rate is None else f'{100 * rate:.0f}%':>6}"
            row += f" {pair(rot):>17} {pair(trans):>17}"
        lines.append(row)
    return "\n".join(lines)


# ---------------------------------------------------------------------------- entry point


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("ar-anchor: %(levelname)s: %(message)s"))
    root = logging.getLogger("ar_anchor")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _interrupt_on_sigterm() -> None:
    """SIGTERM ends a run like Ctrl-C: outputs are closed and stay valid."""

    def handler(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (embedded use): leave signals alone
        pass


def _steady_malloc() -> None:
    """glibc: allocations of 1 MiB and more always come from (and go back to) the system.

    By default glibc raises that threshold as large blocks are freed, after which whole video frames
    (6 MB at 1080p), allocated and freed from three threads, are carved from its heaps, which then
    fragment: a long live run's memory creeps up. A fixed threshold keeps it flat. Nothing elsewhere.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD (fixing it also stops the dynamic adjustment)
    except (OSError, AttributeError):  # not glibc (e.g. musl): its allocator, its behaviour
        pass


def _quiet_opencv(verbosity: int) -> None:
    """OpenCV, FFmpeg and rerun print their own warnings to stderr; ours say what matters, in one line.
    Theirs show with -vv."""
    if verbosity >= 2:
        return
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET, read when a capture opens
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    # rerun's own (Rust) log lines, e.g. a file sink that hit a full disk: the error we raise names the file
    os.environ.setdefault("RUST_LOG", "off")
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def main(argv: Sequence[str] | None = None) -> int:
    _interrupt_on_sigterm()
    _steady_malloc()
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    _quiet_opencv(args.verbose)
    try:
        return int(args.func(args))
    except InputError as err:
        print(f"ar-anchor: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except ArAnchorError as err:
        print(f"ar-anchor: error: {err}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print("ar-anchor: interrupted; outputs written so far are complete", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as err:  # a bug: say so in one line, show the traceback only when asked
        log.debug("internal error", exc_info=True)
        print(
            f"ar-anchor: internal error: {type(err).__name__}: {err} (rerun with -vv for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
