"""`ar-anchor export RUN_DIR`: a finished run's poses for robotics tools (``poses_ext.csv``, TUM trajectories, a
ROS 2 bag in MCAP); and ``--export`` / ``--export-images`` of ``demo``, ``replay`` and ``live``, which run the
same export on the run's folder once its outputs are closed (:func:`export_after_run`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import Any

from ..errors import EXIT_FAILURE, EXIT_OK, ArAnchorError, InputError, printable
from .options import add_command, output_path, positive_float
from .report import Progress, outputs_line


def _formats(text: str) -> tuple[str, ...]:
    from ..tools.export.run import parse_formats

    try:
        return parse_formats(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_parser(commands: Any) -> None:
    """The ``export`` command's options."""
    export = add_command(
        commands,
        "export",
        "export a run's poses for robotics tools: quaternions/4x4 matrices, TUM trajectories, a ROS 2 bag (MCAP)",
        "Read RUN_DIR/poses.csv (a run of demo, replay or live) and write, beside it or into --out: poses_ext.csv "
        "(quaternion, translation and 4x4 matrix of each pose), tum/<target>.txt (the camera's trajectory in "
        "each target's frame, TUM format) and run.mcap (a ROS 2 bag: /tf, /camera/camera_info and, with "
        "--images, /camera/image/compressed). See docs/outputs-and-viewer.md.",
    )
    export.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="the output directory of a run")
    export.add_argument("--out", type=output_path, default=None, help="write the exports here (default: into RUN_DIR)")
    export.add_argument(
        "--formats",
        type=_formats,
        default=("csv", "tum", "mcap"),
        metavar="LIST",
        help="comma-separated, among csv (poses_ext.csv), tum, mcap (default: all three)",
    )
    export.add_argument(
        "--camera",
        type=Path,
        default=None,
        metavar="FILE",
        help="the camera YAML the run tracked with (default: RUN_DIR/camera.yml, else the camera in its summary.json)",
    )
    export.add_argument(
        "--images",
        action="store_true",
        help="also put the frames into the MCAP (JPEG): from RUN_DIR/raw.mkv (live --record) or --video",
    )
    export.add_argument(
        "--video",
        metavar="SOURCE",
        default=None,
        help="the video file, image folder or glob the run tracked (for --images; implies it)",
    )
    export.add_argument(
        "--fps", type=positive_float, default=30.0, help="--video an image folder: its frame rate, as replayed (30)"
    )
    export.set_defaults(func=cmd_export)


def add_export_options(parser: argparse.ArgumentParser, images_from: str) -> None:
    """``--export`` and ``--export-images`` of a run command; ``images_from``: where its frames come from."""
    parser.add_argument(
        "--export",
        action="store_true",
        help="after the run, export its poses into --out as `ar-anchor export` does: poses_ext.csv, tum/, "
        "run.mcap (docs/outputs-and-viewer.md)",
    )
    parser.add_argument(
        "--export-images",
        action="store_true",
        help=f"--export with the frames in run.mcap ({images_from})",
    )


def export_outputs(args: argparse.Namespace, out_dir: Path) -> list[tuple[str, Path]]:
    """The files ``--export`` will write into ``out_dir`` (checked with the run's outputs before it starts)."""
    from ..tools.export.run import export_output_paths

    if not (args.export or args.export_images):
        return []
    return export_output_paths(Path(out_dir))


def _exported_names(result: Any) -> list[str]:
    """The exports' names in the run's folder (``tum/ (N files)`` for the TUM trajectories)."""
    names = [path.name for path in result.files if path.parent == result.out_dir]
    tum = [path for path in result.files if path.parent != result.out_dir]
    if tum:
        names.insert(1 if "poses_ext.csv" in names else 0, f"tum/ ({len(tum)} files)")
    return names


def _mcap_counts(result: Any) -> str:
    messages = result.messages
    return f"run.mcap: {messages['tf']} /tf, {messages['camera_info']} camera_info, {messages['image']} images"


def _print_exported(result: Any) -> None:
    line = f"exports: {printable(result.out_dir)}/ ({', '.join(_exported_names(result))})"
    if result.messages:
        line += f"; {_mcap_counts(result)}"
    print(line)


def export_after_run(
    args: argparse.Namespace,
    out_dir: Path,
    code: int,
    camera: Any,
    images: Callable[[], Any] | None = None,
) -> int:
    """``--export``: export the finished run in ``out_dir`` (with ``camera``; ``images`` opens the run's frames
    for ``--export-images``). A failure is one line and exit code 1; the run's outputs stay as they are."""
    if not (args.export or args.export_images):
        return code
    from ..run.paths import OutDirLock
    from ..tools.export import export_run

    progress = Progress(not args.quiet, "export")
    try:
        with OutDirLock(Path(out_dir)):
            result = export_run(
                out_dir, camera=camera, images=images if args.export_images else None, progress=progress
            )
    except ArAnchorError as err:
        print(outputs_line(out_dir))  # the run's own files, complete
        print(f"ar-anchor: error: export of {printable(out_dir)} failed: {printable(err)}", file=sys.stderr)
        return max(code, EXIT_FAILURE)
    finally:
        progress.close()
    if result.messages:
        print(_mcap_counts(result))  # (the files are in the last line)
    print(outputs_line(out_dir, exported=_exported_names(result)))
    return code


def cmd_export(args: argparse.Namespace) -> int:
    """``ar-anchor export RUN_DIR``: write the exports; the exit code."""
    from ..camera import CameraModel
    from ..run.outputs import prepare_out_dir
    from ..run.paths import OutDirLock, spec_inputs
    from ..tools.export import export_run
    from ..tools.export.run import check_run_dir, default_images

    check_run_dir(args.run_dir)
    if (args.images or args.video is not None) and "mcap" not in args.formats:
        raise InputError("--images/--video: the images go into the MCAP file: add mcap to --formats")
    images = None
    inputs: list[tuple[str, Path]] = []
    if args.video is not None:
        from ..sources.open import open_source

        video, fps = args.video, args.fps
        images = lambda: open_source(video, live=False, fps=fps)  # noqa: E731
        inputs += spec_inputs(video, "--video")
    elif args.images:
        images = default_images(args.run_dir)
    camera = None
    if args.camera is not None:
        camera = CameraModel.from_yaml(args.camera)
        inputs.append(("--camera", args.camera))
    out = args.out if args.out is not None else args.run_dir
    option = "--out" if args.out is not None else "RUN_DIR"
    created = not out.exists()
    out = prepare_out_dir(out, option)
    progress = Progress(not args.quiet, "export")
    try:
        with OutDirLock(out, option):
            result = export_run(
                args.run_dir, out, formats=args.formats, camera=camera, images=images, progress=progress, inputs=inputs
            )
    except InputError:
        if created:  # bad input: no empty folder left behind
            with suppress(OSError):
                out.rmdir()
        raise
    finally:
        progress.close()
    _print_exported(result)
    return EXIT_OK
