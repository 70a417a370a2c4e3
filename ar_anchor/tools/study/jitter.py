"""The ``jitter`` study: a static marker and a 2x2 board seen at several distances, tracked.

Each distance's view is rendered once and every frame adds fresh sensor noise; the tracker's raw
per-frame pose and its output give, per target and pipeline, the spread of the distance and of the
orientation, the flipped-frame rate, and (for the marker) the gap between the two IPPE solutions.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ...camera import CameraModel
from ...config import BoardConfig, TrackerConfig
from ...geometry import Pose, angle_between_deg, mean_rotation
from ...sources.base import Frame
from ...sources.synthetic import SyntheticSource
from ...synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory
from ...targets import TargetId
from . import interrupt
from .stats import Progress, finite

# The tracker takes a while to import (OpenCV): it is imported where the study runs, so that `ar-anchor`'s
# parser, which calls configure_parser, stays quick to build.
if TYPE_CHECKING:
    from ...track.tracker import Tracker

__all__ = [
    "FLIP_DEG",
    "JITTER_SERIES",
    "ONSET_FACTOR",
    "PIPELINES",
    "SETTLE_FRAMES",
    "STYLES",
    "JitterSetup",
    "run_jitter",
]

ONSET_FACTOR = 2.0  # orientation noise this far above the d^2 trend from the nearest distance: disproportionate
FLIP_DEG = 10.0  # a rotation error above this is a flip: the wrong planar solution (as in ar-anchor bench)
SETTLE_FRAMES = 30  # statistics start after the first second (the filter's convergence), as in ar-anchor bench


@dataclass(frozen=True)
class JitterSetup:
    """The static scene of the ``jitter`` study.

    A lone marker (id 0, ``marker_m``) and a 2x2 grid board of the same markers (ids 10-13, gaps of
    a fifth of a marker) side by side on a cluttered wall, seen by a static camera ``tilt_deg`` off
    their normal (about the vertical axis), aimed between them.
    """

    camera: CameraModel = field(default_factory=CameraModel.default_synthetic)
    config: TrackerConfig = field(default_factory=TrackerConfig)
    marker_m: float = 0.05
    distances_m: tuple[float, ...] = (0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0)
    frames: int = 300
    tilt_deg: float = 10.0
    sensor_noise: float = 2.0  # grey levels
    blur_px: float = 0.6
    fps: float = 30.0
    seed: int = 0
    roi: bool | None = None  # ROI tracking (region search between full-frame searches); None: the config's

    @property
    def board(self) -> BoardConfig:
        return BoardConfig(
            name="study",
            cols=2,
            rows=2,
            marker_length_m=self.marker_m,
            separation_m=self.marker_m / 5.0,
            first_id=10,
            dictionary=self.config.detector.dictionary,
        )

    def scene(self) -> tuple[SyntheticScene, np.ndarray]:
        """The scene (no noise: it is added per frame) and the point the camera looks at."""
        length, board = self.marker_m, self.board
        width, height = board.size_m
        # lone marker's quiet zone (L/6), the board's paper margin and a gap of L/4 between them
        margin = max(board.separation_m, length / 4.0)
        marker_x = -(length / 2.0 + length / 6.0 + margin + length / 4.0)
        flip_yz = np.diag([1.0, -1.0, -1.0])  # board frame: y down, z into the wall
        scene = SyntheticScene(
            camera=self.camera,
            dictionary=self.config.detector.dictionary,
            markers=(PlacedMarker(0, length, Pose(np.zeros(3), np.array([marker_x, 0.0, 0.0]))),),
            boards=(PlacedBoard(board, Pose.from_matrix(flip_yz, np.array([0.0, height / 2.0, 0.0]))),),
            frames=0,
            seed=self.seed,
            blur_sigma=self.blur_px,
        )
        return scene, np.array([(marker_x + width / 2.0) / 2.0, 0.0, 0.0])

    def tracker_config(self) -> TrackerConfig:
        """The user's (or default) tracker config, tracking exactly the scene's marker and board.

        ROI tracking as the config says unless ``roi`` is set (on or off).
        """
        config = self.config
        return dataclasses.replace(
            config,
            detector=dataclasses.replace(config.detector, roi=config.detector.roi if self.roi is None else self.roi),
            markers=dataclasses.replace(config.markers, length_m=self.marker_m, lengths_m={}, ids=(0,)),
            boards=(self.board,),
            filter=dataclasses.replace(config.filter, enabled=True),
        )

    def describe(self) -> dict[str, Any]:
        k = self.camera.camera_matrix
        return {
            "camera": f"{self.camera.width}x{self.camera.height} fx={k[0, 0]:g}",
            "config": self.config.source,
            "marker_m": self.marker_m,
            "board": f"2x2 of {self.marker_m * 100:g} cm markers, {self.marker_m * 20:g} cm gaps",
            "distances_m": list(self.distances_m),
            "frames": self.frames,
            "settle_frames": SETTLE_FRAMES,
            "tilt_deg": self.tilt_deg,
            "sensor_noise_grey": self.sensor_noise,
            "blur_px": self.blur_px,
            "fps": self.fps,
            "seed": self.seed,
            "roi": self.config.detector.roi if self.roi is None else self.roi,
            "flip_deg": FLIP_DEG,
            "onset_factor": ONSET_FACTOR,
        }


JITTER_SERIES = (("marker", TargetId.marker(0)), ("board", TargetId.board("study")))
PIPELINES = ("raw", "tracker")

# the four series (target, pipeline) of the figure, the Markdown and the recording: colour, line, marker, label
STYLES = {
    ("marker", "raw"): ("tab:red", "-", "o", "marker, raw per-frame"),
    ("marker", "tracker"): ("tab:red", "--", "s", "marker, tracker"),
    ("board", "raw"): ("tab:blue", "-", "o", "2x2 board, raw per-frame"),
    ("board", "tracker"): ("tab:blue", "--", "s", "2x2 board, tracker"),
}


def _static_metrics(poses: Sequence[Pose | None], truth: Pose | None) -> dict[str, Any]:
    """Spread of a static target's poses: std of ``||t||``, RMS angle about the mean rotation, flips."""
    measured = [p for p in poses if p is not None]
    out: dict[str, Any] = {"frames": len(measured), "detected_pct": 100.0 * len(measured) / max(len(poses), 1)}
    if len(measured) < 2 or truth is None:
        return out
    distances = np.array([np.linalg.norm(p.tvec) for p in measured])
    mean = mean_rotation([p.rotation for p in measured])
    spread = np.array([angle_between_deg(p.rotation, mean) for p in measured])
    errors = np.array([angle_between_deg(p.rotation, truth.rotation) for p in measured])
    out.update(
        {
            "distance_std_mm": 1e3 * float(np.std(distances)),
            "distance_bias_mm": 1e3 * float(np.mean(distances) - np.linalg.norm(truth.tvec)),
            "rotation_std_deg": float(np.sqrt(np.mean(spread**2))),
            "rotation_error_median_deg": float(np.median(errors)),
            "flipped_pct": 100.0 * float(np.mean(errors > FLIP_DEG)),
        }
    )
    return out


def _noisy(clean: np.ndarray, noise: np.ndarray, sigma: float) -> np.ndarray:
    """``clean`` plus fresh Gaussian noise of ``sigma`` grey levels, rounded and saturated to uint8.

    ``cv2.randn`` (OpenCV's per-thread generator, seeded once per distance) is three times faster
    than numpy's here, and rendering cost decides whether the study fits its time budget.
    """
    if sigma <= 0:
        return clean.copy()
    cv2.randn(noise.reshape(noise.shape[0], -1), 0.0, sigma)  # one channel: a scalar sigma covers every value
    return cv2.add(clean, noise, dtype=cv2.CV_8U)


def run_jitter(
    setup: JitterSetup, *, progress: Progress | None = None, on_frame: Callable[..., None] | None = None
) -> dict[str, Any]:
    """Track the static scene at each distance; spread of the raw and tracked poses of marker and board.

    ``on_frame(distance_index, frame_index, result, truth)`` is called for each frame (for the
    recording) when given. The result's ``views`` holds each distance's noise-free image (for the
    recording; not JSON).
    """
    from ...track.tracker import Tracker

    scene, aim = setup.scene()
    source = SyntheticSource(scene)
    config = setup.tracker_config()
    length, focal = setup.marker_m, float(setup.camera.camera_matrix[0, 0])
    rows = []
    views = []
    for d_index, distance in enumerate(setup.distances_m):
        if progress is not None:
            progress(f"jitter: {distance:g} m ({d_index + 1}/{len(setup.distances_m)})")
        trajectory = Trajectory(
            kind="static", near_m=distance, azimuth_deg=setup.tilt_deg, elevation_deg=0.0, roll_deg=0.0, look_at=aim
        )
        camera_from_world = trajectory.camera_from_world(0.0)
        clean = source.render_view(camera_from_world)
        truth = source.truth(camera_from_world)
        views.append(clean)
        noise_free_margin = _noise_free_margin(Tracker(config, setup.camera), clean, truth)
        tracker = Tracker(config, setup.camera)
        cv2.setRNGSeed(int(setup.seed) * 1000 + d_index)
        noise = np.empty(clean.shape, np.float32)
        series: dict[tuple[str, str], list[Pose | None]] = {(t, p): [] for t, _ in JITTER_SERIES for p in PIPELINES}
        gaps: list[float] = []
        states: list[str] = []
        for index in range(setup.frames):
            interrupt.check()
            image = _noisy(clean, noise, setup.sensor_noise)
            frame = Frame(image, index, int(round(index * 1e9 / setup.fps)), truth)
            result = tracker.process(frame)
            if on_frame is not None:
                on_frame(d_index, index, result, truth)
            if index < SETTLE_FRAMES:
                continue
            for short, name in JITTER_SERIES:
                target = result.targets.get(name)
                series[short, "raw"].append(target.raw if target is not None else None)
                series[short, "tracker"].append(target.pose if target is not None else None)
            marker = result.targets.get(TargetId.marker(0))
            states.append(marker.state if marker is not None else "")
            hyps = marker.hypotheses if marker is not None else ()
            gaps.append(hyps[1].reproj_px - hyps[0].reproj_px if len(hyps) == 2 else math.nan)
        row: dict[str, Any] = {"distance_m": distance, "marker_px": focal * length / distance}
        for short, name in JITTER_SERIES:
            for pipeline in PIPELINES:
                row[f"{short}_{pipeline}"] = _static_metrics(series[short, pipeline], truth.get(name))
        finite_gaps = [g for g in gaps if math.isfinite(g)]
        row["marker_gap_median_px"] = float(np.median(finite_gaps)) if finite_gaps else None
        row["marker_noise_free_margin_px"] = noise_free_margin
        settled = [s for s in states if s]
        row["marker_tracker_states_pct"] = {
            state: 100.0 * settled.count(state) / max(len(settled), 1)
            for state in ("tracked", "ambiguous", "predicted")
        }
        rows.append(row)
    return {
        "study": "jitter",
        "settings": setup.describe(),
        "distances": rows,
        "summary": _jitter_summary(rows, setup.config.filter.decide_margin_px),
        "views": views,
    }


def _noise_free_margin(tracker: Tracker, clean: np.ndarray, truth: dict[str, Pose]) -> float | None:
    """On the noise-free view: how much better (px) the marker's IPPE solution nearer the truth reprojects
    than the other (negative: the wrong one wins even without noise; None: a single solution or none)."""
    marker = tracker.process(Frame(clean, 0, 0, truth)).targets.get(TargetId.marker(0))
    true = truth.get(TargetId.marker(0))
    if marker is None or true is None or len(marker.hypotheses) != 2:
        return None
    right, wrong = sorted(marker.hypotheses, key=lambda h: angle_between_deg(h.pose.rotation, true.rotation))
    return float(wrong.reproj_px - right.reproj_px)


def _jitter_summary(rows: Sequence[dict[str, Any]], decide_margin_px: float) -> dict[str, Any]:
    def values(key: str, metric: str) -> list[float]:
        return [r[key].get(metric, math.nan) for r in rows]

    raw = values("marker_raw", "rotation_std_deg")
    summary: dict[str, Any] = {"decide_margin_px": decide_margin_px}
    # ambiguity onset: orientation noise outgrowing the d^2 law of a well-conditioned planar pose
    onset = None
    if rows and math.isfinite(raw[0]):
        d0 = rows[0]["distance_m"]
        for row, value in zip(rows[1:], raw[1:]):
            if value > ONSET_FACTOR * raw[0] * (row["distance_m"] / d0) ** 2:
                onset = row["distance_m"]
                break
    summary["onset_noise_m"] = onset
    summary["onset_gap_m"] = next(
        (
            r["distance_m"]
            for r in rows
            if r["marker_gap_median_px"] is not None and r["marker_gap_median_px"] < decide_margin_px
        ),
        None,
    )
    steps = [b >= a for a, b in zip(raw, raw[1:])]
    summary["raw_marker_rotation_std_near_far_deg"] = [finite(raw[0]), finite(raw[-1])] if rows else None
    summary["raw_marker_growth_steps"] = f"{sum(steps)} of {len(steps)}"
    for short in ("marker", "board"):
        r_far = rows[-1][f"{short}_raw"].get("rotation_std_deg", math.nan) if rows else math.nan
        t_far = rows[-1][f"{short}_tracker"].get("rotation_std_deg", math.nan) if rows else math.nan
        summary[f"{short}_raw_over_tracker_far"] = finite(r_far / t_far) if t_far and t_far > 0 else None
    for pipeline in PIPELINES:
        for metric in ("rotation_std_deg", "distance_std_mm"):
            pairs = zip(values(f"board_{pipeline}", metric), values(f"marker_{pipeline}", metric))
            summary[f"board_not_below_marker_{pipeline}_{metric}"] = [
                r["distance_m"] for r, (b, m) in zip(rows, pairs) if not b < m
            ]
    return summary
