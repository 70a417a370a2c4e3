"""Synthetic worlds with exact ground truth: what is in the scene, and how a camera renders it.

- :mod:`.scene`: the scene (:class:`SyntheticScene`): lone markers, grid boards and sheets placed on a
  cluttered wall, lighting changes, a hand crossing the view, frame timing, and each frame's truth.
- :mod:`.trajectory`: how the camera moves (:class:`Trajectory`): calm sweeps and orbits, a
  hand-held webcam (sway, tremor, quick turns), unrelated stills one per frame
  (:func:`turntable_stills`), or a video with a cut between paths.
- :mod:`.render`: how a camera renders it (:class:`Renderer`): textured quads through the exact
  pinhole homography, lens distortion, motion blur and rolling shutter, optics, noise, JPEG and H.264.

The frame source over a scene is :class:`ar_anchor.sources.synthetic.SyntheticSource`. This package
depends on the core modules only (camera, geometry, errors, and config for board geometry, tracker
configs and dictionary names), never on sources, tracking, running or drawing.
"""

from __future__ import annotations

from .render import H264RoundTrip, Renderer, pinhole_canvas
from .scene import (
    COMPRESSIONS,
    SKIN_BGR,
    Lighting,
    Occluder,
    PlacedBoard,
    PlacedMarker,
    PlacedSheet,
    SyntheticScene,
    board_marker_poses,
    demo_scene,
    marker_sheet,
    webcam_camera,
)
from .trajectory import StillView, Trajectory, still_view, turntable_stills

__all__ = [
    "COMPRESSIONS",
    "SKIN_BGR",
    "StillView",
    "H264RoundTrip",
    "Lighting",
    "Occluder",
    "PlacedBoard",
    "PlacedMarker",
    "PlacedSheet",
    "Renderer",
    "SyntheticScene",
    "Trajectory",
    "board_marker_poses",
    "demo_scene",
    "marker_sheet",
    "pinhole_canvas",
    "still_view",
    "turntable_stills",
    "webcam_camera",
]
