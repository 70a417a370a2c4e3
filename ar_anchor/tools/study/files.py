"""Where a study writes: the ``--out`` directory, checked before any study runs, and each study's
figure, Markdown and JSON, written under partial names and put in place together only when the whole
study (its recording included) is complete."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ...errors import InputError, OutputError, printable

__all__ = ["DEFAULT_OUT", "StudyFiles", "check_out", "create_out"]

DEFAULT_OUT = Path("recordings") / "study"


def check_out(text: str | os.PathLike[str] | None) -> Path:
    """The ``--out`` directory (default :data:`DEFAULT_OUT`), checked without creating anything: an
    :class:`InputError` for an empty or non-UTF-8 path (the rerun recording cannot be named so) or a
    file in the way."""
    from ...run.outputs import check_not_a_file  # not at import: the command line's parser reads DEFAULT_OUT

    if text is None:
        return DEFAULT_OUT
    if not os.fspath(text):
        raise InputError("--out: empty path; name a directory (--out . for the current one)")
    out = Path(text)
    try:
        os.fsencode(out).decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(
            f"--out {printable(out)}: the path is not valid UTF-8, and the rerun recording cannot be written "
            "under such a name; choose a UTF-8 name"
        ) from None
    check_not_a_file(out)
    return out


def create_out(out: Path) -> Path:
    """Create ``out`` (checked by :func:`check_out`) and make sure a file can be written in it; an
    :class:`InputError` naming it otherwise (no permission, read-only file system)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".study-probe-", dir=out)
        os.close(handle)
        os.unlink(probe)
    except OSError as err:
        raise InputError(f"--out {printable(out)}: cannot write there ({err.strerror or err})") from None
    return out


class StudyFiles:
    """``<out>/<name>.png``, ``.md`` and ``.json``, written as ``.<name>.<pid>.partial.<suffix>``:
    :meth:`commit` renames them into place, :meth:`discard` removes them."""

    SUFFIXES = ("png", "md", "json")

    def __init__(self, out: Path, name: str) -> None:
        self.final = {suffix: out / f"{name}.{suffix}" for suffix in self.SUFFIXES}
        self.partial = {suffix: out / f".{name}.{os.getpid()}.partial.{suffix}" for suffix in self.SUFFIXES}

    def write_text(self, suffix: str, text: str) -> None:
        """Write the partial ``suffix`` file; an :class:`OutputError` naming the file when it fails."""
        try:
            self.partial[suffix].write_text(text, encoding="utf-8")
        except OSError as err:
            raise self.error(suffix, err) from None

    def error(self, suffix: str, err: OSError) -> OutputError:
        """The error for a failed write of the ``suffix`` file."""
        return OutputError(f"{printable(self.final[suffix])}: cannot write ({err.strerror or err})")

    def commit(self) -> None:
        """Rename the partial files into place (all were written)."""
        for suffix in self.SUFFIXES:
            try:
                os.replace(self.partial[suffix], self.final[suffix])
            except OSError as err:
                raise self.error(suffix, err) from None

    def discard(self) -> None:
        """Remove the partial files that exist."""
        for path in self.partial.values():
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
