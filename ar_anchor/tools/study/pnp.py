"""The PnP problem of the ``outliers`` and ``ransac`` studies, solved, and the two studies.

A problem (:func:`make_correspondences`) is points in view of a camera at a known pose, their noisy
pixels, and a share of them replaced by uniform random pixels; :func:`solve_trial` solves it with
plain ``solvePnP`` and with ``solvePnPRansac`` + ``solvePnPRefineLM`` and measures both against the
truth. :func:`run_outliers` compares the two over many seeds; :func:`run_ransac` sweeps RANSAC's
inlier threshold against the contamination.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ...camera import CameraModel
from ...geometry import Pose, angle_between_deg
from . import interrupt
from .stats import Progress, finite, spread

__all__ = [
    "OTHER_SOLVERS",
    "RANSAC_SAMPLE",
    "SUCCESS_ERROR_M",
    "SUCCESS_RECALL",
    "Correspondences",
    "PnPSetup",
    "PnPTrial",
    "clean_sample_probability",
    "make_correspondences",
    "recall_bound",
    "run_outliers",
    "run_ransac",
    "solve_plain",
    "solve_trial",
]

SUCCESS_ERROR_M = 0.01  # a RANSAC trial succeeds with a translation error below 1 cm ...
SUCCESS_RECALL = 0.9  # ... keeping at least 90 % of the honest points
RANSAC_SAMPLE = 5  # points per minimal sample of OpenCV's solvePnPRansac (EPnP kernel)
# other least-squares solvers on all points, for context (none is robust to outliers)
OTHER_SOLVERS = (("epnp", cv2.SOLVEPNP_EPNP), ("sqpnp", cv2.SOLVEPNP_SQPNP))


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
        interrupt.check()
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
        "plain_error_m": spread([r["plain_error_m"] for r in rows]),
        **{f"{name}_error_m": spread([r[f"{name}_error_m"] for r in rows]) for name, _ in OTHER_SOLVERS},
        "ransac_error_m": spread([r["ransac_error_m"] for r in rows]),
        "plain_rotation_deg": spread([r["plain_rotation_deg"] for r in rows]),
        "ransac_rotation_deg": spread([r["ransac_rotation_deg"] for r in rows]),
        "inliers": spread([r["inliers"] for r in rows]),
        "honest_inliers": spread([r["honest_inliers"] for r in rows]),
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
            trials = [_ransac_trial(setup, contamination, first_seed + i, threshold) for i in range(seeds)]
            errors = [t.ransac_error_m for t in trials]
            recalls = [t.recall for t in trials]
            precisions = [t.precision for t in trials]
            cells.append(
                {
                    "threshold_px": threshold,
                    "contamination_pct": 100.0 * contamination,
                    "median_error_m": spread(errors)["median"],
                    "median_recall": float(np.median(recalls)),
                    "median_precision": finite(np.nanmedian(precisions)) if any(t.inliers for t in trials) else None,
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


def _ransac_trial(setup: PnPSetup, contamination: float, seed: int, threshold_px: float) -> PnPTrial:
    """One seed's problem solved by RANSAC + LM alone (after a check for Ctrl-C)."""
    interrupt.check()
    return solve_trial(setup, make_correspondences(setup, contamination, seed), threshold_px, plain=False)


def _succeeds_up_to(row: Sequence[dict[str, Any]], min_success_pct: float) -> float | None:
    """The highest contamination up to which every cell of a threshold's row succeeds (None: not even the first)."""
    best = None
    for cell in row:
        if cell["success_pct"] < min_success_pct:
            break
        best = cell["contamination_pct"]
    return best
