"""Export a finished run (:func:`export_run`): its ``poses.csv`` in the forms robotics tools read.

Formats (:data:`FORMATS`), each written beside the run (or into another folder):

- ``csv``: ``poses_ext.csv`` (:class:`~.tables.PosesExtWriter`),
- ``tum``: ``tum/<target>.txt`` (:class:`~.tables.TumWriter`),
- ``mcap``: ``run.mcap``, a ROS 2 bag (:class:`~.bag.McapExportWriter`), with the images when a frame source
  is given (the run's ``raw.mkv``, the video it replayed, or the synthetic scene rendered again).

``poses.csv`` is read once, frame by frame, and every format takes each frame in turn. Everything is
written into a temporary folder inside the output folder and moved into place only when every format is
complete: an export that fails (a malformed row, a video that is not the run's) leaves the previous
export, and the run's own outputs, as they were.

The run side (:func:`camera_summary`, :func:`clear_previous_exports`): a run records the camera it tracked
with (scaled to the source) in ``summary.json`` (``camera``), which the MCAP export reads for CameraInfo
(``camera.yml``, which ``live --record`` writes, first); a new run in an old run's folder removes that
run's exports, which would no longer match its ``poses.csv``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...camera import CameraModel
from ...errors import InputError, OutputError, printable
from ...run.outputs import prepare_out_dir
from ...run.paths import Named, _previous_run_here, check_paths
from ...run.written import WrittenFiles, refuse_theirs
from ...sources.base import Frame, FrameSource
from .poses import PoseRow, frames_of, read_poses_csv
from .tables import FrameNames, PosesExtWriter, TumWriter

__all__ = [
    "CAMERA_YML",
    "FORMATS",
    "ExportResult",
    "camera_summary",
    "clear_previous_exports",
    "export_output_paths",
    "export_run",
    "parse_formats",
]

log = logging.getLogger(__name__)

FORMATS = ("csv", "tum", "mcap")
POSES_EXT = "poses_ext.csv"
TUM_DIR = "tum"
MCAP = "run.mcap"
CAMERA_YML = "camera.yml"
RAW_VIDEO = "raw.mkv"
_TUM_FILE = ("marker_", "board_")  # the TUM files an export writes (tum/ may hold the user's files too)

Progress = Callable[[int, int | None], Any]
Opener = Callable[[], AbstractContextManager[FrameSource]]


@dataclass(frozen=True)
class ExportResult:
    """What an export wrote: the files (in place), pose frames and rows read, images and messages written."""

    out_dir: Path
    files: list[Path]
    frames: int
    rows: int
    images: int = 0
    messages: dict[str, int] = field(default_factory=dict)


def parse_formats(text: str) -> tuple[str, ...]:
    """``csv,tum,mcap`` (any of them, comma-separated) -> the formats, in :data:`FORMATS` order."""
    asked = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [part for part in asked if part not in FORMATS]
    if unknown or not asked:
        raise ValueError(f"expected formats among {','.join(FORMATS)} (comma-separated), got {text!r}")
    return tuple(name for name in FORMATS if name in asked)


def export_output_paths(out_dir: Path, formats: Sequence[str] = FORMATS, option: str = "--out") -> list[Named]:
    """The files (and the ``tum`` folder) an export into ``out_dir`` writes, as (option, path) pairs."""
    names = {"csv": POSES_EXT, "tum": TUM_DIR, "mcap": MCAP}
    return [(option, Path(out_dir) / names[name]) for name in formats]


# ---------------------------------------------------------------------------------------------- the run side
def camera_summary(camera: CameraModel) -> dict[str, Any]:
    """``camera`` for ``summary.json`` (key ``camera``): what the run tracked with, scaled to its source."""
    return {
        "image_width": camera.width,
        "image_height": camera.height,
        "camera_matrix": [[float(v) for v in row] for row in camera.camera_matrix],
        "distortion_coefficients": [float(v) for v in camera.dist_coeffs],
    }


def _written(out_dir: Path) -> WrittenFiles:
    """What earlier exports wrote into ``out_dir`` (``.ar-anchor-export.json``). A run's folder from before that
    manifest existed (a run's ``summary.json``, no manifest) counts its export names as an export's, as then."""
    written = WrittenFiles(out_dir, "export")
    if not written.exists and _previous_run_here(out_dir):
        names = [POSES_EXT, MCAP]
        tum = out_dir / TUM_DIR
        if tum.is_dir() and not tum.is_symlink():
            names += [f"{TUM_DIR}/{p.name}" for p in tum.iterdir() if _is_tum_name(p.name)]
        for name in names:
            written.record(name)
    return written


def _is_tum_name(name: str) -> bool:
    return name.endswith(".txt") and name.startswith(_TUM_FILE)


def clear_previous_exports(out_dir: Path) -> list[str]:
    """At a run's start, in its claimed ``out_dir`` (new, or a previous run's): remove the exports an earlier
    export wrote there, when a run wrote it before (they belong to the ``poses.csv`` this run replaces); files
    of those names that no export wrote are the user's and stay, and so do the exports of another run in a
    folder no run wrote. Returns the names removed."""
    out_dir = Path(out_dir)
    if not _previous_run_here(out_dir):
        return []
    written = _written(out_dir)
    removed = []
    for name in written.names():
        try:
            (out_dir / name).unlink()
        except OSError as err:
            raise OutputError(
                f"--out {printable(out_dir / name)}: cannot remove an old export ({err.strerror})"
            ) from None
        written.forget(name)
        removed.append(name)
    tum = out_dir / TUM_DIR
    if any(name.startswith(f"{TUM_DIR}/") for name in removed) and tum.is_dir() and not tum.is_symlink():
        with suppress(OSError):  # not empty: the user's files stay
            tum.rmdir()
    if written.exists:
        written.save()
    if removed:
        log.info("--out %s: removed the previous run's exports %s", printable(out_dir), ", ".join(removed))
    return removed


# ---------------------------------------------------------------------------------------------- the export
def _run_frames(run_dir: Path) -> int | None:
    """The frames the run processed (``summary.json``), None when it does not say."""
    try:
        frames = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))["frames"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return frames if isinstance(frames, int) and frames >= 0 else None


def check_run_dir(run_dir: Path) -> Path:
    """``run_dir`` as a run's folder (it holds ``poses.csv``), or an :class:`InputError` saying what it is."""
    if not run_dir.exists():
        raise InputError(f"RUN_DIR {printable(run_dir)}: no such directory")
    if not run_dir.is_dir():
        raise InputError(f"RUN_DIR {printable(run_dir)}: is a file, not a run's output directory")
    poses = run_dir / "poses.csv"
    if not poses.is_file():
        raise InputError(
            f"RUN_DIR {printable(run_dir)}: has no poses.csv: not the output directory of an ar-anchor run "
            "(demo, replay, live)"
        )
    return poses


def run_camera(run_dir: Path) -> CameraModel:
    """The camera the run tracked with: its ``camera.yml`` (``live --record``) or the ``camera`` of its
    ``summary.json``; an :class:`InputError` when it has neither."""
    path = run_dir / CAMERA_YML
    if path.is_file():
        return CameraModel.from_yaml(path)
    summary_path = run_dir / "summary.json"
    try:
        entry = json.loads(summary_path.read_text(encoding="utf-8"))["camera"]
    except (OSError, ValueError, KeyError, TypeError):
        raise InputError(
            f"RUN_DIR {printable(run_dir)}: neither a {CAMERA_YML} nor a camera in its summary.json (runs record it "
            "since exports exist): give --camera FILE, the calibration the run tracked with"
        ) from None
    try:
        return CameraModel(
            np.array(entry["camera_matrix"], dtype=np.float64),
            np.array(entry["distortion_coefficients"], dtype=np.float64),
            entry["image_width"],
            entry["image_height"],
        )
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{printable(summary_path)}: camera: not a camera ({printable(err)})") from None


def default_images(run_dir: Path) -> Opener:
    """The run's own frames: its ``raw.mkv`` (``live --record``); an :class:`InputError` when it has none."""
    video = run_dir / RAW_VIDEO
    if not video.is_file():
        raise InputError(
            f"--images: RUN_DIR {printable(run_dir)} has no {RAW_VIDEO} (live --record): give --video SOURCE, the "
            "video or images the run tracked"
        )
    from ...sources.open import open_source  # noqa: PLC0415

    return lambda: open_source(video, live=False)


def export_run(
    run_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str] | None = None,
    *,
    formats: Sequence[str] = FORMATS,
    camera: CameraModel | None = None,
    images: Opener | None = None,
    progress: Progress | None = None,
    inputs: Sequence[Named] = (),
) -> ExportResult:
    """Export the run in ``run_dir`` (its ``poses.csv``) as ``formats`` into ``out_dir`` (default ``run_dir``).

    ``camera``: for the MCAP's CameraInfo (default :func:`run_camera`: the run's ``camera.yml`` or the camera
    its ``summary.json`` records). ``images``: opens the frame
    source whose frames go into the MCAP (None: no images); its frames must be the run's (same indices and
    timestamps as ``poses.csv``), up to the frames the run processed (``summary.json``).
    ``progress(done, total)`` after each frame. ``inputs``: further input files (option, path) that no
    output may overwrite. Bad input is an :class:`InputError` naming the file; nothing is moved into place
    unless every format is complete.
    """
    run_dir = Path(run_dir)
    poses_csv = check_run_dir(run_dir)
    formats = tuple(name for name in FORMATS if name in formats)
    if not formats:
        raise InputError("--formats: no format to write")
    if images is not None and "mcap" not in formats:
        raise InputError("--images: images go into the MCAP file: add mcap to --formats")
    if "mcap" in formats and camera is None:
        camera = run_camera(run_dir)
    out = Path(out_dir) if out_dir is not None else run_dir
    outputs = export_output_paths(out, formats)
    check_paths(outputs, [("RUN_DIR's poses.csv", poses_csv), *inputs])
    option = "RUN_DIR" if _same_folder(out, run_dir) else "--out"
    if out.is_dir():
        names = [{"csv": POSES_EXT, "mcap": MCAP}[name] for name in formats if name != "tum"]
        _refuse_theirs(out, option, _written(out).theirs(names))
    out = prepare_out_dir(out, option)
    tum = out / TUM_DIR
    if "tum" in formats and (tum.is_symlink() or (tum.exists() and not tum.is_dir())):
        raise OutputError(f"{printable(tum)}: is not a folder (the TUM files go into {TUM_DIR}/)")
    work = out / f".export-{os.getpid()}.tmp"
    shutil.rmtree(work, ignore_errors=True)
    try:
        work.mkdir()
        (work / TUM_DIR).mkdir()
    except OSError as err:
        raise OutputError(f"--out {printable(out)}: cannot write ({err.strerror or err})") from None
    try:
        result = _export(run_dir, poses_csv, work, formats, camera, images, progress)
        files = _move_into_place(work, out, formats, option)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    _warn_of_the_run(run_dir, result.rows)
    return ExportResult(out, files, result.frames, result.rows, result.images, result.messages)


_ENDED = {
    "interrupted": "was interrupted",
    "failed": "failed",
    "running": "did not finish (it was still running or was killed)",
}


def _warn_of_the_run(run_dir: Path, rows: int) -> None:
    """A warning when the exports are of a run that did not complete (its ``summary.json``), or hold no pose."""
    try:
        status = json.loads((run_dir / "summary.json").read_text(encoding="utf-8")).get("status")
    except (OSError, ValueError, AttributeError):
        status = None
    where = f"RUN_DIR {printable(run_dir)}"
    if status in _ENDED:
        log.warning(
            "%s: the run %s (its summary.json): the exports hold the %d pose(s) it wrote", where, _ENDED[status], rows
        )
    elif rows == 0:
        log.warning("%s: its poses.csv holds no pose: the exports are empty", where)


@dataclass
class _Counts:
    frames: int = 0
    rows: int = 0
    images: int = 0
    messages: dict[str, int] = field(default_factory=dict)


def _export(
    run_dir: Path,
    poses_csv: Path,
    work: Path,
    formats: tuple[str, ...],
    camera: CameraModel | None,
    images: Opener | None,
    progress: Progress | None,
) -> _Counts:
    from .bag import McapExportWriter  # noqa: PLC0415 - mcap is imported only when it is written

    names = FrameNames()
    csv_writer = PosesExtWriter(work / POSES_EXT) if "csv" in formats else None
    tum = TumWriter(work / TUM_DIR, names) if "tum" in formats else None
    bag = None
    counts = _Counts()
    try:
        if "mcap" in formats:
            assert camera is not None
            bag = McapExportWriter(work / MCAP, camera, names)

        def take(group: list[PoseRow]) -> None:
            for row in group:  # two targets of one export name: refused at the row of the second
                names(row.target, f"{printable(poses_csv)}: line {row.line}, column target")
            counts.frames += 1
            counts.rows += len(group)
            if csv_writer is not None:
                csv_writer.write(group)
            if tum is not None:
                tum.write(group)
            if bag is not None:
                bag.write_poses(group)

        groups = frames_of(read_poses_csv(poses_csv))
        if images is None:
            for group in groups:
                if bag is not None:
                    bag.write_camera_info(group[0].timestamp_ns)
                take(group)
                if progress is not None:
                    progress(counts.frames, None)
        else:
            assert bag is not None
            with images() as source:
                counts.images = _with_images(source, groups, bag, take, _run_frames(run_dir), progress)
        if csv_writer is not None:
            csv_writer.close()
        if tum is not None:
            tum.close()
        if bag is not None:
            bag.close()
            counts.messages = dict(bag.messages)
            bag = None
    finally:
        if bag is not None:
            bag.abandon()
    return counts


def _source_name(source: FrameSource) -> str:
    path = getattr(source, "path", None) or source.info.video_path
    return printable(path) if path is not None else "the run's frames"


def _with_images(
    source: FrameSource,
    groups: Iterator[list[PoseRow]],
    bag: Any,
    take: Callable[[list[PoseRow]], None],
    limit: int | None,
    progress: Progress | None,
) -> int:
    """Every frame of ``source`` (up to ``limit``) as image + camera info, each pose frame's /tf beside its image;
    the frames must be the run's: every frame of ``poses.csv`` found in the source, at the same time."""
    name = _source_name(source)
    if tuple(source.resolution) != bag.camera.size:  # a --camera calibrated at another size, as the run scaled it
        try:
            bag.camera = bag.camera.scaled_to(*source.resolution)
        except InputError as err:
            raise InputError(f"{name}: {err}") from None
    total = source.info.frame_count if limit is None else limit
    pending = next(groups, None)
    written = 0
    last: Frame | None = None
    for frame in source:
        if limit is not None and written >= limit:
            break
        if pending is not None and pending[0].frame < frame.index:
            where = f"frame {frame.index} follows {last.index}" if last else f"its frames start at frame {frame.index}"
            raise InputError(_missing(name, pending[0], where))
        bag.write_camera_info(frame.timestamp_ns)
        bag.write_image(frame.image, frame.timestamp_ns)
        if pending is not None and pending[0].frame == frame.index:
            if pending[0].timestamp_ns != frame.timestamp_ns:
                raise InputError(
                    f"{name}: frame {frame.index} is at {frame.timestamp_ns * 1e-9:.9f} s, in poses.csv (line "
                    f"{pending[0].line}) at {pending[0].timestamp_text} s: not the frames of this run"
                )
            take(pending)
            pending = next(groups, None)
        written += 1
        last = frame
        if progress is not None:
            progress(written, total)
    if pending is not None:
        where = "it has no frames" if last is None else f"its frames end at frame {last.index}"
        if limit is not None and written >= limit:
            where += f", the {limit} frames the run processed (summary.json)"
        raise InputError(_missing(name, pending[0], where))
    return written


def _missing(name: str, row: PoseRow, where: str) -> str:
    return f"{name}: has no frame {row.frame} (poses.csv line {row.line}; {where}): not the frames of this run"


def _same_folder(one: Path, other: Path) -> bool:
    try:
        return one.resolve() == other.resolve()
    except (OSError, RuntimeError):
        return os.path.abspath(one) == os.path.abspath(other)


def _refuse_theirs(out: Path, option: str, theirs: list[str]) -> None:
    """An :class:`InputError` when ``theirs`` (files an export would write over, which no export wrote) is not empty."""
    refuse_theirs(out, theirs, not_written_by="no ar-anchor export wrote", writer="the export", option=option)


def _move_into_place(work: Path, out: Path, formats: tuple[str, ...], option: str = "--out") -> list[Path]:
    """Move the finished exports from ``work`` into ``out``, replacing only what an earlier export wrote there (its
    TUM files of targets this run has not are removed); their paths. A file of the user's in the way refuses
    the whole move (:class:`InputError`: nothing is moved); ``.ar-anchor-export.json`` lists what is in place."""
    names = []
    if "csv" in formats:
        names.append(POSES_EXT)
    if "tum" in formats:
        names += [f"{TUM_DIR}/{new.name}" for new in sorted((work / TUM_DIR).iterdir())]
    if "mcap" in formats:
        names.append(MCAP)
    written = _written(out)
    _refuse_theirs(out, option, written.theirs(names))
    files = []
    try:
        if "tum" in formats:
            tum = out / TUM_DIR
            if tum.is_symlink() or (tum.exists() and not tum.is_dir()):
                raise OutputError(f"{printable(tum)}: is not a folder (the TUM files go into {TUM_DIR}/)")
            tum.mkdir(exist_ok=True)
            for old in written.names():  # the previous export's trajectories of targets this one has not
                if old.startswith(f"{TUM_DIR}/") and old not in names:
                    (out / old).unlink()
                    written.forget(old)
        for name in names:
            os.replace(work / name, out / name)
            written.record(name)
            files.append(out / name)
    except OSError as err:
        problem = err.strerror or err
        raise OutputError(f"{option} {printable(out)}: cannot move the exports into place ({problem})") from None
    finally:
        written.save()
    return files
