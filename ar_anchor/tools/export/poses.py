"""Reading a run's ``poses.csv`` back, checked, and the pose conversions every export shares.

:func:`read_poses_csv` yields one :class:`PoseRow` per line, in file order, and refuses (an
:class:`~ar_anchor.errors.InputError` naming the file, the line and the column) anything that is not what
:class:`~ar_anchor.run.outputs.PosesCsvWriter` writes: another header, a cell that is not a number, a
target or state it does not know, frames that go back. Timestamps are kept exact: ``timestamp_s`` is
parsed as a decimal (nine digits after the point: nanoseconds), never through a float, so that a live
run's timestamps survive to the nanosecond in every export.

Conversions (pytransform3d's naming: ``<to>_from_<from>``; quaternions ``xyzw``, Hamilton, scalar last,
as ROS and TUM write them, with ``w >= 0``): :func:`quaternion_xyzw_from_rvec`,
:func:`quaternion_xyzw_inverse`.
"""

from __future__ import annotations

import csv
import functools
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from ...errors import InputError, printable
from ...geometry import Pose
from ...run.outputs import POSES_CSV_HEADER
from ...targets import TargetId, TrackState

__all__ = [
    "PoseRow",
    "frames_of",
    "quaternion_xyzw_from_rvec",
    "quaternion_xyzw_inverse",
    "read_poses_csv",
    "timestamp_ns_from_text",
]

# limits of what is read as a poses.csv (documented in docs/outputs-and-viewer.md): a row is ~400 characters, and the
# file is read line by line with this bound (a longer line is refused before it is parsed: memory stays small)
MAX_LINE_CHARS = 65536
# a rotation vector longer than this is no rotation ar-anchor wrote (it writes at most pi: one turn is 2 pi)
MAX_ROTATION_RAD = 2 * math.pi
MAX_TRANSLATION_M = 1e6  # a translation longer than this (1000 km) is no pose ar-anchor wrote
# timestamps: from 0 (a run's clock starts there, or at boot) to the last second a ROS 2 time holds (int32)
MAX_TIMESTAMP_S = 2**31 - 1


@dataclass(frozen=True)
class PoseRow:
    """One row of ``poses.csv``.

    Attributes
    ----------
    frame : frame index.
    timestamp_ns : the frame's time, nanoseconds (exact).
    timestamp_text : ``timestamp_s`` as written in ``poses.csv`` (seconds), copied as it is into the exports.
    target : ``marker:<id>`` or ``board:<name>``.
    state : the tracker's state of this pose.
    pose : the output ``camera_from_target`` (what is rendered).
    raw : the frame's plain per-frame solution, None when the target was not measured this frame.
    line : line number in ``poses.csv`` (1-based; the header is line 1), for messages.
    """

    frame: int
    timestamp_ns: int
    timestamp_text: str
    target: TargetId
    state: TrackState
    pose: Pose
    raw: Pose | None
    line: int

    @functools.cached_property
    def quaternion(self) -> np.ndarray:
        """The output pose's rotation as a quaternion (x, y, z, w), ``w >= 0`` (computed once)."""
        return quaternion_xyzw_from_rvec(self.pose.rvec)

    @functools.cached_property
    def raw_quaternion(self) -> np.ndarray | None:
        """The raw pose's rotation as a quaternion (x, y, z, w), ``w >= 0``; None without a raw pose."""
        return None if self.raw is None else quaternion_xyzw_from_rvec(self.raw.rvec)


def timestamp_ns_from_text(text: str) -> int:
    """``timestamp_s`` text (seconds, a decimal number) -> integer nanoseconds, exactly (ValueError otherwise):
    from 0 to :data:`MAX_TIMESTAMP_S`, at most nine digits after the point that are not 0. Computed from the
    decimal digits (no rounding context: ``1e999999999`` and ``1.0000000000000000000000000000001`` are refused,
    not overflowed or rounded)."""
    shown = _cell(text.strip())
    try:
        seconds = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"expected a time in seconds, got {shown!r}") from None
    if not seconds.is_finite():
        raise ValueError(f"expected a finite time in seconds, got {shown!r}")
    if seconds < 0:
        raise ValueError(f"a negative time: {shown!r} s (a run's times start at 0)")
    if seconds >= MAX_TIMESTAMP_S + 1:  # (2147483647.999999999 s is a ROS 2 time still)
        raise ValueError(f"{shown!r} s is beyond the last time a ROS 2 stamp holds ({MAX_TIMESTAMP_S} s)")
    _sign, digits, exponent = seconds.as_tuple()
    assert isinstance(exponent, int)  # (finite)
    if not any(digits):
        return 0
    if exponent < -9:  # digits below the nanosecond: all of them must be 0
        below = -9 - exponent
        if any(digits[-below:]):
            raise ValueError(f"more than nanosecond resolution: {shown!r}")
        digits, exponent = digits[:-below], -9
    # 0 < seconds <= MAX: exponent + 9 is small here (at most the digits of MAX_TIMESTAMP_S and 9)
    return int("".join(map(str, digits)) or "0") * 10 ** (exponent + 9)


def _cell(text: str, most: int = 40) -> str:
    """A cell's text for a message: printable, and cut to ``most`` characters (a cell may be 64 kB long)."""
    shown = printable(text)
    return shown if len(shown) <= most else shown[:most] + "..."


def _where(path: Path, line: int, column: str | None = None) -> str:
    return f"{printable(path)}: line {line}" + (f", column {column}" if column else "")


def _number(text: str, path: Path, line: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{_where(path, line, column)}: expected a number, got {_cell(text)!r}") from None
    if not math.isfinite(value):
        raise InputError(f"{_where(path, line, column)}: expected a finite number, got {_cell(text)!r}")
    return value


def _pose(cells: dict[str, str], prefix: str, path: Path, line: int, *, required: bool) -> Pose | None:
    names = [f"{prefix}{kind}_{axis}" for kind in ("rvec", "tvec") for axis in "xyz"]
    texts = [cells[name].strip() for name in names]
    if not any(texts) and not required:
        return None
    values = [_number(text, path, line, name) for text, name in zip(texts, names)]
    angle = math.hypot(*values[:3])
    if angle > MAX_ROTATION_RAD:
        raise InputError(
            f"{_where(path, line, names[0])}: a rotation vector of {angle:.6g} rad is no rotation ar-anchor writes "
            f"(at most pi; refused beyond 2 pi)"
        )
    distance = math.hypot(*values[3:])
    if distance > MAX_TRANSLATION_M:
        raise InputError(
            f"{_where(path, line, names[3])}: a translation of {distance:.6g} m is no pose ar-anchor writes "
            f"(refused beyond {MAX_TRANSLATION_M:g} m)"
        )
    return Pose(np.array(values[:3]), np.array(values[3:]))


def read_poses_csv(path: str | os.PathLike[str]) -> Iterator[PoseRow]:
    """The rows of ``path`` (a run's ``poses.csv``), checked; an :class:`InputError` naming the file, line and
    column at the first thing that is not what ``ar-anchor`` writes."""
    path = Path(path)
    try:
        # utf-8-sig: a byte order mark (a spreadsheet's "CSV UTF-8") is read as nothing
        handle = open(path, encoding="utf-8-sig", newline="")  # noqa: SIM115 - closed in the finally below
    except FileNotFoundError:
        raise InputError(f"{printable(path)}: not found (a run directory holds the poses.csv it wrote)") from None
    except IsADirectoryError:
        raise InputError(f"{printable(path)}: is a directory, not a poses.csv file") from None
    except OSError as err:
        raise InputError(f"{printable(path)}: cannot read ({err.strerror or err})") from None
    try:
        yield from _rows(handle, path)
    except UnicodeDecodeError:
        raise InputError(f"{printable(path)}: not UTF-8 text (not a poses.csv written by ar-anchor)") from None
    except csv.Error as err:
        raise InputError(f"{printable(path)}: not valid CSV ({err})") from None
    finally:
        handle.close()


def _bounded_lines(handle, path: Path) -> Iterator[str]:  # noqa: ANN001 - a text file
    """The lines of ``handle``, each read with at most :data:`MAX_LINE_CHARS` characters: a longer one is an
    :class:`InputError` before it is held whole (one line of 200 M commas is refused after 64 kB, not parsed)."""
    number = 0
    while True:
        line = handle.readline(MAX_LINE_CHARS + 1)
        if not line:
            return
        number += 1
        if len(line) > MAX_LINE_CHARS:
            raise InputError(
                f"{_where(path, number)}: longer than {MAX_LINE_CHARS} characters: not a row of a poses.csv"
            )
        yield line


def _rows(handle, path: Path) -> Iterator[PoseRow]:  # noqa: ANN001 - a text file
    reader = csv.reader(_bounded_lines(handle, path))
    header = next(reader, None)
    if header != POSES_CSV_HEADER:
        shown = "an empty file" if header is None else printable(",".join(header))[:120]
        raise InputError(
            f"{_where(path, 1)}: not the header of a poses.csv (expected {','.join(POSES_CSV_HEADER[:5])},...; "
            f"got {shown})"
        )
    previous_frame = -1
    previous_time: int | None = None
    frame_targets: dict[TargetId, int] = {}  # the targets of the current frame -> their line
    for cells_list in reader:
        line = reader.line_num
        if not cells_list:
            continue
        if len(cells_list) != len(POSES_CSV_HEADER):
            raise InputError(
                f"{_where(path, line)}: expected {len(POSES_CSV_HEADER)} columns, got {len(cells_list)}"
                + (" (a row cut short: was the run's disk full?)" if len(cells_list) < len(POSES_CSV_HEADER) else "")
            )
        if sum(map(len, cells_list)) > MAX_LINE_CHARS:
            raise InputError(f"{_where(path, line)}: a row of {sum(map(len, cells_list))} characters is no poses row")
        cells = dict(zip(POSES_CSV_HEADER, cells_list))
        frame_text = cells["frame"].strip()
        if not (frame_text.isascii() and frame_text.isdigit()) or len(frame_text) > 18:  # (up to 10^18 - 1)
            raise InputError(f"{_where(path, line, 'frame')}: expected a frame index, got {_cell(frame_text)!r}")
        frame = int(frame_text)
        if frame < previous_frame:
            raise InputError(f"{_where(path, line, 'frame')}: frame {frame} after frame {previous_frame}")
        try:
            timestamp_ns = timestamp_ns_from_text(cells["timestamp_s"])
        except ValueError as err:
            raise InputError(f"{_where(path, line, 'timestamp_s')}: {printable(err)}") from None
        if frame == previous_frame and timestamp_ns != previous_time:
            raise InputError(f"{_where(path, line, 'timestamp_s')}: frame {frame} has two timestamps")
        if frame != previous_frame and previous_time is not None and timestamp_ns < previous_time:
            raise InputError(
                f"{_where(path, line, 'timestamp_s')}: time goes backwards: frame {frame} at "
                f"{printable(cells['timestamp_s'].strip())} s is before frame {previous_frame} at "
                f"{previous_time / 1e9:.9f} s"
            )
        try:
            target = TargetId.parse(cells["target"])
        except ValueError as err:
            raise InputError(f"{_where(path, line, 'target')}: {_cell(str(err), 160)}") from None
        try:
            state = TrackState(cells["state"])
        except ValueError:
            known = ", ".join(s.value for s in TrackState)
            raise InputError(
                f"{_where(path, line, 'state')}: expected one of {known}, got {_cell(cells['state'])!r}"
            ) from None
        if frame != previous_frame:
            frame_targets.clear()
        if target in frame_targets:
            raise InputError(
                f"{_where(path, line, 'target')}: {printable(target)} twice in frame {frame} (line "
                f"{frame_targets[target]} too): one pose per target and frame"
            )
        frame_targets[target] = line
        pose = _pose(cells, "", path, line, required=True)
        raw = _pose(cells, "raw_", path, line, required=False)
        assert pose is not None
        previous_frame, previous_time = frame, timestamp_ns
        yield PoseRow(frame, timestamp_ns, cells["timestamp_s"].strip(), target, state, pose, raw, line)


def frames_of(rows: Iterator[PoseRow]) -> Iterator[list[PoseRow]]:
    """``rows`` grouped by frame (consecutive rows of one frame index), in order."""
    group: list[PoseRow] = []
    for row in rows:
        if group and row.frame != group[0].frame:
            yield group
            group = []
        group.append(row)
    if group:
        yield group


def quaternion_xyzw_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w; Hamilton, scalar last) of the rotation ``rvec`` (Rodrigues vector,
    radians), with ``w >= 0`` (of q and -q, the one with the non-negative scalar)."""
    x, y, z = (float(v) for v in np.asarray(rvec, dtype=np.float64).reshape(3))  # plain floats: once per row
    angle = math.sqrt(x * x + y * y + z * z)
    half = 0.5 * angle
    # sin(angle / 2) / angle, with its series near 0 (no division by a vanishing angle)
    scale = math.sin(half) / angle if angle > 1e-8 else 0.5 - angle * angle / 48.0
    w = math.cos(half)
    x, y, z = x * scale, y * scale, z * scale
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    sign = -1.0 if w < 0 else 1.0
    return np.array([x, y, z, w]) * (sign / norm)


def quaternion_xyzw_inverse(quaternion: np.ndarray) -> np.ndarray:
    """The inverse rotation of a unit quaternion (x, y, z, w): its conjugate (the sign of w kept)."""
    x, y, z, w = np.asarray(quaternion, dtype=np.float64).reshape(4)
    return np.array([-x, -y, -z, w])
