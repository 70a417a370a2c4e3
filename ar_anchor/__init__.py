"""ar_anchor: real-time fiducial-marker AR tracking.

The public API is importable from the top level (loaded lazily, so ``ar-anchor --help`` stays fast)::

    from ar_anchor import CameraModel, Tracker, load_config, open_source
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "CameraModel": "ar_anchor.camera",
    "Frame": "ar_anchor.sources.base",
    "FrameResult": "ar_anchor.track.results",
    "FrameSource": "ar_anchor.sources.base",
    "Pose": "ar_anchor.geometry",
    "SourceInfo": "ar_anchor.sources.base",
    "SyntheticScene": "ar_anchor.synthetic",
    "SyntheticSource": "ar_anchor.sources.synthetic",
    "TargetResult": "ar_anchor.track.results",
    "Tracker": "ar_anchor.track.tracker",
    "TrackerConfig": "ar_anchor.config",
    "demo_scene": "ar_anchor.synthetic",
    "load_config": "ar_anchor.config",
    "open_source": "ar_anchor.sources.open",
    "smooth": "ar_anchor.track.offline",
}

__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ar_anchor' has no attribute {name!r}")
