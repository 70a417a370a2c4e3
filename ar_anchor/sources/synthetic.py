"""Synthetic frames with exact ground truth: ArUco markers and grid boards on a cluttered wall.

Rendering model
---------------
Every planar thing (the wall, a board's paper, each marker with its white quiet zone) is a
textured quad. A quad is drawn through the homography ``image_from_texture = K [r1 r2 t]
plane_from_texture`` (``warpPerspective``, bilinear), so straight edges land exactly where the
pinhole model puts them. Texel centres and pixel centres both sit at integer coordinates
(OpenCV's convention): texel ``(0, 0)`` covers ``[-0.5, 0.5]^2`` in texture coordinates, and a
supersampled pixel ``i`` of factor ``s`` has its centre at ``(i + 0.5) / s - 0.5`` in output
pixels, so area-averaging ``s x s`` blocks (``INTER_AREA``) gives the exact pixel coverage.
Targets are rendered supersampled inside their bounding box with a coverage mask and composited
far-to-near over the wall (premultiplied alpha); the wall itself is rendered at output
resolution (its texture is clutter, not geometry). Marker edges are interior to their texture
(the quiet zone surrounds them), so an edge's 50 % crossing is unbiased.

Frames of the world: the wall is the plane ``z = 0``, x right, y up, z toward the viewer. A
lone marker's frame is its centre, x right, y up, z toward the viewer (IPPE_SQUARE's); a grid
board's frame is OpenCV's ``GridBoard.getObjPoints()`` frame (top-left of the first marker,
x right, y down, z into the board).

Lens distortion: a camera with distortion coefficients is rendered as its ideal pinhole camera on
a canvas large enough to hold the undistorted view, then resampled (bilinear) at each output
pixel's undistorted position (``undistortPoints`` iterated to convergence), so straight edges come
out curved exactly as ``projectPoints`` with the same coefficients predicts.

Hand-held webcam realism
------------------------
The temporal layer of the tracker has to be scored on clips that look like a hand-held webcam,
not only on calm renders. Every effect below is optional, deterministic for the scene's seed, and
off by default (a default scene renders bit-identical frames to the calm renderer):

- **Hand-held motion** (``Trajectory(kind="handheld")``): a function of time in seconds (so a
  different ``fps`` samples the same motion), built from seeded sums of sinusoids and smooth
  bursts: sway of the viewpoint at 0.1-0.5 Hz around the targets (azimuth, elevation, roll, and a
  wandering aim point), approach and retreat between ``near_m`` and ``far_m`` (0.05-0.2 Hz),
  tremor at 5-10 Hz (a small rotation about the camera's own centre) and quick turns: raised-cosine
  bursts of rotation about the camera centre (out and back, ``turn_every_s`` apart on average) whose
  angular speed peaks at exactly ``turn_peak_deg_s``.
- **Motion blur and rolling shutter** (``exposure_s``, ``rolling_shutter_s``): the frame is an
  average of sub-frame renders along the trajectory. Row ``r`` integrates the scene over
  ``[t_r - e/2, t_r + e/2]`` with ``t_r = t + r / height * readout`` (a box shutter, so truth at
  ``t`` is the blur's centroid on the first row; lower rows see the scene ``readout`` later, as a
  real rolling shutter does). The sub-frames are ``N`` renders at evenly spaced times over the
  whole span; each row weights them by the integral of their linear-interpolation basis over the
  row's window (trapezoidal integration in time, with row-dependent weights for the rolling
  shutter). ``N`` follows the motion: about one sub-frame per 2 px of image motion of the targets
  within the span, at most ``max_subframes``. Sub-frames are rendered with half the supersampling
  (averaging them already low-passes the image along the motion).
- **Lighting** (:class:`Lighting`): a slow gain and offset drift and brightness steps (an
  auto-exposure jump), applied to the linear image before noise.
- **Occlusion** (:class:`Occluder`): a skin-coloured hand (palm and fingers, soft edged) crossing
  the image along a straight line over a frame range; truth is kept for occluded targets (they are
  still there: a tracker that predicts them is scored against it).
- **Duplicated frames** (``content_fps`` < ``fps``): the container runs at ``fps`` and repeats the
  last rendered frame (identical pixels and truth, new timestamps), as webcams do in low light.
- **Compression** (``compression = "jpeg" | "h264"``): a MJPEG webcam's per-frame JPEG
  (``jpeg_quality``) or an H.264 round trip through PyAV/libx264 at ``h264_kbps`` (zero-latency
  tuning, no B-frames: one frame in, one frame out, so order and count are exact). H.264 is
  sequential: iterating the source encodes frame by frame with a persistent encoder/decoder; a
  random access ``frame(i)`` out of order restarts the codec from frame 0.
- **Sheets** (:func:`marker_sheet`, :class:`PlacedSheet`): K lone markers printed on one rigid
  sheet of paper (each a :class:`PlacedMarker` with its own truth), so a tracker's per-marker outputs
  can be checked for rigid consistency. A sheet flat on the wall is painted into the wall texture
  (free to render); any other is a paper quad drawn under the targets.
- Webcam cameras: :func:`webcam_camera` (640x480, 720p, ..., optional radial distortion).
- Image border: a target is in a frame's truth only while all its corners are in the image (as
  before); the hand-held path (aim point, sway) can push markers partly out, and they come back.

Order of the effects on a frame: sub-frame renders (blur, rolling shutter) -> hand -> lighting ->
optical blur (``blur_sigma``) -> sensor noise -> rounding -> JPEG / H.264. Frames that use any of
the pixel-changing options draw their sensor noise from OpenCV's generator seeded per content
frame (3x faster than numpy's Gaussian); the calm path keeps numpy's, so its frames are unchanged.
The cost: a 150-frame 640x480 hand-held clip with blur, rolling shutter and H.264 renders in about
5 s on one core (about 3 sub-frames per frame on average, up to ``max_subframes`` in quick turns).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from types import TracebackType

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig, dictionary_id
from ..errors import SourceError
from ..geometry import Pose, look_at, marker_corners_in_marker
from .base import Frame

__all__ = [
    "COMPRESSIONS",
    "Lighting",
    "Occluder",
    "PlacedBoard",
    "PlacedMarker",
    "PlacedSheet",
    "SyntheticScene",
    "SyntheticSource",
    "Trajectory",
    "board_marker_poses",
    "demo_scene",
    "marker_sheet",
    "webcam_camera",
]

log = logging.getLogger(__name__)

# Print contrast: black ink is not 0, paper is not 255.
_INK = 20.0
_PAPER = 240.0
_CELL_TEXELS = 24  # texels per marker bit cell
_SKY_BGR = (180, 160, 140)
# board_from_marker rotation: marker frame (y up, z out) inside the board frame (y down, z in).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])
COMPRESSIONS = ("", "jpeg", "h264")
_SUBFRAME_PX = 2.0  # motion blur: about one sub-frame per this much image motion of the targets
_SKIN_BGR = (120.0, 150.0, 205.0)


def board_marker_poses(board: BoardConfig) -> dict[int, Pose]:
    """``board_from_marker`` for each marker of a grid board (marker frame: centre, y up, z out)."""
    poses = {}
    h = board.marker_length_m / 2.0
    step = board.marker_length_m + board.separation_m
    for index, marker_id in enumerate(board.marker_ids):
        row, col = divmod(index, board.cols)
        centre = np.array([col * step + h, row * step + h, 0.0])
        poses[marker_id] = Pose.from_matrix(_FLIP_YZ, centre)
    return poses


# ---------------------------------------------------------------------------- scene description


@dataclass(frozen=True)
class PlacedMarker:
    """A lone marker: ``world_from_target`` is its centre frame (x right, y up, z out)."""

    marker_id: int
    length_m: float
    world_from_target: Pose

    @property
    def target(self) -> str:
        return f"marker:{self.marker_id}"


@dataclass(frozen=True)
class PlacedBoard:
    """A grid board: ``world_from_target`` is OpenCV's board frame (y down, z into the board)."""

    board: BoardConfig
    world_from_target: Pose

    @property
    def target(self) -> str:
        return self.board.target


@dataclass(frozen=True)
class Trajectory:
    """Camera path over the clip.

    The calm kinds are functions of normalised time ``u`` in [0, 1] (:meth:`camera_from_world`);
    ``handheld`` is a function of time in seconds (:meth:`at_time`), so the motion does not change
    with the frame rate or the clip length.

    kind:
        ``sweep``: distance grows from ``near_m`` to ``far_m`` while the camera swings in azimuth
        and elevation (the demo's path: near, well-conditioned views to far, ambiguous ones).
        ``orbit``: constant distance ``near_m``, azimuth swings ``±azimuth_deg``.
        ``static``: a fixed camera at ``near_m``, ``azimuth_deg``, ``elevation_deg``.
        ``handheld``: a hand-held webcam looking roughly at ``look_at``: the viewpoint sways
        (0.1-0.5 Hz, up to ``azimuth_deg`` / ``elevation_deg`` / ``roll_deg``, aim point wandering
        by ``aim_m``), the distance goes back and forth between ``near_m`` and ``far_m``, tremor
        (5-10 Hz, ``tremor_deg``) shakes it, and quick turns (out and back by up to ``turn_deg``,
        peak angular speed ``turn_peak_deg_s``, one every ``turn_every_s`` on average; 0 disables)
        jerk it away from the targets and back. The phases, frequencies and turn times come from
        ``seed``.
    """

    kind: str = "sweep"
    near_m: float = 0.35
    far_m: float = 3.0
    azimuth_deg: float = 35.0
    elevation_deg: float = 20.0
    roll_deg: float = 10.0
    cycles: float = 1.5
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # handheld only
    tremor_deg: float = 0.15
    turn_peak_deg_s: float = 200.0
    turn_deg: float = 15.0
    turn_every_s: float = 2.5
    aim_m: float = 0.02
    seed: int = 0
    duration_s: float = 10.0  # handheld: the time u = 1 maps to in camera_from_world(u)

    def __post_init__(self) -> None:
        if self.kind not in ("sweep", "orbit", "static", "handheld"):
            raise ValueError(f"trajectory kind must be sweep, orbit, static or handheld, got {self.kind!r}")
        if not (0 < self.near_m and (self.kind not in ("sweep", "handheld") or self.near_m <= self.far_m)):
            raise ValueError(f"trajectory distances must satisfy 0 < near <= far, got {self.near_m}, {self.far_m}")
        if self.kind == "handheld":
            if self.turn_peak_deg_s < 0 or self.turn_deg < 0 or self.tremor_deg < 0 or self.aim_m < 0:
                raise ValueError("handheld: tremor_deg, turn_deg, turn_peak_deg_s and aim_m must be >= 0")
            if self.turn_peak_deg_s > 0 and self.turn_deg > 0 and not self.turn_every_s > 0:
                raise ValueError("handheld: turn_every_s must be > 0")

    def camera_from_world(self, u: float) -> Pose:
        if self.kind == "handheld":
            return self.at_time(u * self.duration_s)
        az, el, roll, dist = self._angles(u)
        centre = np.asarray(self.look_at, dtype=np.float64)
        direction = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        pose = look_at(centre + dist * direction, centre, up=(0.0, 1.0, 0.0))
        if roll:
            roll_pose = Pose(np.array([0.0, 0.0, roll]), np.zeros(3))
            pose = roll_pose.compose(pose)
        return pose

    def at_time(self, t_s: float, clip_s: float | None = None) -> Pose:
        """``camera_from_world`` at ``t_s`` seconds; the calm kinds need the clip length ``clip_s``
        (``u = t_s / clip_s``)."""
        if self.kind != "handheld":
            if clip_s is None or not clip_s > 0:
                raise ValueError(f"{self.kind} trajectories need clip_s > 0 to be evaluated at a time")
            return self.camera_from_world(t_s / clip_s)
        return self._handheld(float(t_s))

    def _angles(self, u: float) -> tuple[float, float, float, float]:
        az0, el0, roll0 = (math.radians(v) for v in (self.azimuth_deg, self.elevation_deg, self.roll_deg))
        if self.kind == "static":
            return az0, el0, roll0, self.near_m
        phase = 2.0 * math.pi * self.cycles * u
        az = az0 * math.sin(phase)
        el = el0 * math.sin(0.73 * phase + 0.9)
        roll = roll0 * math.sin(0.41 * phase + 0.3)
        if self.kind == "orbit":
            return az, el, roll, self.near_m
        dist = self.near_m + (self.far_m - self.near_m) * (0.5 - 0.5 * math.cos(math.pi * u))
        return az, el, roll, dist

    # ------------------------------------------------------------------ handheld

    @functools.cached_property
    def _handheld_terms(self) -> dict[str, np.ndarray]:
        """Seeded frequencies (Hz), phases and weights of every sum of sinusoids."""
        rng = np.random.default_rng([self.seed, 0x4A4D])

        def band(n: int, low: float, high: float) -> np.ndarray:
            weights = rng.uniform(0.5, 1.0, n)
            # columns: frequency, phase, weight (weights sum to 1: the sum stays within its amplitude)
            return np.column_stack([rng.uniform(low, high, n), rng.uniform(0, 2 * np.pi, n), weights / weights.sum()])

        terms = {name: band(3, 0.1, 0.5) for name in ("az", "el", "roll", "aim_x", "aim_y")}
        terms["dist"] = band(2, 0.05, 0.2)
        for axis in "xyz":
            terms[f"tremor_{axis}"] = band(3, 5.0, 10.0)
        return terms

    @staticmethod
    def _sines(terms: np.ndarray, t_s: float) -> float:
        return float(np.sum(terms[:, 2] * np.sin(2 * np.pi * terms[:, 0] * t_s + terms[:, 1])))

    def _turn(self, t_s: float) -> np.ndarray:
        """Rotation vector (camera frame) of the quick turns at ``t_s``: raised-cosine bursts out and
        back, ``A (1 - cos(2 pi s)) / 2`` over ``D = pi A / peak`` seconds, so the angular speed peaks at
        exactly ``turn_peak_deg_s`` in every burst. Burst ``k`` starts near ``(k + 0.5) * turn_every_s``
        (seeded jitter), with a seeded size (50-100 % of ``turn_deg``) and direction."""
        if not (self.turn_peak_deg_s > 0 and self.turn_deg > 0):
            return np.zeros(3)
        period = self.turn_every_s
        rotation = np.zeros(3)
        k0 = math.floor(t_s / period)
        for k in (k0 - 1, k0, k0 + 1):
            if k < 0:
                continue
            rng = np.random.default_rng([self.seed, 0x7E4, k])
            size_deg = self.turn_deg * rng.uniform(0.5, 1.0)
            duration = math.pi * size_deg / self.turn_peak_deg_s
            start = (k + 0.5 + rng.uniform(-0.25, 0.25)) * period
            start = min(start, (k + 1) * period - duration)  # a burst stays inside its slot: no overlaps
            direction = rng.uniform(0, 2 * np.pi)
            axis = np.array([math.sin(direction), math.cos(direction), 0.2 * rng.uniform(-1, 1)])
            axis /= np.linalg.norm(axis)
            s = (t_s - start) / duration
            if 0.0 <= s <= 1.0:
                rotation += axis * math.radians(size_deg) * 0.5 * (1.0 - math.cos(2 * math.pi * s))
        return rotation

    def _handheld(self, t_s: float) -> Pose:
        terms = self._handheld_terms
        az = math.radians(self.azimuth_deg) * self._sines(terms["az"], t_s)
        el = math.radians(self.elevation_deg) * self._sines(terms["el"], t_s)
        roll = math.radians(self.roll_deg) * self._sines(terms["roll"], t_s)
        mix = 0.5 + 0.5 * self._sines(terms["dist"], t_s)
        dist = self.near_m + (self.far_m - self.near_m) * mix
        aim = np.asarray(self.look_at, dtype=np.float64) + self.aim_m * np.array(
            [self._sines(terms["aim_x"], t_s), self._sines(terms["aim_y"], t_s), 0.0]
        )
        direction = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        pose = look_at(aim + dist * direction, aim, up=(0.0, 1.0, 0.0))
        tremor = math.radians(self.tremor_deg) * np.array([self._sines(terms[f"tremor_{axis}"], t_s) for axis in "xyz"])
        about_centre = np.array([0.0, 0.0, roll]) + tremor + self._turn(t_s)
        # rotations about the camera's own centre: applied in the camera frame, translation-free
        return Pose(about_centre, np.zeros(3)).compose(pose)


@dataclass(frozen=True)
class PlacedSheet:
    """A plain sheet of paper (``width_m`` x ``height_m``, centred on ``world_from_sheet``'s origin, in
    its x-y plane) drawn over the wall and under every target: the paper that :func:`marker_sheet`'s
    markers are printed on."""

    world_from_sheet: Pose
    width_m: float
    height_m: float


@dataclass(frozen=True)
class Lighting:
    """Global lighting changes over time ``t`` (seconds), applied to the linear image as
    ``image * gain(t) + offset(t)`` before sensor noise.

    ``gain(t) = (1 + gain_drift * sin(2 pi t / period_s + a)) * product of the steps' gains reached``
    and ``offset(t) = offset_drift * sin(2 pi t / (1.37 period_s) + b)`` (grey levels); ``a`` and
    ``b`` come from the scene's seed. ``steps``: ``(t_s, gain)`` pairs, each a brightness step (an
    auto-exposure jump) that ramps linearly over ``step_ramp_s`` (0: a hard step between frames).
    """

    gain_drift: float = 0.15
    offset_drift: float = 8.0
    period_s: float = 7.0
    steps: tuple[tuple[float, float], ...] = ((2.0, 0.7),)
    step_ramp_s: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.gain_drift < 1 and self.period_s > 0 and self.step_ramp_s >= 0):
            raise ValueError("lighting: need 0 <= gain_drift < 1, period_s > 0, step_ramp_s >= 0")
        if any(not gain > 0 for _, gain in self.steps):
            raise ValueError("lighting: step gains must be > 0")

    def gain_offset(self, t_s: float, seed: int) -> tuple[float, float]:
        a, b = np.random.default_rng([seed, 0x119]).uniform(0, 2 * np.pi, 2)
        gain = 1.0 + self.gain_drift * math.sin(2 * math.pi * t_s / self.period_s + a)
        for at_s, step_gain in self.steps:
            if self.step_ramp_s > 0:
                reached = min(max((t_s - at_s) / self.step_ramp_s, 0.0), 1.0)
            else:
                reached = 1.0 if t_s >= at_s else 0.0
            gain *= 1.0 + (step_gain - 1.0) * reached
        offset = self.offset_drift * math.sin(2 * math.pi * t_s / (1.37 * self.period_s) + b)
        return gain, offset


@dataclass(frozen=True)
class Occluder:
    """A hand passing in front of the camera over the container frames ``[start, stop)``.

    Its palm centre moves in a straight line from ``from_xy`` to ``to_xy`` (image coordinates as
    fractions of width and height; outside [0, 1] is off-image); ``size`` is the palm's height as a
    fraction of the image height, the fingers point along ``angle_deg`` (0: up). Skin coloured, softly
    shaded, edges blurred by ``edge_px``. The occluded targets keep their truth.
    """

    start: int
    stop: int
    from_xy: tuple[float, float] = (-0.25, 0.55)
    to_xy: tuple[float, float] = (1.25, 0.45)
    size: float = 0.35
    angle_deg: float = 20.0
    colour_bgr: tuple[float, float, float] = _SKIN_BGR
    edge_px: float = 1.5

    def __post_init__(self) -> None:
        if not (0 <= self.start < self.stop and self.size > 0 and self.edge_px >= 0):
            raise ValueError("occluder: need 0 <= start < stop, size > 0, edge_px >= 0")

    def mask(self, frame_pos: float, width: int, height: int) -> np.ndarray | None:
        """Coverage (H, W) float32 in [0, 1] at container frame position ``frame_pos`` (None: not there)."""
        if not self.start <= frame_pos < self.stop:
            return None
        u = (frame_pos - self.start) / max(self.stop - 1 - self.start, 1)
        cx = (self.from_xy[0] + (self.to_xy[0] - self.from_xy[0]) * u) * width
        cy = (self.from_xy[1] + (self.to_xy[1] - self.from_xy[1]) * u) * height
        palm = self.size * height
        up = np.array([math.sin(math.radians(self.angle_deg)), -math.cos(math.radians(self.angle_deg))])
        side = np.array([-up[1], up[0]])
        shift = 4  # fixed-point drawing: 1/16 px
        scale = 1 << shift
        mask = np.zeros((height, width), np.uint8)

        def pt(p: np.ndarray) -> tuple[int, int]:
            return int(round(p[0] * scale)), int(round(p[1] * scale))

        centre = np.array([cx, cy])
        cv2.ellipse(
            mask, pt(centre), (int(0.42 * palm * scale), int(0.5 * palm * scale)),
            self.angle_deg, 0, 360, 255, -1, cv2.LINE_AA, shift,
        )  # fmt: skip
        finger_w = 0.16 * palm
        for k, length in enumerate((0.75, 0.85, 0.8, 0.65)):
            base = centre + up * 0.35 * palm + side * (k - 1.5) * 0.2 * palm
            tip = base + up * length * palm
            cv2.line(mask, pt(base), pt(tip), 255, max(int(finger_w), 1), cv2.LINE_AA, shift)
        thumb_base = centre - side * 0.35 * palm
        cv2.line(mask, pt(thumb_base), pt(thumb_base - side * 0.4 * palm + up * 0.3 * palm), 255,
                 max(int(0.18 * palm), 1), cv2.LINE_AA, shift)  # fmt: skip
        coverage = mask.astype(np.float32) / 255.0
        if self.edge_px > 0:
            coverage = cv2.GaussianBlur(coverage, (0, 0), self.edge_px)
        return coverage

    def shade(self, width: int, height: int) -> np.ndarray:
        """The hand's colour (H, W, 3) float32: skin, lit from above (a soft vertical gradient)."""
        ramp = np.linspace(1.08, 0.85, height, dtype=np.float32)[:, None, None]
        return np.broadcast_to(np.asarray(self.colour_bgr, np.float32) * ramp, (height, width, 3))


@dataclass(frozen=True)
class SyntheticScene:
    """Everything that defines a synthetic clip; the same scene and seed give the same frames.

    The hand-held options (see the module notes) all default to off: ``exposure_s`` (motion blur),
    ``rolling_shutter_s`` (readout time, top row to bottom row), ``max_subframes``, ``lighting``,
    ``occluders``, ``content_fps`` (< ``fps``: duplicated frames), ``compression`` (``""``, ``"jpeg"``,
    ``"h264"``) with ``jpeg_quality`` / ``h264_kbps`` / ``h264_gop``, and ``sheets`` (paper under markers).
    """

    camera: CameraModel
    dictionary: str = "DICT_4X4_50"
    markers: tuple[PlacedMarker, ...] = ()
    boards: tuple[PlacedBoard, ...] = ()
    trajectory: Trajectory = field(default_factory=Trajectory)
    frames: int = 300
    fps: float = 30.0
    seed: int = 0
    noise_sigma: float = 0.0  # Gaussian sensor noise, grey levels
    blur_sigma: float = 0.0  # Gaussian optical blur, pixels
    supersample: int = 4
    clutter: bool = True
    hidden: tuple[tuple[int, int], ...] = ()  # frame ranges [start, stop) in which no target is visible (dropouts)
    # hand-held webcam realism (all off by default)
    exposure_s: float = 0.0  # motion blur: shutter open time
    rolling_shutter_s: float = 0.0  # readout time from the first row to the last
    max_subframes: int = 8  # cap on renders averaged per frame
    lighting: Lighting | None = None
    occluders: tuple[Occluder, ...] = ()
    content_fps: float | None = None  # < fps: the container repeats the last rendered frame
    compression: str = ""  # "" | "jpeg" | "h264"
    jpeg_quality: int = 70  # MJPEG webcams: about 50-80
    h264_kbps: float = 1000.0
    h264_gop: int = 60
    sheets: tuple[PlacedSheet, ...] = ()

    def is_hidden(self, index: int) -> bool:
        return any(start <= index < stop for start, stop in self.hidden)

    def __post_init__(self) -> None:
        if self.frames < 0:
            raise ValueError(f"frames must be >= 0, got {self.frames}")
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not 1 <= self.supersample <= 16:
            raise ValueError(f"supersample must be in 1..16, got {self.supersample}")
        if self.noise_sigma < 0 or self.blur_sigma < 0:
            raise ValueError("noise_sigma and blur_sigma must be >= 0")
        if self.exposure_s < 0 or self.rolling_shutter_s < 0 or not 1 <= self.max_subframes <= 64:
            raise ValueError("exposure_s and rolling_shutter_s must be >= 0, max_subframes in 1..64")
        if self.content_fps is not None and not 0 < self.content_fps <= self.fps:
            raise ValueError(f"content_fps must be in (0, fps], got {self.content_fps}")
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {COMPRESSIONS}, got {self.compression!r}")
        if not 1 <= self.jpeg_quality <= 100 or not self.h264_kbps > 0 or self.h264_gop < 1:
            raise ValueError("jpeg_quality must be in 1..100, h264_kbps > 0, h264_gop >= 1")
        dictionary_id(self.dictionary)

    def content_index(self, index: int) -> int:
        """The rendered frame container frame ``index`` shows (``index`` itself unless ``content_fps``)."""
        if self.content_fps is None:
            return index
        return int(math.floor(index * self.content_fps / self.fps + 1e-9))

    def content_time(self, index: int) -> float:
        """Seconds at which container frame ``index``'s image was taken."""
        if self.content_fps is None:
            return index / self.fps
        return self.content_index(index) / self.content_fps


def marker_sheet(
    ids: Sequence[int] = (0, 1, 2, 3, 4, 5),
    *,
    length_m: float = 0.05,
    cols: int = 3,
    gap_m: float = 0.025,
    world_from_sheet: Pose | None = None,
    margin_m: float | None = None,
) -> tuple[tuple[PlacedMarker, ...], PlacedSheet]:
    """K lone markers printed on one rigid sheet: ``cols`` per row, row-major from the top left,
    ``gap_m`` between neighbouring markers' black squares.

    The sheet's frame is its centre, x right, y up, z out of the paper (a lone marker's convention):
    every marker has the sheet's orientation, so on a rigid sheet all the markers' true rotations are
    equal and their centres keep their layout. Returns the markers (each a :class:`PlacedMarker`
    with its own truth) and the paper (:class:`PlacedSheet`, ``margin_m`` around the markers,
    default half a marker) to put in the scene's ``sheets``.
    """
    ids = tuple(int(i) for i in ids)
    if not ids or cols < 1 or not length_m > 0 or gap_m < 0:
        raise ValueError("marker_sheet: need ids, cols >= 1, length_m > 0, gap_m >= 0")
    world_from_sheet = world_from_sheet or Pose.identity()
    rows = math.ceil(len(ids) / cols)
    step = length_m + gap_m
    width, height = cols * step - gap_m, rows * step - gap_m
    markers = []
    for k, marker_id in enumerate(ids):
        row, col = divmod(k, cols)
        centre = np.array([-width / 2 + length_m / 2 + col * step, height / 2 - length_m / 2 - row * step, 0.0])
        sheet_from_marker = Pose(np.zeros(3), centre)
        markers.append(PlacedMarker(marker_id, length_m, world_from_sheet.compose(sheet_from_marker)))
    margin = length_m / 2 if margin_m is None else margin_m
    return tuple(markers), PlacedSheet(world_from_sheet, width + 2 * margin, height + 2 * margin)


def webcam_camera(
    width: int = 640, height: int = 480, hfov_deg: float = 62.0, k1: float = 0.0, k2: float = 0.0
) -> CameraModel:
    """A webcam-like camera: principal point at the centre, square pixels, horizontal field of view
    ``hfov_deg``, optional radial distortion ``k1``, ``k2`` (OpenCV's model; cheap webcams are near
    k1 = -0.1 ... 0.1)."""
    fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    camera = CameraModel.from_fov(width, height, fx)
    if k1 or k2:
        camera = CameraModel(camera.camera_matrix, np.array([k1, k2, 0.0, 0.0, 0.0]), width, height)
    return camera


def demo_scene(
    config: TrackerConfig,
    camera: CameraModel,
    *,
    frames: int = 300,
    seed: int = 0,
    trajectory: Trajectory | None = None,
    noise_sigma: float = 2.0,
    blur_sigma: float = 0.6,
    fps: float = 30.0,
) -> SyntheticScene:
    """The demo's scene: lone markers 0 and 7 left of centre, the config's boards right of it."""
    markers = []
    lone_ids = [i for i in (0, 7) if config.board_of(i) is None and config.tracks_marker(i)]
    if config.markers.ids and not lone_ids:
        lone_ids = [config.markers.ids[0]]
    for k, marker_id in enumerate(lone_ids):
        centre = np.array([-0.09, 0.045 - 0.1 * k, 0.0])
        markers.append(
            PlacedMarker(marker_id, config.marker_length(marker_id), Pose(np.array([0, 0, 0.15 * k]), centre))
        )
    boards = []
    y = 0.0
    for board in config.boards:
        height = board.size_m[1]
        # board frame: origin top-left, y down, z into the wall -> rotate 180 degrees about x.
        top_left = np.array([0.04, y + height / 2.0, 0.0])
        boards.append(PlacedBoard(board, Pose.from_matrix(_FLIP_YZ, top_left)))
        y -= height + 0.03
    return SyntheticScene(
        camera=camera,
        dictionary=config.detector.dictionary,
        markers=tuple(markers),
        boards=tuple(boards),
        trajectory=trajectory or Trajectory(look_at=(-0.01, 0.0, 0.0)),
        frames=frames,
        fps=fps,
        seed=seed,
        noise_sigma=noise_sigma,
        blur_sigma=blur_sigma,
    )


# ---------------------------------------------------------------------------- rendering


@dataclass(frozen=True)
class _Quad:
    world_from_plane: Pose
    texture: np.ndarray  # (h, w, 2) uint8: grey, coverage (255 inside)
    plane_from_texture: np.ndarray  # 3x3: texture pixel (x, y, 1) -> plane (X, Y, 1)

    @property
    def outline_in_plane(self) -> np.ndarray:
        """Texture outline (texel edges) in the plane frame, (4, 3)."""
        h, w = self.texture.shape[:2]
        corners = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
        plane = corners @ self.plane_from_texture.T
        plane = plane[:, :2] / plane[:, 2:]
        return np.column_stack([plane, np.zeros(4)])


def _with_coverage(grey: np.ndarray) -> np.ndarray:
    return np.dstack([grey, np.full_like(grey, 255)])


def _marker_texture(dictionary: cv2.aruco.Dictionary, marker_id: int, pad_texels: int) -> tuple[np.ndarray, int]:
    """Marker image (black border included) with a white quiet zone; returns (texture, marker side in texels)."""
    side = (dictionary.markerSize + 2) * _CELL_TEXELS
    image = cv2.aruco.generateImageMarker(dictionary, marker_id, side, borderBits=1)
    image = cv2.copyMakeBorder(image, pad_texels, pad_texels, pad_texels, pad_texels, cv2.BORDER_CONSTANT, value=255)
    grey = (_INK + image.astype(np.float32) * ((_PAPER - _INK) / 255.0)).round().astype(np.uint8)
    return _with_coverage(grey), side


def _marker_quad(
    dictionary: cv2.aruco.Dictionary, marker_id: int, length_m: float, world_from_marker: Pose, quiet_zone_m: float
) -> _Quad:
    """A marker in its own frame (centre, x right, y up) as a textured quad."""
    cell_m = length_m / (dictionary.markerSize + 2)
    texel = cell_m / _CELL_TEXELS
    pad = max(1, int(round(quiet_zone_m / texel)))
    texture, _ = _marker_texture(dictionary, marker_id, pad)
    h = length_m / 2.0
    # x_tex = (X + h) / texel + pad - 0.5 ; y_tex = (h - Y) / texel + pad - 0.5  (inverted below)
    plane_from_texture = np.array(
        [[texel, 0.0, (0.5 - pad) * texel - h], [0.0, -texel, h - (0.5 - pad) * texel], [0.0, 0.0, 1.0]]
    )
    return _Quad(world_from_marker, texture, plane_from_texture)


def _paper_quad(world_from_plane: Pose, x0: float, y0: float, x1: float, y1: float) -> _Quad:
    """A uniform sheet of paper covering [x0, x1] x [y0, y1] of its plane."""
    n = 1024  # fine texels keep the sheet's outline sharp (coverage falls off over one texel)
    texture = _with_coverage(np.full((n, n), _PAPER, np.uint8))
    sx, sy = (x1 - x0) / n, (y1 - y0) / n
    plane_from_texture = np.array([[sx, 0.0, x0 + 0.5 * sx], [0.0, sy, y0 + 0.5 * sy], [0.0, 0.0, 1.0]])
    return _Quad(world_from_plane, texture, plane_from_texture)


def _clutter_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """A colourful, cluttered wall texture (BGR): shapes, lines, text and marker-like squares that do not decode."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    base = np.stack(
        [150 + 40 * np.sin(6.3 * xx + 1.0), 140 + 30 * np.cos(4.1 * yy), 120 + 35 * np.sin(3.0 * (xx + yy))], -1
    )
    image = np.clip(base + rng.normal(0, 6, base.shape), 0, 255).astype(np.uint8)
    for _ in range(60):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(10, 70))
        shape = rng.integers(0, 4)
        if shape == 0:
            cv2.rectangle(image, (x, y), (x + r, y + int(rng.integers(10, 70))), colour, -1, cv2.LINE_AA)
        elif shape == 1:
            cv2.circle(image, (x, y), r // 2, colour, -1, cv2.LINE_AA)
        elif shape == 2:
            x2, y2 = (int(v) for v in rng.integers(0, size, 2))
            cv2.line(image, (x, y), (x2, y2), colour, int(rng.integers(1, 6)), cv2.LINE_AA)
        else:
            cv2.putText(image, "ar_anchor", (x, y), cv2.FONT_HERSHEY_SIMPLEX, r / 40.0, colour, 2, cv2.LINE_AA)
    for _ in range(8):  # decoys: a black square border with a grey, non-binary inside
        x, y = (int(v) for v in rng.integers(0, size - 80, 2))
        side = int(rng.integers(30, 80))
        cv2.rectangle(image, (x, y), (x + side, y + side), (25, 25, 25), -1)
        inner = side // 6
        cv2.rectangle(image, (x + inner, y + inner), (x + side - inner, y + side - inner), (200, 200, 200), -1)
        cv2.circle(image, (x + side // 2, y + side // 2), side // 5, (110, 110, 110), -1, cv2.LINE_AA)
    return cv2.GaussianBlur(image, (0, 0), 1.2)


def _pinhole_canvas(camera: CameraModel) -> tuple[CameraModel, tuple[np.ndarray, np.ndarray] | None]:
    """The pinhole camera to render with, and for a distorted camera the maps from each output pixel
    to its position on that pinhole canvas (``None``: render directly)."""
    if not camera.has_distortion:
        return camera, None
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    k = camera.camera_matrix
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        ideal = cv2.undistortPointsIter(pixels, k, camera.dist_coeffs, None, k, criteria)
    else:  # OpenCV 5 folded the criteria into undistortPoints
        ideal = cv2.undistortPoints(pixels, k, camera.dist_coeffs, R=None, P=k, criteria=criteria)
    # the inversion must round-trip: a model that folds over (e.g. a strongly negative k1 at the
    # image's corners) has pixels no ideal point projects to
    rays = cv2.undistortPoints(ideal, k, np.zeros(5)).reshape(-1, 2)
    back = cv2.projectPoints(
        np.column_stack([rays, np.ones(len(rays))]), np.zeros(3), np.zeros(3), k, camera.dist_coeffs
    )[0]
    ideal = ideal.reshape(height, width, 2)
    if not (np.all(np.isfinite(back)) and np.abs(back.reshape(-1, 2) - pixels.reshape(-1, 2)).max() < 0.01):
        raise SourceError("synthetic source: the camera's distortion model cannot be inverted over the whole image")
    x0, y0 = np.floor(ideal.reshape(-1, 2).min(axis=0)) - 2
    x1, y1 = np.ceil(ideal.reshape(-1, 2).max(axis=0)) + 2
    if (x1 - x0) * (y1 - y0) > 9 * width * height:
        raise SourceError("synthetic source: the camera's distortion is too strong to render (view > 9x the image)")
    shifted = k.copy()
    shifted[0, 2] -= x0
    shifted[1, 2] -= y0
    pinhole = CameraModel(shifted, np.zeros(0), int(x1 - x0) + 1, int(y1 - y0) + 1)
    maps = ((ideal[..., 0] - x0).astype(np.float32), (ideal[..., 1] - y0).astype(np.float32))
    return pinhole, maps


class _Renderer:
    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self.camera, self._undistort_maps = _pinhole_canvas(scene.camera)
        rng = np.random.default_rng([scene.seed, 0xC1077E7])
        self.wall_texture = _clutter_texture(rng) if scene.clutter else np.full((8, 8, 3), 128, np.uint8)
        wall_m = 2.0
        ts = wall_m / self.wall_texture.shape[1]
        self.wall_from_texture = np.array(
            [[ts, 0.0, 0.5 * ts - wall_m / 2], [0.0, -ts, wall_m / 2 - 0.5 * ts], [0.0, 0.0, 1.0]]
        )
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(scene.dictionary))
        self.groups: list[tuple[np.ndarray, list[_Quad]]] = []  # (centre in world, quads drawn in order)
        for marker in scene.markers:
            quad = _marker_quad(
                dictionary, marker.marker_id, marker.length_m, marker.world_from_target, marker.length_m / 6
            )
            self.groups.append((marker.world_from_target.tvec, [quad]))
        for placed in scene.boards:
            board = placed.board
            width, height = board.size_m
            margin = max(board.separation_m, board.marker_length_m / 4)
            quads = [_paper_quad(placed.world_from_target, -margin, -margin, width + margin, height + margin)]
            quiet = min(board.marker_length_m / (dictionary.markerSize + 2), board.separation_m / 2)
            for marker_id, board_from_marker in board_marker_poses(board).items():
                world_from_marker = placed.world_from_target.compose(board_from_marker)
                quads.append(_marker_quad(dictionary, marker_id, board.marker_length_m, world_from_marker, quiet))
            centre = placed.world_from_target.apply(np.array([[width / 2, height / 2, 0.0]]))[0]
            self.groups.append((centre, quads))
        # paper sheets lie under the targets: a sheet flat on the wall is painted into the wall's texture
        # (free to render; its outline is not measured), any other is a quad drawn right after the wall
        self.sheets = []
        for sheet in scene.sheets:
            w2, h2 = sheet.width_m / 2, sheet.height_m / 2
            pose = sheet.world_from_sheet
            if scene.clutter and abs(pose.rotation[2, 2]) > 1 - 1e-9 and abs(pose.tvec[2]) < 1e-9:
                corners = pose.apply(np.array([[-w2, -h2, 0], [w2, -h2, 0], [w2, h2, 0], [-w2, h2, 0]]))
                texels = np.column_stack([corners[:, :2], np.ones(4)]) @ np.linalg.inv(self.wall_from_texture).T
                points = np.round(texels[:, :2] / texels[:, 2:] * 16).astype(np.int32)
                cv2.fillConvexPoly(self.wall_texture, points, (_PAPER,) * 3, cv2.LINE_AA, 4)
            else:
                self.sheets.append(_paper_quad(pose, -w2, -h2, w2, h2))
        self.k = self.camera.camera_matrix
        self._supersample = scene.supersample

    def render(self, camera_from_world: Pose, *, targets: bool = True, supersample: int | None = None) -> np.ndarray:
        """Noise-free BGR image of the scene seen from ``camera_from_world`` (float32, linear grey levels)."""
        self._supersample = supersample or self.scene.supersample
        canvas = self._render_wall(camera_from_world).astype(np.float32)
        for sheet in self.sheets:
            self._composite(canvas, sheet, camera_from_world)
        if targets:
            depth = [float(camera_from_world.apply(centre[None])[0, 2]) for centre, _ in self.groups]
            for order in np.argsort(depth)[::-1]:
                for quad in self.groups[order][1]:
                    self._composite(canvas, quad, camera_from_world)
        if self._undistort_maps is not None:
            map_x, map_y = self._undistort_maps
            canvas = cv2.remap(canvas, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return canvas

    def _homography(self, camera_from_plane: Pose, plane_from_texture: np.ndarray) -> np.ndarray:
        rotation = camera_from_plane.rotation
        image_from_plane = self.k @ np.column_stack([rotation[:, 0], rotation[:, 1], camera_from_plane.tvec])
        return image_from_plane @ plane_from_texture

    def _render_wall(self, camera_from_world: Pose) -> np.ndarray:
        width, height = self.camera.size
        homography = self._homography(camera_from_world, self.wall_from_texture)
        wall = cv2.warpPerspective(
            self.wall_texture, homography, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101
        )
        # texture_from_image (u, v, 1) = texture point / depth: its last entry is 1 / depth along the
        # pixel's ray. Where it is <= 0 the ray meets the wall's plane behind the camera: sky.
        w_row = np.linalg.inv(homography)[2]
        corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], float)
        if np.any(corners @ w_row <= 0):
            u = np.arange(width, dtype=np.float64)[None, :]
            v = np.arange(height, dtype=np.float64)[:, None]
            wall[w_row[0] * u + w_row[1] * v + w_row[2] <= 0] = _SKY_BGR
        return wall

    def _composite(self, canvas: np.ndarray, quad: _Quad, camera_from_world: Pose) -> None:
        camera_from_plane = camera_from_world.compose(quad.world_from_plane)
        outline = camera_from_plane.apply(quad.outline_in_plane)
        if np.any(outline[:, 2] <= 1e-3):
            return  # crosses or lies behind the camera plane
        pixels = outline[:, :2] / outline[:, 2:] * np.diag(self.k)[:2] + self.k[:2, 2]
        height, width = canvas.shape[:2]
        x0 = max(int(math.floor(pixels[:, 0].min())) - 1, 0)
        y0 = max(int(math.floor(pixels[:, 1].min())) - 1, 0)
        x1 = min(int(math.ceil(pixels[:, 0].max())) + 2, width)
        y1 = min(int(math.ceil(pixels[:, 1].max())) + 2, height)
        if x1 <= x0 or y1 <= y0:
            return
        s = self._supersample
        # output pixel u -> supersampled pixel s*u + (s-1)/2 (centres at integers), then shift to the box.
        hires_from_image = np.array([[s, 0.0, (s - 1) / 2.0 - s * x0], [0.0, s, (s - 1) / 2.0 - s * y0], [0, 0, 1.0]])
        homography = hires_from_image @ self._homography(camera_from_plane, quad.plane_from_texture)
        warped = cv2.warpPerspective(
            quad.texture,
            homography,
            ((x1 - x0) * s, (y1 - y0) * s),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        small = cv2.resize(warped.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
        grey_premultiplied, coverage = small[..., 0], small[..., 1] / 255.0
        region = canvas[y0:y1, x0:x1]
        region *= (1.0 - coverage)[..., None]
        region += grey_premultiplied[..., None]


class _H264RoundTrip:
    """A persistent libx264 encoder and H.264 decoder (PyAV, in memory): one BGR frame in, the same
    frame after compression out. Zero-latency tuning (no B-frames, no lookahead) makes every
    ``encode`` return its packet at once, so the round trip keeps frame order and count exactly."""

    def __init__(self, width: int, height: int, fps: float, kbps: float, gop: int) -> None:
        import av  # noqa: PLC0415  (PyAV: only needed for h264 clips)

        self._av = av
        self.encoder = av.CodecContext.create("libx264", "w")
        self.encoder.width, self.encoder.height = width, height
        self.encoder.pix_fmt = "yuv420p"
        rate = Fraction(fps).limit_denominator(1001)
        self.encoder.framerate = rate
        self.encoder.time_base = 1 / rate
        self.encoder.bit_rate = int(kbps * 1000)
        self.encoder.gop_size = gop
        self.encoder.options = {"preset": "veryfast", "tune": "zerolatency", "bframes": "0"}
        self.decoder = av.CodecContext.create("h264", "r")
        self._pts = 0

    def __call__(self, image: np.ndarray) -> np.ndarray:
        # colour conversion with OpenCV both ways (one BT.601 matrix, 3x faster than swscale here); the
        # image size must be even for 4:2:0 (webcam sizes are)
        height, width = image.shape[:2]
        frame = self._av.VideoFrame.from_ndarray(cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420), format="yuv420p")
        frame.pts = self._pts
        self._pts += 1
        decoded = [d for packet in self.encoder.encode(frame) for d in self.decoder.decode(packet)]
        if len(decoded) != 1:
            raise SourceError(f"synthetic source: the H.264 round trip gave {len(decoded)} frames for one")
        planes = decoded[0].to_ndarray(format="yuv420p")
        return cv2.cvtColor(planes.reshape(height * 3 // 2, width), cv2.COLOR_YUV2BGR_I420)


class SyntheticSource:
    """Renders :class:`SyntheticScene` frames with per-frame ground truth (a :class:`FrameSource`)."""

    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self._renderer = _Renderer(scene)
        self._closed = False
        # the last rendered content frame: (content index, hidden) -> (image, truth); duplicates reuse it
        self._last: tuple[tuple[int, bool], np.ndarray, dict[str, Pose]] | None = None
        self._h264: _H264RoundTrip | None = None
        self._h264_next = 0  # the container frame the codec expects next
        self._probe_points = self._target_points()

    # FrameSource
    @property
    def resolution(self) -> tuple[int, int]:
        return self.scene.camera.size

    @property
    def camera(self) -> CameraModel:
        return self.scene.camera

    @property
    def frame_count(self) -> int:
        return self.scene.frames

    def __enter__(self) -> SyntheticSource:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._closed = True
        self._h264 = None

    def __iter__(self) -> Iterator[Frame]:
        for index in range(self.scene.frames):
            if self._closed:
                return
            yield self.frame(index)

    # rendering
    def camera_from_world(self, index: int) -> Pose:
        """``camera_from_world`` when container frame ``index``'s image was taken (mid-exposure, first row)."""
        scene = self.scene
        if scene.content_fps is None and scene.trajectory.kind != "handheld":
            u = index / max(scene.frames - 1, 1)
            return scene.trajectory.camera_from_world(u)
        return self.camera_at(scene.content_time(index))

    def camera_at(self, t_s: float) -> Pose:
        """``camera_from_world`` at any time (seconds); the calm trajectories span the container's
        ``(frames - 1) / fps`` seconds."""
        scene = self.scene
        if scene.trajectory.kind == "handheld":
            return scene.trajectory.at_time(t_s)
        return scene.trajectory.camera_from_world(t_s * scene.fps / max(scene.frames - 1, 1))

    def frame(self, index: int) -> Frame:
        """Frame ``index`` of the clip (deterministic for the scene's seed)."""
        scene = self.scene
        hidden = scene.is_hidden(index)
        key = (scene.content_index(index), hidden)
        if self._last is not None and self._last[0] == key:
            image, truth = self._last[1], self._last[2]  # a duplicated frame: same pixels, same truth
        else:
            camera_from_world = self.camera_from_world(index)
            rng = np.random.default_rng([scene.seed, key[0]])
            if self._plain:
                image = self.render_view(camera_from_world, rng, targets=not hidden)
            else:
                image = self._render_realistic(index, rng, targets=not hidden)
            truth = {} if hidden else self.truth(camera_from_world)
            self._last = (key, image, truth)
        if scene.compression == "h264":
            image = self._h264_frame(index)
        timestamp_ns = int(round(index * 1e9 / scene.fps))
        return Frame(image, index, timestamp_ns, truth)

    @property
    def _plain(self) -> bool:
        """No hand-held option that changes the pixels of a rendered frame: the calm renderer's path."""
        scene = self.scene
        return not (scene.exposure_s > 0 or scene.rolling_shutter_s > 0 or scene.lighting or scene.occluders
                    or scene.compression == "jpeg")  # fmt: skip

    def _h264_frame(self, index: int) -> np.ndarray:
        """Container frame ``index`` after the H.264 round trip (sequential; out of order restarts)."""
        assert self._last is not None
        if self._h264 is None or index != self._h264_next:
            width, height = self.scene.camera.size
            self._h264 = _H264RoundTrip(width, height, self.scene.fps, self.scene.h264_kbps, self.scene.h264_gop)
            self._h264_next = 0
            last = self._last
            for earlier in range(index):  # replay the stream up to here (random access only)
                self.frame(earlier)
            self._last = last
        self._h264_next = index + 1
        return self._h264(self._last[1])

    def render_view(
        self, camera_from_world: Pose, rng: np.random.Generator | None = None, *, targets: bool = True
    ) -> np.ndarray:
        """BGR uint8 image from any camera pose, with the scene's blur and noise (noise needs ``rng``)."""
        canvas = self._renderer.render(camera_from_world, targets=targets)
        return self._finish(canvas, rng)

    def _finish(self, canvas: np.ndarray, rng: np.random.Generator | None, *, fast_noise: bool = False) -> np.ndarray:
        """Optical blur, sensor noise, rounding. ``fast_noise``: OpenCV's generator seeded from ``rng``
        (3x faster than numpy's Gaussian at 640x480; the hand-held path uses it, the calm path keeps
        numpy's so its frames stay as they were)."""
        if self.scene.blur_sigma > 0:
            canvas = cv2.GaussianBlur(canvas, (0, 0), self.scene.blur_sigma)
        if self.scene.noise_sigma > 0 and rng is not None:
            if fast_noise:
                noise = np.empty(canvas.shape, np.float32)
                cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
                cv2.randn(noise, (0.0,) * 3, (self.scene.noise_sigma,) * 3)
                canvas = canvas + noise
            else:
                noise = rng.standard_normal(canvas.shape, dtype=np.float32) * np.float32(self.scene.noise_sigma)
                canvas = canvas + noise
        return np.clip(canvas + 0.5, 0, 255).astype(np.uint8)

    # ------------------------------------------------------------------ hand-held realism

    def _target_points(self) -> np.ndarray:
        """World points whose image motion sets the number of blur sub-frames: every target's corners."""
        points = [m.world_from_target.apply(marker_corners_in_marker(m.length_m)) for m in self.scene.markers]
        for placed in self.scene.boards:
            width, height = placed.board.size_m
            outline = np.array([[0, 0, 0], [width, 0, 0], [width, height, 0], [0, height, 0]], float)
            points.append(placed.world_from_target.apply(outline))
        if not points:  # nothing but the wall: where the first frame's optical axis meets it
            points.append(np.zeros((1, 3)))
        return np.concatenate(points)

    def _image_motion_px(self, times: np.ndarray) -> float:
        """Path length (pixels, pinhole) of the fastest target point over ``times``."""
        k = self._renderer.k
        tracks = []
        for t in times:
            camera_points = self.camera_at(float(t)).apply(self._probe_points)
            z = np.maximum(camera_points[:, 2:], 1e-3)
            tracks.append(camera_points[:, :2] / z * np.diag(k)[:2])
        tracks = np.array(tracks)
        return float(np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0).max()) if len(tracks) > 1 else 0.0

    def exposure_samples(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Sub-frame times (N,) and per-row weights (H, N) (rows sum to 1) of a frame taken at ``t_s``.

        Row ``r`` integrates ``[t_r - e/2, t_r + e/2]``, ``t_r = t_s + r / H * readout``; the N renders
        at evenly spaced times over the whole span are the nodes of a linear interpolation in time, and
        a row's weight for a node is the integral of that node's hat function over the row's window.
        """
        scene = self.scene
        height = scene.camera.size[1]
        exposure, readout = scene.exposure_s, scene.rolling_shutter_s
        start, stop = t_s - exposure / 2, t_s + readout + exposure / 2
        probe = np.linspace(start, stop, 5)
        n = min(int(math.ceil(self._image_motion_px(probe) / _SUBFRAME_PX)) + 1, scene.max_subframes)
        if n == 1:
            return np.array([t_s]), np.ones((height, 1))
        nodes = np.linspace(start, stop, n)
        q = 16 if exposure > 0 else 1
        offsets = (np.arange(q) + 0.5) / q * exposure - exposure / 2 if exposure > 0 else np.zeros(1)
        row_times = t_s + np.arange(height)[:, None] / height * readout + offsets[None, :]  # (H, q)
        weights = np.empty((height, n))
        for j in range(n):
            weights[:, j] = np.interp(row_times, nodes, np.eye(n)[j]).mean(axis=1)
        weights /= weights.sum(axis=1, keepdims=True)
        return nodes, weights

    def _render_realistic(self, index: int, rng: np.random.Generator, *, targets: bool) -> np.ndarray:
        """Motion blur / rolling shutter, occluders, lighting, then optics, noise and JPEG."""
        scene = self.scene
        t_s = scene.content_time(index)
        if scene.exposure_s > 0 or scene.rolling_shutter_s > 0:
            nodes, weights = self.exposure_samples(t_s)
        else:
            nodes, weights = np.array([t_s]), None
        if len(nodes) == 1:
            canvas = self._renderer.render(self.camera_from_world(index), targets=targets)
        else:
            supersample = max(1, scene.supersample // 2)
            canvas = None
            same_rows = bool(np.all(weights == weights[:1]))
            for j, node in enumerate(nodes):
                sub = self._renderer.render(self.camera_at(float(node)), targets=targets, supersample=supersample)
                w = np.float32(weights[0, j]) if same_rows else weights[:, j].astype(np.float32)[:, None, None]
                np.multiply(sub, w, out=sub)
                if canvas is None:
                    canvas = sub
                else:
                    canvas += sub
        height, width = canvas.shape[:2]
        frame_pos = round(t_s * scene.fps, 6)  # container frame units (duplicates: their first frame)
        for occluder in scene.occluders:
            mask = occluder.mask(frame_pos, width, height)
            if mask is not None:
                canvas += (occluder.shade(width, height) - canvas) * mask[..., None]
        if scene.lighting is not None:
            gain, offset = scene.lighting.gain_offset(t_s, scene.seed)
            canvas = canvas * np.float32(gain) + np.float32(offset)
        image = self._finish(canvas, rng, fast_noise=True)
        if scene.compression == "jpeg":
            ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, scene.jpeg_quality])
            if not ok:
                raise SourceError("synthetic source: JPEG encoding failed")
            image = cv2.imdecode(data, cv2.IMREAD_COLOR)
        return image

    def truth(self, camera_from_world: Pose) -> dict[str, Pose]:
        """``camera_from_target`` of every target fully in view (all four corners of a marker;
        at least one marker of a board)."""
        truth: dict[str, Pose] = {}
        camera = self.scene.camera

        def in_view(camera_from_marker: Pose, length_m: float) -> bool:
            points = camera_from_marker.apply(marker_corners_in_marker(length_m))
            if np.any(points[:, 2] <= 1e-3):
                return False
            pixels = camera.project(points)
            return bool(np.all((pixels >= -0.5) & (pixels <= np.array(camera.size) - 0.5)))

        for marker in self.scene.markers:
            pose = camera_from_world.compose(marker.world_from_target)
            if in_view(pose, marker.length_m):
                truth[marker.target] = pose
        for placed in self.scene.boards:
            camera_from_board = camera_from_world.compose(placed.world_from_target)
            any_seen = False
            for marker_id, board_from_marker in board_marker_poses(placed.board).items():
                pose = camera_from_board.compose(board_from_marker)
                if in_view(pose, placed.board.marker_length_m):
                    truth[f"marker:{marker_id}"] = pose
                    any_seen = True
            if any_seen:
                truth[placed.target] = camera_from_board
        return truth
