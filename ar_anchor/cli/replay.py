"""`ar-anchor replay`: track a video file, an image folder or a glob of images."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import EXIT_FAILURE, printable
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
    load_tracker_config,
    output_path,
    positive_float,
    run_options,
)
from .report import Progress, finish

if TYPE_CHECKING:
    from ..run.stills import StillsPlan
    from ..sources.base import SourceInfo

log = logging.getLogger(__name__)


def add_parser(commands: Any) -> None:
    """The ``replay`` command's options."""
    replay = add_command(
        commands,
        "replay",
        "track a video file, an image folder or a glob of images",
        "Track every frame of a video file (container timestamps), an image folder or a glob "
        "(natural order, --fps timestamps) and write poses.csv, summary.json and recording.rrd. "
        "Each frame is decided with the whole recording (the flip filter also runs backwards; gaps are "
        "interpolated): three passes, the source decoded twice. --causal: each frame from the frames "
        "before it only, exactly as live.",
    )
    replay.add_argument(
        "source", metavar="SOURCE", help="video file, image folder, or a quoted glob such as 'shots/*.png'"
    )
    add_replay_options(replay)
    replay.add_argument(
        "--max-megapixels",
        type=positive_float,
        default=None,
        metavar="MP",
        help="largest image or video frame read, in megapixels (default 50; read from the file's header "
        "before it is decoded): a larger image is skipped, a larger video refused",
    )
    add_run_options(replay, "replay")
    replay.add_argument(
        "--images-out",
        type=output_path,
        default=None,
        metavar="DIR",
        help="an image folder or glob: also write each image with its overlays drawn (as --video-out draws "
        "them) to DIR, under the same file name and format; DIR may not be the images' own folder",
    )
    add_camera_options(replay)
    add_export_options(replay, "SOURCE decoded again")
    replay.set_defaults(func=cmd_replay)


def add_replay_options(parser: argparse.ArgumentParser) -> None:
    """--camera, the tracker options, --fps and --causal: how a recording is replayed (``replay``, ``batch``)."""
    parser.add_argument(
        "--camera",
        type=Path,
        default=None,
        help="camera calibration: OpenCV YAML/XML/JSON (as `calibrate` writes), ROS camera_info YAML or PhotonVision "
        "JSON (default: camera.yml beside SOURCE, as `live --record` writes it; none: --focal-px or --hfov-deg)",
    )
    add_assumed_camera_options(parser)
    add_tracker_options(parser)
    parser.add_argument(
        "--fps",
        type=positive_float,
        default=None,
        help="frame rate of image folders (default 30); giving it says the images are a sequence (--sequence)",
    )
    parser.add_argument(
        "--sequence",
        action="store_true",
        help="an image folder or glob holds one video's frames, in order: track them as a sequence (flip filter, "
        "offline replay) instead of as independent stills, each decided alone (the default for images)",
    )
    parser.add_argument(
        "--causal",
        action="store_true",
        help="decide each frame from the frames before it only (what live produces; one pass) instead of "
        "with the whole recording",
    )


def _replay_camera(args: argparse.Namespace) -> Path | None:
    """``--camera``, or the ``camera.yml`` beside the source (as ``live --record`` leaves it); None for
    ``--focal-px`` or ``--hfov-deg`` (an assumed camera, built at the source's resolution)."""
    from ..errors import CameraError

    if args.camera is not None:
        return args.camera
    if assumed_camera_option(args) is not None:
        return None
    beside = Path(args.source).parent / "camera.yml"
    if not beside.is_file():
        raise CameraError(
            f"--camera FILE is required: the calibration of the camera that took {printable(args.source)} (none found "
            f"at {printable(beside)}); without one, --focal-px F or --hfov-deg A gives approximate distances"
        )
    log.warning("using %s, found beside the source", beside)
    return beside


def replay_camera(args: argparse.Namespace, source: Any) -> tuple[Any, Path | None, str]:
    """The camera a replay of ``source`` tracks with, at the source's resolution: the calibration file (and its
    path) or the assumed pinhole (path None), and how it was given (summary.json's ``camera`` ``from``)."""
    from ..camera import CameraModel

    camera_path = _replay_camera(args)
    if camera_path is None:
        warn = not getattr(args, "batch_warned", False)  # (batch says it once for all its recordings)
        return assumed_camera(args, source.resolution, warn=warn), None, assumed_camera_option(args)
    camera = camera_for_source(
        CameraModel.from_yaml(camera_path),
        source.resolution,
        f"--camera {camera_path}",
        frames_from=getattr(source, "resolution_from", None),
    )
    given = f"--camera {camera_path}" if args.camera is not None else f"{camera_path} (beside the source)"
    return camera, camera_path, given


def _images_out(args: argparse.Namespace, source: Any) -> StillsPlan | None:
    """``--images-out DIR`` checked against the source (an image folder or glob only: a video's frames have no
    file names to keep) and the files in DIR (:func:`~ar_anchor.run.stills.plan_images_out`); None without it."""
    from ..errors import InputError
    from ..run.stills import plan_images_out

    if args.images_out is None:
        return None
    if not hasattr(source, "files"):
        raise InputError(
            f"--images-out {printable(args.images_out)}: {printable(args.source)} is a video; --images-out writes "
            "one annotated image per image of a folder or glob (an annotated video: --video-out FILE.mp4)"
        )
    return plan_images_out(args.images_out, source.files)


def stills_assumed(args: argparse.Namespace, info: SourceInfo) -> bool:
    """Are the source's frames independent stills (an image folder or glob, without ``--sequence`` or
    ``--fps``)? Says which was assumed, in one line (unless ``-q``; summary.json's ``decided_with`` says it
    too). A video given ``--fps`` or ``--sequence`` (options of image sources) is warned that they are ignored."""
    fps_given, sequence_given = args.fps is not None, getattr(args, "sequence", False)
    if not info.stills:
        ignored = [name for name, given in (("--fps", fps_given), ("--sequence", sequence_given)) if given]
        if ignored:
            log.warning(
                "%s: ignored, %s is a video (its frames are a sequence, timed by the video itself); %s only for "
                "image folders and globs",
                " and ".join(ignored),
                printable(args.source),
                "they are" if len(ignored) > 1 else "it is",
            )
        return False
    sequence = sequence_given or fps_given
    count = f"{info.frame_count} image(s)" if info.frame_count is not None else "the images"
    if sequence and getattr(args, "no_filter", False):
        note = f"{count} tracked in order, each decided alone (--no-filter)"
    elif sequence:
        note = f"{count} tracked as one sequence, in order"
    else:
        note = f"{count} taken as independent stills, each decided alone (--sequence if they are one video's frames)"
    if not args.quiet:
        print(f"{printable(args.source)}: {note}", flush=True)
    return not sequence


def decided_with(stills: bool, offline: bool, filtered: bool) -> str:
    """How each frame was decided (summary.json's ``decided_with``)."""
    if stills:
        return "each image alone (independent stills)"
    if not filtered:
        return "each frame alone (--no-filter)"
    return "the whole recording" if offline else "the frames before each (causal)"


def write_frames_csv(path: Path, source: Any) -> None:
    """``frames.csv``: which file each frame of an image source is (``frame`` is poses.csv's column), with the
    timestamp given to it. Written whole before the run, so it is complete whatever happens to the run."""
    import csv
    import io
    import os

    from ..run.outputs import write_failure

    fps = source.info.fps or 30.0
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(["frame", "timestamp_s", "file"])
    for index, file in enumerate(source.files):
        writer.writerow([index, f"{index / fps:.9f}", os.fsdecode(file)])
    try:
        with open(path, "w", encoding="utf-8", errors="backslashreplace", newline="") as out:
            out.write(text.getvalue())
    except OSError as err:
        raise write_failure(path, err) from None


def cmd_replay(args: argparse.Namespace) -> int:
    """``ar-anchor replay SOURCE``: track a video file or images and record the run; the exit code."""
    from ..run.loop import OfflineReplay, check_video_out, run_session
    from ..run.paths import FRAMES_CSV, claim_out_dir, config_inputs, run_output_paths, source_inputs
    from ..sources import open_source
    from ..tools.export.run import camera_summary, clear_previous_exports
    from ..track.tracker import Tracker

    assumed_camera_option(args)  # (both --focal-px and --hfov-deg, or one with --camera: refused before anything)
    config = load_tracker_config(args)
    max_pixels = None if args.max_megapixels is None else max(1, int(args.max_megapixels * 1e6))
    with open_source(args.source, live=False, fps=args.fps, max_pixels=max_pixels) as source:
        camera, camera_path, camera_from = replay_camera(args, source)
        images_out = _images_out(args, source)
        stills = stills_assumed(args, source.info)
        if stills:  # each image alone: exactly the per-frame pipeline, nothing carried from one to the next
            config = config.with_overrides(filter_enabled=False)
        options = run_options(
            args,
            f"replay {args.source}",
            record_fps=source.info.fps or 30.0,
            images_out=images_out,
            extra_summary={
                "command": "replay",
                "source": str(args.source),
                "camera": {"from": camera_from, **camera_summary(camera)},
            },
        )
        check_video_out(args.video_out)  # (before frames.csv is written)
        out_dir = args.out or default_out("replay")
        inputs = source_inputs(source) + config_inputs(config, args.config, camera_path)
        frames_csv = [("--out", out_dir / FRAMES_CSV)] if hasattr(source, "files") else []
        stills_named = (
            [] if images_out is None else [("--images-out", images_out.folder / n) for n in images_out.names.values()]
        )
        outputs_named = run_output_paths(
            out_dir, video_out=args.video_out, extra=[*export_outputs(args, out_dir), *frames_csv, *stills_named]
        )
        offline = None
        if not args.causal and config.filter.enabled:  # (--no-filter: nothing to decide with hindsight)
            offline = OfflineReplay(
                reopen=lambda: open_source(args.source, live=False, fps=args.fps, max_pixels=max_pixels),
                progress=lambda name: Progress(not args.quiet, f"replay {'2/3' if name == 'decide' else '3/3'} {name}"),
            )
        progress = Progress(not args.quiet, "replay" if offline is None else "replay 1/3 track")
        try:
            with claim_out_dir(out_dir, outputs_named, inputs):
                clear_previous_exports(out_dir)  # they belong to the poses.csv this run replaces
                if frames_csv:
                    write_frames_csv(out_dir / FRAMES_CSV, source)
                outputs = run_session(
                    source,
                    Tracker(config, camera, stills=stills),
                    out_dir,
                    options,
                    progress=progress,
                    summary_extras=lambda: {
                        "source_ended_early": source.info.ended_early,
                        "decided_with": decided_with(stills, offline is not None, config.filter.enabled),
                    },
                    offline=offline,
                )
        finally:
            progress.close()
    code = finish(args, outputs)
    if source.info.ended_early:
        print(
            f"ar-anchor: error: {printable(args.source)}: "
            f"{source.info.ended_because or 'the stream ended early (damaged or truncated file)'}; outputs cover "
            f"the {outputs.summary['frames']} frames read before that",
            file=sys.stderr,
        )
        code = EXIT_FAILURE
    return export_after_run(
        args, out_dir, code, camera, lambda: open_source(args.source, live=False, fps=args.fps, max_pixels=max_pixels)
    )
