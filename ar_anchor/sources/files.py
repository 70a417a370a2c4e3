"""Offline sources: video files (FFmpeg through PyAV, see :mod:`.video`) and image folders or globs.

Both are exact and repeatable: frame ``index`` is the position in the file or folder, and
timestamps come from the container, from a ``<video>.timestamps.csv`` written beside a recorded
live session, or, for images, from a configured frame rate.

A file that cannot be opened is a :class:`SourceError` naming it. A video damaged part-way
ends the stream at the last good frame with a warning naming that frame; whatever was produced
until then stays valid. An image that cannot be decoded is skipped with a warning naming it; the
image libraries' own lines about it ("Corrupt JPEG data: ...") are logged at DEBUG, not printed.

Pixels are bounded as well as bytes: an image's header is read before it is decoded
(:mod:`.image_header`), and one of more than ``max_pixels`` (default 50 MP, ``--max-megapixels``) is
skipped with a warning naming it and the limit (a 330 kB PNG of 20000 x 15000 pixels took minutes and
2.6 GB to decode); a video whose frames are larger is refused. An image folder's frame size is the
most common one in its images' headers, so a stray image of another size (a 1x1 placeholder sorted
first) is skipped by name instead of setting the size for the whole folder.
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
from .image_header import MAX_IMAGE_PIXELS, image_size, pixel_limit_text
from .video import VideoFileSource, read_timestamps_csv

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_BYTES",
    "MAX_IMAGE_PIXELS",
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
_SIZE_SAMPLE = 256  # the folder's usual image size: the most common in the headers of its first this many images


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


def _other_files(others: list[Path]) -> str:
    """The hint for a folder with no images but other files (a video in a folder, most likely): what they are
    and how a video is given."""
    if not others:
        return ""
    first = sorted(others, key=natural_key)[:2]
    named = ", ".join(printable(p.name) for p in first) + (", ..." if len(others) > 2 else "")
    return (
        f"; it holds {len(others)} other file(s) ({named}): a video is given as the file itself "
        f"(replay {printable(first[0])}), a folder of videos to `ar-anchor batch`"
    )


class ImageFolderSource(ClosingSource):
    """Images of a folder (or matching a glob), in natural order, at a nominal frame rate.

    Files that are not images (by extension) are ignored; an image that cannot be decoded, one of more
    than ``max_pixels`` (read from its header, before decoding), or one whose size differs from the
    folder's (the most common size in the headers of its first images; else the first readable image's)
    is skipped with a warning naming it.
    """

    camera: CameraModel | None = None  # images carry no calibration of their own

    def __init__(self, spec: str | os.PathLike[str], *, fps: float = 30.0, max_pixels: int = MAX_IMAGE_PIXELS) -> None:
        try:  # else timestamps overflow or all round to 0
            self._fps = in_range("--fps", fps, MIN_FPS, MAX_FPS)
        except InputError as err:
            raise SourceError(str(err)) from None
        self._max_pixels = int(max_pixels)
        self._single = False  # one image named, not a folder or a glob: its error is its own
        self.spec = os.fspath(spec)
        path = Path(self.spec)
        others: list[Path] = []  # a folder's files that are not images
        if path.is_dir():
            entries = [p for p in path.iterdir() if p.is_file()]
            files = [p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS]
            others = [p for p in entries if p.suffix.lower() not in IMAGE_EXTENSIONS]
            if others:
                log.info("%s: ignoring %d non-image file(s)", path, len(others))
            where = f"folder {path}"
        elif _GLOB_CHARS.search(self.spec):
            files = [Path(p) for p in glob.glob(self.spec) if Path(p).is_file()]
            where = f"glob {self.spec!r}"
        elif path.is_file():
            files = [path]
            where = f"image {path}"
            self._single = True
        elif path.exists():
            raise SourceError(f"{printable(self.spec)}: is {file_kind(path.stat().st_mode)}, not an image or a folder")
        else:
            raise SourceError(f"{printable(self.spec)}: not found")
        if not files:
            raise SourceError(f"{where}: no images ({', '.join(sorted(IMAGE_EXTENSIONS))}){_other_files(others)}")
        self.files = sorted(files, key=natural_key)
        self.skipped = 0
        self._headers: dict[Path, tuple[int, int] | None] = {p: image_size(p) for p in self.files[:_SIZE_SAMPLE]}
        self._first_index, first = self._first_readable(self._usual_size())
        self._resolution = (first.shape[1], first.shape[0])
        self.resolution_from = self.files[self._first_index]  # the image whose size the frames have

    def _usual_size(self) -> tuple[int, int] | None:
        """The most common (width, height) in the headers read, among sizes within the pixel limit (a tie:
        the one met first); None when no header could be read."""
        counts: dict[tuple[int, int], int] = {}
        for size in self._headers.values():
            if size is not None and size[0] * size[1] <= self._max_pixels:
                counts[size] = counts.get(size, 0) + 1
        return max(counts, key=counts.__getitem__) if counts else None  # (max keeps the first of equals)

    def _too_large(self, path: Path) -> str | None:
        """Why the image at ``path`` is not decoded for its pixel count (its header's), or None."""
        size = self._headers[path] if path in self._headers else image_size(path)
        if size is None or size[0] * size[1] <= self._max_pixels:
            return None
        return (
            f"{size[0]}x{size[1]} pixels ({size[0] * size[1] / 1e6:.3g} MP), more than the "
            f"{pixel_limit_text(self._max_pixels)} MP limit (--max-megapixels)"
        )

    def _load(self, path: Path) -> tuple[np.ndarray | None, str]:
        """The image at ``path`` as BGR8, or None and why (a warning names the file when a library complained)."""
        unreadable = "not a readable image"
        try:
            source_file_stat(path, what="an image", max_bytes=MAX_IMAGE_BYTES)  # sized and typed before it is read
            too_large = self._too_large(path)  # (its header: before it is decoded)
            if too_large is not None:
                return None, too_large
            data = np.fromfile(path, dtype=np.uint8)
            with _decoder_quiet(path) as complaints:
                image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except SourceError as err:
            log.debug("%s", err)
            return None, unreadable
        except (OSError, cv2.error):
            return None, unreadable
        image = to_bgr8(image) if image is not None else None
        if image is not None and complaints:
            log.warning("%s: damaged image data (%s), decoded anyway", printable(path), complaints[0].rstrip("."))
        return image, unreadable

    def _first_readable(self, usual: tuple[int, int] | None) -> tuple[int, np.ndarray]:
        """The first image that decodes, of the ``usual`` size when known (those before it of another size are
        skipped by name); when none of that size decodes, the first that does (as without headers)."""
        reason = "not a readable image"
        fallback: tuple[int, np.ndarray] | None = None
        other_sizes: list[tuple[Path, tuple[int, int]]] = []
        unreadable: list[int] = []
        for index, path in enumerate(self.files):
            image, reason = self._load(path)
            if image is None:
                if not self._single:  # (one image named alone: the error says it)
                    log.warning("%s: %s, skipped", printable(path), reason)
                unreadable.append(index)
                continue
            size = (image.shape[1], image.shape[0])
            if usual is None or size == usual:
                for other, (width, height) in other_sizes:
                    log.warning(
                        "%s: size %dx%d differs from the folder's %dx%d (most of its images), skipped",
                        printable(other),
                        width,
                        height,
                        *size,
                    )
                self.skipped += len(unreadable) + len(other_sizes)
                return index, image
            if fallback is None:
                fallback = (index, image)
            other_sizes.append((path, size))
        if fallback is not None:  # (the images after it are read again, and skipped again if they must be)
            self.skipped += sum(1 for index in unreadable if index < fallback[0])
            return fallback
        if self._single:
            raise SourceError(f"{printable(self.files[0])}: {reason}")
        last = "" if reason == "not a readable image" else f" (the last, {printable(self.files[-1].name)}: {reason})"
        raise SourceError(f"{printable(self.spec)}: none of its {len(self.files)} image file(s) can be decoded{last}")

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
            image, reason = self._load(path)
            if image is None:
                log.warning("%s: %s, skipped (frame %d)", printable(path), reason, index)
                self.skipped += 1
                continue
            if image.shape[1::-1] != self._resolution:
                log.warning(
                    "%s: size %dx%d differs from the folder's %dx%d, skipped (frame %d)",
                    printable(path),
                    image.shape[1],
                    image.shape[0],
                    *self._resolution,
                    index,
                )
                self.skipped += 1
                continue
            yield Frame(image, index, int(round(index * 1e9 / self._fps)))
