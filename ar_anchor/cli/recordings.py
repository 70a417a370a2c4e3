"""The recordings of ``ar-anchor batch``: what a SOURCE argument or a ``--manifest`` row is (see
:mod:`.batch`), each as a :class:`Recording` with the unique, safe name of its output folder, and the names
of the files a batch writes into ``--out`` itself (no recording is named so).
"""

from __future__ import annotations

import csv
import glob
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError, printable

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".wmv"})
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm"})
MANIFEST_COLUMNS = ("source", "camera", "config", "name")
RUNS_FILE, RUNS_CSV = "runs.parquet", "runs.csv"
STAMP_FILE = "batch.json"
RESERVED_NAMES = (RUNS_FILE, RUNS_CSV, ".ar-anchor.lock")  # files of --out itself: no recording is named so
_GLOB_CHARS = frozenset("*?[")


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


def _image_folder(source: str) -> Path | None:
    """The folder whose files are the frames of an image recording (a folder or a glob); None for a video."""
    if _is_glob(source):
        return Path(source).parent
    return Path(source) if Path(source).is_dir() else None


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents
