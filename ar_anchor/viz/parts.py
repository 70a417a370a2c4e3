"""Shapes for the viewer: a target's marker squares as 3D line strips, an overlay model as a rerun mesh; and
the 3D scene's arithmetic, batched over a frame's targets: where each target is in the world, the filter's
branches as line strips, the live filter's axes, and the camera's recent path.

The recorder runs beside the tracker (in a process of its own, on the same cores): a target's place computed
as :meth:`Pose.compose <ar_anchor.geometry.Pose.compose>` does it goes through a Rodrigues vector and back,
and the branches' strips were one array product per branch; here each is one batched product over all
targets, with rotation matrices throughout (the same values to rounding). A place (:data:`Place`) is
``(R, t)``: a 3x3 rotation and a translation (3,), ``world_from_camera`` or ``world_from_target``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from ..geometry import Pose, marker_corners_in_marker
from ..targets import TargetId
from ..track.results import TargetResult
from .sinks import Recording

__all__ = [
    "BRANCH_COLOURS",
    "CAUSAL_COLOURS",
    "Drawings",
    "Place",
    "Shapes",
    "Trail",
    "branch_strips",
    "camera_in_world",
    "causal_axes",
    "closed_squares",
    "entity_name",
    "mesh3d",
    "placed",
    "shape_key",
]


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


Place = tuple[np.ndarray, np.ndarray]

BRANCH_COLOURS = np.array([(90, 200, 255, 90), (255, 140, 60, 90)], np.uint8)  # the filter's branch 0, 1
CAUSAL_COLOURS = [(255, 120, 120, 160), (120, 255, 120, 160), (120, 120, 255, 160)]  # x, y, z: pale
_CAUSAL_ROWS = np.array(CAUSAL_COLOURS)  # (3, 4), as ``np.array`` of the colours makes it


def camera_in_world(camera_from_world: Pose) -> Place:
    """``world_from_camera`` of a ``camera_from_world`` pose (``R^T``, ``-R^T t``, as :meth:`Pose.inverse`)."""
    rotation = camera_from_world.rotation.T
    return rotation, -rotation @ camera_from_world.tvec


def placed(world_from_camera: Place, poses: Sequence[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """``world_from_target`` of each ``camera_from_target`` pose: rotations (N, 3, 3), translations (N, 3)."""
    if not poses:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    rotation, translation = world_from_camera
    rotations = rotation @ np.array([pose.rotation for pose in poses])
    translations = np.array([pose.tvec for pose in poses]) @ rotation.T + translation
    return rotations, translations


def shape_key(target: TargetResult) -> tuple:
    """What a target's shape in its own frame depends on: its size and its marker squares (a key of
    values: the same from frame to frame, and from a target's results pickled to another process)."""
    outline = target.outline_in_target
    if outline is None:
        return (target.length_m,)
    outline = np.asarray(outline, np.float64)
    return (target.length_m, outline.shape, outline.tobytes())


class Drawings:
    """Each target's 3D object as logged, its outline (its marker squares, closed) and its axes: converted
    once per shape (:func:`shape_key`, at most ``limit`` of them), logged each time the target comes back."""

    def __init__(self, limit: int = 256) -> None:
        self.limit = limit
        self._kept: dict[tuple, tuple[Any, Any]] = {}

    def __call__(self, target: TargetResult) -> tuple[Any, Any]:
        key = shape_key(target)
        drawn = self._kept.get(key)
        if drawn is None:
            if len(self._kept) >= self.limit:
                self._kept.clear()
            length_m = target.length_m
            outline = rr.LineStrips3D(closed_squares(target), colors=[(230, 230, 230)], radii=[length_m / 60])
            axes = rr.TransformAxes3D(axis_length=length_m * 0.75)
            drawn = self._kept[key] = (Recording.prebuilt(outline), Recording.prebuilt(axes))
        return drawn


class Shapes:
    """Each target's branch shape in its own frame: its marker squares and its normal (as long as a square)
    as closed line strips, (S + 1, 5, 3); kept by outline and length (the same frame after frame; a
    learned group's outline changes, and is kept anew), at most ``limit`` of them."""

    def __init__(self, limit: int = 256) -> None:
        self.limit = limit
        self._kept: dict[tuple, np.ndarray] = {}

    def __call__(self, target: TargetResult) -> np.ndarray:
        key = shape_key(target)
        shape = self._kept.get(key)
        if shape is None:
            if len(self._kept) >= self.limit:
                self._kept.clear()
            normal = np.array([[0.0, 0.0, 0.0], *[[0.0, 0.0, target.length_m]] * 4])
            shape = self._kept[key] = np.concatenate([closed_squares(target), normal[None]])
            shape.flags.writeable = False
        return shape


def branch_strips(
    targets: Sequence[TargetResult], world_from_camera: Place, shapes: Shapes
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Every target's solution on each filter branch in the world: its shape's strips (M, 5, 3), their
    colours (M, 4: the branch's, faint) and radii (M,: a 120th of the target's size), in the order of the
    targets and of their branches; None when no target has one."""
    kept: list[np.ndarray] = []
    poses: list[Pose] = []
    branches: list[int] = []
    lengths: list[float] = []
    for target in targets:
        shape = None
        for branch, pose in enumerate(target.branch_poses):
            if pose is None:
                continue
            if shape is None:
                shape = shapes(target)
            kept.append(shape)
            poses.append(pose)
            branches.append(min(branch, 1))
            lengths.append(target.length_m)
    if not poses:
        return None
    rotations, translations = placed(world_from_camera, poses)
    counts = [len(shape) for shape in kept]
    strips = np.concatenate(kept) @ np.repeat(rotations.transpose(0, 2, 1), counts, axis=0)
    strips += np.repeat(translations, counts, axis=0)[:, None]
    colours = np.repeat(BRANCH_COLOURS[branches], counts, axis=0)
    radii = np.repeat((np.array(lengths) / 120).astype(np.float32), counts)
    return strips, colours, radii


def causal_axes(targets: Sequence[TargetResult], world_from_camera: Place) -> tuple[np.ndarray, ...]:
    """Each target's axes in the world (its x, y, z, three quarters of its size): origins, vectors
    (3N, 3) and colours (3N, 4)."""
    rotations, translations = placed(world_from_camera, [target.pose for target in targets])
    lengths = np.array([target.length_m * 0.75 for target in targets])
    vectors = (rotations.transpose(0, 2, 1) * lengths[:, None, None]).reshape(-1, 3)
    return np.repeat(translations, 3, axis=0), vectors, np.tile(_CAUSAL_ROWS, (len(targets), 1))


class Trail:
    """The last ``size`` points (3D) of a path, in order, kept in one preallocated array (twice the size:
    the last ``size - 1`` move to its start when it is full)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._points = np.empty((2 * size, 3))
        self._end = 0

    def __len__(self) -> int:
        return min(self._end, self.size)

    def append(self, point: np.ndarray) -> None:
        """``point`` kept as the newest (the oldest dropped beyond ``size``)."""
        if self._end == len(self._points):
            keep = self.size - 1
            self._points[:keep] = self._points[self._end - keep : self._end]
            self._end = keep
        self._points[self._end] = point
        self._end += 1

    def points(self) -> np.ndarray:
        """The points kept, oldest first (N, 3): a view, valid until the next :meth:`append`."""
        return self._points[max(0, self._end - self.size) : self._end]
