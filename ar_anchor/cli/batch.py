"""`ar-anchor batch`: replay many recordings, one task each, on local processes or a Ray cluster.

What is a recording (docs/batch.md): a video file is one; a folder holding video files is those videos
(its images, if any, are ignored); a folder of images only is one image-sequence recording, as
``replay`` takes it; a quoted glob is expanded: the videos it matches are one recording each, and the
images it matches are, together, one image-sequence recording (the glob itself, as ``replay`` takes it).
``--manifest FILE.csv`` instead lists one recording per row (``source``, optional ``camera``, ``config``,
``name``; relative paths are relative to the manifest's folder).

Each recording is replayed as ``ar-anchor replay`` would (the task, :mod:`.batch_task`, calls the same
command function), into ``OUT/<name>/`` (name: the file stem, or the folder's name; ``_2``, ``_3``, ... when
two collide), and gets one row of ``OUT/runs.parquet`` (``runs.csv`` without pyarrow). A recording whose
folder holds a completed run of the same source (same files, sizes and times) with the same options,
camera and config (``batch.json`` beside ``summary.json``) is skipped; ``--force`` replays it again.
"""

from __future__ import annotations

import argparse
import csv
import glob
import hashlib
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
from .options import add_command, add_run_options, default_out, int_at_least
from .replay import add_replay_options

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".wmv"})
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm"})
MANIFEST_COLUMNS = ("source", "camera", "config", "name")
# the options of the batch command itself (everything else is handed to each replay as it is)
BATCH_ONLY = frozenset(
    {"sources", "manifest", "jobs", "ray", "force", "rigid_sheet", "out", "quiet", "verbose", "command", "func"}
)
RUNS_FILE, RUNS_CSV = "runs.parquet", "runs.csv"
STAMP_FILE = "batch.json"
_GLOB_CHARS = frozenset("*?[")


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
        "See docs/batch.md.",
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


# ============================================================================ the recordings


@dataclass(frozen=True)
class Recording:
    """One recording to replay: its source (as ``replay`` takes it), camera and config (None: replay's
    defaults), and the name of its output folder."""

    source: str
    name: str
    camera: Path | None = None
    config: Path | None = None


def _is_glob(text: str) -> bool:
    return any(ch in text for ch in _GLOB_CHARS) and not Path(text).exists()


def _expand(text: str) -> list[tuple[str, str]]:
    """One SOURCE argument as (source, default name) pairs (see the module doc); InputError when nothing fits."""
    if _is_glob(text):
        matches = sorted(Path(p) for p in glob.glob(text) if Path(p).is_file())
        videos = [p for p in matches if p.suffix.lower() in VIDEO_EXTENSIONS]
        found = [(str(p), p.stem) for p in videos]
        if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in matches):
            found.append((text, Path(text).parent.name or "images"))
        if not found:
            raise InputError(f"{printable(text)}: the glob matches no video or image file")
        return found
    path = Path(text)
    if path.is_dir():
        entries = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
        videos = [p for p in entries if p.suffix.lower() in VIDEO_EXTENSIONS]
        if videos:
            return [(str(p), p.stem) for p in videos]
        if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in entries):
            return [(text, path.resolve().name)]
        raise InputError(f"{printable(text)}: no video or image files in this folder")
    if path.is_file():
        return [(text, path.stem)]
    raise InputError(f"{printable(text)}: no such file or folder (and not a glob matching anything)")


def _unique(names: Sequence[str]) -> list[str]:
    """``names`` made unique (case-insensitively): the second ``clip`` is ``clip_2``, the third ``clip_3``."""
    taken: set[str] = set()
    out = []
    for name in names:
        base = name.strip() or "recording"
        candidate, k = base, 1
        while candidate.lower() in taken:
            k += 1
            candidate = f"{base}_{k}"
        taken.add(candidate.lower())
        out.append(candidate)
    return out


def _safe_name(name: str) -> str:
    """A manifest's ``name`` as one folder name (no separators, not . or ..)."""
    cleaned = "".join("_" if ch in '/\\:<>"|?*' or ord(ch) < 32 else ch for ch in name).strip()
    return "recording" if cleaned in ("", ".", "..") else cleaned


def read_manifest(path: Path) -> list[Recording]:
    """The recordings of a manifest CSV (see the module doc); InputError (exit 2) naming the file and row."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            reader = csv.DictReader(handle)
            columns = [c.strip().lower() for c in reader.fieldnames or []]
            if "source" not in columns:
                raise InputError(f"--manifest {printable(path)}: no 'source' column (columns: {', '.join(columns)})")
            unknown = [c for c in columns if c not in MANIFEST_COLUMNS]
            if unknown:
                raise InputError(
                    f"--manifest {printable(path)}: unknown column {unknown[0]!r} "
                    f"(known: {', '.join(MANIFEST_COLUMNS)})"
                )
            rows = [{k.strip().lower(): (v or "").strip() for k, v in row.items() if k is not None} for row in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise InputError(f"--manifest {printable(path)}: cannot read it ({err})") from None
    base = path.parent

    def resolved(text: str) -> str:
        return text if os.path.isabs(text) else str(base / text)

    recordings, names = [], []
    for number, row in enumerate(rows, start=2):  # (line 1: the header)
        if not any(row.values()):
            continue
        if not row.get("source"):
            raise InputError(f"--manifest {printable(path)}: line {number}: empty source")
        source = resolved(row["source"])
        if not (_is_glob(source) or Path(source).exists()):
            raise InputError(
                f"--manifest {printable(path)}: line {number}: {printable(source)}: no such file or folder"
            )
        camera = Path(resolved(row["camera"])) if row.get("camera") else None
        config = Path(resolved(row["config"])) if row.get("config") else None
        name = _safe_name(row["name"]) if row.get("name") else (Path(source).stem or Path(source).parent.name)
        recordings.append(Recording(source, name, camera, config))
        names.append(name)
    if not recordings:
        raise InputError(f"--manifest {printable(path)}: no recordings in it")
    return [Recording(r.source, n, r.camera, r.config) for r, n in zip(recordings, _unique(names), strict=True)]


def find_recordings(sources: Sequence[str], manifest: Path | None) -> list[Recording]:
    """The recordings of the SOURCE arguments (or of ``manifest``), uniquely named; InputError when none."""
    if manifest is not None:
        if sources:
            raise InputError("give SOURCE arguments or --manifest, not both")
        return read_manifest(manifest)
    if not sources:
        raise InputError("no SOURCE given (video files, folders, quoted globs) and no --manifest")
    found: list[tuple[str, str]] = []
    seen: set[str] = set()
    for text in sources:
        for source, name in _expand(text):
            key = os.path.abspath(source)
            if key not in seen:  # the same file named twice (a glob and a folder): replayed once
                seen.add(key)
                found.append((source, name))
    names = _unique([name for _, name in found])
    return [Recording(source, name) for (source, _), name in zip(found, names, strict=True)]


# ============================================================================ what a run is judged by


def _file_print(path: Path) -> list[Any]:
    try:
        stat = path.stat()
    except OSError:
        return [str(path), None, None]
    return [str(path.resolve()), stat.st_size, stat.st_mtime_ns]


def _source_files(source: str) -> list[Path]:
    if _is_glob(source):
        return sorted(Path(p) for p in glob.glob(source))
    path = Path(source)
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.is_file())
    return [path]


def fingerprint(recording: Recording, options: dict[str, Any]) -> str:
    """What decides whether a finished run still stands: the source's files (path, size, modification
    time), the camera and config files (and a camera.yml beside the source, replay's default) and the
    options handed to replay; a SHA-256 hex digest."""
    files = _source_files(recording.source)
    camera = recording.camera or options.get("camera") or Path(recording.source).parent / "camera.yml"
    config = recording.config or options.get("config")
    what = {
        "source": os.path.abspath(recording.source),
        "files": [_file_print(p) for p in files],
        "camera": _file_print(Path(camera)),
        "config": _file_print(Path(config)) if config else None,
        "options": {k: str(v) for k, v in sorted(options.items())},
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def previous_row(out_dir: Path, stamp: str) -> dict[str, Any] | None:
    """The row of a completed earlier run in ``out_dir`` with the same fingerprint ``stamp``, else None."""
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
        saved = json.loads((out_dir / STAMP_FILE).read_text())
    except (OSError, ValueError):
        return None
    if summary.get("status") != "completed" or saved.get("fingerprint") != stamp:
        return None
    row = saved.get("row")
    if not isinstance(row, dict) or row.get("status") != "ok" or not (out_dir / "poses.csv").is_file():
        return None
    return row


# ============================================================================ the runs table

COLUMNS: tuple[tuple[str, str], ...] = (
    ("name", "string"),
    ("source", "string"),
    ("status", "string"),
    ("error", "string"),
    ("frames", "int64"),
    ("fps", "float64"),
    ("detection_rate", "float64"),
    ("tracked_fraction", "float64"),
    ("ambiguous_fraction", "float64"),
    ("lost_fraction", "float64"),
    ("targets", "string"),
    ("wrong_frame_rate", "float64"),
    ("rotation_error_p95_deg", "float64"),
    ("pair_frames", "int64"),
    ("pair_flip_pct", "float64"),
    ("relative_rotation_rms_deg", "float64"),
    ("wall_s", "float64"),
    ("out", "string"),
)


def empty_row(recording: Recording, out_dir: Path) -> dict[str, Any]:
    """A row with every column, figures None."""
    row: dict[str, Any] = dict.fromkeys(name for name, _ in COLUMNS)
    row.update(name=recording.name, source=recording.source, out=str(out_dir))
    return row


def write_runs(out: Path, rows: list[dict[str, Any]]) -> Path:
    """``out/runs.parquet`` (pyarrow) or ``out/runs.csv`` (without it), rows in the recordings' order; written
    to a temporary file and renamed over the old table. The path written."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        pa = None
    if pa is not None:
        schema = pa.schema([(name, getattr(pa, kind)()) for name, kind in COLUMNS])
        table = pa.Table.from_pylist([{name: row.get(name) for name, _ in COLUMNS} for row in rows], schema=schema)
        path, tmp = out / RUNS_FILE, out / (RUNS_FILE + ".tmp")
        pq.write_table(table, tmp)
    else:
        path, tmp = out / RUNS_CSV, out / (RUNS_CSV + ".tmp")
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, [name for name, _ in COLUMNS])
            writer.writeheader()
            for row in rows:
                writer.writerow({name: "" if row.get(name) is None else row[name] for name, _ in COLUMNS})
    os.replace(tmp, path)
    return path


# ============================================================================ the command


@dataclass
class _Tally:
    rows: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped: int = 0


def replay_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options handed to every replay: the batch's own options left out."""
    return {key: value for key, value in vars(args).items() if key not in BATCH_ONLY}


def cmd_batch(args: argparse.Namespace) -> int:
    """``ar-anchor batch SOURCE... --out DIR``: replay every recording, write the runs table; the exit code."""
    from ..run.outputs import prepare_out_dir
    from .batch_task import BatchTask, run_local, run_ray

    if args.video_out is not None:
        raise InputError("--video-out: batch writes one folder per recording; no single annotated video")
    recordings = find_recordings(args.sources, args.manifest)
    for option in ("camera", "config"):
        path = getattr(args, option)
        if path is not None and not Path(path).is_file():
            raise InputError(f"--{option} {printable(path)}: no such file")
    ray_address = args.ray
    if ray_address is not None:
        from .batch_task import require_ray

        require_ray()
    out = (args.out or default_out("batch")).absolute()  # (absolute paths: what a Ray node is given)
    prepare_out_dir(out)
    options = replay_options(args)
    for option in ("camera", "config"):
        if options.get(option) is not None:
            options[option] = Path(options[option]).absolute()
    tally = _Tally()
    tasks = []
    for recording in recordings:
        recording = Recording(os.path.abspath(recording.source), recording.name, recording.camera, recording.config)
        task_options = dict(options)
        if recording.camera is not None:
            task_options["camera"] = recording.camera.absolute()
        if recording.config is not None:
            task_options["config"] = recording.config.absolute()
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
    started = time.monotonic()
    interrupted = False
    bar = _bar(not args.quiet, len(recordings), tally.skipped)
    try:

        def done(row: dict[str, Any]) -> None:
            tally.rows[row["name"]] = row
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"{row['name']}: {row['status']}")
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
        engine = "ray" if ray_address is not None else f"{min(jobs, max(1, len(tasks)))} local process(es)"
        print(
            f"{len(rows)} recording(s): {ok} replayed, {tally.skipped} skipped (already done), {len(failed)} failed"
            f" in {wall:.1f} s ({engine}); table: {table}"
        )
    if interrupted:
        stop = KeyboardInterrupt()
        stop.note, stop.out_dir = f"{table.name} has a row for every recording", out  # type: ignore[attr-defined]
        raise stop
    if failed:
        names = ", ".join(printable(row["name"]) for row in failed[:5]) + (", ..." if len(failed) > 5 else "")
        print(f"ar-anchor: error: {len(failed)} of {len(rows)} recording(s) failed: {names} (see {table})",
              file=sys.stderr)  # fmt: skip
        return EXIT_FAILURE
    return EXIT_OK


def usable_cores() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def _bar(enabled: bool, total: int, done: int) -> Any:
    """A tqdm bar over the recordings on a terminal (None otherwise or with -q)."""
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="batch", unit="recording", leave=False, dynamic_ncols=True)
