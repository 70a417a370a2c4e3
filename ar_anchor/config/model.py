"""The tracker's configuration: frozen dataclasses whose fields are the TOML keys, each declared once.

Every table of a config file is one dataclass here (``[detector]`` is :class:`DetectorConfig`, ...) and
every key is one field made by :func:`~ar_anchor.config.keys.key`, with its default, its check and the
doc that ``configs/default.toml`` shows beside it. :class:`TrackerConfig`'s fields are the tables, in
the order a file is read and written. Boards are in :mod:`.board`; reading is :mod:`.read`.

``TrackerConfig()`` (what runs without ``--config``) is exactly ``configs/default.toml``, and
:func:`demo_config` is ``configs/demo.toml``: both files are written from these declarations by
``python -m ar_anchor.config.document`` (a test keeps them equal).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError
from ..targets import TargetId, target_pattern_problem
from .board import BoardConfig
from .dictionaries import CORNER_REFINEMENTS, canonical_dictionary, dictionary_id, dictionary_size
from .keys import Check, ConfigValueError, in_range, key, non_negative, one_of, positive, printable

__all__ = [
    "DEMO_BOARD",
    "DEMO_LENGTHS_M",
    "OVERLAY_KINDS",
    "DetectorConfig",
    "FilterConfig",
    "GroupsConfig",
    "MarkersConfig",
    "OverlayConfig",
    "PoseConfig",
    "RecordingConfig",
    "TrackerConfig",
    "demo_config",
    "implausible_length_hint",
]

MAX_PLAUSIBLE_LENGTH_M = 1.0  # a marker side above this is most likely millimetres (34 for 0.034)


def implausible_length_hint(length_m: float, name: str, what: str = "a marker") -> str | None:
    """A warning for a marker side of ``length_m`` metres set by ``name`` (``--marker-length``, ``[markers]
    length_m =``) when it is over a metre: ``--marker-length 34: a marker 34 m wide? did you give
    millimetres? 34 mm is --marker-length 0.034 (or 34mm)``; None for a plausible one."""
    if not length_m > MAX_PLAUSIBLE_LENGTH_M:
        return None
    typed = f" (or {length_m:g}mm)" if name.startswith("--") else ""  # an option reads units, a TOML key does not
    return (
        f"{name} {length_m:g}: {what} {length_m:g} m wide? did you give millimetres? "
        f"{length_m:g} mm is {name} {length_m / 1000:g}{typed}"
    )


def _dictionary_problem(name: str, _limit: int) -> str | None:
    try:
        dictionary_id(name)
    except ConfigError as err:
        return str(err)
    return None


known_dictionary = Check("must be a cv2.aruco predefined dictionary", _dictionary_problem, shows_value=True)


def each_in(lo: float, hi: float) -> Check:
    """Every value of a vector finite and in [lo, hi] (bounds first: no float() of a huge integer)."""
    text = f"values must be finite and in [{lo:g}, {hi:g}]"
    return Check(text, lambda values, _limit: None if all(lo <= v <= hi and math.isfinite(v) for v in values) else text)


def vector_key(default: tuple[float, ...], doc: str, check: Check) -> Any:
    """A key of ``len(default)`` numbers (:func:`~ar_anchor.config.keys.key` with shape ``vector``), each
    of the default's type."""
    return key(default, doc, check, kind=type(default[0]), shape="vector", size=len(default))


@dataclass(frozen=True)
class DetectorConfig:
    """How markers are found in a frame (see :mod:`ar_anchor.track.detection`)."""

    dictionary: str = key("DICT_4X4_50", "any cv2.aruco predefined dictionary name", known_dictionary)
    corner_refinement: str = key(
        "edges",
        "edges (lines fitted to the marker's sides) | none | subpix | contour | apriltag",
        one_of(CORNER_REFINEMENTS),
    )
    refinement_window: float = key(
        0.3, "subpix only: window in marker cells (OpenCV's relativeCornerRefinmentWinSize)", in_range(0.05, 10.0)
    )
    min_perimeter_rate: float = key(
        0.03,
        "smallest marker perimeter, as a fraction of the image's larger side (lower: find farther markers)",
        in_range(0.001, 4.0),
    )
    cell_margin: float = key(
        0.25,
        "bits are read from the middle of each cell, ignoring this fraction of the cell on every side (OpenCV's "
        "perspectiveRemoveIgnoredMarginPerCell, default 0.13; see Detector for the measurements)",
        in_range(0.0, 0.45),
    )
    roi: bool = key(
        True,
        "ROI tracking: while targets are tracked, search only around where their markers were (plus their "
        "motion), at a reduced scale for big markers (see Detector.detect_regions)",
    )
    roi_full_every: int = key(
        15,
        "... and the whole frame every this many frames (and whenever a tracked marker is missed)",
        in_range(1, 10_000),
    )
    roi_margin: float = key(0.6, "region margin around a marker, in marker sides", in_range(0.1, 10.0))
    fast_search: bool = key(
        False,
        "ROI tracking's whole-frame searches with OpenCV's one-threshold Aruco3 search while every marker is at "
        "least 40 px (several times cheaper with many markers; it also outlines some smeared markers the "
        "default search rejects, which the flip filter is not tuned for: see docs/architecture.md)",
    )


@dataclass(frozen=True)
class MarkersConfig:
    """Lone markers: those not part of a board."""

    length_m: float = key(0.05, "side of the black square, metres", positive)
    lengths_m: Mapping[int, float] = key(
        None,
        "optional per-id sizes: marker id = side in metres (a board's markers take the board's)",
        positive,
        kind=float,
        shape="id_values",
        example={7: 0.04},
        factory=dict,
    )
    ids: tuple[int, ...] = key(
        (), "track only these lone markers (empty: every id of the dictionary)", shape="ids", example=[0, 7]
    )

    def length_of(self, marker_id: int) -> float:
        return self.lengths_m.get(int(marker_id), self.length_m)


def _readout_problem(value: float, _limit: int) -> str | None:
    """A readout time's problem: out of [0, 1] s, with a hint when it looks like milliseconds."""
    if 0.0 <= value <= 1.0:
        return None
    if 1.0 < value <= 1000.0:
        return f"must be in [0, 1] seconds: milliseconds? {value:g} ms is {value / 1000:g}"
    return "must be in [0, 1] seconds"


@dataclass(frozen=True)
class PoseConfig:
    """Pose estimation and validation (see :mod:`ar_anchor.track.pose`)."""

    max_reproj_px: float = key(3.0, "reject a solver result whose RMS corner error exceeds this, pixels", positive)
    board_inlier_px: float = key(
        3.0, "boards: a marker (or corner) farther than this from the joint pose is an outlier, pixels", positive
    )
    fit_margin_px: float = key(
        1.0,
        "an output pose (filtered, smoothed, a board's or group's) must reproject on its own frame's corners within "
        "this of the frame's best solution's RMS error, pixels; else that frame's own solution is output and its "
        "track restarts",
        positive,
    )
    recover_markers: bool = key(
        True, "boards: look again for missing markers where the board says they are (refineDetectedMarkers)"
    )
    rolling_shutter_s: float = key(
        0.0,
        "the camera's rolling-shutter readout, first row to last, seconds (0: a global shutter, or unknown); "
        "each marker's corners are then taken back to the frame's first-row time with its image velocity",
        Check("must be in [0, 1] seconds", _readout_problem),
    )


@dataclass(frozen=True)
class FilterConfig:
    """Planar-flip resolution and smoothing (see :mod:`ar_anchor.track.filtering`); times in seconds."""

    enabled: bool = key(True, "false (or --no-filter): the raw per-frame pipeline")
    corner_noise_px: float = key(0.02, "floor of the corner noise; the filter estimates it from residuals", positive)
    still_rotation_rad_sqrt_s: float = key(
        1e-4,
        'two motion models are mixed by how well each predicts (IMM): "still", a slow random walk of this rotation '
        "rate, averages a static marker over many frames",
        positive,
    )
    still_translation_m_sqrt_s: float = key(1e-5, '... and of this translation rate ("still" model)', positive)
    angular_accel_moving_rad_s2: float = key(
        30.0,
        '"moving" (constant velocity, white acceleration of this size) follows real motion without lag',
        positive,
    )
    linear_accel_moving_m_s2: float = key(5.0, '... and of this linear acceleration ("moving" model)', positive)
    evidence_window_s: float = key(2.0, "seconds of flip evidence kept", in_range(0.01, 3600.0))
    decide_margin_px: float = key(
        0.06, "reprojection-error differences below this never decide (detector bias)", non_negative
    )
    decide_z: float = key(3.0, "confidence (standard errors) needed to commit to a solution", non_negative)
    switch_margin_px: float = key(
        0.3, "leaving a committed solution on accumulated evidence needs a larger margin ...", non_negative
    )
    switch_z: float = key(5.0, "... and more confidence", non_negative)
    evidence_noise_px: float = key(0.1, "prior per-frame evidence spread (counts as a few frames' worth)", positive)
    evidence_cap_px: float = key(3.0, "one frame's evidence is clipped to this", positive)
    single_solution_evidence_px: float = key(2.0, "evidence when the other solution failed validation", non_negative)
    decisive_ratio: float = key(
        3.0,
        "one frame alone vouches for a solution when the other's error is this many times larger, ...",
        in_range(1.0, 1e6),
    )
    decisive_sigmas: float = key(2.0, "... this many corner-noise sigmas larger ...", non_negative)
    decisive_px: float = key(
        0.1, "... and at least this much larger (or the other solution failed validation)", non_negative
    )
    decisive_frames: int = key(
        2, "consecutive decisive frames against the output's solution that move it there", in_range(1, 1000)
    )
    interpolate_s: float = key(
        0.5,
        'offline replay: bridge gaps at most this long between measurements (state "interpolated")',
        in_range(0.0, 60.0),
    )
    interpolate_max_deg: float = key(
        3.0,
        "... and only where the motion is steady: end velocities within this of the one across it, over half the gap",
        in_range(0.0, 180.0),
    )
    predict_s: float = key(
        0.2, 'publish predictions through gaps at most this long (state "predicted") ...', in_range(0.0, 60.0)
    )
    predict_damping_s: float = key(
        0.1, "... with the velocity decaying with this time constant ...", in_range(0.001, 60.0)
    )
    predict_max_deg: float = key(
        0.25, "... and only while the motion since the last measurement may be below this", in_range(0.0, 180.0)
    )
    memory_s: float = key(
        2.0, "a lost target keeps its track (flip memory) this long, then is reset", in_range(0.0, 3600.0)
    )
    restart_gap_s: float = key(
        0.1, "after a gap longer than this the smoothers restart from the new measurement", in_range(0.0, 60.0)
    )
    still_s: float = key(
        0.3, "a target whose measurements stayed within their noise this long is still, and ...", in_range(0.0, 60.0)
    )
    output_sigmas: float = key(
        3.0, "... its output stays within this many standard deviations of the measurement;", in_range(0.0, 100.0)
    )
    output_sigmas_moving: float = key(
        0.5, "a moving target's within this many (smoothing never lags real motion)", in_range(0.0, 100.0)
    )
    reset_angle_deg: float = key(
        15.0, "a measurement this far from its solution's smoother restarts the smoother", in_range(0.1, 180.0)
    )
    max_angular_rate_deg_s: float = key(720.0, "bound on the smoothers' angular velocity", in_range(1.0, 1e5))
    spike_translation_m: float = key(
        0.01,
        "an output jumping more than flip_angle_deg with less motion than this is held back one frame (a "
        "measurement that jumped); two frames: it is real",
        in_range(0.0, 10.0),
    )
    glide_step_deg: float = key(
        9.0,
        "a change of branch (or into or out of halfway) is shown as a glide of at most this much per frame when "
        "it is at most three such steps, so the overlay never snaps; 0: shown at once",
        in_range(0.0, 180.0),
    )
    flip_angle_deg: float = key(
        10.0, "an orientation uncertain by more than this (3 sigma) is not vouched for as tracked", in_range(0.0, 180.0)
    )
    tilt_accel_rad_s2: float = key(
        3.0, "motion model of the tilt that tells the two solutions apart where they cross", positive
    )
    crossing_blind_s: float = key(
        0.3, "solutions indistinguishable for longer than this: a commitment ends", in_range(0.0, 3600.0)
    )
    repeat_grey: float = key(
        0.75,
        "a frame within this mean grey-level difference of the last one repeats it: no new evidence (30 fps "
        "files of 12 fps content; 0: bit-identical only)",
        in_range(0.0, 255.0),
    )


@dataclass(frozen=True)
class GroupsConfig:
    """Rigid groups learned while tracking (see :mod:`ar_anchor.track.groups`): lone markers whose relative
    pose holds over many frames (and, out of one plane, viewpoints) are solved jointly, like a board. Opt-in."""

    learn: bool = key(
        False,
        "learn rigid groups of lone markers seen together and solve each group jointly (--learn-groups); "
        "two objects that only stand still together look rigid too: a member that moves leaves",
    )
    min_frames: int = key(45, "frames a pair's relative pose must hold before the two join", in_range(5, 1_000_000))
    agreement: float = key(
        0.8, "... in at least this share of the frames that saw both since that pose first appeared", in_range(0.5, 1.0)
    )
    agree_px: float = key(
        1.0,
        "a frame supports a pair's relative pose when both markers' corners fit it jointly within this RMS, pixels",
        positive,
    )
    leave_frames: int = key(
        5, "a member its group's joint pose rejects this many measured frames in a row leaves", in_range(1, 100_000)
    )


@dataclass(frozen=True)
class RecordingConfig:
    """What the rerun recording keeps (see :mod:`ar_anchor.viz`)."""

    image_every: int = key(1, "log every N-th frame image to rerun (0: never)", in_range(0, 10_000))
    image_scale: float = key(1.0, "downscale logged images by this factor", in_range(0.05, 1.0))
    jpeg_quality: int = key(80, "JPEG quality of logged images", in_range(1, 100))
    part_minutes: float = key(
        0.5,
        "long runs: recording.rrd, recording.part2.rrd, ... each this long, in wall time or the frames' own "
        "(0: one file): rerun's file writer "
        "grows in memory until its file closes (about 1 MB/s at 1080p; rerun issue #12623). Open the parts "
        "together: rerun recording*.rrd",
        in_range(0.0, 1e6),
    )
    overlay_images: bool = key(
        False,
        "also draw the overlay into each logged image (camera/overlay; costs the output thread a render and a "
        "JPEG per frame): the viewer's AR overlay view projects the 3D overlay onto the frame itself, but "
        "without lens distortion",
    )
    metrics_every: int = key(
        10,
        "send the plotted metrics (metrics/*), and in a recording no viewer watches each frame's 3D scene and "
        "detections too, every N frames, each entity's N values in one call: every frame's value is kept; a "
        "live viewer shows the metrics up to N frames late (1: every frame)",
        in_range(1, 1000),
    )
    flush_timeout_s: float = key(
        10.0,
        "how long the recording's writes may wait on its sinks (a viewer that stopped reading, a stalled disk) "
        "before the run ends with an error naming them; checked every 2 s and at the end",
        in_range(0.5, 600.0),
    )


OVERLAY_KINDS = ("cube", "mesh", "axes")


def _target_problem(pattern: str, _limit: int) -> str | None:
    return target_pattern_problem(pattern)


@dataclass(frozen=True)
class OverlayConfig:
    """One virtual object drawn on a target (``[[overlays]]``; see :mod:`ar_anchor.render.overlay`).

    ``target``: ``marker:<id>``, ``board:<name>``, ``marker:*`` (every marker that is not part of a
    board), ``board:*`` or ``*``; a target named exactly takes only its own overlays. Placement is in
    the target's anchor frame: its centre, x right, y up, z out of the marker or board.
    """

    target: str = key(
        "marker:*",
        'what it is drawn on: "marker:<id>", "board:<name>", "marker:*" (every marker that is not part of a '
        'board), "board:*" or "*"',
        Check("must name a target or pattern", _target_problem),
    )
    kind: str = key("cube", " | ".join(OVERLAY_KINDS), one_of(OVERLAY_KINDS))
    size_m: float = key(
        0.0, "cube side / axis length / mesh's largest extent, metres (0: the target's size)", in_range(0.0, 100.0)
    )
    path: str = key(
        "",
        'mesh: a model file relative to this one (OBJ, PLY, STL, GLB/glTF, OFF) or "builtin:pin" '
        "(configs/models/pin.ply is the same model as a file)",
        printable,
    )
    scale: float = key(1.0, "mesh: file units -> metres, used when size_m is 0", in_range(1e-9, 1e6))
    offset_m: tuple[float, float, float] = vector_key(
        (0.0, 0.0, 0.0),
        "in the target's anchor frame: its centre, x right, y up, z out of the marker or board",
        each_in(-100.0, 100.0),
    )
    rotation_deg: tuple[float, float, float] = vector_key(
        (0.0, 0.0, 0.0), "x, y, z Euler angles in that frame (extrinsic, in this order)", each_in(-360.0, 360.0)
    )
    colour: tuple[int, int, int] = vector_key(
        (70, 140, 240), "RGB (a mesh's own colours are kept unless colour is given)", each_in(0.0, 255.0)
    )
    colour_set: bool = False  # colour was given explicitly (not a key: the reader sets it)
    opacity: float = key(
        1.0, "ambiguous targets are drawn at half this, predicted ones greyed at 0.3", in_range(0.0, 1.0)
    )

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


@dataclass(frozen=True)
class TrackerConfig:
    """A whole config file: its tables in the order they are read and written."""

    detector: DetectorConfig = key(None, "", shape="table", factory=DetectorConfig)
    markers: MarkersConfig = key(None, "", shape="table", factory=MarkersConfig)
    boards: tuple[BoardConfig, ...] = key(
        (),
        "Rigid boards; their markers take the board's marker length. Frames as OpenCV's Board.getObjPoints() "
        "(origin top-left, x right, y down, z into the board); a custom layout's are its own",
        kind=BoardConfig,
        shape="tables",
    )
    pose: PoseConfig = key(None, "", shape="table", factory=PoseConfig)
    filter: FilterConfig = key(None, "", shape="table", factory=FilterConfig)
    groups: GroupsConfig = key(None, "", shape="table", factory=GroupsConfig)
    recording: RecordingConfig = key(None, "", shape="table", factory=RecordingConfig)
    overlays: tuple[OverlayConfig, ...] = key(
        None,
        'What is drawn on each target (ar-anchor demo/replay/live: rerun\'s "AR overlay" view and --video-out); '
        "a target named exactly takes only its own overlays. Without [[overlays]]: the two below.",
        kind=OverlayConfig,
        shape="tables",
        factory=_default_overlays,
    )
    source: str = "<defaults>"  # where it was read from (not a key)

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
        self,
        *,
        dictionary: str | None = None,
        marker_length_m: float | None = None,
        filter_enabled: bool | None = None,
        learn_groups: bool | None = None,
    ) -> TrackerConfig:
        """Copy with values from elsewhere (the command line) applied and validated. A bad value is a
        :class:`~ar_anchor.config.keys.ConfigValueError` naming the key it would set (``[detector]
        dictionary``, ``[markers] length_m``); the caller knows where the value came from and may say so."""
        config = self
        if filter_enabled is not None:
            config = dataclasses.replace(config, filter=dataclasses.replace(config.filter, enabled=filter_enabled))
        if learn_groups is not None:
            config = dataclasses.replace(config, groups=dataclasses.replace(config.groups, learn=learn_groups))
        if dictionary is not None:
            config = config._with_dictionary(dictionary)
        if marker_length_m is not None:
            if not (math.isfinite(marker_length_m) and marker_length_m > 0):
                raise _override_error(
                    "markers",
                    "length_m",
                    marker_length_m,
                    f"must be a positive length in metres, got {marker_length_m}",
                )
            config = dataclasses.replace(
                config, markers=dataclasses.replace(config.markers, length_m=float(marker_length_m))
            )
        return config

    def _with_dictionary(self, dictionary: str) -> TrackerConfig:
        """Any spelling in (``tag36h11``, errors name it as typed), OpenCV's canonical name stored and written."""
        try:
            canonical = canonical_dictionary(dictionary)
            size = dictionary_size(canonical)
        except ConfigValueError as err:
            raise _override_error("detector", "dictionary", dictionary, err.problem) from None
        for board in self.boards:
            too_big = [i for i in board.marker_ids if i >= size]
            if too_big:
                problem = (
                    f"{dictionary} has {size} markers, but board '{board.name}' ({self.source}) uses ids {too_big[:5]}"
                )
                raise _override_error("detector", "dictionary", dictionary, problem)
        return dataclasses.replace(
            self,
            detector=dataclasses.replace(self.detector, dictionary=canonical),
            boards=tuple(dataclasses.replace(b, dictionary=canonical) for b in self.boards),
        )


def _override_error(table: str, name: str, value: object, problem: str) -> ConfigValueError:
    return ConfigValueError(f"[{table}] {name}: {problem}", problem=problem, key=name, table=f"[{table}]", value=value)


DEMO_BOARD = BoardConfig(name="desk", cols=2, rows=2, marker_length_m=0.04, separation_m=0.02, first_id=10)
DEMO_LENGTHS_M = {7: 0.04}


def demo_config() -> TrackerConfig:
    """The demo scene's config (``configs/demo.toml``): the built-in defaults plus the demo's ``desk``
    board (ids 10-13, 0.04 m) and marker 7 at 0.04 m. Only ``ar-anchor demo`` and ``live --device
    synthetic`` use it without being asked: a real video tracks exactly what its config and options say."""
    return TrackerConfig(
        markers=MarkersConfig(lengths_m=dict(DEMO_LENGTHS_M)), boards=(DEMO_BOARD,), source="<demo defaults>"
    )
