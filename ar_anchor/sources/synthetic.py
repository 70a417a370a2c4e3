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
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from types import TracebackType

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig, dictionary_id
from ..errors import SourceError
from ..geometry import Pose, look_at, marker_corners_in_marker
from .base import Frame

__all__ = [
    "PlacedBoard",
    "PlacedMarker",
    "SyntheticScene",
    "SyntheticSource",
    "Trajectory",
    "board_marker_poses",
    "demo_scene",
]

log = logging.getLogger(__name__)

# Print contrast: black ink is not 0, paper is not 255.
_INK = 20.0
_PAPER = 240.0
_CELL_TEXELS = 24  # texels per marker bit cell
_SKY_BGR = (180, 160, 140)
# board_from_marker rotation: marker frame (y up, z out) inside the board frame (y down, z in).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])


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
    """Camera path over the clip, as a function of normalised time ``u`` in [0, 1].

    kind:
        ``sweep``: distance grows from ``near_m`` to ``far_m`` while the camera swings in azimuth
        and elevation (the demo's path: near, well-conditioned views to far, ambiguous ones).
        ``orbit``: constant distance ``near_m``, azimuth swings ``±azimuth_deg``.
        ``static``: a fixed camera at ``near_m``, ``azimuth_deg``, ``elevation_deg``.
    """

    kind: str = "sweep"
    near_m: float = 0.35
    far_m: float = 3.0
    azimuth_deg: float = 35.0
    elevation_deg: float = 20.0
    roll_deg: float = 10.0
    cycles: float = 1.5
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.kind not in ("sweep", "orbit", "static"):
            raise ValueError(f"trajectory kind must be sweep, orbit or static, got {self.kind!r}")
        if not (0 < self.near_m and (self.kind != "sweep" or self.near_m <= self.far_m)):
            raise ValueError(f"trajectory distances must satisfy 0 < near <= far, got {self.near_m}, {self.far_m}")

    def camera_from_world(self, u: float) -> Pose:
        az, el, roll, dist = self._angles(u)
        centre = np.asarray(self.look_at, dtype=np.float64)
        direction = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        pose = look_at(centre + dist * direction, centre, up=(0.0, 1.0, 0.0))
        if roll:
            roll_pose = Pose(np.array([0.0, 0.0, roll]), np.zeros(3))
            pose = roll_pose.compose(pose)
        return pose

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


@dataclass(frozen=True)
class SyntheticScene:
    """Everything that defines a synthetic clip; the same scene and seed give the same frames."""

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
        dictionary_id(self.dictionary)


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
        self.k = self.camera.camera_matrix

    def render(self, camera_from_world: Pose, *, targets: bool = True) -> np.ndarray:
        """Noise-free BGR image of the scene seen from ``camera_from_world``."""
        canvas = self._render_wall(camera_from_world).astype(np.float32)
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
        s = self.scene.supersample
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


class SyntheticSource:
    """Renders :class:`SyntheticScene` frames with per-frame ground truth (a :class:`FrameSource`)."""

    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self._renderer = _Renderer(scene)
        self._closed = False

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

    def __iter__(self) -> Iterator[Frame]:
        for index in range(self.scene.frames):
            if self._closed:
                return
            yield self.frame(index)

    # rendering
    def camera_from_world(self, index: int) -> Pose:
        u = index / max(self.scene.frames - 1, 1)
        return self.scene.trajectory.camera_from_world(u)

    def frame(self, index: int) -> Frame:
        """Frame ``index`` of the clip (deterministic for the scene's seed)."""
        camera_from_world = self.camera_from_world(index)
        rng = np.random.default_rng([self.scene.seed, index])
        hidden = self.scene.is_hidden(index)
        image = self.render_view(camera_from_world, rng, targets=not hidden)
        timestamp_ns = int(round(index * 1e9 / self.scene.fps))
        return Frame(image, index, timestamp_ns, {} if hidden else self.truth(camera_from_world))

    def render_view(
        self, camera_from_world: Pose, rng: np.random.Generator | None = None, *, targets: bool = True
    ) -> np.ndarray:
        """BGR uint8 image from any camera pose, with the scene's blur and noise (noise needs ``rng``)."""
        canvas = self._renderer.render(camera_from_world, targets=targets)
        if self.scene.blur_sigma > 0:
            canvas = cv2.GaussianBlur(canvas, (0, 0), self.scene.blur_sigma)
        if self.scene.noise_sigma > 0 and rng is not None:
            canvas = canvas + rng.standard_normal(canvas.shape, dtype=np.float32) * np.float32(self.scene.noise_sigma)
        return np.clip(canvas + 0.5, 0, 255).astype(np.uint8)

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
