"""Shapes for the viewer: a target's marker squares as 3D line strips, an overlay model as a rerun mesh."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from ..geometry import marker_corners_in_marker
from ..targets import TargetId
from ..track.results import TargetResult

__all__ = ["closed_squares", "entity_name", "mesh3d"]


def entity_name(target: str) -> str:
    """``marker:3`` -> ``marker_3`` (a single entity path part)."""
    return TargetId.parse(target).path_part


def closed_squares(target: TargetResult) -> np.ndarray:
    """The target's marker squares as closed 3D line strips in its own frame, (S, 5, 3) (one array: rerun
    takes strips of one length without a conversion per strip)."""
    quads = target.outline_in_target
    if quads is None:
        quads = marker_corners_in_marker(target.length_m)[None]
    quads = np.asarray(quads, np.float64).reshape(-1, 4, 3)
    return np.concatenate([quads, quads[:, :1]], axis=1)


def mesh3d(model: Any) -> rr.Mesh3D:
    """A :class:`~ar_anchor.render.models.Model` as flat-shaded ``rr.Mesh3D`` (vertices repeated per face, so
    each face keeps its own colour and normal)."""
    corners = model.vertices[model.faces]  # (F, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    count = len(model.faces)
    return rr.Mesh3D(
        vertex_positions=corners.reshape(-1, 3).astype(np.float32),
        triangle_indices=np.arange(3 * count, dtype=np.uint32).reshape(-1, 3),
        vertex_normals=np.repeat(normals, 3, axis=0).astype(np.float32),
        vertex_colors=np.repeat(np.clip(model.face_colours, 0, 255).astype(np.uint8), 3, axis=0),
    )
