"""Frame sources: synthetic renders with ground truth (video files, image folders and webcams follow)."""

from __future__ import annotations

from .base import Frame, FrameSource, SourceError
from .synthetic import PlacedBoard, PlacedMarker, SyntheticScene, SyntheticSource, Trajectory, demo_scene

__all__ = [
    "Frame",
    "FrameSource",
    "PlacedBoard",
    "PlacedMarker",
    "SourceError",
    "SyntheticScene",
    "SyntheticSource",
    "Trajectory",
    "demo_scene",
]
