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
"""

from __future__ import annotations

import argparse
import contextlib
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
from .options import add_command, add_run_options, assumed_camera_option, default_out, int_at_least, output_path
from .replay import add_replay_options

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".wmv"})
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm"})
MANIFEST_COLUMNS = ("source", "camera", "config", "name")
# the options of the batch command itself (everything else is handed to each replay as it is)
BATCH_ONLY = frozenset(
    {"sources", "manifest", "jobs", "ray", "force", "rigid_sheet", "out", "quiet", "verbose", "command", "func"}
    | {"images_out"}  # (given to the image recordings only, each its own folder: see _run_batch)
)
RUNS_FILE, RUNS_CSV = "runs.parquet", "runs.csv"
STAMP_FILE = "batch.json"
RESERVED_NAMES = (RUNS_FILE, RUNS_CSV, ".ar-anchor.lock")  # files of --out itself: no recording is named so
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
        found = [(str(p), _default_name(str(p))) for p in videos]
        if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in matches):
            found.append((text, _default_name(text)))
        if not found:
            if not matches:
                raise InputError(f"{printable(text)}: no file matches this pattern")
            raise InputError(f"{printable(text)}: the pattern matches {len(matches)} file(s), none a video or an image")
        return found
    path = Path(text)
    if path.is_dir():
        entries = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
        videos = [p for p in entries if p.suffix.lower() in VIDEO_EXTENSIONS]
        if videos:
            return [(str(p), _default_name(str(p))) for p in videos]
        if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in entries):
            return [(text, _default_name(text))]
        raise InputError(f"{printable(text)}: no video or image files in this folder")
    if path.is_file():
        return [(text, _default_name(text))]
    raise InputError(f"{printable(text)}: {_not_a_source(path)}")


def _not_a_file(path: Path, expected: str) -> str:
    """Why ``path`` is not the regular file (or folder) ``expected``: missing, or what it is (never opened: a
    named pipe would block)."""
    from ..sources.checks import file_kind

    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return "no such file" + (" or folder" if "folder" in expected else "")
    except OSError as err:
        return f"cannot be examined ({err.strerror or err})"
    return f"is {file_kind(mode)}, not {expected} (not supported)"


def _not_a_source(path: Path) -> str:
    return _not_a_file(path, "a video file, an image folder or a glob")


def _unique(names: Sequence[str]) -> list[str]:
    """``names`` made unique (case-insensitively): the second ``clip`` is ``clip_2``, the third ``clip_3``; a name
    of a file the batch writes into ``--out`` itself (``runs.parquet``, ``runs.csv``, the lock) gets ``_2`` too."""
    taken: set[str] = {name.lower() for name in RESERVED_NAMES}
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


def _unsafe(ch: str) -> bool:
    code = ord(ch)
    return ch in '/\\:<>"|?*' or code < 0x20 or code == 0x7F or 0x80 <= code < 0xA0 or 0xD800 <= code < 0xE000


def _safe_name(name: str) -> str:
    """A recording's name (a manifest's ``name``, a file stem, a folder's name) as one folder name inside
    ``--out``: separators, control characters and bytes that are not UTF-8 become ``_``; empty, ``.`` and
    ``..`` become ``recording``."""
    cleaned = "".join("_" if _unsafe(ch) else ch for ch in name).strip()
    return "recording" if cleaned in ("", ".", "..") else cleaned


def _default_name(source: str) -> str:
    """The name of a recording whose name is not given: a glob's folder, a folder's name, a file's stem."""
    if _is_glob(source):
        return _safe_name(Path(source).parent.name or "images")
    path = Path(source)
    return _safe_name(path.resolve().name if path.is_dir() else path.stem)


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
        if _is_glob(source):
            _check_manifest_glob(path, number, source)
        elif not (Path(source).is_file() or Path(source).is_dir()):
            raise InputError(
                f"--manifest {printable(path)}: line {number}: {printable(source)}: {_not_a_source(Path(source))}"
            )
        camera = Path(resolved(row["camera"])) if row.get("camera") else None
        config = Path(resolved(row["config"])) if row.get("config") else None
        for column, file in (("camera", camera), ("config", config)):
            if file is not None and not file.is_file():
                raise InputError(
                    f"--manifest {printable(path)}: line {number}: {column} {printable(file)}: "
                    f"{_not_a_file(file, 'a regular file')}"
                )
        name = _safe_name(row["name"]) if row.get("name") else _default_name(source)
        recordings.append(Recording(source, name, camera, config))
        names.append(name)
    if not recordings:
        raise InputError(f"--manifest {printable(path)}: no recordings in it")
    return [Recording(r.source, n, r.camera, r.config) for r, n in zip(recordings, _unique(names), strict=True)]


def _check_manifest_glob(manifest: Path, number: int, pattern: str) -> None:
    """A manifest row's glob is one image sequence (as ``replay`` takes it): it must match an image file."""
    matches = [p for p in glob.glob(pattern) if Path(p).is_file()]
    if any(Path(p).suffix.lower() in IMAGE_EXTENSIONS for p in matches):
        return
    where = f"--manifest {printable(manifest)}: line {number}: {printable(pattern)}"
    if not matches:
        raise InputError(f"{where}: no file matches this pattern")
    raise InputError(
        f"{where}: the pattern matches {len(matches)} file(s), none an image (a glob in a manifest row is one "
        "image sequence; list videos one per row)"
    )


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
    if path.is_dir():  # (its images only: nothing else in the folder is a frame)
        return sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
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
    ("frames_with_markers", "int64"),
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


def _pyarrow() -> Any:
    """``pyarrow`` (and its parquet module loaded), or None when it is not installed."""
    try:
        import pyarrow
        import pyarrow.parquet  # noqa: F401
    except ImportError:
        return None
    return pyarrow


def runs_path(out: Path) -> Path:
    """The runs table a batch into ``out`` writes: ``runs.parquet``, or ``runs.csv`` without pyarrow."""
    return out / (RUNS_FILE if _pyarrow() is not None else RUNS_CSV)


_TABLE_KEYS = frozenset({"name", "source", "status", "error", "out"})  # every batch's table has these columns


def _is_runs_table(path: Path) -> bool:
    """Is ``path`` a runs table a batch wrote (a regular file, not a link, with the table's columns)?"""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        if path.suffix == ".parquet":
            names = _pyarrow().parquet.read_schema(path).names
        else:
            with open(path, newline="", encoding="utf-8") as handle:
                names = next(csv.reader(handle), [])
    except Exception:  # noqa: BLE001 - whatever it is, it is no table of ours
        return False
    return _TABLE_KEYS <= set(names)


def _text(value: Any) -> Any:
    """A string made writable as UTF-8 (bytes of a file name that is not UTF-8 spelled ``\\udcff``)."""
    return value.encode("utf-8", "backslashreplace").decode("utf-8") if isinstance(value, str) else value


def write_runs(out: Path, rows: list[dict[str, Any]]) -> Path:
    """``out/runs.parquet`` (pyarrow) or ``out/runs.csv`` (without it), rows in the recordings' order; written
    to a temporary file of its own and renamed over the old table. The path written; a failure to write it
    is an :class:`~ar_anchor.errors.OutputError` naming it."""
    import secrets

    from ..run.outputs import write_failure

    pa = _pyarrow()
    path = runs_path(out)
    cells = [{name: _text(row.get(name)) for name, _ in COLUMNS} for row in rows]
    tmp = out / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"  # (a new file: never one of the user's)
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    except OSError as err:
        raise write_failure(path, err) from None
    try:
        if pa is not None:
            schema = pa.schema([(column, getattr(pa, kind)()) for column, kind in COLUMNS])
            pa.parquet.write_table(pa.Table.from_pylist(cells, schema=schema), tmp)
        else:
            with open(tmp, "w", newline="", encoding="utf-8") as handle_:
                writer = csv.DictWriter(handle_, [column for column, _ in COLUMNS])
                writer.writeheader()
                for row in cells:
                    writer.writerow({column: "" if value is None else value for column, value in row.items()})
        os.replace(tmp, path)
    except OSError as err:
        raise write_failure(path, err) from None
    finally:
        tmp.unlink(missing_ok=True)
    return path


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


def _image_folder(source: str) -> Path | None:
    """The folder whose files are the frames of an image recording (a folder or a glob); None for a video."""
    if _is_glob(source):
        return Path(source).parent
    return Path(source) if Path(source).is_dir() else None


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


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
    from .batch_task import BatchTask, ray_session

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


def format_runs(rows: list[dict[str, Any]], out: Path) -> str:
    """The batch's table on the console: one line per recording (name, frames, status, frames with markers,
    speed, wall time, output folder), its columns explained below it."""

    def cell(value: Any, form: str) -> str:
        return "-" if value is None else format(value, form)

    width = max([len("recording"), *(len(printable(row["name"])) for row in rows)])
    header = f"{'recording':<{width}} {'frames':>7} {'status':<11} {'markers in':<12} {'fps':>7} {'wall s':>7}  output"
    lines = [header, "-" * len(header)]
    for row in rows:
        frames, markers = row.get("frames"), row.get("frames_with_markers")
        found = "-" if frames is None or markers is None else f"{markers} of {frames}"
        folder = Path(row.get("out") or out / row["name"])
        here = Path.cwd()
        shown = f"{printable(folder.relative_to(here) if _inside(folder, here) else folder)}/"
        lines.append(
            f"{printable(row['name']):<{width}} {cell(frames, 'd'):>7} {printable(row['status']):<11} {found:<12} "
            f"{cell(row.get('fps'), '.1f'):>7} {cell(row.get('wall_s'), '.1f'):>7}  {shown}"
        )
    lines += [
        "markers in: frames with markers found, of the frames replayed; fps: frames tracked per second;",
        "  wall s: the replay's time, start to end (skipped: its earlier run's)",
    ]
    return "\n".join(lines)


def _outputs_line(out: Path, table: Path, rows: list[dict[str, Any]]) -> str:
    """The batch's last line: its table, then each run's folder with the files in it (every part of a split
    recording), for the recordings replayed now or before (skipped)."""
    from .report import run_files

    folders = []
    for row in rows:
        folder = out / row["name"]
        if row["status"] not in ("ok", "skipped") or not folder.is_dir():
            continue
        try:
            summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            summary = {}
        names = [*run_files(folder, summary), *([STAMP_FILE] if (folder / STAMP_FILE).is_file() else [])]
        folders.append(f"{printable(row['name'])}/ ({', '.join(names)})")
    return f"outputs: {printable(out)}/ ({', '.join([printable(table.name), *folders])})"


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
