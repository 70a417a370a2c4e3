"""The AR overlay: shaded, occlusion-correct cubes and meshes, and debug axes, drawn on the frame.

Every overlay has one shape, ``annotate(image, frame_result) -> image`` (:class:`Overlay`);
:class:`OverlayRenderer` draws all of a config's ``[[overlays]]`` at once, because visibility is a
property of the whole scene, not of one object.

How a frame is drawn
--------------------
1. Each target with a pose gets its overlays' triangles, placed in the target's *anchor frame*
   (:func:`target_from_anchor`: centre of the marker or board, x right, y up, z out of it) and
   moved into the camera frame by the target's pose (``X_cam = R X_target + t``).
2. Back-face culling: a triangle whose outward normal points away from the camera (its plane
   does not face the camera centre) is dropped. Triangles reaching behind the near plane too.
3. Lambert shading from a fixed light above-left of the camera, plus ambient light.
4. Every vertex is projected with ``cv2.projectPoints`` and the camera's distortion coefficients;
   with distortion, cube faces are subdivided so their edges bend as the real ones do.
5. Painter's algorithm: planar facets (a cube face, or one mesh triangle) are sorted by depth over
   all objects and filled far to near (sub-pixel vertex positions, anti-aliased edges), so nearer
   faces and objects hide farther ones. Cube faces get a thin darker outline.
6. Opacity: faces are drawn on a copy of the frame together with a coverage map of the
   front-most face's opacity, then blended in one pass.

The tracker's state shows: ``tracked`` targets are drawn as configured, ``ambiguous`` ones at
half opacity with a label, ``predicted`` ones greyed and faint, so users see when the tracker is
unsure. A marker a board's pose was solved from (:meth:`FrameResult.board_members`) is part of that board:
the board's label tells the state, the marker gets none of its own.
"""

from __future__ import annotations

import difflib
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import OverlayConfig, TrackerConfig, dictionary_size
from ..targets import TargetId, TrackState
from ..track.results import FrameResult, TargetResult
from .models import Model, cube_model, load_mesh

__all__ = ["Overlay", "OverlayRenderer", "target_from_anchor", "STATE_STYLE", "unmatched_target_problem"]

log = logging.getLogger(__name__)

_LIGHT = np.array([-0.35, -0.6, -0.72])  # toward the light, camera frame (x right, y down, z forward)
_LIGHT = _LIGHT / np.linalg.norm(_LIGHT)
_AMBIENT = 0.35
_NEAR_M = 0.01
_SHIFT = 4  # fixed-point bits of vertex coordinates passed to OpenCV's fill functions (1/16 px)
_DISTORTED_SUBDIVISIONS = 8

# state -> (opacity factor, saturation kept, label)
STATE_STYLE = {
    TrackState.TRACKED: (1.0, 1.0, ""),
    TrackState.AMBIGUOUS: (0.5, 1.0, "ambiguous"),
    TrackState.PREDICTED: (0.3, 0.25, "predicted"),
    TrackState.INTERPOLATED: (0.6, 0.5, "interpolated"),
}


class Overlay(Protocol):
    """Anything that draws on a frame from the tracker's result."""

    def annotate(self, image: np.ndarray, result: FrameResult) -> np.ndarray: ...


def target_from_anchor(target: TargetResult) -> np.ndarray:
    """4x4 ``target_from_anchor``: the anchor frame (centre, x right, y up, z out of the target) in
    the target's own frame. A marker's frame already is one; a board's is found from its marker
    squares (OpenCV's board frames have y down and z into the board)."""
    outline = target.outline_in_target
    matrix = np.eye(4)
    if outline is None or not target.target.is_board:
        return matrix
    squares = np.asarray(outline, np.float64).reshape(-1, 4, 3)
    # squares run TL, TR, BR, BL seen from the front: (BL - TL) x (TR - TL) points out of the target
    normal = np.cross(squares[:, 3] - squares[:, 0], squares[:, 1] - squares[:, 0]).sum(axis=0)
    matrix[:3, 3] = squares.reshape(-1, 3).mean(axis=0)
    right = squares[0, 1] - squares[0, 0]
    if np.linalg.norm(normal) < 1e-9 * max(float(np.linalg.norm(right)) ** 2, 1e-12):
        return matrix  # a closed non-planar layout (e.g. a cube of markers): no outside to face; its own axes
    z = normal / np.linalg.norm(normal)
    x = right - z * float(right @ z)
    if np.linalg.norm(x) < 1e-12:
        return matrix
    x /= np.linalg.norm(x)
    matrix[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    return matrix


def _target_size(target: TargetResult, anchor_in_target: np.ndarray) -> float:
    """A natural object size: a marker's side; a board's smaller in-plane extent."""
    if not target.target.is_board or target.outline_in_target is None:
        return float(target.length_m)
    points = np.asarray(target.outline_in_target, np.float64).reshape(-1, 3) - anchor_in_target[:3, 3]
    in_anchor = points @ anchor_in_target[:3, :3]
    extent = in_anchor.max(axis=0) - in_anchor.min(axis=0)
    return float(max(min(extent[0], extent[1]), target.length_m))


@dataclass(frozen=True)
class _Placed:
    """A model in a target's frame, ready to be posed each frame."""

    model: Model
    normals: np.ndarray  # (F, 3) outward unit normals, target frame
    outlined: bool  # draw facet outlines (cubes)
    opacity: float


@dataclass
class _Facet:
    depth: float
    polygon: np.ndarray  # (K, 2) pixels
    colour: tuple[float, float, float]  # BGR
    opacity: float
    outline: tuple[float, float, float] | None


class OverlayRenderer:
    """Draws a config's overlays on frames (an :class:`Overlay`).

    Models are built on first sight of each target (sizes depend on the target) and cached; mesh
    files are read once, when the renderer is created, so a bad file fails before any frame.
    """

    def __init__(self, config: TrackerConfig, camera: CameraModel | None = None) -> None:
        self.config = config
        self.camera = camera
        self._meshes: dict[str, Model] = {}
        for problem in dict.fromkeys(
            filter(None, (unmatched_target_problem(config, o.target) for o in config.overlays))
        ):
            log.warning("%s", problem)
        for overlay in config.overlays:
            if overlay.kind == "mesh" and overlay.path not in self._meshes:
                self._meshes[overlay.path] = load_mesh(overlay.path)
        self._placed: dict[tuple[str, bool], list[_Placed]] = {}
        self._axes: dict[str, list[tuple[np.ndarray, float]]] = {}

    # ------------------------------------------------------------------ models
    def models_for(self, target: TargetResult, distorted: bool = False) -> list[_Placed]:
        """The target's overlay models in the target's frame (cached per target)."""
        key = (target.target, distorted)
        if key in self._placed:
            return self._placed[key]
        anchor_in_target = target_from_anchor(target)
        size = _target_size(target, anchor_in_target)
        placed = []
        for overlay in self.config.overlays_for(target.target):
            if overlay.kind == "axes":
                continue
            model = self._model(overlay, size, distorted)
            matrix = anchor_in_target @ _placement(overlay)
            model = model.transformed(matrix)
            placed.append(_Placed(model, _face_normals(model), overlay.kind == "cube", overlay.opacity))
        self._placed[key] = placed
        return placed

    def _model(self, overlay: OverlayConfig, target_size: float, distorted: bool) -> Model:
        rgb = tuple(float(c) for c in overlay.colour)
        if overlay.kind == "cube":
            return cube_model(overlay.size_m or target_size, _DISTORTED_SUBDIVISIONS if distorted else 1, rgb)
        model = self._meshes[overlay.path]
        if overlay.colour_set:
            model = model.with_colour(rgb)
        extent = float(np.max(model.vertices.max(axis=0) - model.vertices.min(axis=0)))
        if overlay.size_m > 0:
            scale = overlay.size_m / extent
        elif overlay.path.startswith("builtin:"):
            scale = target_size / extent
        else:
            scale = overlay.scale
        return model.transformed(np.diag([scale, scale, scale, 1.0]))

    def _axes_for(self, target: TargetResult) -> list[tuple[np.ndarray, float]]:
        if target.target not in self._axes:
            anchor_in_target = target_from_anchor(target)
            size = _target_size(target, anchor_in_target)
            self._axes[target.target] = [
                (anchor_in_target @ _placement(o), o.size_m or size)
                for o in self.config.overlays_for(target.target)
                if o.kind == "axes"
            ]
        return self._axes[target.target]

    # ------------------------------------------------------------------ drawing
    def annotate(self, image: np.ndarray, result: FrameResult) -> np.ndarray:
        """A copy of ``image`` (BGR) with every target's overlays drawn at its output pose."""
        camera = result.camera or self.camera
        if camera is None:
            raise ValueError("OverlayRenderer.annotate: the frame result carries no camera and none was given")
        facets: list[_Facet] = []
        axes: list[tuple[np.ndarray, float, TargetResult]] = []
        labels: list[tuple[str, TargetResult]] = []
        members = result.board_members()  # drawn as part of their board: its label says its state, theirs none
        for name, target in result.targets.items():
            style = STATE_STYLE[target.state]
            for placed in self.models_for(target, camera.has_distortion):
                facets.extend(_facets(placed, target, camera, style))
            axes.extend((matrix, length, target) for matrix, length in self._axes_for(target))
            if style[2] and name not in members:
                labels.append((style[2], target))
        out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if facets:
            out = _paint(out, facets)
        for matrix, length, target in axes:
            _draw_axes(out, matrix, length, target, camera)
        for text, target in labels:
            _draw_label(out, text, target, camera)
        return out


def unmatched_target_problem(config: TrackerConfig, target: str) -> str | None:
    """Why an overlay's exact ``target`` (``board:<name>``, ``marker:<id>``) can never be drawn with
    ``config``, naming what is configured; None when it can (or for a pattern: ``marker:*`` ...)."""
    try:
        target = TargetId.parse(target)
    except ValueError:
        return None  # a pattern (the config reader refused anything else)
    where = f"[[overlays]] target {target!r}"
    if target.is_board:
        names = [board.name for board in config.boards]
        if target.name in names:
            return None
        close = difflib.get_close_matches(target.name, names, n=1)
        hint = f"; did you mean board:{close[0]}?" if close else ""
        known = f"boards: {', '.join(names)}" if names else "no [[boards]] are configured"
        return f"{where} is never drawn: no such board ({known}{hint})"
    marker_id, dictionary = target.marker_id, config.detector.dictionary
    if marker_id >= dictionary_size(dictionary):
        return f"{where} is never drawn: {dictionary} has ids 0 to {dictionary_size(dictionary) - 1}"
    if not config.tracks_marker(marker_id):
        tracked = ", ".join(map(str, config.markers.ids))
        return f"{where} is never drawn: only markers {tracked} are tracked ([markers] ids)"
    return None


def _placement(overlay: OverlayConfig) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_from_euler_xyz_deg(overlay.rotation_deg)
    matrix[:3, 3] = overlay.offset_m
    return matrix


def _face_normals(model: Model) -> np.ndarray:
    tri = model.vertices[model.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def _facets(
    placed: _Placed, target: TargetResult, camera: CameraModel, style: tuple[float, float, str]
) -> list[_Facet]:
    """The visible, shaded facets of one posed model."""
    pose = target.pose
    if not pose.is_finite():
        return []
    rotation = pose.rotation
    model = placed.model
    vertices = model.vertices @ rotation.T + pose.tvec
    normals = placed.normals @ rotation.T
    tri = vertices[model.faces]  # (F, 3, 3)
    facing = np.einsum("ij,ij->i", normals, tri[:, 0]) < 0  # the camera centre is on the normal's side
    in_front = tri[:, :, 2].min(axis=1) > _NEAR_M
    visible = facing & in_front & (np.linalg.norm(normals, axis=1) > 0)
    if not visible.any():
        return []
    used = np.unique(model.faces[visible])
    pixels = np.full((len(vertices), 2), np.nan)
    projected, _ = cv2.projectPoints(
        vertices[used], np.zeros(3), np.zeros(3), camera.camera_matrix, camera.dist_or_none
    )
    pixels[used] = projected.reshape(-1, 2)
    shade = _AMBIENT + (1.0 - _AMBIENT) * np.clip(normals @ _LIGHT, 0.0, None)
    opacity_factor, saturation, _ = style
    colours = model.face_colours.astype(np.float64)
    if saturation < 1.0:
        grey = colours.mean(axis=1, keepdims=True)
        colours = grey + saturation * (colours - grey)
    opacity = placed.opacity * opacity_factor
    visible_ids = np.flatnonzero(visible)
    rgb = np.clip(colours[visible_ids] * shade[visible_ids, None], 0, 255)
    bgr = rgb[:, ::-1]
    depth = tri[visible_ids, :, 2].mean(axis=1)
    facets = model.facets[visible_ids]
    out: list[_Facet] = []
    if len(np.unique(facets)) == len(facets):  # every triangle is its own facet (meshes): no grouping
        polygons = pixels[model.faces[visible_ids]]  # (N, 3, 2)
        finite = np.all(np.isfinite(polygons), axis=(1, 2))
        for k in np.flatnonzero(finite):
            out.append(_Facet(float(depth[k]), polygons[k], tuple(bgr[k].tolist()), opacity, None))
        return out
    order = np.argsort(facets, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(facets[order]) != 0])
    for group in np.split(order, starts[1:]):
        members = visible_ids[group]
        polygon = _facet_boundary(model.faces[members], pixels)
        if polygon is None or not np.all(np.isfinite(polygon)):
            continue
        colour = tuple(bgr[group[0]].tolist())
        outline = tuple(0.55 * c for c in colour) if placed.outlined else None
        out.append(_Facet(float(depth[group].mean()), polygon, colour, opacity, outline))
    return out


def _facet_boundary(faces: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
    """The boundary polygon (pixels) of a subdivided planar facet: its edges used by one triangle only."""
    edges: dict[tuple[int, int], int] = {}
    for a, b, c in faces.tolist():
        for u, v in ((a, b), (b, c), (c, a)):
            key = (min(u, v), max(u, v))
            edges[key] = edges.get(key, 0) + 1
    following: dict[int, int] = {}
    for a, b, c in faces.tolist():
        for u, v in ((a, b), (b, c), (c, a)):
            if edges[(min(u, v), max(u, v))] == 1:
                following[u] = v
    if not following:
        return None
    start = next(iter(following))
    loop = [start]
    while len(loop) <= len(following):
        nxt = following.get(loop[-1])
        if nxt is None:
            return None
        if nxt == start:
            break
        loop.append(nxt)
    return pixels[loop]


def _paint(image: np.ndarray, facets: list[_Facet]) -> np.ndarray:
    """Fill facets far to near, supersampled, and blend them over ``image`` (in place).

    The facets' region is drawn ``s`` times finer (s = 4, or 2 / 1 for very large regions) into a
    premultiplied colour layer and an opacity layer, then area-averaged back: exact anti-aliasing,
    no seams between a mesh's triangles, and the front-most facet's opacity per sub-pixel. OpenCV's
    polygon fill covers every pixel the polygon touches (half a pixel too far on average), so cube
    faces are first inset by half a fine pixel (see :func:`_fine_fills`).
    """
    facets.sort(key=lambda f: -f.depth)
    height, width = image.shape[:2]
    limit = 4.0 * max(width, height)
    points = np.concatenate([np.clip(f.polygon, -limit, limit) for f in facets])
    x0, y0 = (max(int(math.floor(v)) - 2, 0) for v in points.min(axis=0))
    x1 = min(int(math.ceil(points[:, 0].max())) + 3, width)
    y1 = min(int(math.ceil(points[:, 1].max())) + 3, height)
    if x1 <= x0 or y1 <= y0:
        return image
    area = (x1 - x0) * (y1 - y0)
    s = 4 if area <= 300_000 else 2 if area <= 1_200_000 else 1
    premultiplied = np.zeros(((y1 - y0) * s, (x1 - x0) * s, 3), np.uint8)
    opacity = np.zeros(premultiplied.shape[:2], np.uint8)
    to_fine = np.array([x0, y0], float)
    scale = float(1 << _SHIFT)
    fills = _fine_fills(facets, s, to_fine, limit)
    for facet, fill in zip(facets, fills):
        cv2.fillPoly(premultiplied, [fill], tuple(c * facet.opacity for c in facet.colour), cv2.LINE_8, _SHIFT)
        if facet.outline is not None:  # a line one output pixel wide, just inside the facet's edge
            fine = s * (np.clip(facet.polygon, -limit, limit) - to_fine) + (s - 1) / 2.0
            line = np.round(_inset(fine, 0.5 * s + 0.5) * scale).astype(np.int32).reshape(-1, 1, 2)
            outline = tuple(c * facet.opacity for c in facet.outline)
            cv2.polylines(premultiplied, [line], True, outline, s, cv2.LINE_8, _SHIFT)
    # the front-most facet's opacity wins, as its colour does (one polygon per call: fillPoly given
    # several overlapping polygons at once fills their overlaps by the even-odd rule, i.e. not at all)
    for facet, fill in zip(facets, fills):
        cv2.fillPoly(opacity, [fill], round(255 * facet.opacity), cv2.LINE_8, _SHIFT)
    size = (x1 - x0, y1 - y0)
    if s > 1:
        premultiplied = cv2.resize(premultiplied, size, interpolation=cv2.INTER_AREA)
        opacity = cv2.resize(opacity, size, interpolation=cv2.INTER_AREA)
    if not opacity.any():
        return image
    alpha = opacity[..., None].astype(np.float32) / 255.0
    region = image[y0:y1, x0:x1].astype(np.float32)
    blended = region * (1.0 - alpha) + premultiplied.astype(np.float32)
    image[y0:y1, x0:x1] = np.clip(blended + 0.5, 0, 255).astype(np.uint8)
    return image


def _fine_fills(facets: list[_Facet], s: int, to_fine: np.ndarray, limit: float) -> list[np.ndarray]:
    """Each facet's polygon on the fine grid as OpenCV fixed point. Outlined facets (cube faces, whose
    silhouette must be exact) are inset by the half fine pixel OpenCV's fill adds; a mesh's triangles
    are not, as insetting them would open cracks between neighbours (and the fill's excess is only
    1 / (2 s) of an output pixel)."""
    fills: list[np.ndarray | None] = [None] * len(facets)
    groups: dict[tuple[int, bool], list[int]] = {}
    for index, facet in enumerate(facets):
        groups.setdefault((len(facet.polygon), facet.outline is not None), []).append(index)
    for (_, exact), indices in groups.items():  # same-size polygons (a mesh's triangles) in one go
        polygons = np.clip(np.stack([facets[i].polygon for i in indices]), -limit, limit)
        fine = s * (polygons - to_fine) + (s - 1) / 2.0  # pixel centres stay centres
        if exact:
            fine = _inset(fine, 0.5)
        fixed = np.round(fine * float(1 << _SHIFT)).astype(np.int32)
        for i, polygon in zip(indices, fixed):
            fills[i] = polygon.reshape(-1, 1, 2)
    return fills  # type: ignore[return-value]


def _inset(polygon: np.ndarray, distance: float) -> np.ndarray:
    """Polygons (..., K, 2) with every edge moved ``distance`` inward (mitred corners; capped for tiny ones)."""
    p = np.asarray(polygon, np.float64)
    if p.shape[-2] < 3:
        return p
    after_p = np.roll(p, -1, axis=-2)
    area = 0.5 * np.sum(p[..., 0] * after_p[..., 1] - after_p[..., 0] * p[..., 1], axis=-1)
    edges = after_p - p
    lengths = np.linalg.norm(edges, axis=-1, keepdims=True)
    edges = np.divide(edges, lengths, out=np.zeros_like(edges), where=lengths > 1e-12)
    sign = np.where(area > 0, 1.0, -1.0)[..., None, None]  # area > 0: clockwise on screen (y down)
    inward = sign * np.stack([-edges[..., 1], edges[..., 0]], axis=-1)
    before = np.roll(inward, 1, axis=-2)  # vertex k joins edge k-1 and edge k
    miter = before + inward
    denominator = (1.0 + np.sum(before * inward, axis=-1))[..., None]
    offset = np.divide(miter, denominator, out=np.zeros_like(miter), where=denominator > 0.2)
    inradius = 2.0 * np.abs(area) / np.maximum(lengths.sum(axis=(-2, -1)), 1e-9)
    step = np.minimum(distance, 0.5 * inradius)[..., None, None]
    return p + step * offset


def _draw_axes(
    image: np.ndarray, target_from_axes: np.ndarray, length: float, target: TargetResult, camera: CameraModel
) -> None:
    """x red, y green, z blue; each axis a polyline of projected points, so it bends with the lens."""
    pose = target.pose
    steps = np.linspace(0.0, length, 17)
    for axis, bgr in enumerate(((40, 40, 230), (40, 200, 40), (230, 90, 30))):
        points = np.zeros((len(steps), 3))
        points[:, axis] = steps
        in_target = points @ target_from_axes[:3, :3].T + target_from_axes[:3, 3]
        in_camera = in_target @ pose.rotation.T + pose.tvec
        if np.any(in_camera[:, 2] <= _NEAR_M):
            continue
        pixels = camera.project(in_camera)
        cv2.polylines(image, [np.round(pixels * 16).astype(np.int32)], False, bgr, 2, cv2.LINE_AA, _SHIFT)


def _draw_label(image: np.ndarray, text: str, target: TargetResult, camera: CameraModel) -> None:
    centre = target.pose.tvec
    if centre[2] <= _NEAR_M or not np.all(np.isfinite(centre)):
        return
    x, y = camera.project(centre[None])[0]
    if not (math.isfinite(x) and math.isfinite(y)):
        return
    origin = (int(x) + 8, int(y) - 8)
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)


def rotation_from_euler_xyz_deg(angles_deg: Sequence[float]) -> np.ndarray:
    """Rotation matrix of turns about the fixed x, then y, then z axes (degrees): ``Rz Ry Rx``, as
    ``scipy.spatial.transform.Rotation.from_euler("xyz", angles, degrees=True)`` (without importing scipy,
    a quarter of a second at start-up)."""
    rx, ry, rz = (math.radians(float(a)) for a in angles_deg)
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    turn_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    turn_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    turn_z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return turn_z @ turn_y @ turn_x
