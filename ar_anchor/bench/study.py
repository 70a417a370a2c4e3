"""``ar-anchor study``: the PnP textbook's experiments, reproduced with our own code.

Three studies, each writing ``<name>.png`` (figure), ``<name>.md`` (table and the facts it shows),
``<name>.json`` (settings, every raw number, summary) and ``<name>.rrd`` (rerun recording) to ``--out``:

``outliers``
    Points 4-8 m ahead of a 1920x1080 camera (fx = fy = 1480), 0.5 px pixel noise, a quarter of the
    correspondences replaced by uniform random pixels: plain ``solvePnP`` against ``solvePnPRansac``
    (2 px, 300 iterations) followed by ``solvePnPRefineLM`` on its inliers, over many seeds.
    The points are drawn in the camera frame (a uniform pixel and a uniform depth in 4-8 m, so every
    point is in view) and expressed in the world frame with the inverse of the true pose
    ``camera_from_world`` (rvec (0.10, -0.30, 0.05), tvec (0.20, -0.10, 0.50)); the true pose maps
    them back into view.
``ransac``
    The same problem over a grid of contamination x inlier threshold: median translation error,
    inlier recall (share of the honest points RANSAC keeps) and the share of seeds that succeed.
``jitter``
    A lone 5 cm marker and a 2x2 board of the same markers, seen by a static synthetic camera
    (1280x720, fx = 1000) at 0.3-3 m; each distance's view is rendered once (blur included) and each of
    its frames adds fresh Gaussian sensor noise. The tracker (as configured: ROI tracking on by default) runs
    on those frames; its per-frame raw pose and its output give the spread of the distance ``||t||``
    and of the orientation for both pipelines, the flipped-frame rate and the ambiguity onset.

A seed fixes one problem: its points, pixel noise and the order in which points get contaminated
are drawn in a fixed sequence, so the same seed at a higher contamination replaces a superset of
the same points (common random numbers across the grid).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig, load_config
from ..errors import CameraError, InputError, OutputError
from ..geometry import Pose, angle_between_deg
from ..sources.base import Frame
from ..sources.synthetic import SyntheticSource
from ..synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory

# The tracker (and bench, which imports it) load scipy and filterpy: they are imported where a study
# runs, so that `ar-anchor`'s parser, which calls configure_parser, stays quick to build.
if TYPE_CHECKING:
    from ..track.tracker import Tracker

__all__ = [
    "DEFAULT_OUT",
    "STUDIES",
    "Correspondences",
    "JitterSetup",
    "PnPSetup",
    "PnPTrial",
    "configure_parser",
    "make_correspondences",
    "run_jitter",
    "run_outliers",
    "run_ransac",
    "run_study",
    "solve_trial",
]

STUDIES = ("outliers", "ransac", "jitter")
DEFAULT_OUT = Path("recordings") / "study"
SUCCESS_ERROR_M = 0.01  # a RANSAC trial succeeds with a translation error below 1 cm ...
SUCCESS_RECALL = 0.9  # ... keeping at least 90 % of the honest points
RANSAC_SAMPLE = 5  # points per minimal sample of OpenCV's solvePnPRansac (EPnP kernel)
# other least-squares solvers on all points, for context (none is robust to outliers)
OTHER_SOLVERS = (("epnp", cv2.SOLVEPNP_EPNP), ("sqpnp", cv2.SOLVEPNP_SQPNP))
ONSET_FACTOR = 2.0  # orientation noise this far above the d^2 trend from the nearest distance: disproportionate

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------- PnP problem (outliers, ransac)


def _textbook_pose() -> Pose:
    return Pose(np.array([0.10, -0.30, 0.05]), np.array([0.20, -0.10, 0.50]))


@dataclass(frozen=True)
class PnPSetup:
    """The synthetic PnP problem of the ``outliers`` and ``ransac`` studies.

    Attributes
    ----------
    camera : the camera the points are seen by (default 1920x1080, fx = fy = 1480, centred).
    points : correspondences per problem.
    near_m, far_m : depth range of the points in the camera frame, metres.
    noise_px : Gaussian pixel noise, standard deviation per coordinate, pixels.
    camera_from_world : the true pose.
    iterations, confidence : ``solvePnPRansac``'s iteration limit and confidence.
    """

    camera: CameraModel = field(default_factory=lambda: CameraModel.from_fov(1920, 1080, 1480.0))
    points: int = 120
    near_m: float = 4.0
    far_m: float = 8.0
    noise_px: float = 0.5
    camera_from_world: Pose = field(default_factory=_textbook_pose)
    iterations: int = 300
    confidence: float = 0.99

    def describe(self) -> dict[str, Any]:
        """JSON-ready description."""
        k = self.camera.camera_matrix
        return {
            "camera": f"{self.camera.width}x{self.camera.height} fx={k[0, 0]:g} fy={k[1, 1]:g} "
            f"cx={k[0, 2]:g} cy={k[1, 2]:g}",
            "image_size": list(self.camera.size),
            "points": self.points,
            "depth_m": [self.near_m, self.far_m],
            "noise_px": self.noise_px,
            "true_rvec": self.camera_from_world.rvec.tolist(),
            "true_tvec_m": self.camera_from_world.tvec.tolist(),
            "iterations": self.iterations,
            "confidence": self.confidence,
        }


@dataclass(frozen=True)
class Correspondences:
    """One PnP problem: ``points_in_world`` (N, 3), observed ``pixels`` (N, 2), ``honest`` (N,) bool
    (False: the pixel was replaced by a uniform random one)."""

    points_in_world: np.ndarray
    pixels: np.ndarray
    honest: np.ndarray


def make_correspondences(setup: PnPSetup, contamination: float, seed: int) -> Correspondences:
    """Draw a problem: points in view at ``near_m``-``far_m``, noisy pixels, ``contamination``
    (0..1) of them replaced by uniform random pixels. All draws happen in a fixed order, so one seed
    at a higher contamination replaces a superset of the points it replaces at a lower one."""
    rng = np.random.default_rng([seed, 0x57D7])
    n = setup.points
    width, height = setup.camera.size
    image_max = np.array([width - 1.0, height - 1.0])
    pixels_true = rng.uniform(0.0, 1.0, (n, 2)) * image_max
    depth = rng.uniform(setup.near_m, setup.far_m, n)
    noise = rng.standard_normal((n, 2)) * setup.noise_px
    order = rng.permutation(n)
    replacement = rng.uniform(0.0, 1.0, (n, 2)) * image_max
    rays = cv2.undistortPoints(
        pixels_true.reshape(-1, 1, 2), setup.camera.camera_matrix, setup.camera.dist_or_none
    ).reshape(-1, 2)
    points_in_camera = np.column_stack([rays, np.ones(n)]) * depth[:, None]
    points_in_world = setup.camera_from_world.inverse().apply(points_in_camera)
    # re-project through the true pose (exactly pixels_true up to rounding) and add the noise
    pixels = _project(setup.camera, setup.camera_from_world, points_in_world) + noise
    honest = np.ones(n, dtype=bool)
    replaced = order[: int(round(contamination * n))]
    pixels[replaced] = replacement[replaced]
    honest[replaced] = False
    return Correspondences(points_in_world, pixels, honest)


def _project(camera: CameraModel, camera_from_world: Pose, points_in_world: np.ndarray) -> np.ndarray:
    pixels, _ = cv2.projectPoints(
        points_in_world, camera_from_world.rvec, camera_from_world.tvec, camera.camera_matrix, camera.dist_or_none
    )
    return pixels.reshape(-1, 2)


@dataclass(frozen=True)
class PnPTrial:
    """The result of one problem. Errors are None when the solver found no pose.

    ``inliers`` / ``honest_inliers``: RANSAC's inlier set and the honest points in it;
    ``honest_within_refined``: honest points within the threshold of the refined pose (what a
    re-classification after the refinement would keep).
    """

    plain_error_m: float | None
    plain_rotation_deg: float | None
    ransac_error_m: float | None
    ransac_rotation_deg: float | None
    inliers: int
    honest_inliers: int
    honest: int
    honest_within_refined: int

    @property
    def recall(self) -> float:
        return self.honest_inliers / self.honest if self.honest else math.nan

    @property
    def precision(self) -> float:
        return self.honest_inliers / self.inliers if self.inliers else math.nan

    @property
    def succeeded(self) -> bool:
        return (
            self.ransac_error_m is not None and self.ransac_error_m < SUCCESS_ERROR_M and self.recall >= SUCCESS_RECALL
        )


def _errors(camera_from_world: Pose, rvec: np.ndarray, tvec: np.ndarray) -> tuple[float, float] | tuple[None, None]:
    estimate = Pose(rvec, tvec)
    if not estimate.is_finite():
        return None, None
    translation = float(np.linalg.norm(estimate.tvec - camera_from_world.tvec))
    return translation, angle_between_deg(estimate.rotation, camera_from_world.rotation)


def solve_plain(setup: PnPSetup, problem: Correspondences, flags: int) -> tuple[float, float] | tuple[None, None]:
    """(translation error m, rotation error deg) of plain ``solvePnP`` with ``flags`` on all points
    ((None, None) when it finds no pose)."""
    try:
        ok, rvec, tvec = cv2.solvePnP(
            problem.points_in_world, problem.pixels, setup.camera.camera_matrix, setup.camera.dist_or_none, flags=flags
        )
    except cv2.error:
        return None, None
    return _errors(setup.camera_from_world, rvec, tvec) if ok else (None, None)


def solve_trial(setup: PnPSetup, problem: Correspondences, threshold_px: float, *, plain: bool = True) -> PnPTrial:
    """Plain ``solvePnP`` (iterative, all points; skipped unless ``plain``) and ``solvePnPRansac``
    (``threshold_px``) followed by ``solvePnPRefineLM`` on RANSAC's inliers."""
    k, dist = setup.camera.camera_matrix, setup.camera.dist_or_none
    truth = setup.camera_from_world
    objects, pixels = problem.points_in_world, problem.pixels
    plain_error, plain_rotation = solve_plain(setup, problem, cv2.SOLVEPNP_ITERATIVE) if plain else (None, None)
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            objects,
            pixels,
            k,
            dist,
            iterationsCount=setup.iterations,
            reprojectionError=threshold_px,
            confidence=setup.confidence,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
    except cv2.error:
        ok, inliers = False, None
    honest = int(problem.honest.sum())
    if not ok or inliers is None or len(inliers) < 4:
        return PnPTrial(plain_error, plain_rotation, None, None, 0, 0, honest, 0)
    inliers = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(objects[inliers], pixels[inliers], k, dist, rvec.copy(), tvec.copy())
    ransac_error, ransac_rotation = _errors(truth, rvec, tvec)
    residual = np.linalg.norm(_project(setup.camera, Pose(rvec, tvec), objects) - pixels, axis=1)
    return PnPTrial(
        plain_error,
        plain_rotation,
        ransac_error,
        ransac_rotation,
        int(len(inliers)),
        int(problem.honest[inliers].sum()),
        honest,
        int(np.sum(problem.honest & (residual <= threshold_px))),
    )


def _failures_last(values: Sequence[float | None]) -> np.ndarray:
    """Errors with failed solves as +inf (a failure is worse than any error)."""
    return np.array([math.inf if v is None else v for v in values], dtype=np.float64)


def _spread(values: Sequence[float | None]) -> dict[str, float | int | None]:
    """Median, 10th and 90th percentile and maximum (failures count as +inf), and the failure count."""
    array = _failures_last(values)
    if array.size == 0:
        return {"median": None, "p10": None, "p90": None, "max": None, "failed": 0}
    return {
        "median": _percentile(array, 50),
        "p10": _percentile(array, 10),
        "p90": _percentile(array, 90),
        "max": _finite(np.max(array)),
        "failed": int(np.sum(~np.isfinite(array))),
    }


def _percentile(array: np.ndarray, q: float) -> float | None:
    """Percentile of errors with failures as +inf; None when it falls among the failures."""
    with np.errstate(invalid="ignore"):  # inf - inf between two failures: NaN, i.e. a failure
        value = float(np.percentile(array, q))
    return value if math.isfinite(value) else None


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


# ---------------------------------------------------------------------------- study 1: outliers


def run_outliers(
    setup: PnPSetup,
    *,
    seeds: int,
    contamination: float,
    threshold_px: float,
    first_seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Plain ``solvePnP`` vs RANSAC + LM refinement over ``seeds`` problems; per-seed numbers and summary."""
    rows = []
    for i in range(seeds):
        seed = first_seed + i
        if progress is not None and (i % max(seeds // 4, 1) == 0):
            progress(f"outliers: seed {i + 1}/{seeds}")
        problem = make_correspondences(setup, contamination, seed)
        trial = solve_trial(setup, problem, threshold_px)
        others = {f"{name}_error_m": solve_plain(setup, problem, flags)[0] for name, flags in OTHER_SOLVERS}
        rows.append({"seed": seed, **dataclasses.asdict(trial), "recall": trial.recall, **others})
    honest = rows[0]["honest"] if rows else 0
    all_recovered = [r["honest_inliers"] == r["honest"] for r in rows]
    summary = {
        "plain_error_m": _spread([r["plain_error_m"] for r in rows]),
        **{f"{name}_error_m": _spread([r[f"{name}_error_m"] for r in rows]) for name, _ in OTHER_SOLVERS},
        "ransac_error_m": _spread([r["ransac_error_m"] for r in rows]),
        "plain_rotation_deg": _spread([r["plain_rotation_deg"] for r in rows]),
        "ransac_rotation_deg": _spread([r["ransac_rotation_deg"] for r in rows]),
        "inliers": _spread([r["inliers"] for r in rows]),
        "honest_inliers": _spread([r["honest_inliers"] for r in rows]),
        "honest_points": honest,
        "all_honest_recovered_pct": 100.0 * float(np.mean(all_recovered)) if rows else None,
        "at_most_one_honest_missed_pct": 100.0 * float(np.mean([r["honest"] - r["honest_inliers"] <= 1 for r in rows]))
        if rows
        else None,
        "all_honest_within_refined_pct": 100.0
        * float(np.mean([r["honest_within_refined"] == r["honest"] for r in rows]))
        if rows
        else None,
        "replaced_admitted_max": max((r["inliers"] - r["honest_inliers"] for r in rows), default=0),
    }
    return {
        "study": "outliers",
        "settings": {
            **setup.describe(),
            "seeds": seeds,
            "first_seed": first_seed,
            "contamination": contamination,
            "threshold_px": threshold_px,
        },
        "seeds": rows,
        "summary": summary,
    }


# ---------------------------------------------------------------------------- study 2: ransac


def clean_sample_probability(contamination: float, iterations: int, sample: int = RANSAC_SAMPLE) -> float:
    """Chance that ``iterations`` random minimal samples include at least one free of outliers."""
    return 1.0 - (1.0 - (1.0 - contamination) ** sample) ** iterations


def recall_bound(threshold_px: float, noise_px: float) -> float:
    """Share of honest points within ``threshold_px`` of their true projection (isotropic Gaussian
    noise ``noise_px`` per coordinate: a Rayleigh distance), the recall of even a perfect pose."""
    if noise_px <= 0:
        return 1.0
    return 1.0 - math.exp(-(threshold_px**2) / (2.0 * noise_px**2))


def run_ransac(
    setup: PnPSetup,
    *,
    seeds: int,
    contaminations: Sequence[float],
    thresholds_px: Sequence[float],
    default_threshold_px: float,
    first_seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """RANSAC + LM over contamination x threshold (the same ``seeds`` problems in every cell)."""
    cells = []
    for t_index, threshold in enumerate(thresholds_px):
        if progress is not None:
            progress(f"ransac: threshold {threshold:g} px ({t_index + 1}/{len(thresholds_px)})")
        for contamination in contaminations:
            trials = [
                solve_trial(setup, make_correspondences(setup, contamination, first_seed + i), threshold, plain=False)
                for i in range(seeds)
            ]
            errors = [t.ransac_error_m for t in trials]
            recalls = [t.recall for t in trials]
            precisions = [t.precision for t in trials]
            cells.append(
                {
                    "threshold_px": threshold,
                    "contamination_pct": 100.0 * contamination,
                    "median_error_m": _spread(errors)["median"],
                    "median_recall": float(np.median(recalls)),
                    "median_precision": _finite(np.nanmedian(precisions)) if any(t.inliers for t in trials) else None,
                    "success_pct": 100.0 * float(np.mean([t.succeeded for t in trials])),
                    "failed_solves": sum(e is None for e in errors),
                    "errors_m": errors,
                    "recalls": recalls,
                }
            )
    summary: dict[str, Any] = {"thresholds": {}}
    for threshold in thresholds_px:
        row = [c for c in cells if c["threshold_px"] == threshold]
        failing = [c["contamination_pct"] for c in row if c["success_pct"] < 50.0]
        summary["thresholds"][f"{threshold:g}"] = {
            "first_failing_contamination_pct": min(failing) if failing else None,
            "succeeds_up_to_pct": _succeeds_up_to(row, 50.0),
            "reliable_up_to_pct": _succeeds_up_to(row, 90.0),
            "recall_at_lowest_contamination": row[0]["median_recall"] if row else None,
            "recall_bound": recall_bound(threshold, setup.noise_px),
        }
    summary["default_threshold_px"] = default_threshold_px
    summary["clean_sample_probability"] = {
        f"{100.0 * c:g}": clean_sample_probability(c, setup.iterations) for c in contaminations
    }
    return {
        "study": "ransac",
        "settings": {
            **setup.describe(),
            "seeds": seeds,
            "first_seed": first_seed,
            "contaminations_pct": [100.0 * c for c in contaminations],
            "thresholds_px": list(thresholds_px),
            "success": f"translation error < {SUCCESS_ERROR_M * 100:g} cm and recall >= {SUCCESS_RECALL:.0%}",
        },
        "cells": cells,
        "summary": summary,
    }


def _succeeds_up_to(row: Sequence[dict[str, Any]], min_success_pct: float) -> float | None:
    """The highest contamination up to which every cell of a threshold's row succeeds (None: not even the first)."""
    best = None
    for cell in row:
        if cell["success_pct"] < min_success_pct:
            break
        best = cell["contamination_pct"]
    return best


# ---------------------------------------------------------------------------- study 3: jitter


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
        from .stability import FLIP_DEG, SETTLE_FRAMES

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


JITTER_SERIES = (("marker", "marker:0"), ("board", "board:study"))
PIPELINES = ("raw", "tracker")


def _static_metrics(poses: Sequence[Pose | None], truth: Pose | None) -> dict[str, Any]:
    """Spread of a static target's poses: std of ``||t||``, RMS angle about the mean rotation, flips."""
    from .stability import FLIP_DEG, _mean_rotation

    measured = [p for p in poses if p is not None]
    out: dict[str, Any] = {"frames": len(measured), "detected_pct": 100.0 * len(measured) / max(len(poses), 1)}
    if len(measured) < 2 or truth is None:
        return out
    distances = np.array([np.linalg.norm(p.tvec) for p in measured])
    mean = _mean_rotation([p.rotation for p in measured])
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
    from ..track.tracker import Tracker
    from .stability import SETTLE_FRAMES

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
            marker = result.targets.get("marker:0")
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
    marker = tracker.process(Frame(clean, 0, 0, truth)).targets.get("marker:0")
    true = truth.get("marker:0")
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
    summary["raw_marker_rotation_std_near_far_deg"] = [_finite(raw[0]), _finite(raw[-1])] if rows else None
    summary["raw_marker_growth_steps"] = f"{sum(steps)} of {len(steps)}"
    for short in ("marker", "board"):
        r_far = rows[-1][f"{short}_raw"].get("rotation_std_deg", math.nan) if rows else math.nan
        t_far = rows[-1][f"{short}_tracker"].get("rotation_std_deg", math.nan) if rows else math.nan
        summary[f"{short}_raw_over_tracker_far"] = _finite(r_far / t_far) if t_far and t_far > 0 else None
    for pipeline in PIPELINES:
        for metric in ("rotation_std_deg", "distance_std_mm"):
            pairs = zip(values(f"board_{pipeline}", metric), values(f"marker_{pipeline}", metric))
            summary[f"board_not_below_marker_{pipeline}_{metric}"] = [
                r["distance_m"] for r, (b, m) in zip(rows, pairs) if not b < m
            ]
    return summary


# ---------------------------------------------------------------------------- figures


def _figure(width_in: float, height_in: float, columns: int) -> tuple[Any, Any]:
    from matplotlib.figure import Figure  # no pyplot: no global state, no display backend

    figure = Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    return figure, figure.subplots(1, columns)


def _save(figure: Any, path: Path) -> None:
    figure.savefig(path, dpi=100)


def plot_outliers(result: dict[str, Any], path: Path) -> None:
    """Per-seed translation errors (log scale) and RANSAC's inlier counts."""
    rows, settings = result["seeds"], result["settings"]
    figure, (errors_ax, inliers_ax) = _figure(11.0, 4.2, 2)
    rng = np.random.default_rng(0)
    for position, (key, colour) in enumerate((("plain_error_m", "tab:red"), ("ransac_error_m", "tab:blue"))):
        values = np.array([r[key] for r in rows if r[key] is not None])
        errors_ax.scatter(position + rng.uniform(-0.15, 0.15, values.size), values, s=10, alpha=0.6, color=colour)
        if values.size:
            errors_ax.hlines(np.median(values), position - 0.3, position + 0.3, color="black", linewidth=2)
            errors_ax.annotate(
                _metres(float(np.median(values))),
                (position + 0.32, float(np.median(values))),
                va="center",
                fontsize=9,
            )
    errors_ax.set_yscale("log")
    errors_ax.set_xticks([0, 1], ["solvePnP\n(all points)", "solvePnPRansac\n+ RefineLM"])
    errors_ax.set_xlim(-0.6, 1.9)
    errors_ax.set_ylabel("translation error (m, log)")
    errors_ax.set_title(f"{len(rows)} seeds, {settings['contamination']:.0%} of points replaced; bar: median")
    errors_ax.grid(True, axis="y", which="both", alpha=0.3)
    honest = result["summary"]["honest_points"]
    counts = np.array([r["inliers"] for r in rows])
    honest_counts = np.array([r["honest_inliers"] for r in rows])
    low = int(min(counts.min(initial=honest), honest_counts.min(initial=honest))) - 1
    bins = np.arange(low, int(counts.max(initial=honest)) + 2) - 0.5
    inliers_ax.hist(counts, bins=bins, color="tab:blue", alpha=0.6, label="RANSAC inliers")
    inliers_ax.hist(honest_counts, bins=bins, histtype="step", color="black", linewidth=1.5, label="honest among them")
    inliers_ax.axvline(honest, color="tab:green", linestyle="--", label=f"{honest} honest points")
    inliers_ax.set_xlabel("points")
    inliers_ax.set_ylabel("seeds")
    inliers_ax.set_title(f"inlier threshold {settings['threshold_px']:g} px, {settings['iterations']} iterations")
    inliers_ax.legend(fontsize=8)
    _save(figure, path)


def plot_ransac(result: dict[str, Any], path: Path) -> None:
    """Heatmaps over contamination x threshold: median translation error and median recall."""
    thresholds = result["settings"]["thresholds_px"]
    contaminations = result["settings"]["contaminations_pct"]
    error = np.full((len(thresholds), len(contaminations)), np.nan)
    recall = np.full_like(error, np.nan)
    success = np.full_like(error, np.nan)
    for cell in result["cells"]:
        i, j = thresholds.index(cell["threshold_px"]), contaminations.index(cell["contamination_pct"])
        error[i, j] = math.inf if cell["median_error_m"] is None else cell["median_error_m"]
        recall[i, j] = cell["median_recall"]
        success[i, j] = cell["success_pct"]
    from matplotlib.colors import LogNorm

    figure, (error_ax, recall_ax) = _figure(13.0, 4.6, 2)
    shown = np.where(np.isfinite(error), error * 1e3, 1e4)
    image = error_ax.imshow(shown, cmap="viridis_r", norm=LogNorm(vmin=0.3, vmax=1e4), aspect="auto")
    figure.colorbar(image, ax=error_ax, label="median translation error (mm, log)")
    image = recall_ax.imshow(recall, cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    figure.colorbar(image, ax=recall_ax, label="median inlier recall")
    for ax, values, title in (
        (error_ax, error, "translation error after RANSAC + LM"),
        (recall_ax, recall, "inlier recall (honest points kept)"),
    ):
        for i in range(len(thresholds)):
            for j in range(len(contaminations)):
                if ax is error_ax:
                    text = "fail" if not np.isfinite(values[i, j]) else f"{values[i, j] * 1e3:.3g}"
                else:
                    text = f"{values[i, j]:.2f}"
                if success[i, j] < 50.0:
                    text += "\n✗"
                if ax is error_ax:
                    dark = not np.isfinite(values[i, j]) or values[i, j] > 0.05
                else:
                    dark = values[i, j] < 0.5
                ax.text(j, i, text, ha="center", va="center", fontsize=7, color="white" if dark else "black")
        ax.set_xticks(range(len(contaminations)), [f"{c:g}" for c in contaminations])
        ax.set_yticks(range(len(thresholds)), [f"{t:g}" for t in thresholds])
        ax.set_xlabel("contamination (% of points replaced)")
        ax.set_ylabel("inlier threshold (px)")
        ax.set_title(title)
    figure.suptitle(
        f"{result['settings']['seeds']} seeds per cell, pixel noise {result['settings']['noise_px']:g} px, "
        f"{result['settings']['iterations']} iterations; ✗: fewer than half the seeds succeed "
        f"(error < {SUCCESS_ERROR_M * 100:g} cm and recall >= {SUCCESS_RECALL:.0%})",
        fontsize=10,
    )
    _save(figure, path)


_STYLES = {
    ("marker", "raw"): ("tab:red", "-", "o", "marker, raw per-frame"),
    ("marker", "tracker"): ("tab:red", "--", "s", "marker, tracker"),
    ("board", "raw"): ("tab:blue", "-", "o", "2x2 board, raw per-frame"),
    ("board", "tracker"): ("tab:blue", "--", "s", "2x2 board, tracker"),
}


def plot_jitter(result: dict[str, Any], path: Path) -> None:
    """Std of ||t|| and of orientation, and the flipped-frame rate, versus distance."""
    rows, summary = result["distances"], result["summary"]
    distances = [r["distance_m"] for r in rows]
    figure, axes = _figure(15.0, 4.6, 3)
    for ax, metric, label in (
        (axes[0], "distance_std_mm", "std of distance ||t|| (mm)"),
        (axes[1], "rotation_std_deg", "orientation std (deg, RMS about the mean)"),
        (axes[2], "flipped_pct", f"flipped frames (% > {result['settings']['flip_deg']:g} deg off)"),
    ):
        for (target, pipeline), (colour, line, marker, name) in _STYLES.items():
            values = [r[f"{target}_{pipeline}"].get(metric, math.nan) for r in rows]
            ax.plot(distances, values, color=colour, linestyle=line, marker=marker, markersize=4, label=name)
        ax.set_xlabel("distance (m)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if metric != "flipped_pct":
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xticks(distances, [f"{d:g}" for d in distances], fontsize=7)
            ax.minorticks_off()
        if metric == "rotation_std_deg" and rows and rows[0]["marker_raw"].get(metric) is not None:
            near = rows[0]["marker_raw"][metric]
            trend = [ONSET_FACTOR * near * (d / distances[0]) ** 2 for d in distances]
            ax.plot(distances, trend, color="grey", linewidth=0.8, label=f"{ONSET_FACTOR:g}x d² trend of marker raw")
        for key, style, text in (("onset_noise_m", "-.", "noise onset"), ("onset_gap_m", ":", "IPPE gap < margin")):
            if summary.get(key) is not None:
                ax.axvline(
                    summary[key], color="grey", linestyle=style, linewidth=1.2, label=f"{text} {summary[key]:g} m"
                )
    axes[1].legend(fontsize=7)
    settings = result["settings"]
    figure.suptitle(
        f"static {settings['marker_m'] * 100:g} cm marker and 2x2 board, {settings['camera']}, "
        f"{settings['tilt_deg']:g} deg off-axis, {settings['frames']} frames per distance "
        f"(first {settings['settle_frames']} skipped), noise {settings['sensor_noise_grey']:g} grey levels",
        fontsize=10,
    )
    _save(figure, path)


# ---------------------------------------------------------------------------- markdown


def _metres(value: float | None) -> str:
    if value is None:
        return "failed"
    if value >= 1.0:
        return f"{value:.2f} m"
    if value >= 0.01:
        return f"{value * 100:.1f} cm"
    return f"{value * 1e3:.2f} mm"


def _num(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def outliers_markdown(result: dict[str, Any]) -> str:
    s, summary = result["settings"], result["summary"]
    plain, ransac = summary["plain_error_m"], summary["ransac_error_m"]
    inliers, honest_inliers = summary["inliers"], summary["honest_inliers"]
    honest = summary["honest_points"]
    lines = [
        "# Outlier rescue: least squares vs RANSAC",
        "",
        _produced(result),
        "",
        f"{s['points']} points at {s['depth_m'][0]:g}-{s['depth_m'][1]:g} m depth, drawn in the camera frame (uniform "
        "pixel, uniform depth) and expressed in the world frame with the inverse of the true pose "
        f"(rvec {_vector(s['true_rvec'])}, tvec {_vector(s['true_tvec_m'])} m); camera {s['camera']}; "
        f"pixel noise {s['noise_px']:g} px per coordinate; {s['contamination']:.0%} of the correspondences "
        f"replaced by uniform random pixels. Plain `solvePnP` (iterative) uses all points; `solvePnPRansac` "
        f"({s['threshold_px']:g} px, {s['iterations']} iterations, confidence {s['confidence']:g}) is followed by "
        "`solvePnPRefineLM` on its inliers. Translation error: `||t - t_true||`.",
        "",
        "![outliers](outliers.png)",
        "",
        f"| over {s['seeds']} seeds | median | 10th pct | 90th pct | max |",
        "|---|---|---|---|---|",
        f"| translation error, `solvePnP` | {_metres(plain['median'])} | {_metres(plain['p10'])} "
        f"| {_metres(plain['p90'])} | {_metres(plain['max'])} |",
        *[
            f"| translation error, `solvePnP` {name.upper()} | {_metres(summary[f'{name}_error_m']['median'])} "
            f"| {_metres(summary[f'{name}_error_m']['p10'])} | {_metres(summary[f'{name}_error_m']['p90'])} "
            f"| {_metres(summary[f'{name}_error_m']['max'])} |"
            for name, _ in OTHER_SOLVERS
        ],
        f"| translation error, RANSAC + LM | {_metres(ransac['median'])} | {_metres(ransac['p10'])} "
        f"| {_metres(ransac['p90'])} | {_metres(ransac['max'])} |",
        f"| rotation error, `solvePnP` (deg) | {_num(summary['plain_rotation_deg']['median'])} "
        f"| {_num(summary['plain_rotation_deg']['p10'])} | {_num(summary['plain_rotation_deg']['p90'])} "
        f"| {_num(summary['plain_rotation_deg']['max'])} |",
        f"| rotation error, RANSAC + LM (deg) | {_num(summary['ransac_rotation_deg']['median'], 4)} "
        f"| {_num(summary['ransac_rotation_deg']['p10'], 4)} | {_num(summary['ransac_rotation_deg']['p90'], 4)} "
        f"| {_num(summary['ransac_rotation_deg']['max'], 4)} |",
        f"| RANSAC inliers | {_num(inliers['median'], 0)} | {_num(inliers['p10'], 0)} | {_num(inliers['p90'], 0)} "
        f"| {_num(inliers['max'], 0)} |",
        f"| honest points among them (of {honest}) | {_num(honest_inliers['median'], 0)} "
        f"| {_num(honest_inliers['p10'], 0)} | {_num(honest_inliers['p90'], 0)} | {_num(honest_inliers['max'], 0)} |",
        "",
        "What this shows:",
        "",
        f"- {s['contamination']:.0%} of wrong correspondences drag least squares off by {_metres(plain['median'])} "
        f"(median; 10-90 % of seeds: {_metres(plain['p10'])} to {_metres(plain['p90'])}; the non-iterative "
        + " and ".join(f"{n.upper()} {_metres(summary[f'{n}_error_m']['median'])}" for n, _ in OTHER_SOLVERS)
        + f"); RANSAC + LM recovers "
        f"{_metres(ransac['median'])} (90th percentile {_metres(ransac['p90'])}). "
        f"{ransac['failed']} RANSAC and {plain['failed']} `solvePnP` solves failed outright.",
        f"- RANSAC keeps all {honest} honest points in {summary['all_honest_recovered_pct']:.0f} % of the seeds and "
        f"misses at most one in {summary['at_most_one_honest_missed_pct']:.0f} %; "
        + (
            "no replaced point slipped into an inlier set. "
            if summary["replaced_admitted_max"] == 0
            else f"at most {summary['replaced_admitted_max']} replaced point(s) slipped into an inlier set. "
        )
        + "The inlier set is "
        "the one of RANSAC's best minimal-sample model, which is itself noisy: at the refined pose, all honest "
        f"points lie within the threshold in {summary['all_honest_within_refined_pct']:.0f} % of the seeds.",
        "",
    ]
    return "\n".join(lines)


def ransac_markdown(result: dict[str, Any]) -> str:
    s, summary = result["settings"], result["summary"]
    thresholds, contaminations = s["thresholds_px"], s["contaminations_pct"]
    cells = {(c["threshold_px"], c["contamination_pct"]): c for c in result["cells"]}
    default = summary["default_threshold_px"]
    d = summary["thresholds"][f"{default:g}"]
    lowest = summary["thresholds"][f"{thresholds[0]:g}"]
    header = "| threshold \\ contamination | " + " | ".join(f"{c:g} %" for c in contaminations) + " |"
    rule = "|---|" + "---|" * len(contaminations)

    def table(fmt: Callable[[dict[str, Any]], str]) -> list[str]:
        return [header, rule] + [
            f"| {t:g} px | " + " | ".join(fmt(cells[t, c]) for c in contaminations) + " |" for t in thresholds
        ]

    clean = summary["clean_sample_probability"]
    failing = d["first_failing_contamination_pct"]
    lines = [
        "# RANSAC inlier threshold vs contamination",
        "",
        _produced(result),
        "",
        f"The problem of the [outliers study](outliers.md) ({s['points']} points, {s['noise_px']:g} px noise, camera "
        f"{s['camera']}), {s['seeds']} seeds per cell (the same problems in every cell of a column), "
        f"`solvePnPRansac` with {s['iterations']} iterations then `solvePnPRefineLM` on its inliers. "
        "*Recall*: share of the honest (not replaced) points that RANSAC marks inlier. A seed *succeeds* "
        f"when its {s['success']}; a cell fails when fewer than half its seeds succeed.",
        "",
        "![ransac](ransac.png)",
        "",
        "Median translation error (mm; *fail*: more than half the solves failed):",
        "",
        *table(lambda c: "fail" if c["median_error_m"] is None else f"{c['median_error_m'] * 1e3:.3g}"),
        "",
        "Median inlier recall:",
        "",
        *table(lambda c: f"{c['median_recall']:.2f}"),
        "",
        "Seeds that succeed (%):",
        "",
        *table(lambda c: f"{c['success_pct']:.0f}"),
        "",
        "What this shows:",
        "",
    ]
    up_to = {t: summary["thresholds"][f"{t:g}"]["succeeds_up_to_pct"] for t in thresholds}
    wide = [t for t in thresholds if t >= default]
    lines.append(
        "- Thresholds >= "
        f"{default:g} px succeed up to "
        + ", ".join(f"{_num(up_to[t], 0)} % ({t:g} px)" for t in wide)
        + " contamination."
    )
    if failing is None:
        lines.append(
            f"- The default threshold ({default:g} px) does not fail within the contaminations measured "
            f"(up to {contaminations[-1]:g} %)."
        )
    else:
        lines.append(
            f"- The default threshold ({default:g} px) starts failing at {failing:g} % contamination "
            f"(success in {cells[default, failing]['success_pct']:.0f} % of seeds; it succeeds in at least 90 % of "
            f"seeds up to {_num(d['reliable_up_to_pct'], 0)} %). The cause is sampling, not the threshold: "
            f"OpenCV draws {RANSAC_SAMPLE}-point minimal samples, and {s['iterations']} of them contain at least one "
            "free of outliers with probability 1 - (1 - (1 - e)^5)^N = "
            + ", ".join(f"{clean[f'{c:g}']:.0%} at {c:g} %" for c in contaminations if c >= failing - 10.0)
            + "; every threshold fails together there."
        )
    lines.append(
        f"- A threshold far below the pixel noise fails even with no outliers: at {thresholds[0]:g} px "
        f"(noise {s['noise_px']:g} px per coordinate) RANSAC keeps a median "
        f"{lowest['recall_at_lowest_contamination']:.0%} "
        f"of the honest points at {contaminations[0]:g} % contamination. An honest point's distance from its true "
        f"projection is Rayleigh-distributed, so even the exact pose has only 1 - exp(-t^2 / 2 sigma^2) = "
        f"{lowest['recall_bound']:.0%} of them within {thresholds[0]:g} px; the consensus is then a random "
        "subset of the good data, and the winning model the one that happens to fit that subset. "
        "The sweet spot is a threshold of 3-4 sigma or more: "
        + ", ".join(f"{t:g} px keeps {summary['thresholds'][f'{t:g}']['recall_bound']:.2%}" for t in thresholds[:4])
        + " of honest points at best."
    )
    disc = math.pi * thresholds[-1] ** 2 / (s["image_size"][0] * s["image_size"][1])
    lines.append(
        f"- Large thresholds cost nothing here because the replaced pixels are uniform over the whole image (a "
        f"{thresholds[-1]:g} px disc covers {disc:.2%} of it); "
        "wrong matches that land near their true position (repeated texture) would be admitted by them."
    )
    return "\n".join(lines) + "\n"


def jitter_markdown(result: dict[str, Any]) -> str:
    s, summary, rows = result["settings"], result["summary"], result["distances"]
    lines = [
        "# Jitter versus distance: a lone marker and a 2x2 board, raw and tracked",
        "",
        _produced(result),
        "",
        f"A static {s['marker_m'] * 100:g} cm marker and, beside it, a 2x2 grid board of the same markers "
        f"({s['board']}), seen {s['tilt_deg']:g} deg off their normal by a static {s['camera']} camera. Each "
        f"distance's view is rendered once (blur {s['blur_px']:g} px) and each of its {s['frames']} frames adds fresh "
        f"Gaussian sensor noise of {s['sensor_noise_grey']:g} grey levels per channel; the tracker ({s['config']}) "
        f"runs on those frames at {s['fps']:g} fps, and the first {s['settle_frames']} frames (the filter's "
        "settling time) are left out of the statistics. *raw*: the tracker's per-frame solution (lower-error "
        "IPPE solution for the marker, the joint solve for the board); *tracker*: its output. *orientation std*: "
        "RMS angle of the frames' rotations about their mean rotation; *flipped*: rotation error against the "
        f"ground truth above {s['flip_deg']:g} deg; *IPPE gap*: how much worse the second IPPE solution of the "
        "marker reprojects (median, px).",
        "",
        "![jitter](jitter.png)",
        "",
        "| distance | marker px | detected % marker / board | std ‖t‖ mm marker raw / trk | board raw / trk "
        "| orientation std deg marker raw / trk | board raw / trk | flipped % marker raw / trk | board raw / trk "
        "| IPPE gap px | noise-free margin px | marker tracked / ambiguous % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:

        def pair(target: str, metric: str, r: dict[str, Any] = r) -> str:
            return f"{_sig(r[f'{target}_raw'].get(metric))} / {_sig(r[f'{target}_tracker'].get(metric))}"

        states = r["marker_tracker_states_pct"]
        lines.append(
            f"| {r['distance_m']:g} m | {r['marker_px']:.0f} "
            f"| {r['marker_raw']['detected_pct']:.0f} / {r['board_raw']['detected_pct']:.0f} "
            f"| {pair('marker', 'distance_std_mm')} "
            f"| {pair('board', 'distance_std_mm')} | {pair('marker', 'rotation_std_deg')} "
            f"| {pair('board', 'rotation_std_deg')} | {pair('marker', 'flipped_pct')} "
            f"| {pair('board', 'flipped_pct')} | {_num(r['marker_gap_median_px'], 3)} "
            f"| {_num(r['marker_noise_free_margin_px'], 3)} | {states['tracked']:.0f} / {states['ambiguous']:.0f} |"
        )
    near, far = rows[0], rows[-1]
    onset, gap_onset = summary["onset_noise_m"], summary["onset_gap_m"]
    onset_text = f"at **{onset:g} m**" if onset is not None else "not reached within the distances measured"
    lines += [
        "",
        "What this shows:",
        "",
        f"- The raw marker's orientation std grows from {_num(near['marker_raw'].get('rotation_std_deg'), 4)} deg at "
        f"{near['distance_m']:g} m to {_num(far['marker_raw'].get('rotation_std_deg'), 3)} deg at "
        f"{far['distance_m']:g} m (it grows in {summary['raw_marker_growth_steps']} distance steps).",
        f"- Ambiguity onset (noise): the first distance at which the raw marker's orientation std exceeds "
        f"{ONSET_FACTOR:g}x the d^2 trend from the nearest distance. A well-conditioned planar pose's tilt noise "
        "grows like d^2 (the tilt is seen only through perspective foreshortening, which falls as (L/d)^2); faster "
        f"growth means the two IPPE solutions have merged into one shallow valley. Here it is {onset_text}. "
        + (
            f"The marker's IPPE gap falls below the filter's decision margin ({summary['decide_margin_px']:g} px) "
            f"from {gap_onset:g} m on: a single frame no longer tells the two solutions apart."
            if gap_onset is not None
            else f"The marker's IPPE gap stays above the filter's decision margin ({summary['decide_margin_px']:g} px)."
        ),
        "- Flipped frames: "
        + "; ".join(f"{_STYLES[key][3]} {_flips(rows, *key)}" for key in _STYLES)
        + ". Where the IPPE gap is below the margin the tracker holds one solution (state *ambiguous*) instead "
        "of alternating: steady, but not necessarily the right one. The raw rate need not grow monotonically "
        "with distance: the *noise-free margin* (how much better the right solution reprojects on the view "
        "without sensor noise, set by the small systematic corner error of renderer and detector) is what the "
        "noise has to overcome, and it varies from one distance to the next.",
        f"- At the far end the tracker's orientation std is {_num(summary['marker_raw_over_tracker_far'], 1)}x below "
        f"the raw marker's and {_num(summary['board_raw_over_tracker_far'], 1)}x below the raw board's.",
        "- Board below the lone marker at every distance? Orientation std: raw "
        f"{_yes(summary['board_not_below_marker_raw_rotation_std_deg'])}, tracker "
        f"{_yes(summary['board_not_below_marker_tracker_rotation_std_deg'])}; distance std: raw "
        f"{_yes(summary['board_not_below_marker_raw_distance_std_mm'])}, tracker "
        f"{_yes(summary['board_not_below_marker_tracker_distance_std_mm'])}.",
    ]
    return "\n".join(lines) + "\n"


def _yes(exceptions: Sequence[float]) -> str:
    """'yes', or 'no' with the distances where the board is not below the marker."""
    return "yes" if not exceptions else "**no** (not at " + ", ".join(f"{d:g}" for d in exceptions) + " m)"


def _flips(rows: Sequence[dict[str, Any]], target: str, pipeline: str) -> str:
    flipped = [(r["distance_m"], r[f"{target}_{pipeline}"].get("flipped_pct")) for r in rows]
    shown = [f"{pct:.1f} % at {d:g} m" for d, pct in flipped if pct]
    return ", ".join(shown) if shown else "none"


def _sig(value: float | None) -> str:
    """Three significant digits (the spreads span four decades)."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.3g}"


def _vector(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in values) + ")"


def _seconds(value: float) -> str:
    return f"{value:.0f} s" if value >= 10 else f"{value:.1f} s"


def _produced(result: dict[str, Any]) -> str:
    meta = result["meta"]
    return (
        f"Produced by `{meta['command']}` in {_seconds(meta['wall_time_s'])} (OpenCV {meta['opencv']}, "
        f"{meta['machine']}, {meta['cpus']} CPUs)."
    )


# ---------------------------------------------------------------------------- rerun


class _Recording:
    """One study's rerun recording, written to ``<out>/<name>.rrd`` (renamed into place when complete)."""

    def __init__(self, path: Path, name: str, plots: Sequence[tuple[str, str]]) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        self.rr = rr
        self.path = path
        self.partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        self.rec = rr.RecordingStream("ar_anchor_study")
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin=f"{name}/figure", name="Figure"),
                    rrb.TextDocumentView(origin=f"{name}/table", name="Table"),
                    row_shares=[3, 2],
                ),
                rrb.Vertical(*[rrb.TimeSeriesView(origin=origin, name=title) for origin, title in plots]),
                column_shares=[3, 2],
            ),
            collapse_panels=True,
        )
        self.rec.set_sinks(rr.FileSink(str(self.partial)), default_blueprint=blueprint)
        self.rec.send_recording_name(f"ar-anchor study {name}")

    def scalar(self, entity: str, value: float | None) -> None:
        if value is not None and math.isfinite(value):
            self.rec.log(entity, self.rr.Scalars(float(value)))

    def time(self, timeline: str, value: int) -> None:
        self.rec.set_time(timeline, sequence=int(value))

    def documents(self, name: str, figure: Path, markdown: str) -> None:
        rr = self.rr
        self.rec.log(f"{name}/figure", rr.EncodedImage(path=figure), static=True)
        self.rec.log(f"{name}/table", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)

    def close(self) -> None:
        try:
            self.rec.flush(timeout_sec=30.0)
        finally:
            self.rec.disconnect()
        try:
            os.replace(self.partial, self.path)
        except OSError as err:
            self.partial.unlink(missing_ok=True)
            raise OutputError(f"{self.path}: cannot write ({err.strerror})") from None


def _record_outliers(recording: _Recording, setup: PnPSetup, result: dict[str, Any]) -> None:
    rr = recording.rr
    for row in result["seeds"]:
        recording.time("seed", row["seed"])
        recording.scalar("outliers/translation_error_m/solvePnP", row["plain_error_m"])
        recording.scalar("outliers/translation_error_m/ransac_lm", row["ransac_error_m"])
        recording.scalar("outliers/inliers/ransac", row["inliers"])
        recording.scalar("outliers/inliers/honest", row["honest_inliers"])
        problem = make_correspondences(setup, result["settings"]["contamination"], row["seed"])
        recording.rec.log(
            "outliers/image/honest",
            rr.Points2D(problem.pixels[problem.honest] + 0.5, radii=3.0, colors=[(40, 200, 80)]),
        )
        recording.rec.log(
            "outliers/image/replaced",
            rr.Points2D(problem.pixels[~problem.honest] + 0.5, radii=3.0, colors=[(230, 50, 50)]),
        )
    first = make_correspondences(setup, result["settings"]["contamination"], result["seeds"][0]["seed"])
    recording.rec.log(
        "outliers/world/points", rr.Points3D(first.points_in_world, radii=0.03, colors=[(200, 200, 200)]), static=True
    )
    recording.rec.log(
        "outliers/world/true_camera",
        rr.Points3D(
            [setup.camera_from_world.camera_centre()], radii=0.08, colors=[(40, 200, 80)], labels=["true camera"]
        ),
        static=True,
    )


def _record_ransac(recording: _Recording, result: dict[str, Any]) -> None:
    for cell in result["cells"]:
        recording.time("contamination_pct", round(cell["contamination_pct"]))
        key = f"{cell['threshold_px']:g}px".replace(".", "_")
        error = cell["median_error_m"]
        recording.scalar(f"ransac/median_error_mm/{key}", None if error is None else 1e3 * error)
        recording.scalar(f"ransac/median_recall/{key}", cell["median_recall"])
        recording.scalar(f"ransac/success_pct/{key}", cell["success_pct"])


def _record_jitter_summary(recording: _Recording, result: dict[str, Any]) -> None:
    rr = recording.rr
    for row, view in zip(result["distances"], result["views"]):
        recording.time("distance_mm", round(1e3 * row["distance_m"]))
        for target, pipeline in _STYLES:
            metrics = row[f"{target}_{pipeline}"]
            for metric in ("rotation_std_deg", "distance_std_mm", "flipped_pct"):
                recording.scalar(f"jitter/{metric}/{target}_{pipeline}", metrics.get(metric))
        small = cv2.resize(view, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
        if ok:
            recording.rec.log("jitter/view", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))


def _jitter_frame_logger(recording: _Recording, setup: JitterSetup) -> Callable[..., None]:
    """Per-frame rotation error against the truth, raw and tracked, on one ``frame`` timeline across distances."""

    def log_frame(d_index: int, index: int, result: Any, truth: dict[str, Pose]) -> None:
        recording.time("frame", d_index * setup.frames + index)
        recording.time("distance_mm", round(1e3 * setup.distances_m[d_index]))
        for target, name in JITTER_SERIES:
            measured, true = result.targets.get(name), truth.get(name)
            if measured is None or true is None:
                continue
            if measured.raw is not None:
                recording.scalar(
                    f"jitter/frames/rotation_error_deg/{target}_raw",
                    angle_between_deg(measured.raw.rotation, true.rotation),
                )
            recording.scalar(
                f"jitter/frames/rotation_error_deg/{target}_tracker",
                angle_between_deg(measured.pose.rotation, true.rotation),
            )

    return log_frame


# ---------------------------------------------------------------------------- command line


def _float_list(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option}: expected numbers separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(f"{option}: expected numbers separated by commas, got {text!r}")
    return values


@dataclass(frozen=True)
class _Defaults:
    seeds_outliers: int
    seeds_ransac: int
    contaminations: str
    frames: int
    distances: str


_FULL = _Defaults(100, 50, "0,10,20,30,40,50,60,70,80,90", 300, "0.3,0.5,0.75,1,1.5,2,2.5,3")
_QUICK = _Defaults(12, 6, "0,20,40,60", 60, "0.3,1,3")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``study`` command's arguments to ``parser``."""
    parser.add_argument(
        "name",
        choices=(*STUDIES, "all"),
        help="outliers: solvePnP vs RANSAC + LM; ransac: threshold x contamination heatmap; "
        "jitter: pose noise vs distance, marker and board, raw and tracked; all: the three",
    )
    parser.add_argument("--out", type=Path, metavar="DIR", help=f"output directory (default {DEFAULT_OUT}/)")
    parser.add_argument("--quick", action="store_true", help="few seeds, frames and distances (a smoke run)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="first seed (default 0)")
    parser.add_argument(
        "--camera",
        type=Path,
        metavar="FILE",
        help="camera YAML to use (default: 1920x1080 fx 1480 for outliers/ransac, 1280x720 fx 1000 for jitter)",
    )
    pnp = parser.add_argument_group("outliers and ransac")
    pnp.add_argument("--seeds", type=int, metavar="N", help="problems per result (default 100 outliers, 50 ransac)")
    pnp.add_argument("--points", type=int, default=120, metavar="N", help="correspondences per problem (default 120)")
    pnp.add_argument("--pixel-noise", type=float, default=0.5, metavar="PX", help="noise sigma per coordinate (0.5)")
    pnp.add_argument("--contamination", type=float, default=25.0, metavar="PCT", help="outliers: %% replaced (25)")
    pnp.add_argument("--threshold", type=float, default=2.0, metavar="PX", help="RANSAC inlier threshold (2)")
    pnp.add_argument("--iterations", type=int, default=300, metavar="N", help="RANSAC iterations (default 300)")
    pnp.add_argument(
        "--thresholds", default="0.5,1,2,4,8,16", metavar="PX,...", help="ransac: thresholds (0.5,1,2,4,8,16)"
    )
    pnp.add_argument(
        "--contaminations", metavar="PCT,...", help=f"ransac: contaminations in %% ({_FULL.contaminations})"
    )
    jitter = parser.add_argument_group("jitter")
    jitter.add_argument("--frames", type=int, metavar="N", help=f"frames per distance (default {_FULL.frames})")
    jitter.add_argument("--distances", metavar="M,...", help=f"distances in metres ({_FULL.distances})")
    jitter.add_argument("--marker-m", type=float, default=0.05, metavar="M", help="marker side, metres (0.05)")
    jitter.add_argument("--tilt-deg", type=float, default=10.0, metavar="DEG", help="view angle off the normal (10)")
    jitter.add_argument("--sensor-noise", type=float, default=2.0, metavar="GREY", help="noise sigma, grey levels (2)")
    jitter.add_argument("--blur", type=float, default=0.6, metavar="PX", help="optical blur sigma, px (0.6)")
    jitter.add_argument("--config", type=Path, metavar="FILE", help="tracker TOML (default: configs/default.toml)")
    jitter.add_argument(
        "--roi",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="ROI tracking on or off (default: as the tracker config says; on in the default config)",
    )


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise InputError(message)


def _pnp_setup(args: argparse.Namespace, camera: CameraModel | None) -> PnPSetup:
    _check(args.points >= 6, f"--points: must be >= 6, got {args.points}")
    _check(
        math.isfinite(args.pixel_noise) and args.pixel_noise >= 0,
        f"--pixel-noise: must be >= 0, got {args.pixel_noise}",
    )
    _check(args.iterations >= 1, f"--iterations: must be >= 1, got {args.iterations}")
    _check(math.isfinite(args.threshold) and args.threshold > 0, f"--threshold: must be > 0 px, got {args.threshold}")
    setup = PnPSetup(points=args.points, noise_px=args.pixel_noise, iterations=args.iterations)
    return setup if camera is None else dataclasses.replace(setup, camera=camera)


def _contamination(percent: float, option: str, points: int) -> float:
    _check(0.0 <= percent < 100.0, f"{option}: percentages must be in [0, 100), got {percent:g}")
    honest = points - int(round(percent / 100.0 * points))
    _check(honest >= 6, f"{option}: {percent:g} % of {points} points leaves {honest} honest points; 6 are needed")
    return percent / 100.0


def _seeds(args: argparse.Namespace, default: int) -> int:
    seeds = default if args.seeds is None else args.seeds
    _check(seeds >= 1, f"--seeds: must be >= 1, got {seeds}")
    return seeds


def _jitter_setup(args: argparse.Namespace, defaults: _Defaults, camera: CameraModel | None) -> JitterSetup:
    from .stability import SETTLE_FRAMES

    frames = defaults.frames if args.frames is None else args.frames
    _check(
        frames > SETTLE_FRAMES + 1,
        f"--frames: must be > {SETTLE_FRAMES + 1} (the first {SETTLE_FRAMES} are the filter's settling time), "
        f"got {frames}",
    )
    distances = sorted(
        set(_float_list(defaults.distances if args.distances is None else args.distances, "--distances"))
    )
    _check(all(d > 0 for d in distances), f"--distances: must all be > 0 m, got {args.distances}")
    _check(math.isfinite(args.marker_m) and args.marker_m > 0, f"--marker-m: must be > 0, got {args.marker_m}")
    _check(0.0 <= args.tilt_deg < 80.0, f"--tilt-deg: must be in [0, 80), got {args.tilt_deg}")
    _check(
        math.isfinite(args.sensor_noise) and args.sensor_noise >= 0,
        f"--sensor-noise: must be >= 0, got {args.sensor_noise}",
    )
    _check(math.isfinite(args.blur) and args.blur >= 0, f"--blur: must be >= 0, got {args.blur}")
    setup = JitterSetup(
        config=load_config(args.config),
        marker_m=args.marker_m,
        distances_m=tuple(distances),
        frames=frames,
        tilt_deg=args.tilt_deg,
        sensor_noise=args.sensor_noise,
        blur_px=args.blur,
        seed=args.seed,
        roi=args.roi,
    )
    return setup if camera is None else dataclasses.replace(setup, camera=camera)


_OPTIONS = (
    "quick",
    "seed",
    "camera",
    "seeds",
    "points",
    "pixel_noise",
    "contamination",
    "threshold",
    "iterations",
    "thresholds",
    "contaminations",
    "frames",
    "distances",
    "marker_m",
    "tilt_deg",
    "sensor_noise",
    "blur",
    "roi",
    "config",
)


def _command(args: argparse.Namespace, name: str, out: Path) -> str:
    """The command line that reproduces this run (options that differ from their defaults)."""
    defaults = argparse.ArgumentParser()
    configure_parser(defaults)
    reference = defaults.parse_args([name])
    words = ["ar-anchor", "study", name]
    for option in _OPTIONS:
        value = getattr(args, option, None)
        if value == getattr(reference, option):
            continue
        flag = "--" + option.replace("_", "-")
        if value is False:
            words += ["--no-" + option.replace("_", "-")]
        else:
            words += [flag] if value is True else [flag, str(value)]
    return " ".join(words + ["--out", str(out)])


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as err:
        raise OutputError(f"{path}: cannot write ({err.strerror})") from None


def _json_ready(value: Any) -> Any:
    """NaN and infinities as None (JSON has neither), floats to 6 significant digits."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return float(f"{value:.6g}") if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _meta(command: str, wall_time_s: float) -> dict[str, Any]:
    return {
        "command": command,
        "wall_time_s": wall_time_s,
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }


def _study(
    name: str, args: argparse.Namespace, out: Path, defaults: _Defaults, progress: Progress | None
) -> dict[str, Any]:
    """Run one study and write its four files; returns the result (with ``meta``)."""
    try:
        camera = None if args.camera is None else CameraModel.from_yaml(args.camera)
    except CameraError as err:
        raise CameraError(f"--camera: {err}") from None
    command = _command(args, name, out)
    start = time.perf_counter()
    if name == "outliers":
        setup = _pnp_setup(args, camera)
        contamination = _contamination(args.contamination, "--contamination", setup.points)
        result = run_outliers(
            setup,
            seeds=_seeds(args, defaults.seeds_outliers),
            contamination=contamination,
            threshold_px=args.threshold,
            first_seed=args.seed,
            progress=progress,
        )
        plots = [("outliers/translation_error_m", "Translation error (m)"), ("outliers/inliers", "Inliers")]
    elif name == "ransac":
        setup = _pnp_setup(args, camera)
        thresholds = sorted(set(_float_list(args.thresholds, "--thresholds")) | {args.threshold})
        _check(all(t > 0 for t in thresholds), f"--thresholds: must all be > 0 px, got {args.thresholds}")
        text = defaults.contaminations if args.contaminations is None else args.contaminations
        contaminations = [
            _contamination(c, "--contaminations", setup.points)
            for c in sorted(set(_float_list(text, "--contaminations")))
        ]
        result = run_ransac(
            setup,
            seeds=_seeds(args, defaults.seeds_ransac),
            contaminations=contaminations,
            thresholds_px=thresholds,
            default_threshold_px=args.threshold,
            first_seed=args.seed,
            progress=progress,
        )
        plots = [
            ("ransac/median_error_mm", "Median translation error (mm)"),
            ("ransac/median_recall", "Median recall"),
            ("ransac/success_pct", "Seeds that succeed (%)"),
        ]
    else:
        setup = _jitter_setup(args, defaults, camera)
        plots = [
            ("jitter/rotation_std_deg", "Orientation std (deg)"),
            ("jitter/distance_std_mm", "Distance std (mm)"),
            ("jitter/frames/rotation_error_deg", "Rotation error per frame (deg)"),
        ]
    from ..run.outputs import prepare_out_dir  # (imports the tracker: not on every CLI start)

    prepare_out_dir(out)
    recording = _Recording(out / f"{name}.rrd", name, plots)
    try:
        if name == "jitter":
            result = run_jitter(setup, progress=progress, on_frame=_jitter_frame_logger(recording, setup))
        result["meta"] = _meta(command, time.perf_counter() - start)
        png, markdown = out / f"{name}.png", out / f"{name}.md"
        plotter, writer = {
            "outliers": (plot_outliers, outliers_markdown),
            "ransac": (plot_ransac, ransac_markdown),
            "jitter": (plot_jitter, jitter_markdown),
        }[name]
        plotter(result, png)
        text = writer(result)
        _write(markdown, text)
        views = result.pop("views", None)
        _write(out / f"{name}.json", json.dumps(_json_ready(result), indent=1) + "\n")
        if name == "outliers":
            _record_outliers(recording, setup, result)
        elif name == "ransac":
            _record_ransac(recording, result)
        else:
            _record_jitter_summary(recording, {**result, "views": views})
        recording.documents(name, png, text)
    finally:
        recording.close()
    return result


def _headline(result: dict[str, Any]) -> str:
    summary = result["summary"]
    if result["study"] == "outliers":
        return (
            f"outliers: median translation error solvePnP {_metres(summary['plain_error_m']['median'])}, "
            f"RANSAC + LM {_metres(summary['ransac_error_m']['median'])}; all honest points kept in "
            f"{summary['all_honest_recovered_pct']:.0f} % of seeds"
        )
    if result["study"] == "ransac":
        default = summary["thresholds"][f"{summary['default_threshold_px']:g}"]
        failing = default["first_failing_contamination_pct"]
        return f"ransac: {summary['default_threshold_px']:g} px " + (
            "does not fail" if failing is None else f"starts failing at {failing:g} % contamination"
        )
    onset = summary["onset_noise_m"]
    return (
        "jitter: ambiguity onset "
        + ("not reached" if onset is None else f"at {onset:g} m")
        + f"; far end raw/tracker orientation std {_num(summary['marker_raw_over_tracker_far'], 1)}x (marker)"
    )


def run_study(args: argparse.Namespace) -> int:
    """``ar-anchor study NAME``: run the study (or all three), write its files, print where; 0 on success."""
    quiet = bool(getattr(args, "quiet", False))
    _check(args.seed >= 0, f"--seed: must be >= 0, got {args.seed}")
    out = DEFAULT_OUT if args.out is None else Path(args.out)
    defaults = _QUICK if args.quick else _FULL

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    names = STUDIES if args.name == "all" else (args.name,)
    for name in names:
        result = _study(name, args, out, defaults, None if quiet else progress)
        if not quiet:
            print(_headline(result))
            print(f"wrote {out / name}.png, .md, .json, .rrd ({_seconds(result['meta']['wall_time_s'])})")
    return 0
