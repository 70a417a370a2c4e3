"""Frame sources: synthetic renders with ground truth, video files, image folders, live cameras.

:func:`open_source` opens any of them from a spec (a path, a glob, ``/dev/videoN``, a camera index,
``"synthetic"``); each declares what it is in its :class:`SourceInfo` (``source.info``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..lazy import lazy_exports

if TYPE_CHECKING:  # imported on first use (below): a demo's synthetic frames need no PyAV, the parser nothing
    from .base import Frame, FrameSource, SourceError, SourceInfo
    from .files import ImageFolderSource, VideoFileSource
    from .live import LiveSource
    from .open import DeviceSettings, open_source
    from .synthetic import SyntheticSource

__all__ = [
    "DeviceSettings",
    "Frame",
    "FrameSource",
    "ImageFolderSource",
    "LiveSource",
    "SourceError",
    "SourceInfo",
    "SyntheticSource",
    "VideoFileSource",
    "open_source",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".base": ["Frame", "FrameSource", "SourceError", "SourceInfo"],
        ".files": ["ImageFolderSource", "VideoFileSource"],
        ".live": ["LiveSource"],
        ".open": ["DeviceSettings", "open_source"],
        ".synthetic": ["SyntheticSource"],
    },
    globals(),
)
