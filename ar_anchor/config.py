"""Tracker configuration: TOML read into validated, frozen dataclasses.

Every unknown key and every bad value is a :class:`~ar_anchor.errors.ConfigError` whose message
names the file and the key, e.g. ``configs/x.toml: [markers] length_m: must be > 0, got -1``.

``TrackerConfig()`` (what runs without ``--config``) is exactly ``configs/default.toml`` (a test
keeps them equal). In a config file every scalar key is optional and takes that default, but the
lists are what the file says: a file without ``[[boards]]`` has no boards, one without
``[markers.lengths_m]`` has no per-id sizes.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .boards import layout_from_mapping, read_layout
from .errors import ConfigError
from .targets import TargetId, target_pattern_problem

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = [
    "BoardConfig",
    "DetectorConfig",
    "FilterConfig",
    "MarkersConfig",
    "OverlayConfig",
    "PoseConfig",
    "RecordingConfig",
    "TrackerConfig",
    "demo_config",
    "dictionary_names",
    "load_config",
]

# OpenCV's refinement per option; "edges" is ours (ar_anchor.track.corners), run on unrefined corners
CORNER_REFINEMENTS = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


def dictionary_names() -> list[str]:
    """Names of cv2.aruco's predefined dictionaries (``DICT_4X4_50``, ...), canonical spelling."""
    names = [n for n in dir(cv2.aruco) if n.startswith("DICT_")]
    # OpenCV exposes both DICT_APRILTAG_16h5 and DICT_APRILTAG_16H5; keep one spelling per value.
    by_value: dict[int, str] = {}
    for name in sorted(names):
        by_value.setdefault(int(getattr(cv2.aruco, name)), name)
    return sorted(by_value.values())


def dictionary_id(name: str) -> int:
    """cv2.aruco constant for a predefined dictionary name (case-insensitive)."""
    lookup = {n.upper(): n for n in dir(cv2.aruco) if n.startswith("DICT_")}
    key = name.upper() if isinstance(name, str) else ""
    if key not in lookup:
        raise ConfigError(f"unknown dictionary {name!r} (known: {', '.join(dictionary_names())})")
    return int(getattr(cv2.aruco, lookup[key]))


def dictionary_size(name: str) -> int:
    """Number of markers in a predefined dictionary."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary_id(name)).bytesList.shape[0])


@dataclass(frozen=True)
class DetectorConfig:
    dictionary: str = "DICT_4X4_50"
    corner_refinement: str = "edges"  # edges (lines fitted to the marker's sides) | none | subpix | contour | apriltag
    refinement_window: float = 0.3  # subpix only: window in marker cells (OpenCV's relativeCornerRefinmentWinSize)
    min_perimeter_rate: float = 0.03  # smallest marker perimeter, as a fraction of the image's larger side
    # bits are read from the middle of each cell, ignoring this fraction of the cell on every side
    # (OpenCV's perspectiveRemoveIgnoredMarginPerCell, default 0.13); see Detector for the measurements
    cell_margin: float = 0.25
    # ROI tracking: while targets are tracked, look only around where their markers were (plus their
    # motion), at a reduced scale for big markers; the whole frame every roi_full_every frames and
    # whenever a tracked marker is missed (see Detector.detect_regions)
    roi: bool = True
    roi_full_every: int = 15
    roi_margin: float = 0.6  # region margin around a marker, in marker sides


@dataclass(frozen=True)
class MarkersConfig:
    length_m: float = 0.05
    lengths_m: Mapping[int, float] = field(default_factory=dict)
    ids: tuple[int, ...] = ()  # lone markers to track; empty: every id of the dictionary

    def length_of(self, marker_id: int) -> float:
        return self.lengths_m.get(int(marker_id), self.length_m)


BOARD_KINDS = ("grid", "charuco", "custom")


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
    cols: int = 2
    rows: int = 2
    marker_length_m: float = 0.04
    separation_m: float = 0.02
    first_id: int = 0
    ids: tuple[int, ...] = ()
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


@dataclass(frozen=True)
class PoseConfig:
    max_reproj_px: float = 3.0
    board_inlier_px: float = 3.0  # a board marker (or corner) farther than this from the consensus is an outlier
    recover_markers: bool = True  # look again for a board's missing markers (refineDetectedMarkers)


@dataclass(frozen=True)
class FilterConfig:
    """Flip resolution and smoothing (see :mod:`ar_anchor.track.filtering`)."""

    enabled: bool = True
    corner_noise_px: float = 0.02  # floor of the corner noise; the filter estimates it from residuals
    still_rotation_rad_sqrt_s: float = 1e-4  # random walk of the "still" motion model
    still_translation_m_sqrt_s: float = 1e-5
    angular_accel_moving_rad_s2: float = 30.0  # white acceleration of the "moving" motion model
    linear_accel_moving_m_s2: float = 5.0
    evidence_window_s: float = 2.0  # seconds of flip evidence kept
    decide_margin_px: float = 0.06  # error differences below this never decide (detector bias)
    decide_z: float = 3.0  # standard errors of confidence to commit
    switch_margin_px: float = 0.3  # stronger evidence needed to leave a committed branch
    switch_z: float = 5.0
    evidence_noise_px: float = 0.1  # prior per-frame evidence spread (a few frames' worth)
    evidence_cap_px: float = 3.0  # one frame's evidence is clipped to this
    single_solution_evidence_px: float = 2.0  # evidence when the other solution failed validation
    decisive_ratio: float = 3.0  # one frame decides alone when the other solution's error is this many times ...
    decisive_sigmas: float = 2.0  # ... and this many corner-noise sigmas worse ...
    decisive_px: float = 0.1  # ... and at least this much (or the other failed validation)
    decisive_frames: int = 2  # consecutive decisive frames against the output branch move it there
    predict_s: float = 0.2  # publish predictions through gaps at most this long (state "predicted")
    predict_damping_s: float = 0.1  # a prediction's velocity decays with this time constant
    predict_max_deg: float = 0.25  # ... and it is published only while it may be off by less than this
    memory_s: float = 2.0  # a lost target keeps its track (flip memory) this long, then is reset
    restart_gap_s: float = 0.1  # after a gap longer than this the smoothers restart from the measurement
    still_s: float = 0.3  # a target whose measurements stayed within their noise this long is still:
    output_sigmas: float = 3.0  # its output stays within this many standard deviations of the measurement,
    output_sigmas_moving: float = 0.5  # a moving one's within this many
    reset_angle_deg: float = 15.0  # a branch's measurement this far from its smoother restarts it
    max_angular_rate_deg_s: float = 720.0  # the smoothers' angular velocity is bounded by this
    spike_translation_m: float = 0.01  # an orientation jump above flip_angle_deg with less motion: held 1 frame
    flip_angle_deg: float = 10.0  # orientation uncertainty (3 sigma) above this is not vouched for as tracked
    tilt_accel_rad_s2: float = 3.0  # motion model of the tilt that tells the two branches apart
    crossing_blind_s: float = 0.3  # branches indistinguishable longer than this: the commitment ends
    repeat_grey: float = 0.75  # a frame within this mean grey difference of the last one repeats it (0: exact)


@dataclass(frozen=True)
class RecordingConfig:
    image_every: int = 1
    image_scale: float = 1.0
    jpeg_quality: int = 80
    part_minutes: float = 0.5  # a long run's recording is split into parts this long (0: one file)


OVERLAY_KINDS = ("cube", "mesh", "axes")


@dataclass(frozen=True)
class OverlayConfig:
    """One virtual object drawn on a target (``[[overlays]]``; see :mod:`ar_anchor.render.overlay`).

    ``target``: ``marker:<id>``, ``board:<name>``, ``marker:*`` (every marker that is not part of a
    board), ``board:*`` or ``*``; a target named exactly takes only its own overlays. Placement is in
    the target's anchor frame: its centre, x right, y up, z out of the marker or board.
    """

    target: str = "marker:*"
    kind: str = "cube"
    size_m: float = 0.0  # cube side / axis length / mesh's largest extent; 0: the target's size
    path: str = ""  # mesh: a file (OBJ, PLY, STL, GLB, OFF; relative to the config file) or "builtin:pin"
    scale: float = 1.0  # mesh: file units -> metres (when size_m is 0)
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y, z Euler angles (extrinsic, in order)
    colour: tuple[int, int, int] = (70, 140, 240)  # RGB; a mesh's own colours win unless colour is set
    colour_set: bool = False  # colour was given explicitly
    opacity: float = 1.0

    def matches(self, target: str, board_member: bool) -> bool:
        """Does this overlay go on ``target``? (``marker:*`` skips the markers of a board.)"""
        target = TargetId.parse(target)
        if self.target == "marker:*" and board_member:
            return False
        return target.matches(self.target)


def _default_overlays() -> tuple[OverlayConfig, ...]:
    return (
        OverlayConfig(target="marker:*", kind="cube"),
        OverlayConfig(target="board:*", kind="mesh", path="builtin:pin"),
    )


DEMO_BOARD = BoardConfig(name="desk", cols=2, rows=2, marker_length_m=0.04, separation_m=0.02, first_id=10)
DEMO_LENGTHS_M = {7: 0.04}


@dataclass(frozen=True)
class TrackerConfig:
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    markers: MarkersConfig = field(default_factory=MarkersConfig)
    boards: tuple[BoardConfig, ...] = ()
    pose: PoseConfig = field(default_factory=PoseConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    overlays: tuple[OverlayConfig, ...] = field(default_factory=_default_overlays)
    source: str = "<defaults>"

    def overlays_for(self, target: str) -> tuple[OverlayConfig, ...]:
        """The overlays drawn on ``target``: those naming it exactly, else the matching patterns."""
        exact = tuple(o for o in self.overlays if o.target == target)
        if exact:
            return exact
        target = TargetId.parse(target)
        member = target.marker_id is not None and self.board_of(target.marker_id) is not None
        return tuple(o for o in self.overlays if o.matches(target, member))

    def board_of(self, marker_id: int) -> BoardConfig | None:
        for board in self.boards:
            if marker_id in board.marker_ids:
                return board
        return None

    def marker_length(self, marker_id: int) -> float:
        """Side of marker ``marker_id`` in metres (board markers take their board's length)."""
        board = self.board_of(marker_id)
        return board.marker_length_of(marker_id) if board is not None else self.markers.length_of(marker_id)

    def tracks_marker(self, marker_id: int) -> bool:
        """Is this id one we track (a configured lone marker or a board member)?"""
        if self.board_of(marker_id) is not None:
            return True
        return not self.markers.ids or marker_id in self.markers.ids

    def with_overrides(
        self, *, dictionary: str | None = None, marker_length_m: float | None = None, filter_enabled: bool | None = None
    ) -> TrackerConfig:
        """Copy with command-line overrides applied and validated."""
        import dataclasses

        config = self
        if filter_enabled is not None:
            config = dataclasses.replace(config, filter=dataclasses.replace(config.filter, enabled=filter_enabled))
        if dictionary is not None:
            try:
                dictionary_id(dictionary)
            except ConfigError as err:
                raise ConfigError(f"--dictionary: {err}") from None
            size = dictionary_size(dictionary)
            for board in config.boards:
                too_big = [i for i in board.marker_ids if i >= size]
                if too_big:
                    raise ConfigError(
                        f"--dictionary: {dictionary} has {size} markers, but board '{board.name}' "
                        f"({config.source}) uses ids {too_big[:5]}"
                    )
            config = dataclasses.replace(
                config,
                detector=dataclasses.replace(config.detector, dictionary=dictionary),
                boards=tuple(dataclasses.replace(b, dictionary=dictionary) for b in config.boards),
            )
        if marker_length_m is not None:
            if not (math.isfinite(marker_length_m) and marker_length_m > 0):
                raise ConfigError(f"--marker-length: must be a positive length in metres, got {marker_length_m}")
            config = dataclasses.replace(
                config, markers=dataclasses.replace(config.markers, length_m=float(marker_length_m))
            )
        return config


# ---------------------------------------------------------------------------- parsing


class _Table:
    """One TOML table being read: takes keys, then complains about any left over."""

    def __init__(self, data: Any, where: str, path: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: {where} must be a table, got {type(data).__name__}")
        self.data = dict(data)
        self.where = where
        self.path = path

    def fail(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.path}: {self.where} {_shown_key(key)}: {message}")

    def take(self, key: str, kind: type, default: Any, check: Callable[[Any], str | None] | None = None) -> Any:
        if key not in self.data:
            return default
        value = self.data.pop(key)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            try:
                value = float(value)
            except OverflowError:  # TOML integers are not bounded in tomllib
                raise self.fail(key, "must be finite, got an integer too large for a number") from None
        if kind is int and isinstance(value, bool) or not isinstance(value, kind):
            raise self.fail(key, f"must be {_kind_name(kind)}, got {value!r}")
        if kind is float and not math.isfinite(value):
            raise self.fail(key, f"must be finite, got {value!r}")
        if check is not None:
            problem = check(value)
            if problem:
                raise self.fail(key, f"{problem}, got {value!r}")
        return value

    def take_ids(self, key: str, limit: int) -> tuple[int, ...]:
        if key not in self.data:
            return ()
        value = self.data.pop(key)
        if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise self.fail(key, f"must be a list of integer marker ids, got {value!r}")
        bad = [v for v in value if not 0 <= v < limit]
        if bad:
            raise self.fail(key, f"ids {bad} are outside the dictionary (0..{limit - 1})")
        if len(set(value)) != len(value):
            raise self.fail(key, f"ids must be unique, got {value!r}")
        return tuple(value)

    def done(self) -> None:
        if self.data:
            unknown = ", ".join(sorted(map(_shown_key, self.data)))
            raise ConfigError(f"{self.path}: {self.where}: unknown key(s): {unknown}")


def _shown_key(key: object) -> str:
    """A key as the message shows it: quoted when it holds line breaks or control characters (a TOML
    key may), so that the message stays one line and prints nothing but text."""
    text = str(key)
    return text if text.isprintable() else repr(text)


def _kind_name(kind: type) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false"}.get(kind, kind.__name__)


def _printable(value: str) -> str | None:
    return None if value.isprintable() else "must not contain line breaks or control characters"


def _positive(value: float) -> str | None:
    return None if value > 0 else "must be > 0"


def _non_negative(value: float) -> str | None:
    return None if value >= 0 else "must be >= 0"


def _in_range(lo: float, hi: float) -> Callable[[float], str | None]:
    return lambda value: None if lo <= value <= hi else f"must be in [{lo:g}, {hi:g}]"


_BOARD = BoardConfig(name="defaults")


def _parse_board(bd: _Table, name: str, kind: str, dictionary: str, limit: int, path: str) -> BoardConfig:
    """The kind-specific keys of one ``[[boards]]`` table (keys of other kinds are left: unknown)."""
    if kind == "custom":
        has_file, has_inline = "layout" in bd.data, "markers" in bd.data
        if has_file == has_inline:
            raise bd.fail("layout", 'a custom board needs either layout = "<file>" or inline [[boards.markers]]')
        if has_file:
            layout_name = bd.take("layout", str, None, _printable)
            base = Path(path).parent if path and not path.startswith("<") else Path.cwd()
            layout_path = base / layout_name
            try:
                layout = read_layout(layout_path)
            except ConfigError as err:
                raise bd.fail("layout", str(err)) from None
            source = str(layout_path)
        else:
            try:
                layout = layout_from_mapping({"markers": bd.data.pop("markers")}, "inline markers")
            except ConfigError as err:
                raise bd.fail("markers", str(err)) from None
            source = "inline"
        bad = [marker_id for marker_id, _ in layout if marker_id >= limit]
        if bad:
            key = "markers" if source == "inline" else "layout"
            raise bd.fail(key, f"marker ids {bad} are outside the dictionary (0..{limit - 1})")
        return BoardConfig(name=name, kind=kind, dictionary=dictionary, layout=layout, layout_source=source)
    if kind == "charuco":
        cols = bd.take("squares_x", int, 5, _in_range(2, 100))
        rows = bd.take("squares_y", int, 7, _in_range(2, 100))
        square = bd.take("square_length_m", float, None, _positive)
        if square is None:
            raise bd.fail("square_length_m", "is required for a charuco board")
        marker = bd.take("marker_length_m", float, None, _positive)
        if marker is None:
            raise bd.fail("marker_length_m", "is required for a charuco board")
        if marker >= square:
            raise bd.fail("marker_length_m", f"must be smaller than square_length_m ({square:g}), got {marker!r}")
        board_dictionary = bd.take("dictionary", str, dictionary)
        if board_dictionary.upper() != dictionary.upper():
            raise bd.fail("dictionary", f"must be the detector's dictionary ({dictionary}), got {board_dictionary!r}")
        board = BoardConfig(
            name=name,
            kind=kind,
            cols=cols,
            rows=rows,
            square_length_m=square,
            marker_length_m=marker,
            legacy=bd.take("legacy", bool, False),
            first_id=bd.take("first_id", int, 0, _in_range(0, limit - 1)),
            ids=bd.take_ids("ids", limit),
            dictionary=dictionary,
        )
        count = (cols * rows) // 2
    else:
        board = BoardConfig(
            name=name,
            kind=kind,
            cols=bd.take("cols", int, _BOARD.cols, _in_range(1, 100)),
            rows=bd.take("rows", int, _BOARD.rows, _in_range(1, 100)),
            marker_length_m=bd.take("marker_length_m", float, _BOARD.marker_length_m, _positive),
            separation_m=bd.take("separation_m", float, _BOARD.separation_m, _non_negative),
            first_id=bd.take("first_id", int, _BOARD.first_id, _in_range(0, limit - 1)),
            ids=bd.take_ids("ids", limit),
            dictionary=dictionary,
        )
        count = board.cols * board.rows
    if board.ids and len(board.ids) != count:
        formula = "cols*rows" if kind == "grid" else "squares_x*squares_y//2"
        raise bd.fail("ids", f"needs {formula} = {count} ids, got {len(board.ids)}")
    if not board.ids and board.first_id + count > limit:
        raise bd.fail(
            "first_id", f"ids {board.first_id}..{board.first_id + count - 1} exceed the dictionary's {limit} markers"
        )
    return board


def parse_config(data: Mapping[str, Any], path: str = "<config>") -> TrackerConfig:
    """Validate a parsed TOML document into a :class:`TrackerConfig`."""
    root = _Table(data, "top level", path)
    defaults = TrackerConfig()

    det = _Table(root.data.pop("detector", {}), "[detector]", path)
    dictionary = det.take("dictionary", str, defaults.detector.dictionary)
    try:
        dictionary_id(dictionary)
    except ConfigError as err:
        raise det.fail("dictionary", str(err)) from None
    refinement = det.take(
        "corner_refinement",
        str,
        defaults.detector.corner_refinement,
        lambda v: None if v in CORNER_REFINEMENTS else f"must be one of {', '.join(CORNER_REFINEMENTS)}",
    )
    window = det.take("refinement_window", float, defaults.detector.refinement_window, _in_range(0.05, 10.0))
    perimeter = det.take("min_perimeter_rate", float, defaults.detector.min_perimeter_rate, _in_range(0.001, 4.0))
    cell_margin = det.take("cell_margin", float, defaults.detector.cell_margin, _in_range(0.0, 0.45))
    roi = det.take("roi", bool, defaults.detector.roi)
    roi_full_every = det.take("roi_full_every", int, defaults.detector.roi_full_every, _in_range(1, 10_000))
    roi_margin = det.take("roi_margin", float, defaults.detector.roi_margin, _in_range(0.1, 10.0))
    det.done()
    limit = dictionary_size(dictionary)

    mk = _Table(root.data.pop("markers", {}), "[markers]", path)
    length_m = mk.take("length_m", float, defaults.markers.length_m, _positive)
    ids = mk.take_ids("ids", limit)
    lengths_raw = _Table(mk.data.pop("lengths_m", {}), "[markers.lengths_m]", path)
    lengths: dict[int, float] = {}
    for key in list(lengths_raw.data):
        if not (key.isascii() and key.isdigit()) or not 0 <= int(key) < limit:
            raise lengths_raw.fail(key, f"keys must be marker ids 0..{limit - 1}")
        if int(key) in lengths:  # "7" and "07"
            raise lengths_raw.fail(key, f"marker {int(key)} is listed twice")
        lengths[int(key)] = lengths_raw.take(key, float, None, _positive)
    mk.done()

    boards: list[BoardConfig] = []
    raw_boards = root.data.pop("boards", [])
    if not isinstance(raw_boards, list):
        raise ConfigError(f"{path}: boards must be an array of tables ([[boards]])")
    seen_ids: dict[int, str] = {}
    for index, raw in enumerate(raw_boards):
        bd = _Table(raw, f"[[boards]] #{index + 1}", path)
        name = bd.take("name", str, None)
        if not name or not name.replace("_", "").replace("-", "").isalnum():
            raise bd.fail("name", "is required: letters, digits, '-' and '_'")
        bd.where = f"[[boards]] '{name}'"
        kind = bd.take(
            "kind", str, "grid", lambda v: None if v in BOARD_KINDS else f"must be one of {', '.join(BOARD_KINDS)}"
        )
        board = _parse_board(bd, name, kind, dictionary, limit, path)
        bd.done()
        if any(b.name == name for b in boards):
            raise bd.fail("name", "duplicate board name")
        for marker_id in board.marker_ids:
            if marker_id in seen_ids:
                raise bd.fail("ids", f"marker id {marker_id} is already used by board '{seen_ids[marker_id]}'")
            seen_ids[marker_id] = name
            if marker_id in lengths and abs(lengths[marker_id] - board.marker_length_of(marker_id)) > 1e-9:
                raise bd.fail(
                    "marker_length_m",
                    f"marker {marker_id} also has [markers.lengths_m] "
                    f"{lengths[marker_id]:g}; a board marker's size is the board's",
                )
        boards.append(board)

    ps = _Table(root.data.pop("pose", {}), "[pose]", path)
    pose = PoseConfig(
        max_reproj_px=ps.take("max_reproj_px", float, defaults.pose.max_reproj_px, _positive),
        board_inlier_px=ps.take("board_inlier_px", float, defaults.pose.board_inlier_px, _positive),
        recover_markers=ps.take("recover_markers", bool, defaults.pose.recover_markers),
    )
    ps.done()

    ft = _Table(root.data.pop("filter", {}), "[filter]", path)
    fd = defaults.filter
    filter_config = FilterConfig(
        enabled=ft.take("enabled", bool, fd.enabled),
        corner_noise_px=ft.take("corner_noise_px", float, fd.corner_noise_px, _positive),
        still_rotation_rad_sqrt_s=ft.take("still_rotation_rad_sqrt_s", float, fd.still_rotation_rad_sqrt_s, _positive),
        still_translation_m_sqrt_s=ft.take(
            "still_translation_m_sqrt_s", float, fd.still_translation_m_sqrt_s, _positive
        ),
        angular_accel_moving_rad_s2=ft.take(
            "angular_accel_moving_rad_s2", float, fd.angular_accel_moving_rad_s2, _positive
        ),
        linear_accel_moving_m_s2=ft.take("linear_accel_moving_m_s2", float, fd.linear_accel_moving_m_s2, _positive),
        evidence_window_s=ft.take("evidence_window_s", float, fd.evidence_window_s, _in_range(0.01, 3600.0)),
        decide_margin_px=ft.take("decide_margin_px", float, fd.decide_margin_px, _non_negative),
        decide_z=ft.take("decide_z", float, fd.decide_z, _non_negative),
        switch_margin_px=ft.take("switch_margin_px", float, fd.switch_margin_px, _non_negative),
        switch_z=ft.take("switch_z", float, fd.switch_z, _non_negative),
        evidence_noise_px=ft.take("evidence_noise_px", float, fd.evidence_noise_px, _positive),
        evidence_cap_px=ft.take("evidence_cap_px", float, fd.evidence_cap_px, _positive),
        single_solution_evidence_px=ft.take(
            "single_solution_evidence_px", float, fd.single_solution_evidence_px, _non_negative
        ),
        decisive_ratio=ft.take("decisive_ratio", float, fd.decisive_ratio, _in_range(1.0, 1e6)),
        decisive_sigmas=ft.take("decisive_sigmas", float, fd.decisive_sigmas, _non_negative),
        decisive_px=ft.take("decisive_px", float, fd.decisive_px, _non_negative),
        decisive_frames=ft.take("decisive_frames", int, fd.decisive_frames, _in_range(1, 1000)),
        predict_s=ft.take("predict_s", float, fd.predict_s, _in_range(0.0, 60.0)),
        predict_damping_s=ft.take("predict_damping_s", float, fd.predict_damping_s, _in_range(0.001, 60.0)),
        predict_max_deg=ft.take("predict_max_deg", float, fd.predict_max_deg, _in_range(0.0, 180.0)),
        memory_s=ft.take("memory_s", float, fd.memory_s, _in_range(0.0, 3600.0)),
        restart_gap_s=ft.take("restart_gap_s", float, fd.restart_gap_s, _in_range(0.0, 60.0)),
        still_s=ft.take("still_s", float, fd.still_s, _in_range(0.0, 60.0)),
        output_sigmas=ft.take("output_sigmas", float, fd.output_sigmas, _in_range(0.0, 100.0)),
        output_sigmas_moving=ft.take("output_sigmas_moving", float, fd.output_sigmas_moving, _in_range(0.0, 100.0)),
        reset_angle_deg=ft.take("reset_angle_deg", float, fd.reset_angle_deg, _in_range(0.1, 180.0)),
        max_angular_rate_deg_s=ft.take("max_angular_rate_deg_s", float, fd.max_angular_rate_deg_s, _in_range(1.0, 1e5)),
        spike_translation_m=ft.take("spike_translation_m", float, fd.spike_translation_m, _in_range(0.0, 10.0)),
        flip_angle_deg=ft.take("flip_angle_deg", float, fd.flip_angle_deg, _in_range(0.0, 180.0)),
        tilt_accel_rad_s2=ft.take("tilt_accel_rad_s2", float, fd.tilt_accel_rad_s2, _positive),
        crossing_blind_s=ft.take("crossing_blind_s", float, fd.crossing_blind_s, _in_range(0.0, 3600.0)),
        repeat_grey=ft.take("repeat_grey", float, fd.repeat_grey, _in_range(0.0, 255.0)),
    )
    ft.done()

    rc = _Table(root.data.pop("recording", {}), "[recording]", path)
    recording = RecordingConfig(
        image_every=rc.take("image_every", int, defaults.recording.image_every, _in_range(0, 10_000)),
        image_scale=rc.take("image_scale", float, defaults.recording.image_scale, _in_range(0.05, 1.0)),
        jpeg_quality=rc.take("jpeg_quality", int, defaults.recording.jpeg_quality, _in_range(1, 100)),
        part_minutes=rc.take("part_minutes", float, defaults.recording.part_minutes, _in_range(0.0, 1e6)),
    )
    rc.done()
    overlays = _parse_overlays(root, path, defaults)
    root.done()

    return TrackerConfig(
        detector=DetectorConfig(
            dictionary=dictionary,
            corner_refinement=refinement,
            refinement_window=window,
            min_perimeter_rate=perimeter,
            cell_margin=cell_margin,
            roi=roi,
            roi_full_every=roi_full_every,
            roi_margin=roi_margin,
        ),
        markers=MarkersConfig(length_m=length_m, lengths_m=lengths, ids=ids),
        boards=tuple(boards),
        pose=pose,
        filter=filter_config,
        recording=recording,
        overlays=overlays,
        source=path,
    )


def _parse_overlays(root: _Table, path: str, defaults: TrackerConfig) -> tuple[OverlayConfig, ...]:
    """``[[overlays]]``; absent: the defaults (a cube on every lone marker, the pin on every board)."""
    if "overlays" not in root.data:
        return defaults.overlays
    raw_overlays = root.data.pop("overlays")
    if not isinstance(raw_overlays, list):
        raise ConfigError(f"{path}: overlays must be an array of tables ([[overlays]])")
    # absolute: the models are read later (by the overlay renderer), maybe from another working directory
    base = Path(path).parent.absolute() if path and not path.startswith("<") else Path.cwd()
    result = []
    for index, raw in enumerate(raw_overlays):
        ov = _Table(raw, f"[[overlays]] #{index + 1}", path)
        target = ov.take("target", str, "marker:*", target_pattern_problem)
        kind = ov.take("kind", str, "cube", lambda v: None if v in OVERLAY_KINDS else f"must be one of {OVERLAY_KINDS}")
        mesh_path = ov.take("path", str, "", _printable)
        if kind == "mesh" and not mesh_path:
            raise ov.fail("path", 'a mesh overlay needs a model file (or "builtin:pin")')
        if kind != "mesh" and mesh_path:
            raise ov.fail("path", f"only mesh overlays take a model file (this one is {kind!r})")
        if mesh_path and not mesh_path.startswith("builtin:"):
            mesh_path = str(base / mesh_path)
        elif mesh_path and mesh_path not in ("builtin:pin",):
            raise ov.fail("path", f"unknown built-in model {mesh_path!r} (builtin:pin)")
        colour_set = "colour" in ov.data
        overlay = OverlayConfig(
            target=target,
            kind=kind,
            size_m=ov.take("size_m", float, 0.0, _non_negative),
            path=mesh_path,
            scale=ov.take("scale", float, 1.0, _positive),
            offset_m=_take_vector(ov, "offset_m", 3, (0.0, 0.0, 0.0), 100.0),
            rotation_deg=_take_vector(ov, "rotation_deg", 3, (0.0, 0.0, 0.0), 360.0),
            colour=tuple(int(c) for c in _take_vector(ov, "colour", 3, (70, 140, 240), 255.0, minimum=0.0)),
            colour_set=colour_set,
            opacity=ov.take("opacity", float, 1.0, _in_range(0.0, 1.0)),
        )
        ov.done()
        result.append(overlay)
    return tuple(result)


def _take_vector(
    table: _Table, key: str, size: int, default: tuple[float, ...], limit: float, minimum: float | None = None
) -> tuple[float, ...]:
    if key not in table.data:
        return default
    value = table.data.pop(key)
    numbers = isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not numbers or len(value) != size:
        raise table.fail(key, f"must be a list of {size} numbers, got {value!r}")
    low = -limit if minimum is None else minimum
    if not all(low <= v <= limit and math.isfinite(v) for v in value):  # bounds first: no float() of huge ints
        raise table.fail(key, f"values must be finite and in [{low:g}, {limit:g}], got {value!r}")
    return tuple(float(v) for v in value)


def demo_config() -> TrackerConfig:
    """The demo scene's config (``configs/demo.toml``): the built-in defaults plus the demo's ``desk``
    board (ids 10-13, 0.04 m) and marker 7 at 0.04 m. Only ``ar-anchor demo`` and ``live --device
    synthetic`` use it without being asked: a real video tracks exactly what its config and options say."""
    return TrackerConfig(
        markers=MarkersConfig(lengths_m=dict(DEMO_LENGTHS_M)), boards=(DEMO_BOARD,), source="<demo defaults>"
    )


def load_config(path: str | os.PathLike[str] | None = None, *, demo: bool = False) -> TrackerConfig:
    """Read a tracker TOML file (None: the built-in defaults, identical to ``configs/default.toml``: no
    boards, no per-id sizes; with ``demo``: :func:`demo_config`, identical to ``configs/demo.toml``)."""
    if path is None:
        return demo_config() if demo else TrackerConfig()
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise ConfigError(f"config file {path}: not UTF-8 text ({err.reason})") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path}: invalid TOML: {err}") from None
    except RecursionError:  # tomllib recurses per nesting level of arrays and inline tables
        raise ConfigError(f"config file {path}: invalid TOML: nested too deeply") from None
    except OSError as err:
        raise ConfigError(f"config file {path}: cannot read ({err.strerror})") from None
    return parse_config(data, str(path))
