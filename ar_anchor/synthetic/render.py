"""How a camera renders a synthetic scene: textured quads, lens distortion, sub-frame exposure,
the hand, lighting, optics, sensor noise and compression.

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
(the quiet zone surrounds them), so an edge's 50 % crossing is unbiased. Paper sheets lie under
the targets: a sheet flat on the wall is painted into the wall texture (free to render); any other
is a paper quad drawn right after the wall.

Lens distortion: a camera with distortion coefficients is rendered as its ideal pinhole camera on
a canvas large enough to hold the undistorted view, then resampled (bilinear) at each output
pixel's undistorted position (``undistortPoints`` iterated to convergence), so straight edges come
out curved exactly as ``projectPoints`` with the same coefficients predicts.

Hand-held webcam effects
------------------------
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
- **Compression** (``compression = "jpeg" | "h264"``): a MJPEG webcam's per-frame JPEG
  (``jpeg_quality``) or an H.264 round trip through PyAV/libx264 at ``h264_kbps`` (zero-latency
  tuning, no B-frames: one frame in, one frame out, so order and count are exact). H.264 is
  sequential: iterating the source encodes frame by frame with a persistent encoder/decoder
  (:class:`H264RoundTrip`); a random access ``frame(i)`` out of order restarts the codec from frame 0.

Order of the effects on a frame: sub-frame renders (blur, rolling shutter) -> hand -> lighting ->
optical blur (``blur_sigma``) -> sensor noise -> rounding -> JPEG / H.264. Every frame draws its sensor
noise from OpenCV's Gaussian generator seeded from the frame's own generator (2.5x faster than numpy's at
720p; on a calm frame the noise was most of the render's time).
The cost: a 150-frame 640x480 hand-held clip with blur, rolling shutter and H.264 renders in about
5 s on one core (about 3 sub-frames per frame on average, up to ``max_subframes`` in quick turns).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import dictionary_id
from ..errors import SourceError
from ..geometry import Pose, marker_corners_in_marker
from ..lazy import import_held
from .scene import SyntheticScene, board_marker_poses

__all__ = ["H264RoundTrip", "Renderer", "pinhole_canvas"]

# Print contrast: black ink is not 0, paper is not 255.
_INK = 20.0
_PAPER = 240.0
_CELL_TEXELS = 24  # texels per marker bit cell
_SKY_BGR = (180, 160, 140)
_SUBFRAME_PX = 2.0  # motion blur: about one sub-frame per this much image motion of the targets


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


@functools.lru_cache(maxsize=8)
def _wall_texture(seed: int) -> np.ndarray:
    """The cluttered wall of a scene of ``seed`` (read-only; 3 MB): drawn once per seed in a process, not once per
    renderer (0.1 s each, and a process that renders many short scenes builds a renderer for each)."""
    texture = _clutter_texture(np.random.default_rng([seed, 0xC1077E7]))
    texture.flags.writeable = False
    return texture


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


def pinhole_canvas(camera: CameraModel) -> tuple[CameraModel, tuple[np.ndarray, np.ndarray] | None]:
    """The pinhole camera to render with, and for a distorted camera the maps from each output pixel
    to its position on that pinhole canvas (``None``: render directly; the maps are read-only)."""
    if not camera.has_distortion:
        return camera, None
    k, dist = np.asarray(camera.camera_matrix, np.float64), np.asarray(camera.dist_coeffs, np.float64).reshape(-1)
    return _pinhole_canvas(k.tobytes(), dist.tobytes(), tuple(camera.size))


@functools.lru_cache(maxsize=4)
def _pinhole_canvas(
    k_bytes: bytes, dist_bytes: bytes, size: tuple[int, int]
) -> tuple[CameraModel, tuple[np.ndarray, np.ndarray]]:
    """:func:`pinhole_canvas` of one camera, computed once per process (0.2 s at 640x480, 0.7 s at 1280x720; a
    process that renders many short scenes, a benchmark or a calibration, builds a renderer for each)."""
    camera = CameraModel(np.frombuffer(k_bytes).reshape(3, 3).copy(), np.frombuffer(dist_bytes).copy(), *size)
    width, height = camera.size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    k = camera.camera_matrix
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    # in chunks of 64k pixels (~0.3 s each): a Ctrl-C is not held up for the whole image (seconds at 1080p)
    chunks = []
    for first in range(0, len(pixels), 1 << 16):
        chunk = pixels[first : first + (1 << 16)]
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
            chunks.append(cv2.undistortPointsIter(chunk, k, camera.dist_coeffs, None, k, criteria))
        else:  # OpenCV 5 folded the criteria into undistortPoints
            chunks.append(cv2.undistortPoints(chunk, k, camera.dist_coeffs, R=None, P=k, criteria=criteria))
    ideal = np.concatenate(chunks)
    # the inversion must round-trip: a model that folds over (e.g. a strongly negative k1 at the
    # image's corners) has pixels no ideal point projects to
    rays = cv2.undistortPoints(ideal, k, np.zeros(5)).reshape(-1, 2)
    back = camera.project_rays(rays)
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
    for array in maps:
        array.flags.writeable = False
    return pinhole, maps


class _QuadRenderer:
    """Noise-free images of the scene from any camera pose: the wall, the sheets and the targets as
    textured quads on the pinhole canvas, then resampled through the lens distortion."""

    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self.camera, self._undistort_maps = pinhole_canvas(scene.camera)
        # (a copy: sheets flat on the wall are painted into it below)
        self.wall_texture = _wall_texture(scene.seed).copy() if scene.clutter else np.full((8, 8, 3), 128, np.uint8)
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


class H264RoundTrip:
    """A persistent libx264 encoder and H.264 decoder (PyAV, in memory): one BGR frame in, the same
    frame after compression out. Zero-latency tuning (no B-frames, no lookahead) makes every
    ``encode`` return its packet at once, so the round trip keeps frame order and count exactly."""

    def __init__(self, width: int, height: int, fps: float, kbps: float, gop: int) -> None:
        av = import_held("av")  # PyAV: only needed for h264 clips; whole: a Ctrl-C waits until it is loaded

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


class Renderer:
    """How the scene's camera renders it: a container frame's image (sub-frame exposure, the hand,
    lighting, optics, sensor noise, JPEG) or a single view from any pose. The H.264 round trip is
    sequential over the clip, so its state is the frame source's (:class:`H264RoundTrip`)."""

    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self._quads = _QuadRenderer(scene)
        self._probe_points = self._target_points()

    @property
    def plain(self) -> bool:
        """No hand-held option that changes the pixels of a rendered frame: the calm renderer's path."""
        scene = self.scene
        return not (scene.exposure_s > 0 or scene.rolling_shutter_s > 0 or scene.lighting or scene.occluders
                    or scene.compression == "jpeg")  # fmt: skip

    def render_frame(self, index: int, rng: np.random.Generator, *, targets: bool = True) -> np.ndarray:
        """BGR uint8 image of container frame ``index`` (before any H.264 round trip); ``rng`` draws
        its sensor noise."""
        if self.plain:
            return self.render_view(self.scene.camera_from_world(index), rng, targets=targets)
        return self._render_realistic(index, rng, targets=targets)

    def render_view(
        self, camera_from_world: Pose, rng: np.random.Generator | None = None, *, targets: bool = True
    ) -> np.ndarray:
        """BGR uint8 image from any camera pose, with the scene's blur and noise (noise needs ``rng``)."""
        canvas = self._quads.render(camera_from_world, targets=targets)
        return self._finish(canvas, rng)

    def _finish(self, canvas: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Optical blur, sensor noise, rounding. The noise is OpenCV's Gaussian generator seeded from ``rng``
        (one draw): 10 ms per 720p frame against 26 ms for numpy's, the larger part of a calm frame's render."""
        owned = False  # whether ``canvas`` is an array of this call's own, to work in place (the same values)
        if self.scene.blur_sigma > 0:
            canvas, owned = cv2.GaussianBlur(canvas, (0, 0), self.scene.blur_sigma), True
        if self.scene.noise_sigma > 0 and rng is not None:
            noise = np.empty(canvas.shape, np.float32)
            cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
            cv2.randn(noise, (0.0,) * 3, (self.scene.noise_sigma,) * 3)
            if canvas.dtype == np.float32:
                noise += canvas
                canvas, owned = noise, True
            else:
                canvas = canvas + noise
        if owned and canvas.dtype == np.float32:
            canvas += np.float32(0.5)
            return np.clip(canvas, 0, 255, out=canvas).astype(np.uint8)
        return np.clip(canvas + 0.5, 0, 255).astype(np.uint8)

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
        k = self._quads.k
        tracks = []
        for t in times:
            camera_points = self.scene.camera_at(float(t)).apply(self._probe_points)
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

    def _expose(self, index: int, t_s: float, *, targets: bool) -> np.ndarray:
        """Noise-free float image of container frame ``index`` (taken at ``t_s``): one render, or the
        row-weighted average of the sub-frame renders (motion blur, rolling shutter)."""
        scene = self.scene
        if scene.exposure_s > 0 or scene.rolling_shutter_s > 0:
            nodes, weights = self.exposure_samples(t_s)
        else:
            nodes, weights = np.array([t_s]), None
        if len(nodes) == 1:
            return self._quads.render(scene.camera_from_world(index), targets=targets)
        supersample = max(1, scene.supersample // 2)
        canvas = None
        same_rows = bool(np.all(weights == weights[:1]))
        for j, node in enumerate(nodes):
            sub = self._quads.render(scene.camera_at(float(node)), targets=targets, supersample=supersample)
            w = np.float32(weights[0, j]) if same_rows else weights[:, j].astype(np.float32)[:, None, None]
            np.multiply(sub, w, out=sub)
            if canvas is None:
                canvas = sub
            else:
                canvas += sub
        return canvas

    def _render_realistic(self, index: int, rng: np.random.Generator, *, targets: bool) -> np.ndarray:
        """Motion blur / rolling shutter, occluders, lighting, then optics, noise and JPEG."""
        scene = self.scene
        t_s = scene.content_time(index)
        canvas = self._expose(index, t_s, targets=targets)
        height, width = canvas.shape[:2]
        frame_pos = round(t_s * scene.fps, 6)  # container frame units (duplicates: their first frame)
        for occluder in scene.occluders:
            mask = occluder.mask(frame_pos, width, height)
            if mask is not None:
                canvas += (occluder.shade(width, height) - canvas) * mask[..., None]
        if scene.lighting is not None:
            gain, offset = scene.lighting.gain_offset(t_s, scene.seed)
            canvas = canvas * np.float32(gain) + np.float32(offset)
        image = self._finish(canvas, rng)
        if scene.compression == "jpeg":
            ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, scene.jpeg_quality])
            if not ok:
                raise SourceError("synthetic source: JPEG encoding failed")
            image = cv2.imdecode(data, cv2.IMREAD_COLOR)
        return image
