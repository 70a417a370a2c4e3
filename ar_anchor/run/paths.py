"""Where a run writes, checked before anything is written: no output on an input, no two outputs on one file,
one run per output directory.

:func:`check_paths` compares every output (the files a run writes into ``--out``, ``--video-out``, the
``--record`` raw video, calibrate's ``--out`` and ``--rrd``) with every input (the source's files and
timestamps sidecar, the camera file, the config, its layouts and overlay meshes) and with each other: by
resolved path (symbolic links followed) and by device and inode (hard links), so that a run can never
overwrite the user's files. A clash is an :class:`~ar_anchor.errors.InputError` (exit 2) naming both.

:func:`claim_out_dir` then takes the output directory for one run: it creates it, takes its lock file
(:class:`OutDirLock`, ``.ar-anchor.lock``: a second run on a busy ``--out`` is refused, exit 2; the lock of
a process that no longer exists is taken over, with a note) and clears the previous run's own files
(:func:`clear_previous_run`), so that ``rerun recording*.rrd`` never mixes two runs. Only file names a run
writes are cleared, never an input of this run and never anything else.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from ..errors import InputError, OutputError, printable
from ..sources.files import IMAGE_EXTENSIONS
from .outputs import prepare_out_dir

__all__ = [
    "FRAMES_CSV",
    "LOCK_NAME",
    "OutDirLock",
    "Named",
    "check_paths",
    "check_video_out",
    "claim_out_dir",
    "clear_previous_run",
    "config_inputs",
    "run_output_paths",
    "source_inputs",
]

log = logging.getLogger(__name__)

Named = tuple[str, Path]  # (what the user calls it: "--video-out", "SOURCE", ...; the path)

LOCK_NAME = ".ar-anchor.lock"
# the files a run writes into --out (recording.partN.rrd and the annotated video are matched apart)
RUN_FILES = ("poses.csv", "summary.json", "summary.json.tmp", "recording.rrd", "raw.mkv", "raw.mkv.timestamps.csv")
FRAMES_CSV = "frames.csv"  # a replay of images: which file each frame is (cleared with the run's other files)
_PART = re.compile(r"recording\.part[0-9]+\.rrd")


def _identity(path: Path) -> tuple[Path, tuple[int, int] | None]:
    """``path`` resolved (links followed, not required to exist) and its (device, inode) when it exists."""
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError):  # a symbolic link loop: compare it as written
        resolved = Path(os.path.abspath(path))
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return resolved, None
    return resolved, (st.st_dev, st.st_ino)


def _shown(named: Named) -> str:
    option, path = named
    return f"{option} {printable(path)}"


def check_paths(outputs: Sequence[Named], inputs: Sequence[Named]) -> None:
    """Refuse (:class:`InputError`) an output that is an input or another output: same resolved path, or the
    same file by device and inode. ``outputs`` and ``inputs`` are (option, path) pairs, named in the message."""
    seen_inputs = [(named, *_identity(named[1])) for named in inputs]
    seen_outputs: list[tuple[Named, Path, tuple[int, int] | None]] = []
    for named in outputs:
        resolved, inode = _identity(named[1])
        for other, other_resolved, other_inode in seen_inputs:
            if resolved == other_resolved or (inode is not None and inode == other_inode):
                raise InputError(
                    f"{_shown(named)}: is the input {_shown(other)}; refusing to overwrite it (write somewhere else)"
                )
        for other, other_resolved, other_inode in seen_outputs:
            if resolved == other_resolved or (inode is not None and inode == other_inode):
                if other[0] == named[0] and other[1] == named[1]:
                    continue  # the same output named twice
                raise InputError(f"{_shown(named)}: is also {_shown(other)}; two outputs cannot share one file")
        seen_outputs.append((named, resolved, inode))


def check_video_out(video_out: Path | None, out_dir: Path) -> None:
    """``--video-out`` must name a file whose folder exists (or is ``out_dir``, created by the run)."""
    if video_out is None:
        return
    if not str(video_out) or video_out.is_dir():
        raise InputError(f"--video-out {printable(video_out)}: is a directory (give the video file to write)")
    parent = video_out.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(f"--video-out {printable(video_out)}: {printable(parent)} is a file, not a folder")
    if not parent.exists() and _identity(parent)[0] != _identity(out_dir)[0]:
        raise InputError(f"--video-out {printable(video_out)}: folder {printable(parent)} does not exist")


def run_output_paths(
    out_dir: Path, *, record_raw: bool = False, video_out: Path | None = None, extra: Iterable[Named] = ()
) -> list[Named]:
    """The files a tracking run writes (``--out``'s fixed names, ``--record``'s, ``--video-out``)."""
    outputs: list[Named] = [("--out", out_dir / name) for name in RUN_FILES[:4]]
    if record_raw:
        outputs += [("--record", out_dir / name) for name in RUN_FILES[4:]]
    outputs += list(extra)
    if video_out is not None:
        outputs.append(("--video-out", video_out))
    return outputs


def _parts_among(inputs: Sequence[Named], outputs: Sequence[Named], out_dir: Path) -> None:
    """``recording.partN.rrd`` (any N) in ``out_dir`` is an output too: refuse an input or output named so."""
    where = _identity(out_dir)[0]
    for named in (*inputs, *outputs):
        resolved = _identity(named[1])[0]
        if resolved.parent == where and _PART.fullmatch(resolved.name):
            raise InputError(
                f"{_shown(named)}: is where the run's recording goes on ({printable(out_dir)}/recording.partN.rrd); "
                "refusing to overwrite it (give another --out)"
            )


def source_inputs(source: Any, option: str = "SOURCE") -> list[Named]:
    """A frame source's input files: a video and its ``.timestamps.csv`` sidecar, or the images read."""
    files: list[Named] = []
    path = getattr(source, "path", None)
    if isinstance(path, Path):
        files.append((option, path))
        sidecar = path.with_name(path.name + ".timestamps.csv")
        if sidecar.exists():
            files.append((f"{option}'s timestamps", sidecar))
    files += [(option, Path(p)) for p in getattr(source, "files", ())]
    return files


def spec_inputs(spec: str, option: str = "SOURCE") -> list[Named]:
    """The input files of a source given as text (a file, a folder of images or a glob), without opening it."""
    import glob

    path = Path(spec)
    if path.is_dir():
        return [(option, p) for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS]
    if any(ch in spec for ch in "*?["):
        return [(option, Path(p)) for p in glob.glob(spec)]
    if path.exists():
        sidecar = path.with_name(path.name + ".timestamps.csv")
        return [(option, path)] + ([(f"{option}'s timestamps", sidecar)] if sidecar.exists() else [])
    return []


def config_inputs(config: Any, config_path: Path | None, camera_path: Path | None) -> list[Named]:
    """The files a tracker config was read from: ``--camera``, ``--config``, its layouts and overlay meshes."""
    files: list[Named] = []
    if camera_path is not None:
        files.append(("--camera", Path(camera_path)))
    if config_path is not None:
        files.append(("--config", Path(config_path)))
    for board in getattr(config, "boards", ()):
        source = getattr(board, "layout_source", "")
        if source and source != "inline":
            files.append((f"--config's layout of board {board.name}", Path(source)))
    for overlay in getattr(config, "overlays", ()):
        if overlay.kind == "mesh" and overlay.path and not overlay.path.startswith("builtin:"):
            files.append((f"--config's overlay model for {overlay.target}", Path(overlay.path)))
    return files


# ---------------------------------------------------------------------------------------------- the lock
_HELD: dict[Path, int] = {}  # output directories this process holds -> how many holders


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return pid > 0
    return True


class OutDirLock:
    """``<out>/.ar-anchor.lock``: one run per output directory. The file is created whole (written beside it,
    then hard-linked into place, which fails when it exists) and holds the owner's pid and host; a lock of
    this host whose process is gone is taken over with a warning. Re-entrant within one process. ``option``: what
    the user calls the directory in messages (``--out``; ``RUN_DIR`` for an export into the run's folder)."""

    def __init__(self, out_dir: Path, option: str = "--out") -> None:
        self.out_dir = out_dir
        self.option = option
        self.path = out_dir / LOCK_NAME
        self._key = _identity(out_dir)[0]
        self._held = False

    def acquire(self) -> None:
        """Take the lock, or :class:`InputError` naming the directory and the run that holds it."""
        if _HELD.get(self._key):
            _HELD[self._key] += 1
            self._held = True
            return
        content = f"{os.getpid()} {socket.gethostname()}\n"
        temporary = self.out_dir / f"{LOCK_NAME}.{os.getpid()}.tmp"
        try:
            temporary.write_text(content, encoding="utf-8")
            for _attempt in range(2):
                try:
                    os.link(temporary, self.path)
                    break
                except FileExistsError:
                    self._take_over_stale()
            else:
                raise InputError(f"{self.option} {printable(self.out_dir)}: another run is starting in it")
        except OSError as err:
            raise OutputError(
                f"{self.option} {printable(self.out_dir)}: cannot create {LOCK_NAME} ({err.strerror or err})"
            ) from None
        finally:
            # (on a read-only file system even removing a file that is not there fails: that error is not the
            # one to report, and there is nothing to remove)
            with suppress(OSError):
                temporary.unlink(missing_ok=True)
        _HELD[self._key] = 1
        self._held = True

    def _take_over_stale(self) -> None:
        """The existing lock: a live run's is refused; a dead process's (this host) is removed."""
        try:
            pid_text, _, host = self.path.read_text(encoding="utf-8").strip().partition(" ")
            pid = int(pid_text)
        except (OSError, ValueError):
            pid, host = -1, socket.gethostname()  # unreadable or half written: nobody can hold it
        if host == socket.gethostname() and not _pid_alive(pid):
            log.warning("%s %s: taking over the lock of a run that is gone", self.option, printable(self.out_dir))
            self.path.unlink(missing_ok=True)
            return
        raise InputError(
            f"{self.option} {printable(self.out_dir)}: another run (pid {pid} on {printable(host)}) is writing into "
            f"it; give another --out (or remove {LOCK_NAME} if that run is gone)"
        )

    def release(self) -> None:
        """Give the lock back (the file is removed when this process's last holder releases it)."""
        if not self._held:
            return
        self._held = False
        _HELD[self._key] -= 1
        if _HELD[self._key] == 0:
            del _HELD[self._key]
            try:
                self.path.unlink(missing_ok=True)
            except OSError as err:
                log.warning(
                    "%s %s: cannot remove %s (%s)", self.option, printable(self.out_dir), LOCK_NAME, err.strerror
                )

    def __enter__(self) -> OutDirLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


# ---------------------------------------------------------------------------------------------- clearing
def clear_previous_run(out_dir: Path, keep: Sequence[Named] = ()) -> list[str]:
    """Remove the previous run's own files from ``out_dir`` (its fixed names, ``recording.partN.rrd`` and the
    annotated video its ``summary.json`` names inside ``out_dir``); regular files only, never one of ``keep``
    (this run's inputs). ``summary.json`` itself stays: the new run replaces it. Only a folder whose
    ``summary.json`` says a run wrote it is cleared: files of those names in any other folder are the
    user's. Returns the names removed."""
    if not _previous_run_here(out_dir):
        return []
    kept = {_identity(path)[0] for _, path in keep}
    names = [name for name in (*RUN_FILES, FRAMES_CSV) if name != "summary.json"]
    names += [p.name for p in out_dir.iterdir() if _PART.fullmatch(p.name)]
    names += _previous_video(out_dir)
    removed = []
    for name in names:
        path = out_dir / name
        if path.is_symlink() or not path.is_file() or _identity(path)[0] in kept:
            continue
        try:
            path.unlink()
        except OSError as err:
            raise OutputError(f"--out {printable(path)}: cannot remove the last run's file ({err.strerror})") from None
        removed.append(name)
    if removed:
        log.info("--out %s: removed the previous run's %s", printable(out_dir), ", ".join(removed))
    return removed


_SUMMARY_KEYS = ("status", "frames_with_pose", "latency_ms")  # a run's summary.json has these, from its start


def _previous_run_here(out_dir: Path) -> bool:
    """Does ``out_dir`` hold a run's ``summary.json``? Every run writes one as it starts (status ``running``)."""
    try:
        data = json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and all(key in data for key in _SUMMARY_KEYS)


def _not_ours(out_dir: Path, outputs: Sequence[Named]) -> list[str]:
    """The files of ``out_dir`` a run would write over (its fixed names, ``recording.partN.rrd``) when no run
    wrote the folder: they are the user's."""
    if not out_dir.is_dir() or _previous_run_here(out_dir):
        return []
    names = [path.name for option, path in outputs if option in ("--out", "--record") and path.parent == out_dir]
    names += [p.name for p in out_dir.iterdir() if _PART.fullmatch(p.name)]
    return [name for name in names if (out_dir / name).exists() or (out_dir / name).is_symlink()]


def _previous_video(out_dir: Path) -> list[str]:
    """The annotated video the previous run's ``summary.json`` names, when it lies in ``out_dir``."""
    try:
        data = json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))
        video = Path(data["video_out"]["path"])
    except (OSError, ValueError, KeyError, TypeError):
        return []
    if not video.is_absolute():
        video = Path.cwd() / video
    return [video.name] if _identity(video)[0].parent == _identity(out_dir)[0] else []


@contextmanager
def claim_out_dir(out_dir: Path, outputs: Sequence[Named], inputs: Sequence[Named]) -> Iterator[Path]:
    """Check ``outputs`` against ``inputs`` (and ``--video-out``), create ``out_dir``, lock it, clear the
    previous run's files; the lock is held until the block ends."""
    check_paths(outputs, inputs)
    _parts_among(inputs, outputs, out_dir)
    if theirs := _not_ours(out_dir, outputs):
        raise InputError(
            f"--out {printable(out_dir)}: holds {', '.join(theirs)}, which no ar-anchor run wrote (no run's "
            "summary.json there); a run would overwrite them: give a new or empty folder"
        )
    for option, path in outputs:
        if option == "--video-out":
            check_video_out(path, out_dir)
    created = not out_dir.exists()
    out = prepare_out_dir(out_dir)
    try:
        with OutDirLock(out):
            clear_previous_run(out, keep=inputs)
            yield out
    except InputError:
        if created:  # bad input found before the run wrote anything: no empty folder left behind
            with suppress(OSError):
                out.rmdir()
        raise
