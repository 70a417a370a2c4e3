"""Custom board layouts: marker id -> its four 3D corners (TL, TR, BR, BL) in the board frame, metres.

Two file formats, told apart by their content (not their extension):

* **ar_anchor's own** TOML::

      # my_board.toml
      [[markers]]
      id = 3
      corners = [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.05, 0.05, 0.0], [0.0, 0.05, 0.0]]

* **the ArUco library's marker map** (OpenCV FileStorage YAML, ``aruco_bc_markers``, as written by
  ArUco's ``MarkerMap::saveToFile``; ``aruco_bc_mInfoType`` must be 1 = metres, since a map in
  pixels has no physical size).

Files are data: parsed with ``tomllib`` and OpenCV's FileStorage, nothing is evaluated.
Every problem is a :class:`~ar_anchor.errors.ConfigError` naming the file and what is wrong.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .camera.files import filestorage_nesting_problem, opencv_path_problem
from .errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = ["Layout", "layout_from_mapping", "read_layout", "validate_layout"]

# marker id -> ((x, y, z) x 4), kept as tuples so configs stay hashable and frozen
Layout = tuple[tuple[int, tuple[tuple[float, float, float], ...]], ...]

_MAX_EXTENT_M = 1000.0


def validate_layout(markers: Mapping[int, Any], where: str) -> Layout:
    """Check ids and corners (4 finite 3D points forming a non-degenerate quad) and freeze them."""
    if not markers:
        raise ConfigError(f"{where}: the layout has no markers")
    out = []
    for marker_id, corners in markers.items():
        if isinstance(marker_id, bool) or not isinstance(marker_id, int) or marker_id < 0:
            raise ConfigError(f"{where}: marker id {marker_id!r} must be a non-negative integer")
        try:
            points = np.asarray(corners, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):  # OverflowError: a TOML integer beyond any float
            raise ConfigError(f"{where}: marker {marker_id}: corners must be 4 [x, y, z] numbers") from None
        if points.shape != (4, 3):
            raise ConfigError(
                f"{where}: marker {marker_id}: corners must be 4 [x, y, z] points, got shape {points.shape}"
            )
        if not np.all(np.isfinite(points)) or np.abs(points).max() > _MAX_EXTENT_M:
            raise ConfigError(f"{where}: marker {marker_id}: corners must be finite metres below {_MAX_EXTENT_M:g}")
        edges = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
        if edges.min() <= 1e-6 or edges.min() < 0.2 * edges.max():
            raise ConfigError(f"{where}: marker {marker_id}: the corners do not form a square-like quad")
        out.append((int(marker_id), tuple(tuple(float(v) for v in p) for p in points)))
    ids = [m for m, _ in out]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{where}: marker ids repeat")
    layout = tuple(sorted(out))
    _refuse_coincident(layout, where)
    return layout


_SAME_PLACE = 0.5  # two markers whose centres are closer than this share of the smaller one's side


def _refuse_coincident(layout: Layout, where: str) -> None:
    """ConfigError naming the first two markers at the same place (centres closer than half the smaller
    one's side: printed markers cannot overlap; a cube's markers on adjacent faces are 0.7 side apart). A
    board whose layout holds two such markers, seen as it really is, is solved from corners that disagree
    by a marker's size, so its pose jumps from frame to frame while the solver calls it tracked."""
    if len(layout) < 2:
        return
    points = np.array([corners for _, corners in layout], np.float64)  # (K, 4, 3)
    centres = points.mean(axis=1)
    sides = np.linalg.norm(np.roll(points, -1, axis=1) - points, axis=2).mean(axis=1)
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    close = distance < _SAME_PLACE * np.minimum(sides[:, None], sides[None])
    np.fill_diagonal(close, False)
    pairs = np.argwhere(np.triu(close))
    if len(pairs):
        a, b = (int(k) for k in pairs[0])
        raise ConfigError(
            f"{where}: markers {layout[a][0]} and {layout[b][0]} are at the same place (centres "
            f"{distance[a, b] * 1e3:.1f} mm apart, markers {min(sides[a], sides[b]) * 1e3:.1f} mm wide): a board's "
            "markers cannot overlap"
        )


def layout_from_mapping(data: Any, where: str) -> Layout:
    """Our own format, already parsed: ``{"markers": [{"id": 3, "corners": [[x, y, z], ...]}, ...]}``."""
    if not isinstance(data, Mapping) or "markers" not in data:
        raise ConfigError(f"{where}: expected [[markers]] entries with id and corners")
    entries = data["markers"]
    if not isinstance(entries, list):
        raise ConfigError(f"{where}: markers must be an array of tables ([[markers]])")
    markers: dict[int, Any] = {}
    for index, entry in enumerate(entries):
        if not isinstance(entry, Mapping) or set(entry) != {"id", "corners"}:
            raise ConfigError(f"{where}: markers entry #{index + 1} must have exactly the keys id and corners")
        marker_id = entry["id"]
        if isinstance(marker_id, bool) or not isinstance(marker_id, int):
            raise ConfigError(f"{where}: markers entry #{index + 1}: id must be an integer, got {marker_id!r}")
        if marker_id in markers:
            raise ConfigError(f"{where}: marker id {marker_id} appears twice")
        markers[marker_id] = entry["corners"]
    return validate_layout(markers, where)


def _is_number(node: cv2.FileNode) -> bool:
    """OpenCV reads a string node as a number without complaint (0 or DBL_MAX): check first."""
    return node.isInt() or node.isReal()


def _read_aruco_marker_map(path: Path) -> Layout:
    where = f"layout file {path}"
    try:
        problem = opencv_path_problem(path) or filestorage_nesting_problem(path.read_bytes(), path)
    except OSError as err:
        raise ConfigError(f"{where}: cannot read ({err.strerror})") from None
    if problem is not None:
        raise ConfigError(f"{where}: not a readable OpenCV YAML file ({problem})")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # OpenCV 5 wraps parse errors in SystemError
        cause = err.__cause__ if isinstance(err, SystemError) and err.__cause__ is not None else err
        detail = (str(cause).strip().splitlines() or ["parse error"])[-1]
        raise ConfigError(f"{where}: not a readable OpenCV YAML file ({detail})") from None
    try:
        if not storage.isOpened():
            raise ConfigError(f"{where}: not a readable OpenCV YAML file")
        if not storage.root().isMap():  # getNode() on a list or a scalar document is an OpenCV assertion
            raise ConfigError(f"{where}: expected key: value pairs at the top level (an ArUco marker map)")
        info = storage.getNode("aruco_bc_mInfoType")
        if not info.isNone() and not (_is_number(info) and info.real() == 1):
            shown = f"{info.real():g}" if _is_number(info) else "not a number"
            raise ConfigError(
                f"{where}: aruco_bc_mInfoType is {shown}; a board needs a map in metres (type 1; 0 is pixels)"
            )
        node = storage.getNode("aruco_bc_markers")
        if node.isNone() or not node.isSeq():
            raise ConfigError(f"{where}: no aruco_bc_markers sequence (not an ArUco marker map)")
        markers: dict[int, Any] = {}
        for i in range(node.size()):
            entry = node.at(i)
            ident, corners = (entry.getNode("id"), entry.getNode("corners")) if entry.isMap() else (None, None)
            if ident is None or ident.isNone() or corners is None or not corners.isSeq() or corners.size() != 4:
                raise ConfigError(f"{where}: aruco_bc_markers entry #{i + 1} needs an id and 4 corners")
            value = ident.real()
            if not _is_number(ident) or not math.isfinite(value) or value != int(value):
                raise ConfigError(f"{where}: aruco_bc_markers entry #{i + 1}: id must be an integer")
            points = []
            for j in range(4):
                point = corners.at(j)
                if not point.isSeq() or point.size() != 3 or not all(_is_number(point.at(k)) for k in range(3)):
                    raise ConfigError(f"{where}: marker {int(value)}: corner {j + 1} must be [x, y, z] numbers")
                points.append([point.at(k).real() for k in range(3)])
            if int(value) in markers:
                raise ConfigError(f"{where}: marker id {int(value)} appears twice")
            markers[int(value)] = points
    finally:
        storage.release()
    return validate_layout(markers, where)


def read_layout(path: Path) -> Layout:
    """Read a layout file in either format (see the module doc)."""
    where = f"layout file {path}"
    if not path.is_file():
        raise ConfigError(f"{where}: not found")
    try:
        head = path.read_bytes()[:4096]
    except OSError as err:
        raise ConfigError(f"{where}: cannot read ({err.strerror})") from None
    text_head = head.decode("utf-8", errors="replace")
    if text_head.lstrip().startswith("%YAML") or "aruco_bc_" in text_head:
        return _read_aruco_marker_map(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{where}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{where}: neither an ArUco marker map (YAML) nor a TOML layout: {err}") from None
    except RecursionError:  # tomllib recurses per nesting level of arrays and inline tables
        raise ConfigError(f"{where}: nested too deeply to be a layout") from None
    return layout_from_mapping(data, where)
