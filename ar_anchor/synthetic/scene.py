"""What is in a synthetic scene, and when: placed markers, boards and sheets, lighting, a hand.

Frames of the world: the wall is the plane ``z = 0``, x right, y up, z toward the viewer. A lone
marker's frame is its centre, x right, y up, z toward the viewer (IPPE_SQUARE's); a grid board's
frame is OpenCV's ``GridBoard.getObjPoints()`` frame (top-left of the first marker, x right, y down,
z into the board).

A :class:`SyntheticScene` is everything that defines a clip: the camera and its path
(:class:`~ar_anchor.synthetic.trajectory.Trajectory`), the targets, and the hand-held webcam options.
The same scene and seed give the same frames (:mod:`ar_anchor.synthetic.render` draws them). Every
hand-held option is deterministic for the scene's seed and off by default (a default scene renders
bit-identical frames to the calm renderer):

- **Lighting** (:class:`Lighting`): a slow gain and offset drift and brightness steps (an
  auto-exposure jump), applied to the linear image before noise.
- **Occlusion** (:class:`Occluder`): a skin-coloured hand (palm and fingers, soft edged) crossing
  the image along a straight line over a frame range; truth is kept for occluded targets (they are
  still there: a tracker that predicts them is scored against it).
- **Duplicated frames** (``content_fps`` < ``fps``): the container runs at ``fps`` and repeats the
  last rendered frame (identical pixels and truth, new timestamps), as webcams do in low light.
- **Sheets** (:func:`marker_sheet`, :class:`PlacedSheet`): K lone markers printed on one rigid
  sheet of paper (each a :class:`PlacedMarker` with its own truth), so a tracker's per-marker outputs
  can be checked for rigid consistency.
- Webcam cameras: :func:`webcam_camera` (640x480, 720p, ..., optional radial distortion).
- Image border: a target is in a frame's truth only while all its corners are in the image
  (:meth:`SyntheticScene.truth`); the hand-held path (aim point, sway) can push markers partly out,
  and they come back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig, dictionary_id
from ..geometry import Pose, marker_corners_in_marker
from ..targets import TargetId
from .trajectory import Trajectory

__all__ = [
    "COMPRESSIONS",
    "SKIN_BGR",
    "Lighting",
    "Occluder",
    "PlacedBoard",
    "PlacedMarker",
    "PlacedSheet",
    "SyntheticScene",
    "board_marker_poses",
    "demo_scene",
    "marker_sheet",
    "webcam_camera",
]

# board_from_marker rotation: marker frame (y up, z out) inside the board frame (y down, z in).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])
COMPRESSIONS = ("", "jpeg", "h264")
SKIN_BGR = (120.0, 150.0, 205.0)  # the default hand's colour


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


@dataclass(frozen=True)
class PlacedMarker:
    """A lone marker: ``world_from_target`` is its centre frame (x right, y up, z out)."""

    marker_id: int
    length_m: float
    world_from_target: Pose

    @property
    def target(self) -> TargetId:
        return TargetId.marker(self.marker_id)


@dataclass(frozen=True)
class PlacedBoard:
    """A grid board: ``world_from_target`` is OpenCV's board frame (y down, z into the board)."""

    board: BoardConfig
    world_from_target: Pose

    @property
    def target(self) -> str:
        return self.board.target


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
        """``(gain, offset)`` at ``t_s`` seconds (offset in grey levels); ``seed`` sets the phases ``a``, ``b``."""
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
    colour_bgr: tuple[float, float, float] = SKIN_BGR
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

    The hand-held options (see the notes of this module and of :mod:`ar_anchor.synthetic.render`) all
    default to off: ``exposure_s`` (motion blur), ``rolling_shutter_s`` (readout time, top row to bottom
    row), ``max_subframes``, ``lighting``, ``occluders``, ``content_fps`` (< ``fps``: duplicated frames),
    ``compression`` (``""``, ``"jpeg"``, ``"h264"``) with ``jpeg_quality`` / ``h264_kbps`` /
    ``h264_gop``, and ``sheets`` (paper under markers).
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

    def camera_from_world(self, index: int) -> Pose:
        """``camera_from_world`` when container frame ``index``'s image was taken (mid-exposure, first row)."""
        if self.content_fps is None and self.trajectory.kind != "handheld":
            u = index / max(self.frames - 1, 1)
            return self.trajectory.camera_from_world(u)
        return self.camera_at(self.content_time(index))

    def camera_at(self, t_s: float) -> Pose:
        """``camera_from_world`` at any time (seconds); the calm trajectories span the container's
        ``(frames - 1) / fps`` seconds."""
        if self.trajectory.kind == "handheld":
            return self.trajectory.at_time(t_s)
        return self.trajectory.camera_from_world(t_s * self.fps / max(self.frames - 1, 1))

    def truth(self, camera_from_world: Pose) -> dict[str, Pose]:
        """``camera_from_target`` of every target fully in view (all four corners of a marker;
        at least one marker of a board)."""
        truth: dict[str, Pose] = {}
        camera = self.camera

        def in_view(camera_from_marker: Pose, length_m: float) -> bool:
            points = camera_from_marker.apply(marker_corners_in_marker(length_m))
            if np.any(points[:, 2] <= 1e-3):
                return False
            pixels = camera.project(points)
            return bool(np.all((pixels >= -0.5) & (pixels <= np.array(camera.size) - 0.5)))

        for marker in self.markers:
            pose = camera_from_world.compose(marker.world_from_target)
            if in_view(pose, marker.length_m):
                truth[marker.target] = pose
        for placed in self.boards:
            camera_from_board = camera_from_world.compose(placed.world_from_target)
            any_seen = False
            for marker_id, board_from_marker in board_marker_poses(placed.board).items():
                pose = camera_from_board.compose(board_from_marker)
                if in_view(pose, placed.board.marker_length_m):
                    truth[TargetId.marker(marker_id)] = pose
                    any_seen = True
            if any_seen:
                truth[placed.target] = camera_from_board
        return truth


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
