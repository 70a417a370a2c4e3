"""`ar-anchor live`: track a V4L2 camera (or the synthetic camera) in real time."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from .export import add_export_options, export_after_run, export_outputs
from .options import (
    add_assumed_camera_options,
    add_camera_options,
    add_command,
    add_run_options,
    add_tracker_options,
    assumed_camera,
    assumed_camera_option,
    camera_for_source,
    default_out,
    int_at_least,
    load_tracker_config,
    non_negative_float,
    positive_float,
    run_options,
)
from .report import LiveStatus, finish


def add_parser(commands: Any) -> None:
    """The ``live`` command's options."""
    live = add_command(
        commands,
        "live",
        "track a V4L2 webcam (or --device synthetic) live; view it in rerun",
        "Track a live camera. The live view is the rerun viewer (--spawn, --connect to a running "
        "one, or --serve: a web viewer for a browser); outputs are written as the run goes and finalised on Ctrl-C.",
    )
    live.add_argument(
        "--device",
        default="/dev/video0",
        help="V4L2 device path or index, or 'synthetic' for the demo scene in real time (default /dev/video0)",
    )
    live.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera calibration (OpenCV YAML/XML/JSON, ROS camera_info YAML or PhotonVision JSON); a real camera "
        "needs it, or --focal-px / --hfov-deg",
    )
    add_assumed_camera_options(live)
    add_tracker_options(live)
    live.add_argument("--width", type=int_at_least(1), default=None, help="requested frame width")
    live.add_argument("--height", type=int_at_least(1), default=None, help="requested frame height")
    live.add_argument("--fps", type=positive_float, default=None, help="requested frame rate (synthetic: 30)")
    live.add_argument("--fourcc", default="MJPG", help="requested pixel format (default MJPG, when offered)")
    live.add_argument(
        "--queue",
        type=int_at_least(1),
        default=1,
        help="frames waiting for the tracker at most; older ones are dropped (default 1: newest only)",
    )
    live.add_argument(
        "--reconnect-s",
        type=non_negative_float,
        default=5.0,
        help="keep trying to reopen a vanished device this long (default 5 s)",
    )
    live.add_argument(
        "--stall-s",
        type=positive_float,
        default=10.0,
        help="end the run when no frame arrives for this long (default 10 s)",
    )
    live.add_argument("--seed", type=int_at_least(0), default=0, help="synthetic device: scene seed")
    live.add_argument(
        "--record",
        action="store_true",
        help="also save the processed frames losslessly (raw.mkv + timestamps) for frame-exact replay",
    )
    add_run_options(live, "live")
    add_camera_options(live)
    add_export_options(live, "the frames --record saved in raw.mkv; needs --record")
    live.set_defaults(func=cmd_live)


def _synthetic_camera_scene(args: argparse.Namespace, config: Any) -> Any:
    """What ``live --device synthetic`` shows: the demo scene through ``--camera`` (default the synthetic
    camera) at ``--width``/``--height``, at ``--fps`` (default 30)."""
    from ..camera import CameraModel
    from ..errors import CameraError, SourceError
    from ..sources.live import CLIP_FRAMES
    from ..sources.open import live_demo_scene

    camera = CameraModel.from_yaml(args.camera) if args.camera else CameraModel.default_synthetic()
    if assumed_camera_option(args) is not None:  # the scene seen through that pinhole: exact, nothing to warn
        camera = assumed_camera(args, (args.width or camera.width, args.height or camera.height), warn=False)
    elif args.width or args.height:
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
    """``ar-anchor live``: track ``--device`` (a V4L2 camera or ``synthetic``) until it ends; the exit code."""
    from ..camera import CameraModel
    from ..errors import CameraError, InputError, SourceError
    from ..run.loop import run_session
    from ..run.paths import claim_out_dir, config_inputs, run_output_paths
    from ..sources.open import SYNTHETIC, DeviceSettings, open_source
    from ..tools.export.run import RAW_VIDEO, camera_summary, clear_previous_exports
    from ..track.tracker import Tracker

    if args.export_images and not args.record:
        raise InputError("--export-images: a live run's frames are kept only with --record (raw.mkv)")
    assumed = assumed_camera_option(args)  # (--focal-px with --hfov-deg or --camera: refused before the device opens)
    config = load_tracker_config(args, demo=args.device == SYNTHETIC)
    scene = _synthetic_camera_scene(args, config) if args.device == SYNTHETIC else None
    device = DeviceSettings(
        width=args.width,
        height=args.height,
        fourcc=args.fourcc,
        queue_size=args.queue,
        reconnect_s=args.reconnect_s,
        stall_s=args.stall_s,
    )
    try:
        source = open_source(args.device, live=True, fps=args.fps, device=device, scene=scene, frames=args.max_frames)
    except SourceError as err:  # the library names the device; the user typed it as --device
        if not str(err).startswith(str(args.device)):
            raise
        raise SourceError(f"--device {err}") from None
    try:
        if source.camera is None and assumed is not None:
            camera, camera_from = assumed_camera(args, source.resolution), assumed
        else:
            if args.camera is None and source.camera is None:
                raise CameraError(
                    "--camera FILE is required for a real camera (its calibration: see the README); without one, "
                    "--focal-px F or --hfov-deg A gives approximate distances"
                )
            camera_file = CameraModel.from_yaml(args.camera) if args.camera else source.camera
            camera = camera_for_source(camera_file, source.resolution, f"--camera {args.camera}")
            camera_from = f"--camera {args.camera}" if args.camera else (assumed or "the synthetic scene's camera")
        out_dir = args.out or default_out("live")
        options = run_options(
            args,
            f"live {args.device}",
            record_raw=args.record,
            record_fps=source.info.fps or 30.0,
            extra_summary={
                "command": "live",
                "device": str(args.device),
                "granted": dict(source.grabber.granted),
                "camera": {"from": camera_from, **camera_summary(camera)},
            },
            output_queue=3,  # live: a late logger skips frames rather than holding many (6 MB each at 1080p)
        )
        camera_yml = [("--record", Path(out_dir) / "camera.yml")] if args.record else []
        extra = camera_yml + export_outputs(args, Path(out_dir))
        outputs_named = run_output_paths(out_dir, record_raw=args.record, video_out=args.video_out, extra=extra)
        status = LiveStatus(not args.quiet, source.stats)
        try:
            with claim_out_dir(out_dir, outputs_named, config_inputs(config, args.config, args.camera)), source:
                if args.record:
                    camera.to_yaml(Path(out_dir) / "camera.yml")  # so `ar-anchor replay OUT/raw.mkv` finds it
                clear_previous_exports(Path(out_dir))  # they belong to the poses.csv this run replaces
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
    raw = Path(out_dir) / RAW_VIDEO
    return export_after_run(args, out_dir, finish(args, outputs), camera, lambda: open_source(raw, live=False))
