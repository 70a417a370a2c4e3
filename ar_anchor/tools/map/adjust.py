"""Bundle adjustment of frames and markers together, and the markers' uncertainty from its Jacobian.

Bundle adjustment (:func:`bundle_adjust`)
    ``scipy.optimize.least_squares`` (trust region, Huber loss of scale ``HUBER_PX``) over every located
    frame's ``camera_from_world`` and every marker's ``world_from_marker`` but the reference's (fixed: the
    gauge). Rotations are increments left of the starting rotation (``R = exp([d]x) R0``, re-centred at every
    call, so never near the axis-angle singularity). Residuals: the pixel error of each observed corner,
    projected by ``cv2.projectPoints`` with the camera's distortion; its Jacobian is analytic and sparse
    (each observation's 8 rows touch 6 frame and 6 marker columns), built from ``projectPoints``' own
    derivatives by the chain rule. Observations still off after a solve are dropped and the map solved again
    (:mod:`.solve`).

Uncertainty (:func:`marker_sigmas`)
    The Gauss-Newton normal matrix ``J^T J`` at the solution, scaled by the residual variance
    ``sum(r^2) / (m - n)``; the frame poses are eliminated by their Schur complement (their blocks are 6x6
    and independent), and each marker's centre covariance is the translation block of the inverse:
    reported as ``sqrt(trace)``, a 1-sigma 3D position uncertainty relative to the reference marker.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sparse
from scipy.optimize import least_squares

from ...geometry import Pose
from .problem import HUBER_PX, Problem, rotations

__all__ = ["Adjusted", "bundle_adjust", "marker_sigmas"]


@dataclass
class Adjusted:
    """A bundle adjustment's result: poses, the observations it used with their RMS errors, and its Jacobian."""

    world_from_marker: dict[int, Pose]
    camera_from_world: dict[int, Pose]
    observations: list[tuple[int, int]]  # (frame, position in it)
    errors_px: np.ndarray  # (O,) RMS corner error per observation
    corner_errors_px: np.ndarray  # (O, 4) per-corner distance
    jacobian: sparse.csr_matrix | None
    residuals: np.ndarray
    frames: list[int]
    free_markers: list[int]
    evaluations: int


def _observations(
    problem: Problem,
    world_from_marker: dict[int, Pose],
    camera_from_world: dict[int, Pose],
    observations: list[tuple[int, int]] | None,
) -> list[tuple[int, int]]:
    """The observations to adjust on, sorted by frame: ``observations`` (default: every observation of a placed
    marker in a located frame), less those of frames left with fewer than two."""
    if observations is None:
        observations = [
            (f, k)
            for f in camera_from_world
            for k, marker_id in enumerate(problem.frames[f].ids.tolist())
            if marker_id in world_from_marker
        ]
    per_frame = Counter(f for f, _ in observations)
    return sorted((f, k) for f, k in observations if per_frame[f] >= 2 and f in camera_from_world)


class _Residuals:
    """The adjustment's residuals and sparse analytic Jacobian over the parameter vector (frames' then free
    markers' 6-vectors: rotation increment, translation), with the last evaluation cached."""

    def __init__(
        self,
        problem: Problem,
        world_from_marker: dict[int, Pose],
        camera_from_world: dict[int, Pose],
        reference: int,
        observations: list[tuple[int, int]],
    ) -> None:
        frames = sorted({f for f, _ in observations})
        markers = [reference] + sorted(m for m in world_from_marker if m != reference)
        frame_pos = {f: i for i, f in enumerate(frames)}
        marker_pos = {m: i for i, m in enumerate(markers)}
        n_frames, n_free = len(frames), len(markers) - 1
        obs_frame = np.array([frame_pos[f] for f, _ in observations], dtype=np.int64)
        obs_marker = np.array([marker_pos[int(problem.frames[f].ids[k])] for f, k in observations], dtype=np.int64)
        self.frames, self.markers, self.n_frames, self.n_free = frames, markers, n_frames, n_free
        self.obs_marker = obs_marker
        self.observed = (
            np.stack([problem.frames[f].corners[k] for f, k in observations]) if observations else np.zeros((0, 4, 2))
        )
        self.count = count = len(observations)
        # each frame's observations are contiguous (sorted by frame)
        self.bounds = np.searchsorted(obs_frame, np.arange(n_frames + 1))
        self.frame_rotation0, frame_translation0 = rotations([camera_from_world[f] for f in frames])
        self.marker_rotation0, self.marker_translation0 = rotations([world_from_marker[m] for m in markers])
        self.rotated_square = np.einsum("mij,kj->mki", self.marker_rotation0, problem.square)  # (M, 4, 3): R0_m s
        self.cams = [problem.camera(problem.frames[f]) for f in frames]
        self.x0 = np.concatenate(
            [
                np.hstack([np.zeros((n_frames, 3)), frame_translation0]).ravel(),
                np.hstack([np.zeros((n_free, 3)), self.marker_translation0[1:]]).ravel(),
            ]
        )

        # the Jacobian's structure: observation o's 8 rows x (6 frame columns, 6 marker columns unless the reference)
        rows = np.repeat(np.arange(8 * count).reshape(count, 8, 1), 6, axis=2)
        frame_cols = np.broadcast_to((6 * obs_frame)[:, None, None] + np.arange(6), (count, 8, 6))
        self.free = free = obs_marker > 0
        marker_cols = np.broadcast_to(
            (6 * n_frames + 6 * (obs_marker[free] - 1))[:, None, None] + np.arange(6), (int(free.sum()), 8, 6)
        )
        self.jac_rows = np.concatenate([rows.ravel(), rows[free].ravel()])
        self.jac_cols = np.concatenate([frame_cols.ravel(), marker_cols.ravel()])
        self.shape = (8 * count, 6 * (n_frames + n_free))
        self.corner_of_row = np.repeat(np.arange(4), 2)
        self.cache: dict[str, object] = {}

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residuals (8 O,), frame-part Jacobian (O, 8, 6), marker-part Jacobian (O, 8, 6)) at ``x``."""
        cache = self.cache
        key = x.tobytes()
        if cache.get("key") == key:
            return cache["value"]  # type: ignore[return-value]
        n_frames, n_free, count = self.n_frames, self.n_free, self.count
        frame_x = x[: 6 * n_frames].reshape(n_frames, 6)
        marker_x = np.vstack([np.zeros((1, 6)), x[6 * n_frames :].reshape(n_free, 6)])
        marker_x[0, 3:] = self.marker_translation0[0]
        increments, d_increments = [], []
        for m in range(len(self.markers)):
            rotation, jacobian = cv2.Rodrigues(marker_x[m, :3])
            increments.append(rotation)
            d_increments.append(jacobian.reshape(3, 3, 3))  # [i] = d rotation / d x_i
        increments_arr = np.stack(increments)
        world = np.einsum("mij,mkj->mki", increments_arr, self.rotated_square) + marker_x[:, None, 3:]  # (M, 4, 3)
        # d world corner / d marker increment i: dR_i (R0 s)
        d_world = np.einsum("mipq,mkq->mkpi", np.stack(d_increments), self.rotated_square)  # (M, 4, 3, 3)
        residual = np.empty((count, 8))
        d_frame = np.empty((count, 8, 6))
        d_point = np.empty((count, 8, 3))
        obs_marker, bounds, frame_rotation0 = self.obs_marker, self.bounds, self.frame_rotation0
        for i in range(n_frames):
            lo, hi = bounds[i], bounds[i + 1]
            points = world[obs_marker[lo:hi]].reshape(-1, 3)
            pre = points @ frame_rotation0[i].T
            camera = self.cams[i]
            projected, jacobian = cv2.projectPoints(
                pre, frame_x[i, :3], frame_x[i, 3:], camera.camera_matrix, camera.dist_or_none
            )
            residual[lo:hi] = (projected.reshape(-1, 4, 2) - self.observed[lo:hi]).reshape(-1, 8)
            jacobian = jacobian.reshape(hi - lo, 8, -1)
            d_frame[lo:hi] = jacobian[:, :, :6]
            full_rotation = cv2.Rodrigues(frame_x[i, :3])[0] @ frame_rotation0[i]
            d_point[lo:hi] = jacobian[:, :, 3:6] @ full_rotation  # d pixel / d world point
        rotation_part = np.einsum("orp,orpi->ori", d_point, d_world[obs_marker][:, self.corner_of_row])
        d_marker = np.concatenate([rotation_part, d_point], axis=2)
        value = (residual.ravel(), d_frame, d_marker)
        cache["key"], cache["value"] = key, value
        return value

    def fun(self, x: np.ndarray) -> np.ndarray:
        """The residuals at ``x``."""
        return self.evaluate(x)[0]

    def jac(self, x: np.ndarray) -> sparse.csr_matrix:
        """The sparse Jacobian at ``x``."""
        _, d_frame, d_marker = self.evaluate(x)
        data = np.concatenate([d_frame.ravel(), d_marker[self.free].ravel()])
        return sparse.csr_matrix((data, (self.jac_rows, self.jac_cols)), shape=self.shape)


def bundle_adjust(
    problem: Problem,
    world_from_marker: dict[int, Pose],
    camera_from_world: dict[int, Pose],
    reference: int,
    *,
    observations: list[tuple[int, int]] | None = None,
    max_nfev: int = 100,
) -> Adjusted:
    """Adjust frames and markers together (module doc). ``observations`` (frame, position in it): those to
    use (default: every observation of a placed marker in a located frame); frames left with fewer than two
    are not adjusted (they hold nothing about the map)."""
    observations = _observations(problem, world_from_marker, camera_from_world, observations)
    r = _Residuals(problem, world_from_marker, camera_from_world, reference, observations)
    frames, markers, n_frames, n_free, count, shape = r.frames, r.markers, r.n_frames, r.n_free, r.count, r.shape
    evaluations = 0
    x = r.x0
    if count and shape[1]:
        solved = least_squares(
            r.fun,
            r.x0,
            jac=r.jac,
            method="trf",
            loss="huber",
            f_scale=HUBER_PX,
            x_scale="jac",
            tr_solver="lsmr",
            max_nfev=max_nfev,
            ftol=1e-10,
            xtol=1e-10,
            gtol=1e-10,
        )
        x, evaluations = solved.x, int(solved.nfev)
    residual = r.fun(x) if count else np.zeros(0)
    frame_x = x[: 6 * n_frames].reshape(n_frames, 6)
    marker_x = x[6 * n_frames :].reshape(n_free, 6)
    cameras_out = {
        f: Pose.from_matrix(cv2.Rodrigues(frame_x[i, :3])[0] @ r.frame_rotation0[i], frame_x[i, 3:])
        for i, f in enumerate(frames)
    }
    markers_out = {reference: world_from_marker[reference]}
    for j, m in enumerate(markers[1:]):
        markers_out[m] = Pose.from_matrix(
            cv2.Rodrigues(marker_x[j, :3])[0] @ r.marker_rotation0[j + 1], marker_x[j, 3:]
        )
    corner_errors = np.linalg.norm(residual.reshape(-1, 4, 2), axis=2) if count else np.zeros((0, 4))
    return Adjusted(
        world_from_marker=markers_out,
        camera_from_world=cameras_out,
        observations=observations,
        errors_px=np.sqrt(np.mean(corner_errors**2, axis=1)) if count else np.zeros(0),
        corner_errors_px=corner_errors,
        jacobian=r.jac(x) if count and shape[1] else None,
        residuals=residual,
        frames=frames,
        free_markers=markers[1:],
        evaluations=evaluations,
    )


# ---------------------------------------------------------------------------- uncertainty


def marker_sigmas(adjusted: Adjusted) -> dict[int, float]:
    """Each free marker's 1-sigma 3D centre position uncertainty, millimetres (module doc)."""
    jacobian = adjusted.jacobian
    if jacobian is None or not adjusted.free_markers:
        return {}
    n_frames = len(adjusted.frames)
    rows, params = jacobian.shape
    dof = rows - params
    if dof <= 0:
        return {m: math.nan for m in adjusted.free_markers}
    variance = float(adjusted.residuals @ adjusted.residuals) / dof
    normal = (jacobian.T @ jacobian).tocsr()
    split = 6 * n_frames
    a = normal[:split, :split]
    b = normal[:split, split:]
    c = normal[split:, split:].toarray()
    blocks = np.stack([a[6 * i : 6 * i + 6, 6 * i : 6 * i + 6].toarray() for i in range(n_frames)])
    try:
        inverses = np.linalg.inv(blocks)
    except np.linalg.LinAlgError:
        inverses = np.linalg.pinv(blocks)
    a_inverse = sparse.block_diag(list(inverses), format="csr")
    schur = c - (b.T @ (a_inverse @ b)).toarray()
    try:
        covariance = variance * np.linalg.inv(schur)
    except np.linalg.LinAlgError:
        covariance = variance * np.linalg.pinv(schur)
    sigmas = {}
    for j, marker_id in enumerate(adjusted.free_markers):
        block = covariance[6 * j + 3 : 6 * j + 6, 6 * j + 3 : 6 * j + 6]
        sigmas[marker_id] = 1000.0 * math.sqrt(max(float(np.trace(block)), 0.0))
    return sigmas
