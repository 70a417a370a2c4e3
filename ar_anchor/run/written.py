"""What a command wrote into a folder, so that it replaces only its own files (the rule of every command that
writes: a file it did not write is never replaced).

:class:`WrittenFiles` keeps ``<folder>/.ar-anchor-<command>.json``: each file the command wrote there (its path
relative to the folder) with its size and modification time when written. A file of that name with another
size or time (the user's own, put there since, or one they edited) is not the command's any more; a symbolic
link never is. A run's own files (``poses.csv``, the recording) follow the folder-wide rule of
:func:`~ar_anchor.run.paths.clear_previous_run` (a run's ``summary.json`` is there); the files a command writes
beside them or into a folder of the user's (``export``'s ``poses_ext.csv``, ``run.mcap``, ``tum/*.txt``;
``markers``' sheets) follow this one.
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterable
from pathlib import Path

from ..errors import InputError, OutputError, printable

__all__ = ["WrittenFiles", "refuse_theirs"]


def _inside_name(name: object) -> bool:
    """Is ``name`` a relative path below the folder (no ``..``, no absolute path, no empty part)?"""
    if not isinstance(name, str) or not name or "\x00" in name or "\\" in name or name.startswith("/"):
        return False
    return all(part not in ("", ".", "..") for part in name.split("/"))


def refuse_theirs(out: Path, theirs: list[str], *, not_written_by: str, writer: str, option: str = "--out") -> None:
    """An :class:`InputError` when ``theirs`` (files ``writer`` would write over, which ``not_written_by`` says
    who did not write) is not empty: ``--out D: holds a, b, which no ar-anchor export wrote; the export would
    overwrite them: move them or give another --out``."""
    if theirs:
        shown = ", ".join(printable(name) for name in theirs)
        them = "them" if len(theirs) > 1 else "it"
        raise InputError(
            f"{option} {printable(out)}: holds {shown}, which {not_written_by}; {writer} would overwrite {them}: "
            f"move {them} or give another {option}"
        )


class WrittenFiles:
    """The files ``command`` wrote into ``folder`` (read from its manifest; :meth:`record` and :meth:`save` add)."""

    def __init__(self, folder: Path, command: str) -> None:
        self.folder = Path(folder)
        self.path = self.folder / f".ar-anchor-{command}.json"
        self.command = command
        self._files = self._load()

    def _load(self) -> dict[str, list[int]]:
        try:
            with open(self.path, encoding="utf-8") as handle:
                data = json.loads(handle.read(1 << 20))  # a manifest is small: a bigger one is not ours
        except (OSError, ValueError):
            return {}
        files = data.get("files") if isinstance(data, dict) else None
        if not isinstance(files, dict):
            return {}
        return {
            name: entry
            for name, entry in files.items()
            if _inside_name(name) and isinstance(entry, list) and len(entry) == 2 and all(type(v) is int for v in entry)
        }

    @property
    def exists(self) -> bool:
        """Is there a manifest (has the command written into this folder since manifests exist)?"""
        return self.path.is_file()

    def _stat(self, name: str) -> list[int] | None:
        """Size and time of the regular file ``name``, reached without leaving the folder (no link on the way)."""
        path = self.folder / name
        try:
            if os.path.realpath(path) != os.path.join(os.path.realpath(self.folder), *Path(name).parts):
                return None  # a link on the way: it leads out of the folder, or to another file in it
            st = os.lstat(path)
        except (OSError, ValueError):
            return None
        return [st.st_size, st.st_mtime_ns] if stat.S_ISREG(st.st_mode) else None

    def ours(self, name: str) -> bool:
        """Did the command write ``name`` (relative to the folder), and is it still as it left it?"""
        entry = self._files.get(name)
        return entry is not None and self._stat(name) == entry

    def names(self) -> list[str]:
        """The files recorded that are still as the command left them."""
        return [name for name in self._files if self.ours(name)]

    def theirs(self, names: Iterable[str]) -> list[str]:
        """Of ``names``, those that exist (or are a link) in the folder and that the command did not write."""
        found = []
        for name in names:
            path = self.folder / name
            if (path.exists() or path.is_symlink()) and not self.ours(name):
                found.append(name)
        return found

    def record(self, name: str) -> None:
        """``name`` was just written by the command (recorded with its size and time as they are now)."""
        entry = self._stat(name)
        if entry is not None:
            self._files[name] = entry

    def forget(self, name: str) -> None:
        self._files.pop(name, None)

    def save(self) -> None:
        """Write the manifest (the files still ours), whole (written beside it and renamed); removed when empty."""
        files = {name: self._files[name] for name in self.names()}
        try:
            if not files:
                self.path.unlink(missing_ok=True)
                return
            temporary = self.path.with_name(self.path.name + ".tmp")
            text = json.dumps({"written_by": f"ar-anchor {self.command}", "files": files}, indent=1)
            temporary.write_text(text + "\n", encoding="utf-8")
            os.replace(temporary, self.path)
        except OSError as err:
            raise OutputError(f"{printable(self.path)}: cannot write ({err.strerror or err})") from None
