"""The text exports: ``poses_ext.csv`` (quaternion, translation and 4x4 matrix of every pose) and one TUM
trajectory per target (``tum/<target>.txt``: the camera in that target's frame).

Both take ``poses.csv``'s rows frame by frame (:meth:`write`) and write only whole files (:meth:`close`
puts them in place; until then they are temporary files the export removes when it fails).
Numbers are written as ``poses.csv`` writes them (the shortest text that reads back as the same float),
and timestamps are copied as ``poses.csv`` has them (seconds, nine decimals: exact).
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

from ...errors import InputError, OutputError, printable
from ...targets import TargetId
from .poses import PoseRow, quaternion_xyzw_inverse

__all__ = ["POSES_EXT_HEADER", "FrameNames", "PosesExtWriter", "TumWriter", "frame_name"]

_MATRIX = [f"m{row}{col}" for row in range(4) for col in range(4)]
POSES_EXT_HEADER = [
    "frame",
    "timestamp_s",
    "target",
    "state",
    "qx",
    "qy",
    "qz",
    "qw",
    "tx",
    "ty",
    "tz",
    *_MATRIX,
    "raw_qx",
    "raw_qy",
    "raw_qz",
    "raw_qw",
    "raw_tx",
    "raw_ty",
    "raw_tz",
]

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")
MAX_NAME_BYTES = 200  # a target's export name: its TUM file name (with .txt) within a file system's 255 bytes


def frame_name(target: TargetId) -> str:
    """A target's name as a file name and a ROS frame id: ``marker:3`` -> ``marker_3``, ``board:desk`` ->
    ``board_desk``; characters other than letters, digits, ``_``, ``.`` and ``-`` become ``_``."""
    return _UNSAFE.sub("_", f"{target.kind}_{target.name}")


class FrameNames:
    """:func:`frame_name` of each target, refusing (:class:`InputError`) two targets that would share one name."""

    def __init__(self) -> None:
        self._names: dict[TargetId, str] = {}
        self._owners: dict[str, TargetId] = {}

    def __call__(self, target: TargetId, where: str = "") -> str:
        """``target``'s name; ``where`` (the file and line it was read at) starts the message of a clash."""
        name = self._names.get(target)
        if name is None:
            name = frame_name(target)
            if len(name.encode()) > MAX_NAME_BYTES:
                raise InputError(
                    f"{where + ': ' if where else ''}target {printable(target)[:60]!r}...: a name of {len(name)} "
                    f"characters is too long for its TUM file name (at most {MAX_NAME_BYTES}): rename the board"
                )
            other = self._owners.setdefault(name, target)
            if other != target:
                raise InputError(
                    f"{where + ': ' if where else ''}targets {printable(other)!r} and {printable(target)!r} would "
                    f"both be exported as {name!r}: rename one of the boards"
                )
            self._names[target] = name
        return name


def _num(value: float) -> str:
    return repr(float(value))


class PosesExtWriter:
    """``poses_ext.csv``: per ``poses.csv`` row, ``camera_from_target`` as quaternion + translation and as a
    row-major 4x4 matrix, and the raw pose's quaternion + translation (empty when not measured)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._file = open(path, "w", encoding="utf-8", newline="")  # noqa: SIM115 - closed in close()
        except OSError as err:
            raise OutputError(f"{printable(path)}: cannot write ({err.strerror or err})") from None
        self._buffer = io.StringIO()
        self._csv = csv.writer(self._buffer, lineterminator="\n")
        self._csv.writerow(POSES_EXT_HEADER)
        self.rows = 0

    def write(self, rows: list[PoseRow]) -> None:
        for row in rows:
            quaternion = row.quaternion
            matrix = row.pose.as_homogeneous()
            raw = [""] * 7
            if row.raw is not None:
                raw = [_num(v) for v in (*row.raw_quaternion, *row.raw.tvec)]
            self._csv.writerow(
                [
                    str(row.frame),
                    row.timestamp_text,
                    row.target,
                    row.state.value,
                    *(_num(v) for v in quaternion),
                    *(_num(v) for v in row.pose.tvec),
                    *(_num(v) for v in matrix.reshape(-1)),
                    *raw,
                ]
            )
        self.rows += len(rows)
        self._flush()

    def _flush(self) -> None:
        text = self._buffer.getvalue()
        self._buffer.seek(0)
        self._buffer.truncate()
        try:
            self._file.write(text)
        except OSError as err:
            raise OutputError(f"{printable(self.path)}: cannot write ({err.strerror or err})") from None

    def close(self) -> None:
        self._flush()
        self._file.close()


class TumWriter:
    """``<folder>/<target>.txt`` per target: ``timestamp tx ty tz qx qy qz qw``, one line per frame where the
    target has a pose: ``target_from_camera``, i.e. the camera centre ``C = -R^T t`` and orientation ``R^T``
    in the target's frame (what evo and the TUM RGB-D tools call the camera trajectory)."""

    def __init__(self, folder: Path, names: FrameNames) -> None:
        self.folder = folder
        self._names = names
        self._lines: dict[TargetId, list[str]] = {}

    def write(self, rows: list[PoseRow]) -> None:
        for row in rows:
            rotation = row.pose.rotation
            centre = -rotation.T @ row.pose.tvec
            quaternion = quaternion_xyzw_inverse(row.quaternion)
            values = " ".join(_num(v) for v in (*centre, *quaternion))
            self._lines.setdefault(row.target, []).append(f"{row.timestamp_text} {values}\n")

    def close(self) -> list[Path]:
        """Write the files (targets in the one order); their paths."""
        written = []
        for target in TargetId.ordered(self._lines):
            path = self.folder / f"{self._names(target)}.txt"
            header = (
                f"# ar-anchor: the camera in the frame of {printable(target)} (target_from_camera; metres, seconds)\n"
                "# timestamp tx ty tz qx qy qz qw\n"
            )
            try:
                path.write_text(header + "".join(self._lines[target]), encoding="utf-8")
            except OSError as err:
                raise OutputError(f"{printable(path)}: cannot write ({err.strerror or err})") from None
            written.append(path)
        return written
