"""`ar-anchor demo`: a synthetic scene with exact ground truth, tracked and recorded (no camera)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import InputError
from .export import add_export_options, export_after_run, export_outputs
from .options import (
    add_camera_options,
    add_command,
    add_run_options,
    add_tracker_options,
    default_out,
    float_in,
    int_at_least,
    length,
    load_tracker_config,
    run_options,
)
from .report import Progress, finish


def add_parser(commands: Any) -> None:
    """The ``demo`` command's options."""
    demo = add_command(
        commands,
        "demo",
        "track a built-in synthetic scene with exact ground truth (no camera needed)",
        "Render a synthetic scene (lone markers and a 2x2 board, the camera sweeping from near "
        "to far), track it, and write poses.csv, summary.json and recording.rrd.",
    )
    demo.add_argument("--frames", type=int_at_least(1), default=300, help="frames to render (default 300)")
    demo.add_argument("--seed", type=int_at_least(0), default=0, help="seed of scene texture and noise (default 0)")
    demo.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera YAML to render with (default: configs/camera_synthetic.yml values)",
    )
    add_tracker_options(demo)
    demo.add_argument(
        "--trajectory",
        choices=("sweep", "orbit", "static"),
        default="sweep",
        help="camera path (default sweep: near to far)",
    )
    demo.add_argument(
        "--near",
        type=length("m", low=0.02, high=100.0, inclusive=True),
        default=0.35,
        help="nearest camera distance, e.g. 35cm or 0.35 (a bare number is metres; 0.02-100 m)",
    )
    demo.add_argument(
        "--far",
        type=length("m", low=0.02, high=100.0, inclusive=True),
        default=3.0,
        help="farthest camera distance, e.g. 3m (a bare number is metres; 0.02-100 m)",
    )
    demo.add_argument("--noise", type=float_in(0.0, 100.0), default=2.0, help="sensor noise sigma, grey levels (0-100)")
    demo.add_argument("--blur", type=float_in(0.0, 50.0), default=0.6, help="optical blur sigma, pixels (0-50)")
    add_run_options(demo, "demo")
    add_camera_options(demo)
    add_export_options(demo, "the scene rendered again")
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    """``ar-anchor demo``: render the synthetic scene, track and record it; the exit code."""
    from ..camera import CameraModel
    from ..errors import SourceError
    from ..run.loop import run_session
    from ..run.paths import claim_out_dir, config_inputs, run_output_paths
    from ..sources.synthetic import SyntheticSource
    from ..synthetic import Trajectory, demo_scene
    from ..tools.export.run import camera_summary, clear_previous_exports
    from ..track.tracker import Tracker

    config = load_tracker_config(args, demo=True)
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
    summary = {"command": "demo", "seed": args.seed, "trajectory": args.trajectory, "camera": camera_summary(camera)}
    options = run_options(args, "demo", extra_summary=summary)
    out_dir = args.out or default_out("demo")
    outputs_named = run_output_paths(out_dir, video_out=args.video_out, extra=export_outputs(args, out_dir))
    progress = Progress(not args.quiet, "demo")
    try:
        with claim_out_dir(out_dir, outputs_named, config_inputs(config, args.config, args.camera)):
            clear_previous_exports(out_dir)  # they belong to the poses.csv this run replaces
            with SyntheticSource(scene) as source:
                outputs = run_session(source, Tracker(config, camera), out_dir, options, progress=progress)
    finally:
        progress.close()
    return export_after_run(args, out_dir, finish(args, outputs), camera, lambda: SyntheticSource(scene))
