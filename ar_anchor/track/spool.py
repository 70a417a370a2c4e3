"""The offline replay's frames kept on disk, not in memory (:class:`SpoolStore`), read back by position.

The first pass of ``replay`` (:mod:`ar_anchor.track.offline`) appends every frame's result; the later
passes read them in any order. The file is unnamed (gone when closed or when the process ends, never
visible to another process), and only the package's own classes and numpy arrays are read back.
"""

from __future__ import annotations

import io
import os
import pickle
import tempfile
from typing import Any, Generic, Protocol, TypeVar

__all__ = ["FrameStore", "SpoolStore"]

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)


class FrameStore(Protocol[T_co]):
    """Frames kept for the offline passes, read by position (any order)."""

    def __len__(self) -> int: ...

    def __getitem__(self, position: int) -> T_co: ...


class _SpoolUnpickler(pickle.Unpickler):
    """Reads back only what the spool writes: the package's own classes and numpy arrays. (The spool is an
    unnamed temporary file this process wrote itself, never input; this is defence in depth.)"""

    _NUMPY = {("numpy", "dtype"), ("numpy._core.numeric", "_frombuffer"), ("numpy.core.numeric", "_frombuffer")}
    _NUMPY |= {("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct")}
    _NUMPY |= {("numpy", "ndarray")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._NUMPY:
            return super().find_class(module, name)
        if module.startswith("ar_anchor.") and "." not in name:
            found = super().find_class(module, name)
            if isinstance(found, type):
                return found
        raise pickle.UnpicklingError(f"the offline spool holds no {module}.{name}")


class SpoolStore(Generic[T]):
    """Items pickled one after another into an unnamed temporary file (gone when closed, or when the
    process ends), read back by position (:class:`_SpoolUnpickler`: the package's classes and numpy arrays
    only): a long recording's frames on disk, not in memory."""

    def __init__(self, directory: str | os.PathLike[str] | None = None) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix="ar-anchor-offline-")
        self._offsets: list[int] = []
        self._end = 0

    def append(self, item: T) -> None:
        """Pickle ``item`` at the end of the file."""
        data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
        self._file.seek(self._end)
        self._file.write(data)
        self._offsets.append(self._end)
        self._end += len(data)

    def __len__(self) -> int:
        return len(self._offsets)

    def __getitem__(self, position: int) -> T:
        start = self._offsets[position]
        stop = self._offsets[position + 1] if position + 1 < len(self._offsets) else self._end
        self._file.seek(start)
        return _SpoolUnpickler(io.BytesIO(self._file.read(stop - start))).load()

    @property
    def size_bytes(self) -> int:
        return self._end

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> SpoolStore[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
