"""Offline sources: video files (``cv2.VideoCapture``, FFmpeg) and image folders or globs.

Both are exact and repeatable: frame ``index`` is the position in the file or folder, and
timestamps come from the container (``CAP_PROP_POS_MSEC``), from a ``<video>.timestamps.csv``
written beside a recorded live session, or, for images, from a configured frame rate.

A file that cannot be opened is a :class:`SourceError` naming it. A video damaged part-way
ends the stream at the last good frame with a warning naming that frame; whatever was produced
until then stays valid.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import logging
import math
import os
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraModel, opencv_path_problem
from ..errors import SourceError
from .base import ClosingSource, Frame, SourceInfo

__all__ = [
    "IMAGE_EXTENSIONS",
    "ImageFolderSource",
    "VideoFileSource",
    "natural_key",
    "read_timestamps_csv",
    "to_bgr8",
]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm"})
_GLOB_CHARS = re.compile(r"[*?\[]")
# frame rates of image sequences: a frame per 1000 s at the slowest, one per microsecond at the fastest
MIN_FPS, MAX_FPS = 1e-3, 1e6


def natural_key(path: str | os.PathLike[str]) -> list[object]:
    """Sort key that orders ``frame_2`` before ``frame_10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", os.fspath(path))]


def to_bgr8(image: np.ndarray) -> np.ndarray | None:
    """Any image OpenCV reads (grey, BGR, BGRA; 8 or 16 bit, float) as BGR uint8, or None if it cannot be."""
    if image is None or not isinstance(image, np.ndarray) or image.size == 0:
        return None
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        if not np.issubdtype(image.dtype, np.number):
            return None
        finite = np.nan_to_num(image.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        scale = 255.0 if finite.max(initial=0.0) <= 1.0 else 1.0
        image = np.clip(finite * scale, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim != 3:
        return None
    channels = image.shape[2]
    if channels == 3:
        return np.ascontiguousarray(image)
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if channels == 1:
        return cv2.cvtColor(image[..., 0], cv2.COLOR_GRAY2BGR)
    return None


@contextlib.contextmanager
def _decoder_quiet() -> Iterator[None]:
    """OpenCV's own log line for an image it cannot decode ("[ERROR:0@1.6] ... IHDR chunk shall be first")
    would stand beside our warning naming the file: silence it, unless OpenCV's messages were asked
    for (-vv leaves OpenCV's log level above ERROR)."""
    previous = cv2.utils.logging.getLogLevel()
    if previous > cv2.utils.logging.LOG_LEVEL_ERROR:
        yield
        return
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


def read_timestamps_csv(path: Path) -> list[tuple[int, int]]:
    """Rows (frame, timestamp_ns) of a recorded session's timestamp file."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames is None or not {"frame", "timestamp_ns"} <= set(reader.fieldnames):
                raise SourceError(f"{path}: expected columns frame,timestamp_ns")
            return [(int(row["frame"]), int(row["timestamp_ns"])) for row in reader]
    except (OSError, ValueError, csv.Error) as err:
        raise SourceError(f"{path}: unreadable timestamp file ({err})") from None


class _FileSourceBase(ClosingSource):
    """What the file sources share: the context manager, and no calibration of their own."""

    camera: CameraModel | None = None


class VideoFileSource(_FileSourceBase):
    """Frames of a video file, with container timestamps.

    Parameters
    ----------
    path : the video.
    timestamps : optional ``frame,timestamp_ns`` CSV (default: ``<video>.timestamps.csv`` when it
        exists, as ``ar-anchor live --record`` writes it): restores a recorded session's original
        frame indices and capture timestamps.
    """

    def __init__(self, path: str | os.PathLike[str], *, timestamps: str | os.PathLike[str] | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise SourceError(f"{self.path}: not found")
        if not self.path.is_file():
            raise SourceError(f"{self.path}: not a file")
        if self.path.stat().st_size == 0:
            raise SourceError(f"{self.path}: empty file (0 bytes), not a video")
        if not os.access(self.path, os.R_OK):
            raise SourceError(f"{self.path}: not readable (permission denied)")
        problem = opencv_path_problem(self.path)
        if problem is not None:
            raise SourceError(f"{self.path}: {problem}")
        sidecar = (
            Path(timestamps) if timestamps is not None else self.path.with_name(self.path.name + ".timestamps.csv")
        )
        self._recorded: list[tuple[int, int]] | None = None
        if timestamps is not None or sidecar.is_file():
            self._recorded = read_timestamps_csv(sidecar)
            log.info("using recorded frame indices and timestamps from %s", sidecar)
        self._capture = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        if not self._capture.isOpened():
            self._capture.release()
            raise SourceError(f"{self.path}: cannot be opened as a video (not a video, or a codec FFmpeg lacks)")
        ok, first = self._read()
        if not ok or first is None:
            self._capture.release()
            raise SourceError(f"{self.path}: no frame could be decoded (damaged or not a video)")
        self._first = first
        self._resolution = (first.shape[1], first.shape[0])
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self._fps: float | None = fps if math.isfinite(fps) and fps > 0 else None
        count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
        self._count: int | None = count if count > 0 else None
        self._first_ms = self._capture.get(cv2.CAP_PROP_POS_MSEC)
        self._ended_early = False

    def _read(self) -> tuple[bool, np.ndarray | None]:
        try:
            ok, image = self._capture.read()
        except cv2.error as err:
            log.warning("%s: decoder error: %s", self.path, str(err).strip().splitlines()[-1])
            return False, None
        return ok, (to_bgr8(image) if ok else None)

    @property
    def resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def info(self) -> SourceInfo:
        """The container's frame rate and count; ``video_path`` is this file unless recorded indices replace
        the decode positions (``<video>.timestamps.csv``)."""
        return SourceInfo(
            fps=self._fps,
            frame_count=self._count,
            video_path=self.path if self._recorded is None else None,
            ended_early=self._ended_early,
        )

    def close(self) -> None:
        self._capture.release()

    def __iter__(self) -> Iterator[Frame]:
        image, position_ms = self._first, self._first_ms
        index = 0
        previous_ns: int | None = None
        while image is not None:
            frame_index, timestamp_ns = self._timestamp(index, position_ms, previous_ns)
            if image.shape[1::-1] != self._resolution:
                log.warning(
                    "%s: frame %d has size %dx%d, expected %dx%d: stopping here",
                    self.path,
                    index,
                    image.shape[1],
                    image.shape[0],
                    *self._resolution,
                )
                self._ended_early = True
                return
            previous_ns = timestamp_ns
            yield Frame(image, frame_index, timestamp_ns)
            index += 1
            ok, image = self._read()
            position_ms = self._capture.get(cv2.CAP_PROP_POS_MSEC) if ok else math.nan
            if not ok and self._count is not None and index < self._count:
                log.warning(
                    "%s: stream ended after frame %d of %d (damaged or truncated file); outputs cover frames 0..%d",
                    self.path,
                    index - 1,
                    self._count,
                    index - 1,
                )
                self._ended_early = True

    def _timestamp(self, index: int, position_ms: float, previous_ns: int | None) -> tuple[int, int]:
        if self._recorded is not None and index < len(self._recorded):
            return self._recorded[index]
        if self._recorded is not None and index == len(self._recorded):
            log.warning(
                "%s: more frames than its timestamp file lists; using container time from frame %d", self.path, index
            )
        timestamp_ns = int(round((position_ms - self._first_ms) * 1e6)) if math.isfinite(position_ms) else -1
        if previous_ns is not None and timestamp_ns <= previous_ns:
            # containers without usable timestamps: fall back to the nominal frame rate
            step = int(round(1e9 / self._fps)) if self._fps else 33_333_333
            timestamp_ns = previous_ns + step
        return index, max(timestamp_ns, 0)


class ImageFolderSource(_FileSourceBase):
    """Images of a folder (or matching a glob), in natural order, at a nominal frame rate.

    Files that are not images (by extension) are ignored; an image that cannot be decoded, or
    whose size differs from the first one, is skipped with a warning naming it.
    """

    def __init__(self, spec: str | os.PathLike[str], *, fps: float = 30.0) -> None:
        if not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):  # else timestamps overflow or all round to 0
            raise SourceError(f"--fps: must be in [{MIN_FPS:g}, {MAX_FPS:g}], got {fps:g}")
        self._fps = fps
        self.spec = os.fspath(spec)
        path = Path(self.spec)
        if path.is_dir():
            entries = [p for p in path.iterdir() if p.is_file()]
            files = [p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS]
            ignored = len(entries) - len(files)
            if ignored:
                log.info("%s: ignoring %d non-image file(s)", path, ignored)
            where = f"folder {path}"
        elif _GLOB_CHARS.search(self.spec):
            files = [Path(p) for p in glob.glob(self.spec) if Path(p).is_file()]
            where = f"glob {self.spec!r}"
        elif path.is_file():
            files = [path]
            where = f"image {path}"
        else:
            raise SourceError(f"{self.spec}: not found")
        if not files:
            raise SourceError(f"{where}: no images ({', '.join(sorted(IMAGE_EXTENSIONS))})")
        self.files = sorted(files, key=natural_key)
        self._first_index, first = self._first_readable()
        self._resolution = (first.shape[1], first.shape[0])
        self.skipped = 0

    def _load(self, path: Path) -> np.ndarray | None:
        try:
            data = np.fromfile(path, dtype=np.uint8)
            with _decoder_quiet():
                image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except (OSError, cv2.error):
            return None
        return to_bgr8(image) if image is not None else None

    def _first_readable(self) -> tuple[int, np.ndarray]:
        for index, path in enumerate(self.files):
            image = self._load(path)
            if image is not None:
                return index, image
            log.warning("%s: not a readable image, skipped", path)
        raise SourceError(f"{self.spec}: none of its {len(self.files)} image file(s) can be decoded")

    @property
    def resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def info(self) -> SourceInfo:
        return SourceInfo(fps=self._fps, frame_count=len(self.files))

    def close(self) -> None:
        pass

    def __iter__(self) -> Iterator[Frame]:
        for index, path in enumerate(self.files):
            if index < self._first_index:
                continue
            image = self._load(path)
            if image is None:
                log.warning("%s: not a readable image, skipped (frame %d)", path, index)
                self.skipped += 1
                continue
            if image.shape[1::-1] != self._resolution:
                log.warning(
                    "%s: size %dx%d differs from the first image's %dx%d, skipped (frame %d)",
                    path,
                    image.shape[1],
                    image.shape[0],
                    *self._resolution,
                    index,
                )
                self.skipped += 1
                continue
            yield Frame(image, index, int(round(index * 1e9 / self._fps)))
