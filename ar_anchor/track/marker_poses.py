"""The pose stage over all markers of a frame at once: both IPPE_SQUARE solutions of every marker,
polished together by one Levenberg-Marquardt over arrays, validated together.

It computes what :func:`~ar_anchor.track.pose.solve_marker` computes marker by marker, with the same
rules (see that module), at a fraction of the cost: per marker only OpenCV's closed-form
``solvePnPGeneric(IPPE_SQUARE)`` remains a call of its own; the polish, the reprojection errors and
the checks are a handful of array operations for the whole frame.

**The polish** (:func:`refine_poses`) replaces the two ``solvePnPRefineLM`` calls per marker. It
minimises the same cost (the sum of squared pixel residuals of the four corners, through the
camera's own distortion model: the projections and their derivatives come from one
``cv2.projectPoints`` call for every corner of the frame, with the poses applied beforehand) by
Levenberg-Marquardt steps on the rotation's tangent space (``R <- exp([d]x) R``) and the
translation. It converges to the same minimum as OpenCV's refinement, to within 1e-6 deg and 1e-9 m
on chessboard.avi and synthetic markers (``tests/track/test_marker_poses.py``); each pose's cost
never goes up, so the polished pose is never worse than IPPE's.

A marker whose IPPE_SQUARE solutions all fail a check falls back to the per-marker solver, which
tries IPPE and SQPNP next: the slow path runs only where it can change the answer.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..camera import CameraModel
from ..geometry import Pose, marker_corners_in_marker, rvec_from_matrix
from .kernels import compiled_refine, distortion12
from .pose import _RATIO_EPS_PX, MAX_DISTANCE_M, MarkerPose, PoseFailure, PoseHypothesis, _quad_problem, solve_marker

__all__ = ["refine_poses", "solve_markers"]

# Levenberg-Marquardt: at most this many trial steps per pose; a pose is done once its step is below
# _STEP_DONE (radians / metres) or its cost stops falling (relative _COST_DONE).
_LM_STEPS = 30
_STEP_DONE = 1e-10
_COST_DONE = 1e-12
_LAMBDA0 = 1e-3
# a polished solution within this of another solution of its marker slid into that one's minimum
_SAME_BRANCH_DEG = 1.0


def _exp_so3(vectors: np.ndarray) -> np.ndarray:
    """Rotation matrices (P, 3, 3) of rotation vectors (P, 3) (Rodrigues' formula, small angles exact)."""
    theta2 = np.einsum("pi,pi->p", vectors, vectors)
    theta = np.sqrt(theta2)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    skew = np.zeros((len(vectors), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -vectors[:, 2], vectors[:, 1], -vectors[:, 0]
    skew -= skew.transpose(0, 2, 1)
    out = a[:, None, None] * skew + b[:, None, None] * (skew @ skew)
    out[:, [0, 1, 2], [0, 1, 2]] += 1.0
    return out


def _project(
    rotations: np.ndarray, tvecs: np.ndarray, obj: np.ndarray, k: np.ndarray, dist: np.ndarray | None, jacobian: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Points ``obj`` (P, n, 3) seen by poses (P): their camera coordinates (P, n, 3), pixels (P, n, 2)
    and, with ``jacobian``, the pixels' derivatives by the camera coordinates (P, n, 2, 3)."""
    count, n = obj.shape[:2]
    in_camera = np.einsum("pij,pnj->pni", rotations, obj) + tvecs[:, None, :]
    zero = np.zeros(3)
    if jacobian:
        pixels, derivatives = cv2.projectPoints(in_camera.reshape(-1, 1, 3), zero, zero, k, dist)
        # rows 2i, 2i+1: u, v of point i; columns 3..5: by the translation, i.e. by the camera coordinates
        by_camera = derivatives[:, 3:6].reshape(count, n, 2, 3)
        return in_camera, pixels.reshape(count, n, 2), by_camera
    pixels, _ = cv2.projectPoints(in_camera.reshape(-1, 1, 3), zero, zero, k, dist)
    return in_camera, pixels.reshape(count, n, 2), None


def refine_poses(
    rotations: np.ndarray,
    tvecs: np.ndarray,
    obj: np.ndarray,
    img: np.ndarray,
    k: np.ndarray,
    dist: np.ndarray | None,
    compiled: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Polish poses ``(rotations (P, 3, 3), tvecs (P, 3))`` on their own points ``obj (P, n, 3)`` /
    ``img (P, n, 2)`` (see the module doc). Returns (rotations, tvecs, RMS error after, RMS error before):
    RMS over points of the pixel distance. Poses must be finite with every point in front of the camera.
    ``compiled``: the compiled kernel where it can run (:mod:`.kernels`), else numpy (the same steps)."""
    rotations = np.array(rotations, np.float64)
    tvecs = np.array(tvecs, np.float64)
    kernel = compiled_refine() if compiled else None
    coefficients = distortion12(dist)
    if kernel is not None and coefficients is not None and len(rotations):
        count, n = obj.shape[:2]
        after, before = np.empty(count), np.empty(count)
        kernel(
            rotations, tvecs, np.ascontiguousarray(obj, np.float64), np.ascontiguousarray(img, np.float64), n,
            float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), coefficients,
            _LM_STEPS, _STEP_DONE, _COST_DONE, _LAMBDA0, after, before,
        )  # fmt: skip
        return rotations, tvecs, after, before
    count, n = obj.shape[:2]
    in_camera, pixels, derivatives = _project(rotations, tvecs, obj, k, dist, jacobian=True)
    assert derivatives is not None
    by_camera: np.ndarray = derivatives
    residual = pixels - img
    cost = np.einsum("pni,pni->p", residual, residual)
    before = np.sqrt(cost / n)
    damping = np.full(count, _LAMBDA0)
    active = np.isfinite(cost)
    for _ in range(_LM_STEPS):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        rotated = in_camera[idx] - tvecs[idx, None, :]  # R X
        # d(R X + t) / d(rotation step) = -[R X]x, / d(t) = I: the pixels' derivative by the rotation
        # step is (R X) x d, row by row (d: by the camera coordinates)
        d = by_camera[idx]  # (a, n, 2, 3)
        blocks = np.empty((len(idx), n, 2, 6))
        blocks[..., :3] = np.cross(rotated[:, :, None, :], d)
        blocks[..., 3:] = d
        jac = blocks.reshape(len(idx), 2 * n, 6)
        r = residual[idx].reshape(len(idx), 2 * n, 1)
        jac_t = jac.transpose(0, 2, 1)
        hessian = jac_t @ jac
        gradient = jac_t @ r
        diagonal = hessian[:, [0, 1, 2, 3, 4, 5], [0, 1, 2, 3, 4, 5]]
        damped = hessian.copy()
        damped[:, [0, 1, 2, 3, 4, 5], [0, 1, 2, 3, 4, 5]] += damping[idx, None] * np.maximum(diagonal, 1e-12)
        try:
            step = -np.linalg.solve(damped, gradient)[..., 0]
        except np.linalg.LinAlgError:
            break
        trial_r = _exp_so3(step[:, :3]) @ rotations[idx]
        trial_t = tvecs[idx] + step[:, 3:]
        trial_cam, trial_pix, trial_d = _project(trial_r, trial_t, obj[idx], k, dist, jacobian=True)
        assert trial_d is not None
        trial_res = trial_pix - img[idx]
        trial_cost = np.einsum("pni,pni->p", trial_res, trial_res)
        better = np.isfinite(trial_cost) & (trial_cost < cost[idx]) & (trial_cam[..., 2] > 1e-9).all(axis=1)
        took = idx[better]
        drop = cost[took] - trial_cost[better]
        rotations[took], tvecs[took] = trial_r[better], trial_t[better]
        in_camera[took], residual[took], by_camera[took] = trial_cam[better], trial_res[better], trial_d[better]
        cost[took] = trial_cost[better]
        damping[took] = np.maximum(damping[took] * 0.1, 1e-12)
        damping[idx[~better]] *= 10.0
        small_step = np.sqrt(np.einsum("pi,pi->p", step, step)) < _STEP_DONE
        done = small_step | (damping[idx] > 1e12)
        done[better] |= drop <= _COST_DONE * np.maximum(cost[took], 1e-30)
        active[idx[done]] = False
    return rotations, tvecs, np.sqrt(cost / n), before


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    trace = float(np.vdot(a, b))
    return math.degrees(math.acos(min(1.0, max(-1.0, (trace - 1.0) / 2.0))))


def solve_markers(
    ids: np.ndarray,
    corners: np.ndarray,
    lengths_m: np.ndarray,
    camera: CameraModel,
    max_reproj_px: float = 3.0,
) -> list[MarkerPose | PoseFailure]:
    """Poses of the markers ``ids`` (N,) with corners (N, 4, 2) (TL, TR, BR, BL) and side lengths (N,):
    for each, what :func:`~ar_anchor.track.pose.solve_marker` returns (see the module doc)."""
    ids = np.asarray(ids).reshape(-1)
    corners = np.asarray(corners, np.float64).reshape(-1, 4, 2)
    lengths_m = np.asarray(lengths_m, np.float64).reshape(-1)
    k, dist = camera.camera_matrix, camera.dist_or_none
    results: list[MarkerPose | PoseFailure | None] = [None] * len(ids)
    # every IPPE_SQUARE solution of every well-formed marker: (marker index, rvec, tvec)
    owner: list[int] = []
    starts_r: list[np.ndarray] = []
    starts_t: list[np.ndarray] = []
    for m, (marker_id, quad, length) in enumerate(zip(ids.tolist(), corners, lengths_m.tolist())):
        problem = _quad_problem(quad)
        if problem is not None:
            results[m] = PoseFailure(marker_id, problem)
            continue
        if not (math.isfinite(length) and length > 0):
            results[m] = PoseFailure(marker_id, f"marker length must be > 0, got {length}")
            continue
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                marker_corners_in_marker(length), quad, k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
        except cv2.error:
            continue  # (the per-marker solver says why, and tries the next solvers)
        for rvec, tvec in zip(rvecs[:count], tvecs[:count]):
            owner.append(m)
            starts_r.append(np.asarray(rvec, np.float64).reshape(3))
            starts_t.append(np.asarray(tvec, np.float64).reshape(3))
    if owner:
        _solve_all(ids, corners, lengths_m, camera, max_reproj_px, np.array(owner), starts_r, starts_t, results)
    for m, result in enumerate(results):
        if result is None:  # no IPPE_SQUARE solution passed: the per-marker path tries the other solvers
            results[m] = solve_marker(int(ids[m]), corners[m], float(lengths_m[m]), camera, max_reproj_px)
    return results  # type: ignore[return-value]


def _solve_all(
    ids: np.ndarray,
    corners: np.ndarray,
    lengths_m: np.ndarray,
    camera: CameraModel,
    max_reproj_px: float,
    owner: np.ndarray,
    starts_r: list[np.ndarray],
    starts_t: list[np.ndarray],
    results: list[MarkerPose | PoseFailure | None],
) -> None:
    """Polish, validate and rank every IPPE_SQUARE solution (``owner``: each one's marker), filling
    ``results`` for the markers that keep at least one."""
    k, dist = camera.camera_matrix, camera.dist_or_none
    rvecs, tvecs = np.array(starts_r), np.array(starts_t)
    half = lengths_m[owner] / 2.0
    obj = np.stack(
        [np.stack([-half, half, 0 * half], 1), np.stack([half, half, 0 * half], 1),
         np.stack([half, -half, 0 * half], 1), np.stack([-half, -half, 0 * half], 1)],
        axis=1,
    )  # fmt: skip
    img = corners[owner]
    finite = np.isfinite(rvecs).all(axis=1) & np.isfinite(tvecs).all(axis=1)
    start_rot = np.zeros((len(owner), 3, 3))
    for index in np.flatnonzero(finite).tolist():
        start_rot[index] = cv2.Rodrigues(rvecs[index])[0]
    depth_ok = finite.copy()
    depth_ok[finite] = (
        np.einsum("pij,pnj->pni", start_rot[finite], obj[finite])[..., 2] + tvecs[finite, None, 2] > 1e-9
    ).all(axis=1)
    # (a start behind the camera is rejected below whatever LM makes of it; it is not polished)
    refined_rot, refined_t = start_rot.copy(), tvecs.copy()
    after = np.full(len(owner), np.nan)
    before = np.full(len(owner), np.nan)
    if depth_ok.any():
        sel = np.flatnonzero(depth_ok)
        r_rot, r_t, r_after, r_before = refine_poses(start_rot[sel], tvecs[sel], obj[sel], img[sel], k, dist)
        refined_rot[sel], refined_t[sel], after[sel], before[sel] = r_rot, r_t, r_after, r_before
    for m in np.unique(owner).tolist():
        members: list[int] = np.flatnonzero(owner == m).tolist()
        polished: list[np.ndarray] = []
        candidates: list[PoseHypothesis] = []
        all_errors: list[float] = []
        for p in members:  # (plain ints)
            if not finite[p]:
                all_errors.append(math.nan)
                continue
            if not depth_ok[p]:
                polished.append(start_rot[p])
                all_errors.append(math.nan)  # (check_pose: behind the camera)
                continue
            if any(_angle_deg(refined_rot[p], q) < _SAME_BRANCH_DEG for q in polished):
                rotation, tvec, error = start_rot[p], tvecs[p], float(before[p])
                pose = Pose(rvecs[p], tvec)
            else:
                rotation, tvec, error = refined_rot[p], refined_t[p], float(after[p])
                pose = Pose(rvec_from_matrix(rotation), tvec)
            polished.append(rotation)
            if not _valid(pose, rotation, tvec, obj[p]):
                all_errors.append(math.nan)
                continue
            all_errors.append(error)
            if math.isfinite(error) and error <= max_reproj_px:
                candidates.append(PoseHypothesis(pose, error))
        if not candidates:
            continue
        candidates.sort(key=lambda h: h.reproj_px)
        finite_errors = sorted(e for e in all_errors if math.isfinite(e))
        ambiguity = (
            (finite_errors[1] + _RATIO_EPS_PX) / (finite_errors[0] + _RATIO_EPS_PX)
            if len(finite_errors) >= 2
            else math.nan
        )
        results[m] = MarkerPose(
            int(ids[m]), float(lengths_m[m]), corners[m], tuple(candidates[:2]), ambiguity, "ippe_square"
        )


def _valid(pose: Pose, rotation: np.ndarray, tvec: np.ndarray, obj: np.ndarray) -> bool:
    """:func:`~ar_anchor.track.pose.check_pose`'s checks but the error's: finite, a rotation of at most pi,
    a plausible distance, every corner in front of the camera, the camera on the printed side."""
    if not pose.is_finite():
        return False
    if float(np.sqrt(pose.rvec @ pose.rvec)) > math.pi + 1e-9:
        return False
    if float(np.sqrt(tvec @ tvec)) > MAX_DISTANCE_M:
        return False
    if np.any(obj @ rotation[2] + tvec[2] <= 1e-6):
        return False
    return bool(-(rotation[:, 2] @ tvec) > 0)  # the camera centre's z in the marker frame, (-R^T t)_z
