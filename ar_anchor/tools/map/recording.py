"""The map's rerun recording, logged through :class:`ar_anchor.viz.sinks.Recording` (nothing here imports rerun).

Entity tree (all static): ``world/markers`` the marker squares as a mesh (the reference marker orange),
``world/markers/outlines`` their edges, ``world/markers/ids`` a labelled point at each centre,
``world/cameras`` the adjusted camera centres (the trajectory, one point per frame used), ``report`` the
markdown report. The map frame is the reference marker's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .model import MarkerMap
from .solve import MapSolution

if TYPE_CHECKING:
    from ...viz.sinks import Recording

__all__ = ["MapRecording"]

_MARKER = (235, 235, 235)
_REFERENCE = (255, 150, 40)
_OUTLINE = [(30, 30, 30)]
_LABEL = [(255, 255, 255)]
_CAMERA = [(80, 160, 255)]


@dataclass(frozen=True)
class _Quads:
    """Triangles with per-face colours: what :func:`ar_anchor.viz.parts.mesh3d` draws."""

    vertices: np.ndarray
    faces: np.ndarray
    face_colours: np.ndarray


def _quads(marker_map: MarkerMap) -> _Quads:
    corners = marker_map.all_corners()
    vertices = np.concatenate(list(corners.values()))
    faces, colours = [], []
    for k, marker_id in enumerate(corners):
        base = 4 * k
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
        colour = _REFERENCE if marker_id == marker_map.reference_id else _MARKER
        colours += [colour, colour]
    return _Quads(vertices, np.asarray(faces, np.int32), np.asarray(colours, np.float32))


def _outline_points(marker_map: MarkerMap, per_edge: int = 24) -> np.ndarray:
    """Points along every marker's four edges."""
    steps = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
    points = []
    for quad in marker_map.all_corners().values():
        for a, b in zip(quad, np.roll(quad, -1, axis=0)):
            points.append(a + steps * (b - a))
    return np.concatenate(points)


class MapRecording:
    """The map's ``.rrd`` file (written beside its name and renamed there by :meth:`close` when ``keep``)."""

    def __init__(self, rrd_path: Path | None, *, spawn: bool = False) -> None:
        from ...viz.sinks import Recording

        self.recording: Recording = Recording(
            "ar_anchor_map", path=rrd_path, partial=True, spawn=spawn, name="ar-anchor map", option="--rrd"
        )

    def result(self, solution: MapSolution, report: str) -> None:
        """The map, the camera trajectory and the report."""
        from ...viz.parts import mesh3d

        marker_map = solution.map
        recording = self.recording
        side = marker_map.length_m
        recording.log("world/markers", mesh3d(_quads(marker_map)), static=True)
        recording.points3d(
            "world/markers/outlines", _outline_points(marker_map), radius=side * 0.01, colours=_OUTLINE, static=True
        )
        centres = np.stack([marker_map.world_from_marker[m].tvec for m in marker_map.ids])
        recording.points3d(
            "world/markers/ids",
            centres,
            radius=side * 0.02,
            colours=_LABEL,
            labels=[f"{m}" + (" (reference)" if m == marker_map.reference_id else "") for m in marker_map.ids],
            static=True,
        )
        if solution.camera_from_world:
            cameras = np.stack([solution.camera_from_world[name].camera_centre() for name in solution.frame_order])
            recording.points3d("world/cameras", cameras, radius=side * 0.06, colours=_CAMERA, static=True)
        recording.markdown("report", report, static=True)

    def close(self, *, keep: bool) -> None:
        """Flush and close; the file is renamed into place when ``keep``, removed otherwise."""
        self.recording.close(keep=keep, timeout_s=10.0)
