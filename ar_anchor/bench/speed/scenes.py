"""The speed benchmark's clips: the scenes, the tracker set up for them, and the frames rendered
beforehand with their ground truth."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...camera import CameraModel
from ...config import BoardConfig, TrackerConfig
from ...geometry import Pose
from ...sources.base import Frame
from ...sources.synthetic import SyntheticSource
from ...synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory

__all__ = [
    "BLUR",
    "EXTRA_CLIPS",
    "FIFTY",
    "FIFTY_MARKER_M",
    "FIFTY_SIZE",
    "MARKER_M",
    "NOISE",
    "NOISE_SHIFT",
    "SCENES",
    "SCENE_LABELS",
    "SIZES",
    "CLIP_NAMES",
    "clip_label",
    "fifty_markers_scene",
    "render_clip",
    "speed_config",
    "speed_scene",
    "split_clips",
]

SIZES: tuple[tuple[int, int, float], ...] = ((1280, 720, 1000.0), (1920, 1080, 1480.0))  # width, height, fx
SCENES: tuple[str, ...] = ("one", "eight", "board")
SCENE_LABELS = {"one": "one marker", "eight": "eight markers", "board": "2x2 board", "50markers": "50 markers"}
FIFTY = "50markers"  # the many-marker clip (720p only) ...
EXTRA_CLIPS: tuple[str, ...] = (FIFTY, "chessboard")  # ... and the real video: clips beside the size x scene grid
CLIP_NAMES: tuple[str, ...] = SCENES + EXTRA_CLIPS  # what ``--clips`` takes
FIFTY_SIZE = (1280, 720, 1000.0)
FIFTY_MARKER_M = 0.03
FIFTY_PANEL_DEG = 20.0  # each 5x5 panel turned this much about the vertical hinge between them (an open book)
FIFTY_GAP_M = 0.015

MARKER_M = 0.05
NOISE = 2.0  # grey levels
BLUR = 0.6  # pixels
FPS = 30.0
PEAK_DEG_PER_S = 45.0  # the orbit's peak angular speed
NOISE_SHIFT = 64  # pixels: the per-frame shift of the clip's noise field
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])  # board frame (y down, z into the wall) on the wall (y up, z out)


def speed_scene(kind: str, camera: CameraModel, frames: int, seed: int = 0) -> SyntheticScene:
    """One of the benchmark's clips: ``one`` marker, ``eight`` markers or a 2x2 ``board`` (all 5 cm
    markers), seen by a camera orbiting at 0.6-0.7 m (up to 45 deg/s), sensor noise 2, blur 0.6 px."""
    if kind == FIFTY:
        return fifty_markers_scene(camera, frames, seed)
    markers: tuple[PlacedMarker, ...] = ()
    boards: tuple[PlacedBoard, ...] = ()
    if kind == "one":
        markers = (PlacedMarker(0, MARKER_M, Pose.identity()),)
        near = 0.6  # 83 px wide at 720p (fx 1000), 123 px at 1080p (fx 1480)
    elif kind == "eight":
        # 4 x 2 on the wall, 16 cm apart: all in view at both sizes along the whole orbit
        centres = [np.array([-0.24 + 0.16 * (i % 4), 0.08 - 0.16 * (i // 4), 0.0]) for i in range(8)]
        markers = tuple(PlacedMarker(i, MARKER_M, Pose(np.zeros(3), centre)) for i, centre in enumerate(centres))
        near = 0.7  # 71 px at 720p, 106 px at 1080p
    elif kind == "board":
        board = BoardConfig(name="b", cols=2, rows=2, marker_length_m=MARKER_M, separation_m=0.01)
        width, height = board.size_m
        boards = (PlacedBoard(board, Pose.from_matrix(_FLIP_YZ, np.array([-width / 2, height / 2, 0.0]))),)
        near = 0.6
    else:
        raise ValueError(f"unknown speed scene {kind!r} (one of {', '.join(SCENES + (FIFTY,))})")
    seconds = frames / FPS
    azimuth = 35.0
    trajectory = Trajectory(
        kind="orbit",
        near_m=near,
        azimuth_deg=azimuth,
        elevation_deg=15.0,
        roll_deg=10.0,
        cycles=seconds * PEAK_DEG_PER_S / (2 * math.pi * azimuth),
    )
    return _scene(camera, markers, trajectory, frames, seed, boards)


def fifty_markers_scene(camera: CameraModel, frames: int, seed: int = 0) -> SyntheticScene:
    """The many-marker clip: 50 markers of 3 cm (ids 0-49, all of DICT_4X4_50) on two 5x5 panels hinged
    like an open book (each turned 20 deg toward the viewer), seen by a hand-held camera at 0.6-0.75 m
    (sway, aim wander, tremor; no quick turns, so every marker stays in view: 40-50 px wide at 720p)."""
    step = FIFTY_MARKER_M + FIFTY_GAP_M
    panel = 5 * step - FIFTY_GAP_M
    markers = []
    for side, sign in ((0, -1.0), (1, 1.0)):  # left panel (ids 0-24), right panel (ids 25-49)
        angle = math.radians(FIFTY_PANEL_DEG) * -sign  # the left panel's normal turns toward +x
        rotation = np.array([0.0, angle, 0.0])
        along = np.array([math.cos(angle), 0.0, -math.sin(angle)])  # the panel's x axis in the world
        for k in range(25):
            row, col = divmod(k, 5)
            # distance from the hinge along the panel (the left panel runs leftwards from it)
            offset = FIFTY_GAP_M / 2 + FIFTY_MARKER_M / 2 + (col if sign > 0 else 4 - col) * step
            centre = sign * offset * along + np.array([0.0, panel / 2 - FIFTY_MARKER_M / 2 - row * step, 0.0])
            markers.append(PlacedMarker(25 * side + k, FIFTY_MARKER_M, Pose(rotation, centre)))
    trajectory = Trajectory(
        kind="handheld",
        near_m=0.6,
        far_m=0.75,
        azimuth_deg=20.0,
        elevation_deg=12.0,
        roll_deg=8.0,
        turn_deg=0.0,
        aim_m=0.02,
        look_at=(0.0, 0.0, 0.03),
        seed=seed,
        duration_s=frames / FPS,
    )
    return _scene(camera, tuple(markers), trajectory, frames, seed)


def _scene(camera: CameraModel, markers, trajectory: Trajectory, frames: int, seed: int, boards=()) -> SyntheticScene:
    """A speed clip's scene: the clips' frame rate, sensor noise and blur."""
    return SyntheticScene(
        camera=camera,
        markers=markers,
        boards=boards,
        trajectory=trajectory,
        frames=frames,
        fps=FPS,
        seed=seed,
        noise_sigma=NOISE,
        blur_sigma=BLUR,
    )


def speed_config(base: TrackerConfig, scene: SyntheticScene, *, roi: bool) -> TrackerConfig:
    """``base`` set up for ``scene`` (dictionary, marker lengths, boards; filter on), ROI tracking on or off."""
    lengths = {m.marker_id: m.length_m for m in scene.markers}
    return dataclasses.replace(
        base,
        detector=dataclasses.replace(base.detector, dictionary=scene.dictionary, roi=roi),
        markers=dataclasses.replace(
            base.markers,
            length_m=next(iter(lengths.values()), MARKER_M),
            lengths_m=lengths,
            ids=tuple(sorted(lengths)) if lengths else (),
        ),
        boards=tuple(b.board for b in scene.boards),
        filter=dataclasses.replace(base.filter, enabled=True),
    )


def render_clip(
    scene: SyntheticScene, on_frame: Callable[[np.ndarray], None] | None = None, *, keep: bool = True
) -> list[Frame]:
    """All frames of ``scene`` with their ground truth, in memory.

    The sensor noise (Gaussian, ``scene.noise_sigma`` grey levels, rounded to whole levels) is added to
    the 8-bit render from one noise field drawn per clip, shifted by a random offset of up to
    :data:`NOISE_SHIFT` pixels each frame: the synthetic source's noise statistics at a small fraction of
    its cost (drawing 6 million Gaussian samples per 1080p frame would cost more than most pipelines
    measured here). ``on_frame`` sees every image (e.g. to encode the clip); ``keep=False`` returns no
    frames (a 1080p clip of 600 frames held in memory is 3.7 GB).
    """
    source = SyntheticSource(dataclasses.replace(scene, noise_sigma=0.0))
    width, height = scene.camera.size
    field = None
    if scene.noise_sigma > 0:
        rng = np.random.default_rng([scene.seed, 0x5EED])
        draws = rng.normal(0.0, scene.noise_sigma, size=(height + NOISE_SHIFT, 3 * (width + NOISE_SHIFT)))
        field = np.clip(np.rint(draws), -127, 127).astype(np.int8)
        del draws
    frames = []
    for index in range(scene.frames):
        camera_from_world = source.camera_from_world(index)
        image = source.render_view(camera_from_world)
        if field is not None:
            dy, dx = np.random.default_rng([scene.seed, index, 0x5EED]).integers(0, NOISE_SHIFT + 1, 2)
            noise = field[dy : dy + height, 3 * dx : 3 * (dx + width)]
            image = cv2.add(image.reshape(height, -1), noise, dtype=cv2.CV_8U).reshape(height, width, 3)
        if on_frame is not None:
            on_frame(image)
        timestamp_ns = int(round(index * 1e9 / scene.fps))
        if keep:
            frames.append(Frame(image, index, timestamp_ns, source.truth(camera_from_world)))
    return frames


def clip_label(height: int, scene_key: str) -> str:
    """A clip's name in the report: "720p one marker"."""
    return f"{height}p {SCENE_LABELS[scene_key]}"


def split_clips(names: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``--clips one,50markers``: the scenes (run at every size) and the extra clips named, in
    :data:`CLIP_NAMES` order; ``ValueError`` naming an unknown or missing name."""
    wanted = [name.strip() for name in names.split(",") if name.strip()]
    unknown = [name for name in wanted if name not in CLIP_NAMES]
    if unknown or not wanted:
        got = f"unknown clip {unknown[0]!r}" if unknown else "no clip named"
        raise ValueError(f"{got} (comma-separated, any of {','.join(CLIP_NAMES)})")
    return (
        tuple(name for name in SCENES if name in wanted),
        tuple(name for name in EXTRA_CLIPS if name in wanted),
    )


def encode_scene(path: Path, scene: Any) -> None:
    """A synthetic scene's frames (as ``bench speed`` renders them) encoded to H.264 (CRF 18) with PyAV."""
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=int(scene.fps))
        stream.width, stream.height = scene.camera.size
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}

        def encode(image: np.ndarray) -> None:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)

        render_clip(scene, on_frame=encode, keep=False)
        for packet in stream.encode():
            container.mux(packet)
