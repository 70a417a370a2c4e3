"""``ar-anchor``: the command-line front. It parses options and wires source, tracker and outputs.

Exit codes: 0 success; 1 run-time failure (outputs written so far stay valid); 2 bad input or
usage (config, camera file, option); 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from . import __version__
from .errors import ArAnchorError, InputError

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


# ---------------------------------------------------------------------------- parser


def _add_common_options(parser: argparse.ArgumentParser, *, defaults: bool) -> None:
    """-v / -q, accepted before and after the command name (the command's copy sets no default,
    so ``ar-anchor -q demo`` is not undone by the subparser)."""
    parser.add_argument("-v", "--verbose", action="count", default=0 if defaults else argparse.SUPPRESS,
                        help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=False if defaults else argparse.SUPPRESS,
                        help="no progress bar or summary table")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ar-anchor",
        description="Real-time fiducial-marker AR tracker (ArUco + IPPE + rerun).",
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"ar-anchor {__version__}")
    _add_common_options(parser, defaults=True)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    demo = commands.add_parser(
        "demo",
        help="track a built-in synthetic scene with exact ground truth (no camera needed)",
        description="Render a synthetic scene (lone markers and a 2x2 board, the camera sweeping from near "
        "to far), track it, and write poses.csv, summary.json and recording.rrd.",
        allow_abbrev=False,
    )
    _add_common_options(demo, defaults=False)
    demo.add_argument("--frames", type=_int_at_least(1), default=300, help="frames to render (default 300)")
    demo.add_argument("--max-frames", type=_int_at_least(1), default=None, help="stop after N frames")
    demo.add_argument("--seed", type=_int_at_least(0), default=0, help="seed of scene texture and noise (default 0)")
    demo.add_argument("--config", type=Path, default=None, help="tracker TOML (default: configs/default.toml values)")
    demo.add_argument("--camera", type=Path, default=None,
                      help="camera YAML to render with (default: configs/camera_synthetic.yml values)")
    demo.add_argument("--trajectory", choices=("sweep", "orbit", "static"), default="sweep",
                      help="camera path (default sweep: near to far)")
    demo.add_argument("--near", type=_positive_float, default=0.35, help="nearest camera distance, metres")
    demo.add_argument("--far", type=_positive_float, default=3.0, help="farthest camera distance, metres")
    demo.add_argument("--noise", type=_non_negative_float, default=2.0, help="sensor noise sigma, grey levels")
    demo.add_argument("--blur", type=_non_negative_float, default=0.6, help="optical blur sigma, pixels")
    demo.add_argument("--out", type=Path, default=None, help="output directory (default recordings/demo-<time>/)")
    demo.add_argument("--spawn", action="store_true", help="also stream to a rerun viewer it starts")
    demo.set_defaults(func=cmd_demo)
    return parser


# ---------------------------------------------------------------------------- commands


def _default_out(name: str) -> Path:
    return Path("recordings") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


class _Progress:
    """A tqdm bar on a terminal, nothing otherwise."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(desc=desc, unit="frame", leave=False, dynamic_ncols=True)

    def __call__(self, done: int, total: int | None) -> None:
        if self.bar is None:
            return
        if total is not None and self.bar.total != total:
            self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def cmd_demo(args: argparse.Namespace) -> int:
    from .camera import CameraModel
    from .config import load_config
    from .errors import SourceError
    from .session import run_session
    from .sources.synthetic import SyntheticSource, Trajectory, demo_scene
    from .tracker import Tracker

    config = load_config(args.config)
    camera = CameraModel.from_yaml(args.camera) if args.camera else CameraModel.default_synthetic()
    if args.trajectory == "sweep" and args.far < args.near:
        raise InputError(f"--far {args.far} must not be below --near {args.near}")
    trajectory = Trajectory(kind=args.trajectory, near_m=args.near, far_m=args.far, look_at=(-0.01, 0.0, 0.0))
    try:
        scene = demo_scene(config, camera, frames=args.frames, seed=args.seed, trajectory=trajectory,
                           noise_sigma=args.noise, blur_sigma=args.blur)
    except SourceError as err:
        raise SourceError(f"--camera {args.camera}: {err}") from None
    out_dir = args.out or _default_out("demo")
    progress = _Progress(not args.quiet, "demo")
    try:
        with SyntheticSource(scene) as source:
            outputs = run_session(source, Tracker(config, camera), out_dir, max_frames=args.max_frames,
                                  spawn=args.spawn, recording_name="ar_anchor demo", progress=progress,
                                  extra_summary={"command": "demo", "seed": args.seed, "trajectory": args.trajectory})
    finally:
        progress.close()
    if not args.quiet:
        print(format_summary(outputs.summary))
    print(f"outputs: {outputs.out_dir}/ (poses.csv, summary.json, recording.rrd)")
    return EXIT_OK


def format_summary(summary: dict[str, Any]) -> str:
    """The run's summary as a small fixed-width table."""
    fps = summary.get("fps")
    lines = [f"{summary['frames']} frames in {summary['wall_time_s']:.1f} s ({fps:.1f} fps)" if fps else
             f"{summary['frames']} frames"]
    truth = summary.get("ground_truth")
    header = f"{'target':<12} {'detected':>9}"
    if truth:
        header += f" {'in view':>8} {'rate':>6} {'rot med/p95 deg':>17} {'trans med/p95 %':>17}"
    lines.append(header)
    lines.append("-" * len(header))
    for name, entry in summary["targets"].items():
        row = f"{name:<12} {entry['frames_measured']:>9}"
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


def main(argv: Sequence[str] | None = None) -> int:
    _interrupt_on_sigterm()
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
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
        print(f"ar-anchor: internal error: {type(err).__name__}: {err} (rerun with -vv for the traceback)",
              file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
