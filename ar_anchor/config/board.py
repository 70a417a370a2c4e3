"""Rigid boards of markers: the keys a ``[[boards]]`` table may hold, per kind, and the board itself.

A ``[[boards]]`` table is read in two steps (:func:`ar_anchor.config.read.read_board`): the keys every
board has (:class:`BoardKeys`: name, kind), then the keys of its kind (:data:`BOARD_KEYS`), so a key
of another kind is an unknown key. The per-kind key sets are only the TOML side; :class:`BoardConfig`
is what the tracker uses, the same for every kind (a grid board's keys are its field names, and its
defaults are theirs).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..targets import TargetId
from .dictionaries import dictionary_id
from .keys import REQUIRED, Check, in_range, key, non_negative, one_of, positive, printable, valid_marker_id

__all__ = [
    "BOARD_KEYS",
    "BOARD_KINDS",
    "BoardConfig",
    "BoardKeys",
    "CharucoBoardKeys",
    "CustomBoardKeys",
    "GridBoardKeys",
]

BOARD_KINDS = ("grid", "charuco", "custom")
NAME_RULE = "is required: letters, digits, '-' and '_'"
board_name = Check(
    NAME_RULE,
    lambda value, _limit: None if value and value.replace("_", "").replace("-", "").isalnum() else NAME_RULE,
    shows_value=True,
)


@dataclass(frozen=True, kw_only=True)
class BoardKeys:
    """The keys of every ``[[boards]]`` table, whatever its kind."""

    name: str = key(
        REQUIRED, "the board's name; it is tracked as target board:<name>", board_name, kind=str, required=NAME_RULE
    )
    kind: str = key("grid", "grid | charuco | custom", one_of(BOARD_KINDS))


@dataclass(frozen=True, kw_only=True)
class GridBoardKeys:
    """``kind = "grid"``: ``cols`` x ``rows`` markers with ``separation_m`` between them."""

    cols: int = key(2, "markers across", in_range(1, 100))
    rows: int = key(2, "markers down", in_range(1, 100))
    marker_length_m: float = key(0.04, "side of each marker's black square, metres", positive)
    separation_m: float = key(0.02, "gap between neighbouring markers, metres", non_negative)
    first_id: int = key(0, "ids first_id .. first_id + cols*rows - 1, row-major from the top-left", valid_marker_id)
    ids: tuple[int, ...] = key((), "or explicit ids instead of first_id, cols*rows of them", shape="ids")


_CHARUCO_REQUIRED = "is required for a charuco board"


@dataclass(frozen=True, kw_only=True)
class CharucoBoardKeys:
    """``kind = "charuco"``: a chessboard of squares with markers in its white squares."""

    squares_x: int = key(5, "chessboard squares across", in_range(2, 100))
    squares_y: int = key(7, "chessboard squares down", in_range(2, 100))
    square_length_m: float = key(
        REQUIRED, "side of a chessboard square, metres", positive, kind=float, required=_CHARUCO_REQUIRED
    )
    marker_length_m: float = key(
        REQUIRED, "side of a marker, metres (smaller than a square)", positive, kind=float, required=_CHARUCO_REQUIRED
    )
    dictionary: str = key("", "the detector's dictionary, the only one allowed (default: it)")
    legacy: bool = key(False, "OpenCV's pre-4.6 pattern (boards with an even number of rows)")
    first_id: int = key(0, "ids first_id .. first_id + squares_x*squares_y//2 - 1", valid_marker_id)
    ids: tuple[int, ...] = key((), "or explicit ids, one per marker: squares_x*squares_y//2", shape="ids")


@dataclass(frozen=True, kw_only=True)
class CustomBoardKeys:
    """``kind = "custom"``: any rigid layout, planar or not: each marker's 4 corners (TL, TR, BR, BL).
    Exactly one of ``layout`` and ``markers``."""

    layout: str = key(
        "",
        "a layout file relative to this one: our TOML ([[markers]] id, corners) or an ArUco marker map YAML "
        "(aruco_bc_markers, in metres)",
        printable,
        example="cube_layout.toml",
    )
    markers: tuple = key(
        (),
        "or inline: [[boards.markers]] tables, each an id and its corners, four [x, y, z]",
        shape="inline",
    )


BOARD_KEYS: dict[str, type] = {"grid": GridBoardKeys, "charuco": CharucoBoardKeys, "custom": CustomBoardKeys}

_GRID = GridBoardKeys  # a board's defaults are a grid board's keys' defaults (declared once, above)


@dataclass(frozen=True)
class BoardConfig:
    """A rigid board of markers, in OpenCV's ``Board.getObjPoints()`` frame for grid and ChArUco
    (origin at the top-left outer corner, x right, y down, z into the board) and in the layout's own
    frame for ``custom``.

    kind ``grid``: ``cols`` x ``rows`` markers of ``marker_length_m`` with ``separation_m`` between them.
    kind ``charuco``: ``cols`` x ``rows`` chessboard squares of ``square_length_m`` with markers of
    ``marker_length_m`` in the white squares (``legacy``: OpenCV's pre-4.6 pattern for even rows).
    kind ``custom``: ``layout`` gives each marker's four corners (TL, TR, BR, BL), planar or not.
    """

    name: str
    kind: str = "grid"
    cols: int = _GRID.cols
    rows: int = _GRID.rows
    marker_length_m: float = _GRID.marker_length_m
    separation_m: float = _GRID.separation_m
    first_id: int = _GRID.first_id
    ids: tuple[int, ...] = _GRID.ids
    square_length_m: float = 0.0
    legacy: bool = False
    dictionary: str = "DICT_4X4_50"
    layout: tuple[tuple[int, tuple[tuple[float, float, float], ...]], ...] = ()
    layout_source: str = ""

    @property
    def marker_ids(self) -> tuple[int, ...]:
        """Ids in row-major order from the top-left marker (OpenCV's GridBoard / CharucoBoard order)."""
        if self.kind == "custom":
            return tuple(marker_id for marker_id, _ in self.layout)
        if self.ids:
            return self.ids
        count = self.cols * self.rows if self.kind == "grid" else (self.cols * self.rows) // 2
        return tuple(range(self.first_id, self.first_id + count))

    @property
    def target(self) -> TargetId:
        return TargetId.board(self.name)

    def corners_in_board(self) -> dict[int, np.ndarray]:
        """Each marker's corners (4, 3) in the board frame, TL, TR, BR, BL as the detector orders them."""
        if self.kind == "custom":
            return {marker_id: np.array(corners, dtype=np.float64) for marker_id, corners in self.layout}
        if self.kind == "charuco":
            board = self.cv_board()
            points = np.asarray(board.getObjPoints(), dtype=np.float64).reshape(-1, 4, 3)
            return dict(zip(self.marker_ids, points))
        out = {}
        step = self.marker_length_m + self.separation_m
        unit = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
        for index, marker_id in enumerate(self.marker_ids):
            row, col = divmod(index, self.cols)
            out[marker_id] = unit * self.marker_length_m + np.array([col * step, row * step, 0.0])
        return out

    def cv_board(self) -> cv2.aruco.Board:
        """The OpenCV board object (for ``refineDetectedMarkers`` and ChArUco corner interpolation)."""
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary))
        ids = np.array(self.marker_ids, dtype=np.int32)
        if self.kind == "charuco":
            board = cv2.aruco.CharucoBoard(
                (self.cols, self.rows), self.square_length_m, self.marker_length_m, dictionary, ids
            )
            board.setLegacyPattern(self.legacy)
            return board
        corners = self.corners_in_board()
        points = [corners[i].astype(np.float32) for i in self.marker_ids]
        return cv2.aruco.Board(points, dictionary, ids)

    def marker_length_of(self, marker_id: int) -> float:
        """Side of one of the board's markers (a custom layout's: its mean edge)."""
        if self.kind != "custom":
            return self.marker_length_m
        corners = self.corners_in_board()[int(marker_id)]
        return float(np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))

    @property
    def planar(self) -> bool:
        """Do all corners lie in one plane (to 0.1 % of the board's extent)?"""
        if self.kind != "custom":
            return True
        points = np.concatenate(list(self.corners_in_board().values()))
        centred = points - points.mean(axis=0)
        singular = np.linalg.svd(centred, compute_uv=False)
        return bool(singular[2] <= 1e-3 * max(singular[0], 1e-12))

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the board in metres: outer marker edges (grid), squares (ChArUco),
        the layout's x/y extent (custom)."""
        if self.kind == "charuco":
            return (self.cols * self.square_length_m, self.rows * self.square_length_m)
        if self.kind == "custom":
            points = np.concatenate(list(self.corners_in_board().values()))
            extent = points.max(axis=0) - points.min(axis=0)
            return (float(extent[0]), float(extent[1]))
        return (
            self.cols * self.marker_length_m + (self.cols - 1) * self.separation_m,
            self.rows * self.marker_length_m + (self.rows - 1) * self.separation_m,
        )
