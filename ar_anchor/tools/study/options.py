"""The ``study`` command line: its arguments (:func:`configure_parser`), checked, turned into each
study's setup and settings, and the command line that reproduces a run."""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...errors import CameraError, InputError
from ...units import length_option
from .files import DEFAULT_OUT

if TYPE_CHECKING:  # imported where used: the parser (`ar-anchor --help`) must not load OpenCV and numpy
    from ...camera import CameraModel
    from .jitter import JitterSetup
    from .pnp import PnPSetup

__all__ = [
    "DEFAULT_OUT",
    "FULL",
    "QUICK",
    "STUDIES",
    "Defaults",
    "camera_from_args",
    "check",
    "command_line",
    "configure_parser",
    "jitter_setup",
    "outliers_settings",
    "pnp_setup",
    "ransac_settings",
]

STUDIES = ("outliers", "ransac", "jitter")


def _float_list(text: str, option: str, *, lengths: bool = False) -> list[float]:
    """Numbers separated by commas; ``lengths``: each a length (``30cm``, ``1m``; bare: metres) in metres."""
    from ...units import LENGTH_FORMS, parse_length
    from .limits import MAX_VALUES

    parse = parse_length if lengths else float
    what = f"lengths such as {LENGTH_FORMS} (bare numbers are metres)" if lengths else "numbers"

    try:
        values = [parse(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option}: expected {what} separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(f"{option}: expected numbers separated by commas, got {text!r}")
    if len(values) > MAX_VALUES:
        raise InputError(f"{option}: at most {MAX_VALUES} values, got {len(values)}")
    return values


@dataclass(frozen=True)
class Defaults:
    """The defaults of ``--seeds``, ``--contaminations``, ``--frames`` and ``--distances`` (full run or ``--quick``)."""

    seeds_outliers: int
    seeds_ransac: int
    contaminations: str
    frames: int
    distances: str


FULL = Defaults(100, 50, "0,10,20,30,40,50,60,70,80,90", 300, "0.3,0.5,0.75,1,1.5,2,2.5,3")
QUICK = Defaults(12, 6, "0,20,40,60", 60, "0.3,1,3")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``study`` command's arguments to ``parser``."""
    parser.add_argument(
        "name",
        choices=(*STUDIES, "all"),
        help="outliers: solvePnP vs RANSAC + LM; ransac: threshold x contamination heatmap; "
        "jitter: pose noise vs distance, marker and board, raw and tracked; all: the three",
    )
    parser.add_argument("--out", metavar="DIR", help=f"output directory (default {DEFAULT_OUT}/)")
    parser.add_argument("--quick", action="store_true", help="few seeds, frames and distances (a smoke run)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="first seed (default 0)")
    parser.add_argument(
        "--camera",
        type=Path,
        metavar="FILE",
        help="camera YAML to use (default: 1920x1080 fx 1480 for outliers/ransac, 1280x720 fx 1000 for jitter)",
    )
    pnp = parser.add_argument_group("outliers and ransac")
    pnp.add_argument("--seeds", type=int, metavar="N", help="problems per result (default 100 outliers, 50 ransac)")
    pnp.add_argument("--points", type=int, default=120, metavar="N", help="correspondences per problem (default 120)")
    pnp.add_argument("--pixel-noise", type=float, default=0.5, metavar="PX", help="noise sigma per coordinate (0.5)")
    pnp.add_argument("--contamination", type=float, default=25.0, metavar="PCT", help="outliers: %% replaced (25)")
    pnp.add_argument("--threshold", type=float, default=2.0, metavar="PX", help="RANSAC inlier threshold (2)")
    pnp.add_argument("--iterations", type=int, default=300, metavar="N", help="RANSAC iterations (default 300)")
    pnp.add_argument(
        "--thresholds", default="0.5,1,2,4,8,16", metavar="PX,...", help="ransac: thresholds (0.5,1,2,4,8,16)"
    )
    pnp.add_argument(
        "--contaminations", metavar="PCT,...", help=f"ransac: contaminations in %% ({FULL.contaminations})"
    )
    jitter = parser.add_argument_group("jitter")
    jitter.add_argument("--frames", type=int, metavar="N", help=f"frames per distance (default {FULL.frames})")
    jitter.add_argument(
        "--distances", metavar="M,...", help=f"distances, e.g. 30cm,1m (a bare number is metres; {FULL.distances})"
    )
    jitter.add_argument(
        "--marker-m",
        "--marker-length",
        dest="marker_m",
        type=length_option("m", low=-math.inf),
        default=0.05,
        metavar="LENGTH",
        help="marker side, e.g. 5cm (a bare number is metres; 0.05)",
    )
    jitter.add_argument("--tilt-deg", type=float, default=10.0, metavar="DEG", help="view angle off the normal (10)")
    jitter.add_argument("--sensor-noise", type=float, default=2.0, metavar="GREY", help="noise sigma, grey levels (2)")
    jitter.add_argument("--blur", type=float, default=0.6, metavar="PX", help="optical blur sigma, px (0.6)")
    jitter.add_argument("--config", type=Path, metavar="FILE", help="tracker TOML (default: configs/default.toml)")
    jitter.add_argument(
        "--roi",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="ROI tracking on or off (default: as the tracker config says; on in the default config)",
    )


def check(condition: bool, message: str) -> None:
    """An :class:`InputError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise InputError(message)


def pnp_setup(args: argparse.Namespace, camera: CameraModel | None) -> PnPSetup:
    """The outliers/ransac problem from the options, checked."""
    from .limits import in_range
    from .pnp import PnPSetup

    in_range("--points", args.points)
    in_range("--pixel-noise", args.pixel_noise)
    in_range("--iterations", args.iterations)
    in_range("--threshold", args.threshold)
    setup = PnPSetup(points=args.points, noise_px=args.pixel_noise, iterations=args.iterations)
    return setup if camera is None else dataclasses.replace(setup, camera=camera)


def camera_from_args(args: argparse.Namespace, study: str) -> CameraModel | None:
    """The ``--camera`` file's model, checked for the ``study`` (``jitter`` or ``pnp``), or None (each
    study's own default camera)."""
    from ...camera import CameraModel
    from .limits import check_camera

    if args.camera is None:
        return None
    try:
        camera = CameraModel.from_yaml(args.camera)
    except CameraError as err:
        raise CameraError(f"--camera: {err}") from None
    check_camera(camera, args.camera, study)
    return camera


def outliers_settings(args: argparse.Namespace, defaults: Defaults, setup: PnPSetup) -> dict[str, Any]:
    """:func:`~.pnp.run_outliers`'s keyword arguments from the options, checked."""
    contamination = _contamination(args.contamination, "--contamination", setup.points)
    return {
        "seeds": _seeds(args, defaults.seeds_outliers),
        "contamination": contamination,
        "threshold_px": args.threshold,
        "first_seed": args.seed,
    }


def ransac_settings(args: argparse.Namespace, defaults: Defaults, setup: PnPSetup) -> dict[str, Any]:
    """:func:`~.pnp.run_ransac`'s keyword arguments from the options, checked (the ``--threshold`` is
    always among the thresholds)."""
    from .limits import in_range

    thresholds = sorted(set(_float_list(args.thresholds, "--thresholds")) | {args.threshold})
    for threshold in thresholds:
        in_range("--thresholds", threshold, what="must all be")
    text = defaults.contaminations if args.contaminations is None else args.contaminations
    contaminations = [
        _contamination(c, "--contaminations", setup.points) for c in sorted(set(_float_list(text, "--contaminations")))
    ]
    return {
        "seeds": _seeds(args, defaults.seeds_ransac),
        "contaminations": contaminations,
        "thresholds_px": thresholds,
        "default_threshold_px": args.threshold,
        "first_seed": args.seed,
    }


def _contamination(percent: float, option: str, points: int) -> float:
    check(0.0 <= percent < 100.0, f"{option}: percentages must be in [0, 100), got {percent:g}")
    honest = points - int(round(percent / 100.0 * points))
    check(honest >= 6, f"{option}: {percent:g} % of {points} points leaves {honest} honest points; 6 are needed")
    return percent / 100.0


def _seeds(args: argparse.Namespace, default: int) -> int:
    from .limits import in_range

    seeds = default if args.seeds is None else args.seeds
    in_range("--seeds", seeds)
    return seeds


def jitter_setup(args: argparse.Namespace, defaults: Defaults, camera: CameraModel | None) -> JitterSetup:
    """The jitter scene and tracker config from the options, checked."""
    from ...config import load_config
    from .jitter import SETTLE_FRAMES, JitterSetup
    from .limits import check_distances, in_range

    frames = defaults.frames if args.frames is None else args.frames
    in_range("--frames", frames, why=f"the first {SETTLE_FRAMES} are the filter's settling time")
    text = defaults.distances if args.distances is None else args.distances
    distances = sorted(set(_float_list(text, "--distances", lengths=True)))
    in_range("--marker-m", args.marker_m)
    check(0.0 <= args.tilt_deg < 80.0, f"--tilt-deg: must be in [0, 80), got {args.tilt_deg:g}")
    in_range("--sensor-noise", args.sensor_noise)
    in_range("--blur", args.blur)
    setup = JitterSetup(
        config=load_config(args.config),
        marker_m=args.marker_m,
        distances_m=tuple(distances),
        frames=frames,
        tilt_deg=args.tilt_deg,
        sensor_noise=args.sensor_noise,
        blur_px=args.blur,
        seed=args.seed,
        roi=args.roi,
    )
    setup = setup if camera is None else dataclasses.replace(setup, camera=camera)
    check_distances(setup, distances, text)
    return setup


_OPTIONS = (
    "quick",
    "seed",
    "camera",
    "seeds",
    "points",
    "pixel_noise",
    "contamination",
    "threshold",
    "iterations",
    "thresholds",
    "contaminations",
    "frames",
    "distances",
    "marker_m",
    "tilt_deg",
    "sensor_noise",
    "blur",
    "roi",
    "config",
)


def command_line(args: argparse.Namespace, name: str, out: Path) -> str:
    """The command line that reproduces this run (options that differ from their defaults)."""
    defaults = argparse.ArgumentParser()
    configure_parser(defaults)
    reference = defaults.parse_args([name])
    words = ["ar-anchor", "study", name]
    for option in _OPTIONS:
        value = getattr(args, option, None)
        if value == getattr(reference, option):
            continue
        flag = "--" + option.replace("_", "-")
        if value is False:
            words += ["--no-" + option.replace("_", "-")]
        else:
            words += [flag] if value is True else [flag, str(value)]
    return " ".join(words + ["--out", str(out)])
