"""Offline sources: video files (FFmpeg through PyAV, see :mod:`.video`) and image folders or globs.

Both are exact and repeatable: frame ``index`` is the position in the file or folder, and
timestamps come from the container, from a ``<video>.timestamps.csv`` written beside a recorded
live session, or, for images, from a configured frame rate.

A file that cannot be opened is a :class:`SourceError` naming it. A video damaged part-way
ends the stream at the last good frame with a warning naming that frame; whatever was produced
until then stays valid. An image that cannot be decoded is skipped with a warning naming it; the
image libraries' own lines about it ("Corrupt JPEG data: ...") are logged at DEBUG, not printed.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraModel
from ..errors import InputError, SourceError, printable
from .base import ClosingSource, Frame, SourceInfo
from .checks import file_kind, in_range, library_stderr_to_log, source_file_stat
from .video import VideoFileSource, read_timestamps_csv

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_BYTES",
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
MAX_IMAGE_BYTES = 1 << 30  # an image file larger than this is not read (a 16-bit 16k x 16k RGB TIFF is 1.5 GiB raw)


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
def _decoder_quiet(path: Path) -> Iterator[list[str]]:
    """OpenCV's own log line for an image it cannot decode ("[ERROR:0@1.6] ... IHDR chunk shall be first"),
    and the image libraries' lines written straight to stderr ("Corrupt JPEG data: 2 extraneous bytes
    before marker 0xd9"), would stand beside our warning naming the file: silence OpenCV's and hold the
    libraries' (yielded, for our warning), unless OpenCV's messages were asked for (-vv leaves OpenCV's
    log level above ERROR): then theirs are shown too."""
    previous = cv2.utils.logging.getLogLevel()
    quiet = previous <= cv2.utils.logging.LOG_LEVEL_ERROR
    if quiet:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with library_stderr_to_log(path, quiet=quiet) as lines:
            yield lines
    finally:
        cv2.utils.logging.setLogLevel(previous)


class ImageFolderSource(ClosingSource):
    """Images of a folder (or matching a glob), in natural order, at a nominal frame rate.

    Files that are not images (by extension) are ignored; an image that cannot be decoded, or
    whose size differs from the first one, is skipped with a warning naming it.
    """

    camera: CameraModel | None = None  # images carry no calibration of their own

    def __init__(self, spec: str | os.PathLike[str], *, fps: float = 30.0) -> None:
        try:  # else timestamps overflow or all round to 0
            self._fps = in_range("--fps", fps, MIN_FPS, MAX_FPS)
        except InputError as err:
            raise SourceError(str(err)) from None
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
        elif path.exists():
            raise SourceError(f"{printable(self.spec)}: is {file_kind(path.stat().st_mode)}, not an image or a folder")
        else:
            raise SourceError(f"{printable(self.spec)}: not found")
        if not files:
            raise SourceError(f"{where}: no images ({', '.join(sorted(IMAGE_EXTENSIONS))})")
        self.files = sorted(files, key=natural_key)
        self._first_index, first = self._first_readable()
        self._resolution = (first.shape[1], first.shape[0])
        self.skipped = 0

    def _load(self, path: Path) -> np.ndarray | None:
        """The image at ``path`` as BGR8, or None (a warning names the file when a library complained)."""
        try:
            source_file_stat(path, what="an image", max_bytes=MAX_IMAGE_BYTES)  # sized and typed before it is read
            data = np.fromfile(path, dtype=np.uint8)
            with _decoder_quiet(path) as complaints:
                image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except SourceError as err:
            log.debug("%s", err)
            return None
        except (OSError, cv2.error):
            return None
        image = to_bgr8(image) if image is not None else None
        if image is not None and complaints:
            log.warning("%s: damaged image data (%s), decoded anyway", printable(path), complaints[0].rstrip("."))
        return image

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
        return SourceInfo(fps=self._fps, frame_count=len(self.files), stills=True)

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
