"""`ar-anchor batch`: replay many recordings, one task each, on local processes or a Ray cluster.

What is a recording (docs/batch-and-cluster.md): a video file is one; a folder holding video files is those videos
(its images, if any, are ignored); a folder of images only is one image-sequence recording, as
``replay`` takes it; a quoted glob is expanded: the videos it matches are one recording each, and the
images it matches are, together, one image-sequence recording (the glob itself, as ``replay`` takes it).
``--manifest FILE.csv`` instead lists one recording per row (``source``, optional ``camera``, ``config``,
``name``; relative paths are relative to the manifest's folder).

Each recording is replayed as ``ar-anchor replay`` would (the task, :mod:`.batch_task`, calls the same
command function), into ``OUT/<name>/`` (name: the file stem, or the folder's name, made safe as one folder
inside ``OUT``; ``_2``, ``_3``, ... when two collide or a name is one of ``OUT``'s own files), and gets one row
of ``OUT/runs.parquet`` (``runs.csv`` without pyarrow). A recording whose folder holds a completed run of the
same source (same files, sizes and times) with the same options, camera and config (``batch.json`` beside
``summary.json``) is skipped; ``--force`` replays it again.

``OUT`` is locked for the batch (replay's lock), and checked before anything is written: no file there that a
batch or a run did not write is replaced, and no recording is written into its own image folder.

The recordings are found in :mod:`.recordings`, the runs table kept in :mod:`.runs_table`, and the tasks run
by :mod:`.batch_task`; this module is the command.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import EXIT_FAILURE, EXIT_OK, InputError, printable
from .options import add_command, add_run_options, assumed_camera_option, default_out, int_at_least, output_path
from .recordings import STAMP_FILE, Recording, _image_folder, _inside, _not_a_file, find_recordings
from .replay import add_replay_options
from .runs_table import (
    _is_runs_table,
    _outputs_line,
    empty_row,
    fingerprint,
    format_runs,
    previous_row,
    runs_path,
    write_runs,
)

log = logging.getLogger(__name__)

# the options of the batch command itself (everything else is handed to each replay as it is)
BATCH_ONLY = frozenset(
    {"sources", "manifest", "jobs", "ray", "force", "rigid_sheet", "out", "quiet", "verbose", "command", "func"}
    | {"images_out"}  # (given to the image recordings only, each its own folder: see _run_batch)
)


def add_parser(commands: Any) -> None:
    """The ``batch`` command's options: ``replay``'s, plus the sources, the manifest and the engine."""
    batch = add_command(
        commands,
        "batch",
        "replay many recordings in parallel (local processes or a Ray cluster); a table of all runs",
        "Replay every recording (video files, folders of videos, image folders, quoted globs, or the rows of "
        "--manifest) as `ar-anchor replay` would, each into OUT/<name>/, in parallel: local processes "
        "(--jobs) or Ray (--ray). OUT/runs.parquet (runs.csv without pyarrow) has one row per recording. "
        "Recordings already done with the same source and options are skipped (--force: again). "
        "See docs/batch-and-cluster.md.",
    )
    batch.add_argument(
        "sources",
        metavar="SOURCE",
        nargs="*",
        help="video file, folder of videos, image folder (one recording), or a quoted glob",
    )
    batch.add_argument(
        "--manifest",
        type=Path,
        default=None,
        metavar="FILE.csv",
        help="CSV of recordings: column source, optional camera, config, name (relative to the file's folder)",
    )
    add_replay_options(batch)
    add_run_options(batch, "batch", spawn=False)
    for action in batch._actions:  # one annotated video for many recordings: not offered
        if "--video-out" in action.option_strings:
            action.help = argparse.SUPPRESS
    batch.add_argument(
        "--images-out",
        type=output_path,
        default=None,
        metavar="DIR",
        help="recordings of images: also write each image with its overlays drawn to DIR/<name>/ (replay "
        "--images-out; video recordings get none)",
    )
    batch.add_argument(
        "--jobs",
        type=int_at_least(1),
        default=None,
        metavar="N",
        help="recordings replayed at once (default: the usable cores; with --ray and no address: the local Ray's CPUs)",
    )
    batch.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        type=ray_address,
        metavar="ADDRESS",
        help="run the tasks on Ray (pip install 'ar-anchor[cluster]'): no ADDRESS starts a local Ray; 'auto' "
        "joins the running cluster; ray://HEAD:10001 a remote one (sources and --out on storage every node "
        "mounts at the same path)",
    )
    batch.add_argument("--force", action="store_true", help="replay recordings whose outputs are already complete")
    batch.add_argument(
        "--rigid-sheet",
        action="store_true",
        help="the lone markers of every recording are printed on one rigid sheet: add pair-flip figures to the "
        "runs table (ar_anchor.bench.real.score_rigid_sheet)",
    )
    batch.set_defaults(func=cmd_batch)


def ray_address(text: str) -> str:
    """``--ray``'s ADDRESS: ``auto``, ``ray://HOST:PORT`` or ``HOST:PORT`` (a SOURCE is not taken for one)."""
    import re

    if text in ("", "auto") or re.fullmatch(r"(ray://)?[A-Za-z0-9_.\-\[\]:]+:[0-9]+", text):
        return text
    raise argparse.ArgumentTypeError(
        f"expected auto, ray://HOST:PORT or HOST:PORT, got {text!r} (a SOURCE right after --ray is taken for its "
        "address: put --ray after the sources, or write --ray=)"
    )


# ============================================================================ the command


@dataclass
class _Tally:
    rows: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped: int = 0


def replay_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options handed to every replay: the batch's own options left out."""
    return {key: value for key, value in vars(args).items() if key not in BATCH_ONLY}


def check_cameras(recordings: Sequence[Recording], camera: Path | None, assumed: str | None = None) -> None:
    """Every recording has a camera: its own file (manifest), ``--camera``, ``camera.yml`` beside its source
    (replay's default) or the pinhole ``assumed`` (``--focal-px F`` or ``--hfov-deg A``, for the recordings with
    no file of their own in the manifest: one warning for all); :class:`InputError` naming the first that has
    none, before anything runs."""
    if camera is not None:
        return
    if assumed is not None:
        log.warning(
            "no calibration: %s taken for a pinhole (principal point at the image centre, no lens distortion) for "
            "every recording without a camera file of its own (--manifest): distances are approximate",
            assumed,
        )
        return
    for recording in recordings:
        beside = Path(recording.source).parent / "camera.yml"
        if recording.camera is None and not beside.is_file():
            raise InputError(
                f"{printable(recording.source)}: no camera file: give --camera FILE (or a camera column in "
                f"--manifest), the calibration of the camera that took it (none at {printable(beside)}); without "
                "one, --focal-px F or --hfov-deg A gives approximate distances"
            )


def _run_command(folder: Path) -> str:
    """The command whose run ``folder`` holds (its ``summary.json``'s ``command``; ``?`` when it says none)."""
    try:
        command = json.loads((folder / "summary.json").read_text(encoding="utf-8")).get("command")
    except (OSError, ValueError, AttributeError):
        return "?"
    return command if isinstance(command, str) else "?"


def check_out(out: Path, recordings: Sequence[Recording]) -> None:
    """What a batch into ``out`` would write, checked before anything is: no recording's folder is its image
    folder or inside it (its outputs would become its frames), and no file of ``out`` that a batch or a run
    did not write is replaced (``runs.parquet``, a recording folder's ``poses.csv``, ...), nor a run of another
    command (a ``live --record`` session's ``raw.mkv``). :class:`InputError` naming ``--out`` and the file."""
    from ..run.paths import _previous_run_here

    where = out.resolve()
    for recording in recordings:
        folder = _image_folder(recording.source)
        if folder is None or not _inside(where / recording.name, folder.resolve()):
            continue
        name, shown = printable(recording.name), printable(folder)
        if _inside(where, folder.resolve()):
            what = f"{'is' if where == folder.resolve() else 'is inside'} the image folder {shown} of recording {name}"
        else:
            what = f"recording {name} would be written into {printable(out / recording.name)}, its own image folder"
        raise InputError(f"--out {printable(out)}: {what}: its outputs would be taken for frames; give an --out "
                         "outside it")  # fmt: skip
    table = runs_path(out)
    if (table.exists() or table.is_symlink()) and not _is_runs_table(table):
        raise InputError(
            f"--out {printable(out)}: holds {table.name}, which no ar-anchor batch wrote; the batch would replace "
            "it: give a new or empty folder"
        )
    for recording in recordings:
        folder = out / recording.name
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            raise InputError(
                f"--out {printable(out)}: holds {printable(recording.name)}, which is not a folder a batch made; "
                f"recording {printable(recording.name)} would be written there: give a new or empty folder"
            )
        if not folder.is_dir():
            continue
        if _previous_run_here(folder):
            command = _run_command(folder)
            if command != "replay" and not (folder / STAMP_FILE).is_file():  # (replay would clear it: a live
                # session's raw.mkv is the user's only copy; batch.json: a batch wrote it, whatever its summary says)
                what = "a run" if command == "?" else f"a run of `ar-anchor {printable(command)}`"
                raise InputError(
                    f"--out {printable(folder)}: holds {what} (its summary.json) that no batch wrote; recording "
                    f"{printable(recording.name)} would replace its files: give another --out"
                )
            continue
        names = ("poses.csv", "summary.json", "recording.rrd", "frames.csv", STAMP_FILE)
        theirs = [name for name in names if (folder / name).exists() or (folder / name).is_symlink()]
        if theirs:
            raise InputError(
                f"--out {printable(folder)}: holds {', '.join(theirs)}, which no ar-anchor run wrote (no run's "
                "summary.json there); the batch would overwrite them: give a new or empty folder"
            )


def cmd_batch(args: argparse.Namespace) -> int:
    """``ar-anchor batch SOURCE... --out DIR``: replay every recording, write the runs table; the exit code."""
    from ..run.outputs import prepare_out_dir
    from ..run.paths import OutDirLock

    if args.video_out is not None:
        raise InputError("--video-out: batch writes one folder per recording; no single annotated video")
    assumed_camera_option(args)  # (--focal-px with --hfov-deg or --camera: refused before anything)
    recordings = find_recordings(args.sources, args.manifest)
    for option in ("camera", "config"):
        path = getattr(args, option)
        if path is not None and not Path(path).is_file():
            raise InputError(f"--{option} {printable(path)}: {_not_a_file(Path(path), 'a regular file')}")
    if args.ray is not None:
        from .batch_task import require_ray

        require_ray()
    check_cameras(recordings, args.camera, assumed_camera_option(args))
    out = (args.out or default_out("batch")).absolute()  # (absolute paths: what a Ray node is given)
    check_out(out, recordings)
    created = not out.exists()
    prepare_out_dir(out)
    try:
        with OutDirLock(out):
            check_out(out, recordings)  # (again, now that no other batch can write into it)
            return _run_batch(args, out, recordings)
    except InputError:
        if created:  # bad input found before anything was written: no empty folder left behind
            with contextlib.suppress(OSError):
                out.rmdir()
        raise


def _run_batch(args: argparse.Namespace, out: Path, recordings: list[Recording]) -> int:
    """The batch, once ``out`` is checked and locked: the replays, then the runs table; the exit code."""
    from .batch_task import BatchTask, ray_session, usable_cores

    ray_address = args.ray
    options = replay_options(args)
    for option in ("camera", "config"):
        if options.get(option) is not None:
            options[option] = Path(options[option]).absolute()
    tally = _Tally()
    tasks = []
    for recording in recordings:
        recording = Recording(os.path.abspath(recording.source), recording.name, recording.camera, recording.config)
        task_options = dict(options)
        if recording.camera is not None:  # (the manifest's camera file, instead of --camera, --focal-px, --hfov-deg)
            task_options.update(camera=recording.camera.absolute(), focal_px=None, hfov_deg=None)
        if recording.config is not None:
            task_options["config"] = recording.config.absolute()
        if args.images_out is not None and _image_folder(recording.source) is not None:
            task_options["images_out"] = (args.images_out / recording.name).absolute()
        stamp = fingerprint(recording, task_options)
        out_dir = out / recording.name
        previous = None if args.force else previous_row(out_dir, stamp)
        if previous is not None:
            if args.rigid_sheet and previous.get("pair_frames") is None:  # (scored now: no need to replay)
                from .batch_task import fill_row

                fill_row(previous, out_dir, rigid_sheet=True)
            tally.rows[recording.name] = {**previous, "status": "skipped", "name": recording.name}
            tally.skipped += 1
            continue
        tasks.append(BatchTask(recording, out_dir, task_options, stamp, args.rigid_sheet, args.verbose))
    jobs = args.jobs or usable_cores()
    with contextlib.ExitStack() as stack:
        if tasks and ray_address is not None:  # (joined before anything is written: a cluster not there is exit 2)
            stack.enter_context(ray_session(ray_address, args.jobs))
        return _replay_all(args, out, recordings, tasks, tally, jobs)


def _replay_all(
    args: argparse.Namespace, out: Path, recordings: list[Recording], tasks: list[Any], tally: _Tally, jobs: int
) -> int:
    from .batch_task import run_local, run_ray

    ray_address = args.ray
    started = time.monotonic()
    interrupted = False
    bar = _bar(not args.quiet, len(recordings), tally.skipped)
    try:

        def done(row: dict[str, Any]) -> None:
            tally.rows[row["name"]] = row
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"{printable(row['name'])}: {row['status']}")
            if row["status"] == "failed" and not args.quiet:
                message = f"ar-anchor: {printable(row['name'])}: failed: {printable(row['error'])}"
                print(message, file=sys.stderr, flush=True)

        if tasks:
            if ray_address is not None:
                run_ray(tasks, ray_address, args.jobs, done)
            else:
                run_local(tasks, jobs, done)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if bar is not None:
            bar.close()
    rows = [tally.rows.get(r.name) or {**empty_row(r, out / r.name), "status": "not run"} for r in recordings]
    for row, recording in zip(rows, recordings, strict=True):
        row["source"] = recording.source  # (as the user gave it)
    if interrupted:
        for row in rows:
            if row["status"] == "not run":
                row["status"], row["error"] = "interrupted", "the batch was interrupted before it finished"
    table = write_runs(out, rows)
    failed = [row for row in rows if row["status"] == "failed"]
    ok = sum(row["status"] == "ok" for row in rows)
    wall = time.monotonic() - started
    if not args.quiet:
        print(format_runs(rows, out))
        engine = "ray" if ray_address is not None else f"{min(jobs, max(1, len(tasks)))} local process(es)"
        print(
            f"{len(rows)} recording(s): {ok} replayed, {tally.skipped} skipped (already done), {len(failed)} failed"
            f" in {wall:.1f} s ({engine}); table: {printable(table)}"
        )
    if not interrupted:
        print(_outputs_line(out, table, rows))
    if interrupted:
        stop = KeyboardInterrupt()
        stop.note, stop.out_dir = f"{table.name} has a row for every recording", out  # type: ignore[attr-defined]
        raise stop
    if failed:
        names = ", ".join(printable(row["name"]) for row in failed[:5]) + (", ..." if len(failed) > 5 else "")
        print(f"ar-anchor: error: {len(failed)} of {len(rows)} recording(s) failed: {names} (see {printable(table)})",
              file=sys.stderr)  # fmt: skip
        return EXIT_FAILURE
    return EXIT_OK


def _bar(enabled: bool, total: int, done: int) -> Any:
    """A tqdm bar over the recordings on a terminal (None otherwise or with -q)."""
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="batch", unit="recording", leave=False, dynamic_ncols=True)
