"""A rerun recording and where it goes: :class:`Recording` owns one stream with its sinks.

The sinks are an ``.rrd`` file and/or a viewer (one this process starts, :func:`~.viewer.spawn_local_viewer`,
or a running one given by URL). A file can be written beside its final name (``partial``) and renamed there
when the recording closes complete, so a failed command leaves no half recording behind; or in place, so
that whatever was logged before a failure can still be opened. A long recording can go on in another file
(:meth:`Recording.next_file`). Flushes are bounded: a viewer that went away must not hang a command's end,
and a sink that could not write (disk full) is an :class:`~ar_anchor.errors.OutputError`.

The logging primitives (:meth:`Recording.scalar`, :meth:`~Recording.text`, :meth:`~Recording.image_points`,
...) are what the tools need, so that nothing outside :mod:`ar_anchor.viz` imports rerun. 2D positions
are OpenCV pixel coordinates (integers at pixel centres); rerun puts integers at pixel corners, so they
are shifted by half a pixel here.
"""

from __future__ import annotations

import errno
import functools
import logging
import math
import os
import shutil
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from ..errors import OutputError, printable
from .viewer import spawn_local_viewer

__all__ = ["Recording"]

log = logging.getLogger(__name__)

#: How long the closing of the sinks is waited for after a flush to a viewer timed out (:meth:`Recording.close`)
_STALLED_CLOSE_S = 1.0

Colour = tuple[int, int, int] | tuple[int, int, int, int]


class Recording:
    """One rerun stream with its sinks: an ``.rrd`` file at ``path`` and/or a viewer.

    ``spawn`` starts (or reuses) a local viewer, ``connect`` streams to a running one (its gRPC URL).
    ``partial``: write ``.<name>.<pid>.tmp`` beside ``path`` and rename it to ``path`` on :meth:`close`
    (``keep``). ``blueprint`` is the viewer layout sent with the sinks, ``name`` the recording's name in
    the viewer; ``option`` (e.g. ``--rrd``) is put before the file's name in errors.

    ``recording_id``: the recording's id (default: a new random one). Streams of the same application id and
    recording id are one recording, whichever process logs them: in a viewer they all stream to, and in
    their files opened together or merged (``rerun rrd merge``). ``root``: every entity logged through this
    object is under this entity path (e.g. ``cameras/left``: ``events`` is ``cameras/left/events``), so that
    processes sharing a recording never write the same entity; the caller's blueprint names the full paths.
    """

    def __init__(
        self,
        application_id: str,
        *,
        path: str | os.PathLike[str] | None = None,
        partial: bool = False,
        spawn: bool = False,
        connect: str | None = None,
        blueprint: rrb.Blueprint | None = None,
        name: str | None = None,
        option: str | None = None,
        recording_id: str | None = None,
        root: str | None = None,
    ) -> None:
        self.stream = rr.RecordingStream(application_id, recording_id=recording_id)
        self.root = root.strip("/") if root else None
        self.files: list[Path] = []  # the recording's files (final names), in order
        self._partial = partial
        self._option = option
        self._blueprint = blueprint
        self._name = name
        self._writing: Path | None = None  # the file being written (its partial name when partial)
        self._timed_out: str | None = None  # the error of a flush that timed out (a sink that stopped taking data)
        if path is not None:
            self._writing = self._open(Path(path))
            self.files.append(Path(path))
        self.viewer_url = connect
        if connect is None and spawn:
            self.viewer_url = spawn_local_viewer()
        self._viewer = rr.GrpcSink(self.viewer_url) if self.viewer_url is not None else None
        self._set_sinks()

    # ------------------------------------------------------------------ sinks and files
    def _named(self, path: Path) -> str:
        return f"{self._option} {path}" if self._option else str(path)

    def _open(self, path: Path) -> Path:
        """Create the file a sink writes ``path`` into (``path`` itself or its partial name), or OutputError."""
        writing = path.with_name(f".{path.name}.{os.getpid()}.tmp") if self._partial else path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if path.is_dir():
                raise IsADirectoryError(21, "is a directory")
            writing.touch()
        except OSError as err:
            raise OutputError(f"{self._named(path)}: cannot write ({err.strerror})") from None
        return writing

    def _set_sinks(self) -> None:
        sinks: list[rr.FileSink | rr.GrpcSink] = [rr.FileSink(str(self._writing))] if self._writing else []
        if self._viewer is not None:
            sinks.append(self._viewer)
        if sinks:
            self.stream.set_sinks(*sinks, default_blueprint=self._blueprint)
        if self._name is not None:
            self.stream.send_recording_name(self._name)

    def _finish(self, writing: Path, final: Path, *, keep: bool) -> None:
        """A partial file that was written: renamed to its final name (``keep``) or removed."""
        if not self._partial or not writing.exists():
            return
        if not keep:
            writing.unlink(missing_ok=True)
            return
        try:
            os.replace(writing, final)
        except OSError as err:
            writing.unlink(missing_ok=True)
            raise OutputError(f"{self._named(final)}: cannot write ({err.strerror})") from None

    def send_blueprint(self, blueprint: rrb.Blueprint) -> None:
        """Make ``blueprint`` the layout from now on: the viewer's, the file's, and the next file's."""
        self._blueprint = blueprint
        self.stream.send_blueprint(blueprint, make_active=True, make_default=True)

    def next_file(self, path: str | os.PathLike[str]) -> None:
        """Close the current file complete and go on in ``path`` (the viewer, if any, stays). The new
        file starts with the blueprint and the recording's name; static data is the caller's to log again."""
        self.flush(timeout_s=30.0)
        path = Path(path)
        previous, self._writing = self._writing, self._open(path)
        self._set_sinks()  # closes the previous file's sink
        if previous is not None and self.files:
            self._finish(previous, self.files[-1], keep=True)
        self.files.append(path)

    def flush(self, timeout_s: float) -> None:
        """Flush the sinks, waiting at most ``timeout_s``; a sink that could not write (disk full, file too
        large, viewer gone) is an OutputError."""
        try:
            self.stream.flush(timeout_sec=timeout_s)
        except RuntimeError as err:
            timed_out = "timed out" in str(err).lower()
            if self.files and _disk_full(self.files[-1]):
                raise OutputError(
                    f"{self._named(self.files[-1])}: incomplete, the disk is full (no footer; it holds what was "
                    "written before)"
                ) from OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            where = [self._named(self.files[-1])] if self.files else []
            if self.viewer_url is not None:
                where.append(f"the viewer at {self.viewer_url}")
            waited = f" within {timeout_s:g} s" if timed_out else ""
            message = (
                f"{' and '.join(where) or 'recording'}: cannot write the recording{waited} ({err}: disk full, or "
                "the viewer gone?); the file holds the frames logged before"
            )
            if timed_out:
                self._timed_out = message
            raise OutputError(message) from None

    def close(self, *, keep: bool = True, timeout_s: float = 10.0) -> None:
        """Flush (bounded by ``timeout_s``) and close the sinks. A partial file is renamed into place when
        ``keep`` and the flush succeeded, removed otherwise; a file written in place stays either way.

        After a flush that timed out (a viewer that accepts and never reads), the sinks are not flushed
        again: that error is raised at once, and a stalled viewer costs a command one wait at its end, not
        two: with a viewer connected, the closing of the sinks is then given :data:`_STALLED_CLOSE_S` only
        (it waits on the same viewer, which did not read for a whole flush; the file stays as it is, without
        its footer, either way); without one (a slow disk) it is given ``timeout_s``."""
        try:
            if self._timed_out is not None:
                raise OutputError(self._timed_out)
            self.flush(timeout_s)
        except OutputError:
            keep = False
            raise
        finally:
            stalled = self._timed_out is not None and self.viewer_url is not None
            self._disconnect(min(timeout_s, _STALLED_CLOSE_S) if stalled else timeout_s)
            if self._writing is not None and self.files:
                self._finish(self._writing, self.files[-1], keep=keep)

    def _disconnect(self, timeout_s: float) -> None:
        """Close the sinks, waiting at most ``timeout_s``: a viewer that accepts and never reads would
        hold rerun's disconnect forever."""
        done = threading.Thread(target=self.stream.disconnect, name="rerun-disconnect", daemon=True)
        done.start()
        done.join(timeout_s)
        if done.is_alive():
            rr.unregister_shutdown()  # its at-exit flush would wait on that viewer too
            log.warning(
                "%s: the viewer did not take the rest of the recording within %g s; left it",
                printable(self.viewer_url or "the viewer"),
                timeout_s,
            )

    # ------------------------------------------------------------------ logging primitives
    def _at(self, entity: str) -> str:
        """``entity`` under :attr:`root` (itself when there is none)."""
        return f"{self.root}/{entity.lstrip('/')}" if self.root else entity

    def time(self, timeline: str, *, sequence: int | None = None, seconds: float | None = None) -> None:
        """Set the current position on ``timeline``: a ``sequence`` number or a duration in ``seconds``."""
        if sequence is not None:
            self.stream.set_time(timeline, sequence=int(sequence))
        else:
            self.stream.set_time(timeline, duration=seconds)

    def log(self, entity: str, data: Any, *, static: bool = False) -> None:
        """Any rerun archetype (for the viz package's own loggers)."""
        self.stream.log(self._at(entity), data, static=static)

    def clear(self, entity: str, *, recursive: bool = False) -> None:
        """Clear ``entity`` (and its children when ``recursive``) from now on. Static data stays."""
        self.stream.log(self._at(entity), _clear(recursive))

    def scalar(self, entity: str, value: float | None) -> None:
        """One point of the time series ``entity``; None and non-finite values are skipped."""
        if value is not None and math.isfinite(value):
            self.stream.log(self._at(entity), rr.Scalars(float(value)))

    @staticmethod
    def time_columns(
        *, frames: Sequence[int], seconds: Sequence[float], log_ns: Sequence[int] | None = None
    ) -> list[rr.TimeColumn]:
        """The run recorder's timelines at several frames, for :meth:`scalar_columns` and
        :meth:`transform_columns`: ``frames`` on the ``frame`` sequence, ``seconds`` on ``time``, and
        ``log_ns`` (nanoseconds since the epoch, when given) on ``log_time``, the wall clock ``rr.log``
        stamps each call with. (Given as arrays: rerun converts lists value by value; the seconds are rounded
        to nanoseconds as ``set_time`` rounds them.)"""
        nanoseconds = np.array([round(1e9 * float(s)) for s in seconds], np.int64).astype("timedelta64[ns]")
        columns = [
            rr.TimeColumn("frame", sequence=np.asarray(frames, np.int64)),
            rr.TimeColumn("time", duration=nanoseconds),
        ]
        if log_ns is not None:
            columns.append(rr.TimeColumn("log_time", timestamp=np.asarray(log_ns, "datetime64[ns]")))
        return columns

    def scalar_columns(self, entity: str, values: Sequence[float], times: Any) -> None:
        """Points of the time series ``entity`` at several times in one call: ``values[i]`` at the i-th row
        of ``times`` (:meth:`time_columns`), each row what ``rr.Scalars(value)`` logs. The column is built
        with pyarrow directly, as :meth:`transform_columns` does."""
        if len(values):
            (descriptor,), (kind,) = _columns_of("scalars")
            values = pa.array(np.asarray(values, np.float64), type=kind.value_type)
            column = _Column(descriptor, pa.ListArray.from_arrays(_offsets(len(values)), values, type=kind))
            self.stream.send_columns(self._at(entity), indexes=times, columns=[column])

    def transform(self, entity: str, translation: np.ndarray, rotation: np.ndarray) -> None:
        """A ``Transform3D``: ``translation`` and the 3x3 ``rotation``."""
        self.stream.log(self._at(entity), rr.Transform3D(translation=translation, mat3x3=rotation))

    def transform_columns(
        self, entity: str, translations: Sequence[np.ndarray], rotations: Sequence[np.ndarray], times: Any
    ) -> None:
        """``Transform3D`` s of ``entity`` at several times in one call: ``translations[i]`` and the 3x3
        ``rotations[i]`` at the i-th row of ``times`` (:meth:`time_columns`), each row what
        ``rr.Transform3D(translation=..., mat3x3=...)`` logs (float32; the matrix stored column by column).
        The columns are built with pyarrow directly: ``rr.Transform3D.columns`` costs more than the send."""
        if not len(translations):
            return
        descriptors, types = _columns_of("transform")
        count = len(translations)
        offsets = _offsets(count)
        flat = (
            np.asarray(translations, np.float32).reshape(count, 3).ravel(),
            np.asarray(rotations, np.float32).reshape(count, 3, 3).transpose(0, 2, 1).ravel(),
        )
        columns = [
            _Column(descriptor, pa.ListArray.from_arrays(offsets, _fixed_lists(values, kind.value_type), type=kind))
            for descriptor, kind, values in zip(descriptors, types, flat, strict=True)
        ]
        self.stream.send_columns(self._at(entity), indexes=times, columns=columns)

    @staticmethod
    def component_arrays(data: Any) -> list[tuple[Any, pa.Array]]:
        """An archetype's components as ``rr.log`` sends them: (descriptor, arrow array) each, for
        :meth:`rows_columns`."""
        return [(batch.component_descriptor(), batch.as_arrow_array()) for batch in data.as_component_batches()]

    @staticmethod
    def cells(archetype: str, **fields: Any) -> Any:
        """What ``rr.<archetype>(**fields)`` logs (``LineStrips2D``, ``LineStrips3D``, ``Points2D``, ``Points3D``),
        its arrow arrays built directly from arrays (rerun's own conversion, per field, costs several times
        more): ``strips`` (N, K, D) floats (strips of one length), ``positions`` (N, D) floats, ``colors``
        (N, 3 or 4) integers 0-255 (opaque without alpha), ``radii`` floats, ``labels`` strings. Logged as an archetype
        (:meth:`log`, :meth:`.series.SeriesBuffer.log`); its fields read as arrow columns (``.strips``)."""
        kinds = _fields_of(archetype)
        places = sorted((kinds[name], value, name) for name, value in fields.items())  # (in rerun's order)
        return _Cells([_Column(descriptor, _arrow(name, value, kind)) for (_, descriptor, kind), value, name in places])

    @staticmethod
    def prebuilt(data: Any) -> Any:
        """The archetype ``data`` with its components converted to arrow once, to be logged (:meth:`log`)
        many times: what ``rr.log`` of ``data`` logs, without converting it again each time (its fields
        read as ``data``'s)."""
        return _Prebuilt(data)

    def rows_columns(self, entity: str, rows: Sequence[list[tuple[Any, pa.Array]]], times: Any) -> None:
        """Several rows of one archetype at ``entity`` in one call: ``rows[i]`` (:meth:`component_arrays`, the
        same components in every row) at the i-th row of ``times`` (:meth:`time_columns`)."""
        if not len(rows):
            return
        columns = []
        for index, (descriptor, _) in enumerate(rows[0]):
            arrays = [row[index][1] for row in rows]
            offsets = pa.array(np.cumsum([0, *map(len, arrays)], dtype=np.int32))
            columns.append(_Column(descriptor, pa.ListArray.from_arrays(offsets, pa.concat_arrays(arrays))))
        self.stream.send_columns(self._at(entity), indexes=times, columns=columns)

    def text(self, entity: str, text: str, *, warn: bool = False, static: bool = False) -> None:
        """A line of a text log, level INFO or WARN."""
        level = rr.TextLogLevel.WARN if warn else rr.TextLogLevel.INFO
        self.stream.log(self._at(entity), rr.TextLog(text, level=level), static=static)

    def markdown(self, entity: str, text: str, *, static: bool = True) -> None:
        """A markdown document."""
        self.stream.log(self._at(entity), rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=static)

    def encoded_image(self, entity: str, data: bytes, media_type: str, *, static: bool = False) -> None:
        """An already encoded image (``image/jpeg``, ``image/png``)."""
        self.stream.log(self._at(entity), rr.EncodedImage(contents=data, media_type=media_type), static=static)

    def image_file(self, entity: str, path: str | os.PathLike[str], *, static: bool = True) -> None:
        """An image file (PNG, JPEG), its type from its name."""
        self.stream.log(self._at(entity), rr.EncodedImage(path=path), static=static)

    def jpeg(self, entity: str, image: np.ndarray, *, quality: int, scale: float = 1.0) -> None:
        """``image`` (BGR) resized by ``scale`` and encoded as JPEG of ``quality``."""
        if scale != 1.0:
            size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok:
            self.encoded_image(entity, jpeg.tobytes(), "image/jpeg")

    def image_points(
        self,
        entity: str,
        pixels: np.ndarray,
        *,
        radius: float,
        colours: Sequence[Colour],
        scale: float = 1.0,
        static: bool = False,
    ) -> None:
        """Points on an image: OpenCV pixel coordinates (N, 2), on an image shown at ``scale``."""
        self.stream.log(self._at(entity), self.image_points_data(pixels, radius, colours, scale), static=static)

    @staticmethod
    def image_points_data(pixels: np.ndarray, radius: float, colours: Sequence[Colour], scale: float) -> Any:
        """What :meth:`image_points` logs (for :meth:`~.series.SeriesBuffer.log`): ``rr.Points2D``'s components."""
        pixels = np.asarray(pixels)
        if not np.issubdtype(pixels.dtype, np.floating):
            pixels = pixels.astype(np.float64)
        return Recording.cells("Points2D", positions=(pixels + 0.5) * scale, radii=radius, colors=colours)

    def points3d(
        self,
        entity: str,
        positions: np.ndarray,
        *,
        radius: float,
        colours: Sequence[Colour],
        labels: Sequence[str] | None = None,
        static: bool = False,
    ) -> None:
        """Points in 3D, optionally labelled."""
        self.stream.log(
            self._at(entity), rr.Points3D(positions, radii=radius, colors=colours, labels=labels), static=static
        )


class _Column:
    """A component column for ``send_columns``: its descriptor and its arrow array (one list per row)."""

    __slots__ = ("array", "descriptor")

    def __init__(self, descriptor: Any, array: pa.Array) -> None:
        self.descriptor, self.array = descriptor, array

    def component_descriptor(self) -> Any:
        return self.descriptor

    def as_arrow_array(self) -> pa.Array:
        return self.array


class _Prebuilt:
    """An archetype whose components are converted once (:meth:`Recording.prebuilt`)."""

    __slots__ = ("_batches", "_data")

    def __init__(self, data: Any) -> None:
        self._data = data
        self._batches = [_Column(descriptor, array) for descriptor, array in Recording.component_arrays(data)]

    def as_component_batches(self) -> list[_Column]:
        return self._batches

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):  # (not the archetype's: a copy's slots before they are set)
            raise AttributeError(name)
        return getattr(self._data, name)


class _Cells:
    """An archetype's components built as arrow arrays (:meth:`Recording.cells`), in rerun's order."""

    __slots__ = ("_batches",)

    def __init__(self, columns: list[_Column]) -> None:
        self._batches = columns

    def as_component_batches(self) -> list[_Column]:
        return self._batches

    def __getattr__(self, name: str) -> _Column:
        if name.startswith("_"):  # (not a field: a copy's slots before they are set)
            raise AttributeError(name)
        for column in self._batches:
            if column.descriptor.component.endswith(f":{name}"):
                return column
        raise AttributeError(name)


_SAMPLES = {  # an archetype of each kind Recording.cells builds, with every field it takes
    "LineStrips2D": lambda: rr.LineStrips2D(np.zeros((1, 2, 2)), radii=[1.0], colors=[(1, 2, 3)], labels=["a"]),
    "LineStrips3D": lambda: rr.LineStrips3D(np.zeros((1, 2, 3)), radii=[1.0], colors=[(1, 2, 3)], labels=["a"]),
    "Points2D": lambda: rr.Points2D(np.zeros((1, 2)), radii=[1.0], colors=[(1, 2, 3)], labels=["a"]),
    "Points3D": lambda: rr.Points3D(np.zeros((1, 3)), radii=[1.0], colors=[(1, 2, 3)], labels=["a"]),
}


@functools.cache
def _fields_of(archetype: str) -> dict[str, tuple[int, Any, pa.DataType]]:
    """The components rerun logs for ``archetype``: a field -> its place among them, descriptor and arrow type."""
    arrays = Recording.component_arrays(_SAMPLES[archetype]())
    return {d.component.partition(":")[2]: (place, d, array.type) for place, (d, array) in enumerate(arrays)}


def _arrow(field: str, value: Any, kind: pa.DataType) -> pa.Array:
    """``value`` as rerun converts the archetype's ``field`` (:meth:`Recording.cells`)."""
    if field == "strips":  # (N, K, D): N strips of K points
        value = np.asarray(value)
        count, length = value.shape[:2]
        points = pa.FixedSizeListArray.from_arrays(value.astype(np.float32).ravel(), type=kind.value_type)
        return pa.ListArray.from_arrays(pa.array(np.arange(count + 1, dtype=np.int32) * length), points, type=kind)
    if field == "positions":
        return pa.FixedSizeListArray.from_arrays(np.asarray(value, np.float32).ravel(), type=kind)
    if field == "colors":
        rows = np.asarray(value, np.uint32)
        if rows.size == 0:
            return pa.array(np.zeros(0, np.uint32), type=kind)
        alpha = rows[:, 3] if rows.shape[1] == 4 else 0xFF
        return pa.array(rows[:, 0] << 24 | rows[:, 1] << 16 | rows[:, 2] << 8 | alpha, type=kind)
    if field == "radii":
        return pa.array(np.asarray(value, np.float32).ravel(), type=kind)
    return pa.array([str(text) for text in value], type=kind)  # labels


@functools.cache
def _columns_of(archetype: str) -> tuple[tuple[Any, ...], tuple[pa.ListType, ...]]:
    """The descriptors and arrow types of the columns rerun builds for an archetype: ``scalars``
    (``Scalars:scalars``) or ``transform`` (``Transform3D:translation``, ``Transform3D:mat3x3``)."""
    if archetype == "scalars":
        columns, names = rr.Scalars.columns(scalars=np.zeros(1)), ["Scalars:scalars"]
    else:
        columns = rr.Transform3D.columns(translation=np.zeros((1, 3)), mat3x3=np.eye(3)[None])
        names = ["Transform3D:translation", "Transform3D:mat3x3"]
    by_name = {column.component_descriptor().component: column for column in columns}
    descriptors = tuple(by_name[name].component_descriptor() for name in names)
    types = tuple(by_name[name].as_arrow_array().type for name in names)
    return descriptors, types


@functools.cache
def _clear(recursive: bool) -> _Prebuilt:
    """``rr.Clear(recursive=recursive)``'s components, converted once (a gone target's clears are several a
    frame)."""
    return Recording.prebuilt(rr.Clear(recursive=recursive))


@functools.cache
def _offsets(count: int) -> pa.Array:
    """The list offsets of ``count`` rows of one value each."""
    return pa.array(np.arange(count + 1, dtype=np.int32))


def _fixed_lists(values: np.ndarray, kind: pa.FixedSizeListType) -> pa.FixedSizeListArray:
    """``values`` (flat) as arrow fixed-size lists of ``kind``."""
    return pa.FixedSizeListArray.from_arrays(pa.array(values), type=kind)


def _disk_full(path: Path) -> bool:
    """Is the disk of ``path`` full, or nearly (less than 2 MiB free)? A file sink that failed there failed for
    that reason (rerun's error only says the flush did not finish)."""
    try:
        return shutil.disk_usage(path.parent).free < 2 << 20
    except OSError:
        return False
