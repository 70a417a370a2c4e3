"""Frame sources: synthetic renders with ground truth, video files, image folders, live cameras."""

from __future__ import annotations

import os
import re
from pathlib import Path

from .base import Frame, FrameSource, SourceError
from .files import IMAGE_EXTENSIONS, ImageFolderSource, VideoFileSource
from .synthetic import SyntheticSource

__all__ = [
    "Frame",
    "FrameSource",
    "ImageFolderSource",
    "SourceError",
    "SyntheticSource",
    "VideoFileSource",
    "open_file_source",
]


def open_file_source(spec: str | os.PathLike[str], *, fps: float = 30.0) -> VideoFileSource | ImageFolderSource:
    """A video file, an image folder, a glob of images, or a single image: the right source for it."""
    text = os.fspath(spec)
    path = Path(text)
    if path.is_dir() or re.search(r"[*?\[]", text) and not path.exists():
        return ImageFolderSource(text, fps=fps)
    if path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS:
        return ImageFolderSource(text, fps=fps)
    return VideoFileSource(path)
