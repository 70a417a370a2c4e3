"""``ar-anchor calibrate``: check the options, calibrate, write the camera YAML and the recording,
print the report."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from contextlib import ExitStack
from pathlib import Path

from ...errors import ArAnchorError, InputError, SourceError, printable
from ...run.outputs import prepare_out_file_folder
from ...run.paths import OutDirLock, check_paths, spec_inputs
from ...sources.open import is_device
from .gather import calibrate_source
from .recording import CalibrationRecording
from .report import format_report, write_camera_yaml
from .views import CharucoSpec

__all__ = ["run_calibrate"]

log = logging.getLogger(__name__)


def _check_paths(out: Path, rrd: Path, source: str) -> None:
    """Neither output (``--out``, ``--rrd``, or the temporary files they are written through) may be an input
    file of ``source`` or the other output (:class:`InputError` naming both)."""
    outputs = [("--out", out), ("--rrd", rrd)]
    outputs += [("--out", out.with_name(f".{out.name}.{os.getpid()}.tmp.yml"))]
    outputs += [("--rrd", rrd.with_name(f".{rrd.name}.{os.getpid()}.tmp"))]
    check_paths(outputs, [] if is_device(source) else spec_inputs(source))


_APPLICATION = b"ar_anchor_calibrate"  # the recording's application id, in the head of every .rrd it writes


def _written_by_calibrate(rrd: Path) -> bool:
    """Is ``rrd`` a recording an earlier ``ar-anchor calibrate`` wrote (a rerun file whose head names its
    application id)? A link, a folder or anything else is not."""
    if rrd.is_symlink() or not rrd.is_file():
        return False
    try:
        with rrd.open("rb") as handle:
            head = handle.read(4096)
    except OSError:
        return False
    return head.startswith(b"RRF") and _APPLICATION in head


def _check_rrd_is_ours(rrd: Path, out: Path, given: bool) -> None:
    """The recording replaces only a recording calibrate wrote (:class:`InputError` naming the option)."""
    if (rrd.exists() or rrd.is_symlink()) and not _written_by_calibrate(rrd):
        option = f"--rrd {printable(rrd)}" if given else f"--out {printable(out)}"
        hint = "give another --rrd" if given else "give --rrd elsewhere"
        raise InputError(
            f"{option}: would overwrite {printable(rrd)} (the recording), which ar-anchor calibrate did not write: "
            f"move that file or {hint}"
        )


def run_calibrate(args: argparse.Namespace) -> int:
    """``ar-anchor calibrate``: calibrate, write ``--out`` and the recording, print the report."""
    spec = CharucoSpec.parse(args.charuco, args.square_m, args.marker_m, args.dictionary, args.legacy)
    out = Path(args.out)
    quiet = bool(getattr(args, "quiet", False))
    if out.is_dir():
        raise InputError(f"--out {out}: is a directory (give the camera YAML file to write)")
    if out.suffix.lower() == ".rrd":
        raise InputError(f"--out {out}: the camera file must be YAML, e.g. camera.yml")
    prepare_out_file_folder(out)
    rrd = Path(args.rrd) if getattr(args, "rrd", None) is not None else out.with_suffix(".rrd")
    if rrd.is_dir():
        raise InputError(f"--rrd {printable(rrd)}: is a directory (give the .rrd file to write)")
    source = str(args.source)
    if not is_device(source) and not any(ch in source for ch in "*?[") and not Path(source).exists():
        raise SourceError(f"{source}: not found (expected an image folder or glob, a video file, or a device)")
    _check_paths(out, rrd, source)
    _check_rrd_is_ours(rrd, out, getattr(args, "rrd", None) is not None)
    prepare_out_file_folder(rrd, "--rrd")
    with ExitStack() as locks:  # one run per output folder, as for every command (--out's, and --rrd's)
        locks.enter_context(OutDirLock(out.parent, "--out"))
        if os.path.abspath(rrd.parent) != os.path.abspath(out.parent):
            locks.enter_context(OutDirLock(rrd.parent, "--rrd"))
        return _calibrate(args, spec, source, out, rrd, quiet)


def _calibrate(args: argparse.Namespace, spec: CharucoSpec, source: str, out: Path, rrd: Path, quiet: bool) -> int:
    def progress(message: str) -> None:
        if not quiet:
            print(f"ar-anchor: {message}", file=sys.stderr, flush=True)

    recording = CalibrationRecording(rrd, spawn=bool(getattr(args, "spawn", False)))
    succeeded = False
    try:
        try:
            report = calibrate_source(
                source,
                spec,
                max_views=args.max_views,
                min_views=args.min_views,
                duration_s=getattr(args, "duration_s", 60.0) or 60.0,
                width=getattr(args, "width", None),
                height=getattr(args, "height", None),
                fps=getattr(args, "fps", None),
                previews=True,
                progress=progress,
                on_keep=recording.live_view,
            )
        except ArAnchorError as err:
            recording.event(f"calibration failed: {err}", warn=True)
            raise
        for rejection in report.rejections:
            recording.event(str(rejection), frame=rejection.frame, warn=True)
        recording.result(report)
        write_camera_yaml(out, report)
        succeeded = True
    finally:
        recording.close(keep=succeeded)
    for warning in report.warnings:
        log.warning("%s", warning)
    if not quiet:
        print(format_report(report))
    k = report.camera.camera_matrix
    print(
        f"camera: {out} (fx {k[0, 0]:.1f} fy {k[1, 1]:.1f} cx {k[0, 2]:.1f} cy {k[1, 2]:.1f}, "
        f"RMS {report.result.rms:.3f} px, {len(report.views)} views); recording: {rrd}"
    )
    return 0
