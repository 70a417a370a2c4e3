"""Triangle models for overlays: the cube, the built-in example model, and mesh files (via trimesh).

A :class:`Model` is a triangle mesh in metres with one colour per face and outward-facing
normals (counter-clockwise winding seen from outside), which is what back-face culling and
Lambert shading need. Models are placed in a target's *anchor frame*: origin at the target's
centre, x right, y up, z out of the marker or board toward the viewer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import ConfigError
from ..lazy import import_held

__all__ = ["BUILTIN_MODELS", "Model", "cube_model", "load_mesh", "pin_model"]

_DATA = Path(__file__).resolve().parents[1] / "data"  # package data (pyproject: ar_anchor data/*)
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
MAX_TRIANGLES = 200_000  # refuse larger meshes outright (decimate them first); see the README's budget


@dataclass(frozen=True)
class Model:
    """Triangles with per-face colours.

    Attributes
    ----------
    vertices : (V, 3) float64, metres.
    faces : (F, 3) int32 vertex indices, counter-clockwise seen from outside.
    face_colours : (F, 3) float32 RGB in [0, 255].
    facets : (F,) int32 planar-facet id per triangle; triangles of one facet (a cube face) share a
        normal and are drawn as one polygon, with its outline as an edge.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_colours: np.ndarray
    facets: np.ndarray

    def transformed(self, matrix: np.ndarray) -> Model:
        """The model under a 4x4 similarity transform (rotation, uniform scale, translation)."""
        vertices = self.vertices @ matrix[:3, :3].T + matrix[:3, 3]
        return Model(vertices, self.faces, self.face_colours, self.facets)

    def with_colour(self, rgb: tuple[float, float, float]) -> Model:
        colours = np.tile(np.asarray(rgb, np.float32), (len(self.faces), 1))
        return Model(self.vertices, self.faces, colours, self.facets)


def cube_model(side_m: float, subdivisions: int = 1, rgb: tuple[float, float, float] = (70, 140, 240)) -> Model:
    """A cube standing on the z = 0 plane (its base centred on the origin, top at z = side).

    ``subdivisions`` splits each face into n x n cells, so that under lens distortion its edges,
    whose points are each projected through the distortion model, bend as the real edges would.
    """
    n = max(1, int(subdivisions))
    h = side_m / 2.0
    # each face: origin corner, two edge vectors (u x v points outward)
    faces_def = [
        ((-h, -h, side_m), (side_m, 0, 0), (0, side_m, 0)),  # top (+z)
        ((-h, h, 0.0), (side_m, 0, 0), (0, -side_m, 0)),  # bottom (-z)
        ((h, -h, 0.0), (0, side_m, 0), (0, 0, side_m)),  # +x
        ((-h, h, 0.0), (0, -side_m, 0), (0, 0, side_m)),  # -x
        ((h, h, 0.0), (-side_m, 0, 0), (0, 0, side_m)),  # +y
        ((-h, -h, 0.0), (side_m, 0, 0), (0, 0, side_m)),  # -y
    ]
    steps = np.linspace(0.0, 1.0, n + 1)
    vertices, faces, facets = [], [], []
    for facet, (origin, u, v) in enumerate(faces_def):
        origin, u, v = (np.asarray(a, float) for a in (origin, u, v))
        base = sum(len(g) for g in vertices)
        grid = origin + steps[:, None, None] * u + steps[None, :, None] * v  # (n+1, n+1, 3): [i along u, j along v]
        vertices.append(grid.reshape(-1, 3))
        for i in range(n):
            for j in range(n):
                a, b = base + i * (n + 1) + j, base + (i + 1) * (n + 1) + j
                c, d = b + 1, a + 1
                faces += [(a, b, c), (a, c, d)]  # counter-clockwise seen from u x v
                facets += [facet, facet]
    model = Model(
        np.concatenate(vertices),
        np.asarray(faces, np.int32),
        np.zeros((len(faces), 3), np.float32),
        np.asarray(facets, np.int32),
    )
    return model.with_colour(rgb)


def pin_model(height_m: float = 1.0) -> Model:
    """The built-in example model (``path = "builtin:pin"``): a low-poly map pin standing on the
    origin, ``height_m`` tall along +z: a red ball on a white cone, 368 triangles.

    Read from ``ar_anchor/data/pin_*.npy`` (the cone and icosphere trimesh 5.2 builds, and the same model as
    ``configs/models/pin.ply``; ``tests/render/test_overlay.py`` builds it again and compares): building
    it here would import trimesh, 0.4-1 s of every run's start-up, since the default config puts it on
    every board."""
    vertices, faces, colours = (np.load(_DATA / f"pin_{name}.npy") for name in ("vertices", "faces", "face_colours"))
    if height_m != 1.0:
        vertices = vertices * height_m
    return Model(vertices, faces, colours, np.arange(len(faces), dtype=np.int32))


BUILTIN_MODELS = {"builtin:pin": pin_model}


def _trimesh() -> ModuleType:
    """trimesh, imported when a mesh is first used (0.4-1 s; the cube needs none), whole: a Ctrl-C meanwhile is
    raised once it is loaded, not inside its imports, which would swallow it (:func:`~ar_anchor.lazy.import_held`)."""
    trimesh = import_held("trimesh")
    import_held("trimesh.creation")  # the pin's cone and ball (trimesh 4 imports it itself)
    return trimesh


def load_mesh(path: str | Path, rgb: tuple[float, float, float] | None = None) -> Model:
    """Read a mesh file (OBJ, PLY, STL, GLB/glTF, OFF) with trimesh, or a built-in model by name.

    Vertex or face colours in the file are kept (averaged per face) unless ``rgb`` is given.
    Raises :class:`ConfigError` naming the file for a missing, unreadable or malformed file, a
    mesh without faces, non-finite vertices or more than ``MAX_TRIANGLES`` triangles.
    """
    text = str(path)
    if text in BUILTIN_MODELS:
        model = BUILTIN_MODELS[text]()
        return model if rgb is None else model.with_colour(rgb)
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"mesh file {path}: not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ConfigError(f"mesh file {path}: unsupported format {path.suffix!r} (use {', '.join(MESH_SUFFIXES)})")
    try:
        trimesh = _trimesh()
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise ConfigError(f"mesh file {path}: trimesh is not installed ({err})") from None
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # noqa: BLE001 - trimesh raises anything from its many parsers
        raise ConfigError(f"mesh file {path}: cannot read it ({type(err).__name__}: {_first_line(err)})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise ConfigError(f"mesh file {path}: holds no triangle mesh")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0:
        raise ConfigError(f"mesh file {path}: has no faces")
    if faces.shape[1] != 3:
        raise ConfigError(f"mesh file {path}: faces are not triangles")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise ConfigError(f"mesh file {path}: has non-finite (NaN or infinite) vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ConfigError(f"mesh file {path}: faces refer to vertices that do not exist")
    if len(faces) > MAX_TRIANGLES:
        raise ConfigError(f"mesh file {path}: {len(faces)} triangles, more than the {MAX_TRIANGLES} allowed")
    colours = _face_colours(loaded, len(faces)) if rgb is None else None
    if colours is None:
        colours = np.tile(np.asarray(rgb if rgb is not None else (200, 200, 200), np.float32), (len(faces), 1))
    return Model(vertices, faces.astype(np.int32), colours, np.arange(len(faces), dtype=np.int32))


def _face_colours(mesh, count: int) -> np.ndarray | None:
    """RGB per face from the file's face or vertex colours (None when it has none)."""
    try:
        kind = mesh.visual.kind
        if kind == "face":
            colours = np.asarray(mesh.visual.face_colors, np.float32)[:, :3]
        elif kind == "vertex":
            vertex = np.asarray(mesh.visual.vertex_colors, np.float32)[:, :3]
            colours = vertex[np.asarray(mesh.faces)].mean(axis=1)
        elif kind == "texture":
            vertex = np.asarray(mesh.visual.to_color().vertex_colors, np.float32)[:, :3]
            colours = vertex[np.asarray(mesh.faces)].mean(axis=1)
        else:
            return None
    except Exception:  # noqa: BLE001 - odd visuals: fall back to the flat colour
        return None
    if colours.shape != (count, 3) or not np.all(np.isfinite(colours)):
        return None
    return colours


def _first_line(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else "no detail"
