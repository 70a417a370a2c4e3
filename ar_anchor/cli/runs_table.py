"""The runs table of ``ar-anchor batch``: what a finished run is judged by (its fingerprint, the row kept
beside it), the table's columns, writing it (``runs.parquet``, or ``runs.csv`` without pyarrow) and showing it
on the console with the batch's last line of outputs.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import os
from pathlib import Path
from typing import Any

from ..errors import printable
from .recordings import IMAGE_EXTENSIONS, RUNS_CSV, RUNS_FILE, STAMP_FILE, Recording, _inside, _is_glob

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


def format_runs(rows: list[dict[str, Any]], out: Path) -> str:
    """The batch's table on the console: one line per recording (name, frames, status, frames with markers,
    speed, wall time, output folder: ``-`` where none was made), its columns explained below it."""

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
        if not folder.is_dir():  # (a recording that failed before its run began: nothing written)
            shown = "-"
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
