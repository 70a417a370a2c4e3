"""From observations to a map: a flip-robust initialisation, bundle adjustment, outliers, uncertainty.

Initialisation (:func:`initialise`)
    The reference marker (the most seen, or ``origin``) is the map frame. Rounds, until no marker can be
    added: (1) every frame's camera pose is solved from the placed markers it shows -- each placed marker's
    IPPE solutions give candidate poses, the candidate that reprojects most placed markers within
    ``LOOSE_PX`` wins, is refined with ``solvePnPRefineLM`` on them and re-scored until its inliers settle
    (RANSAC across markers, exhaustive). A frame needs two agreeing placed markers, or one whose IPPE pair is
    decisive (error ratio >= ``DECISIVE_RATIO``); (2) an unplaced marker's candidate poses (its IPPE solutions
    in every located frame showing it, moved into the map frame) are scored by how many of those frames
    they reproject within ``PLACE_INLIER_PX``; the best one, refined on its supporters, places the marker
    when at least ``MIN_FRAMES`` frames agree (never one frame's word), and is refused when it lands on a
    placed marker (a misread id); (3) a short bundle adjustment settles what was placed.

Bundle adjustment (:func:`bundle_adjust`)
    ``scipy.optimize.least_squares`` (trust region, Huber loss of scale ``HUBER_PX``) over every located
    frame's ``camera_from_world`` and every marker's ``world_from_marker`` but the reference's (fixed: the
    gauge). Rotations are increments left of the starting rotation (``R = exp([d]x) R0``, re-centred at every
    call, so never near the axis-angle singularity). Residuals: the pixel error of each observed corner,
    projected by ``cv2.projectPoints`` with the camera's distortion; its Jacobian is analytic and sparse
    (each observation's 8 rows touch 6 frame and 6 marker columns), built from ``projectPoints``' own
    derivatives by the chain rule. Observations still off by more than ``max(OUTLIER_PX, 5 x median)``
    after a solve (a misread id, a smeared corner) are dropped and the map solved again.

Uncertainty (:func:`marker_sigmas`)
    The Gauss-Newton normal matrix ``J^T J`` at the solution, scaled by the residual variance
    ``sum(r^2) / (m - n)``; the frame poses are eliminated by their Schur complement (their blocks are 6x6
    and independent), and each marker's centre covariance is the translation block of the inverse:
    reported as ``sqrt(trace)``, a 1-sigma 3D position uncertainty relative to the reference marker.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sparse
from scipy.optimize import least_squares

from ...camera import CameraModel
from ...errors import InputError
from ...geometry import Pose, marker_corners_in_marker
from .model import FrameObservations, MarkerMap

__all__ = [
    "DECISIVE_RATIO",
    "MIN_FRAMES",
    "OUTLIER_PX",
    "MapSolution",
    "bundle_adjust",
    "build_map",
    "initialise",
    "marker_sigmas",
]

log = logging.getLogger(__name__)

DECISIVE_RATIO = 3.0  # a lone placed marker locates a frame only when its worse IPPE solution is this much worse
LOOSE_PX = 12.0  # initialisation: a candidate camera pose's inlier markers, before refinement
INIT_INLIER_PX = 5.0  # initialisation: inlier markers after refinement (the map is not adjusted yet)
PLACE_INLIER_PX = 6.0  # initialisation: frames agreeing with a candidate marker pose
MIN_FRAMES = 3  # a marker is placed when at least this many frames agree on its pose
OUTLIER_PX = 3.0  # an observation whose RMS corner error stays above max(this, 5 x median) is dropped
HUBER_PX = 1.0  # the robust loss's scale
_MAX_CANDIDATES = 48  # initialisation: candidate poses tried per marker (frames sampled evenly)
_MAX_SCORED = 400  # initialisation: frames a candidate is scored against (sampled evenly)

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------- the problem


@dataclass
class _Problem:
    """The observations with what every step needs precomputed: the cameras, the marker square, and each
    frame's corners undistorted to normalised image coordinates (for fast vectorised scoring)."""

    frames: list[FrameObservations]
    cameras: list[CameraModel]  # per input
    length_m: float
    square: np.ndarray = field(init=False)
    normalised: list[np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.square = marker_corners_in_marker(self.length_m)
        self.normalised = []
        for frame in self.frames:
            camera = self.camera(frame)
            points = cv2.undistortPoints(
                frame.corners.reshape(-1, 1, 2),
                camera.camera_matrix,
                camera.dist_or_none,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
            )
            self.normalised.append(points.reshape(-1, 4, 2))

    def camera(self, frame: FrameObservations) -> CameraModel:
        return self.cameras[frame.source]

    def focal(self, frame: FrameObservations) -> float:
        k = self.camera(frame).camera_matrix
        return float(0.5 * (k[0, 0] + k[1, 1]))


def _rotations(poses: Sequence[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations and (N, 3) translations of ``poses``."""
    return np.stack([p.rotation for p in poses]), np.stack([p.tvec for p in poses])


def _normalised_errors_px(
    rotation: np.ndarray, translation: np.ndarray, world: np.ndarray, observed: np.ndarray, focal: float | np.ndarray
) -> np.ndarray:
    """RMS corner error (pinhole pixels: normalised error x focal) of world quads seen by cameras.

    ``rotation`` (..., 3, 3), ``translation`` (..., 3): camera_from_world; ``world`` (..., 4, 3);
    ``observed`` (..., 4, 2) normalised. Broadcast over the leading axes; inf where a corner is behind."""
    in_camera = np.einsum("...ij,...kj->...ki", rotation, world) + translation[..., None, :]
    depth = in_camera[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        projected = in_camera[..., :2] / depth[..., None]
        error = np.sqrt(np.mean(np.sum((projected - observed) ** 2, axis=-1), axis=-1)) * focal
    return np.where(np.all(depth > 1e-6, axis=-1), error, np.inf)


def _pixel_errors(pose: Pose, world: np.ndarray, observed: np.ndarray, camera: CameraModel) -> np.ndarray:
    """RMS corner error (pixels, the camera's full model) of quads ``world`` (S, 4, 3) seen by ``pose``."""
    projected, _ = cv2.projectPoints(
        world.reshape(-1, 3), pose.rvec, pose.tvec, camera.camera_matrix, camera.dist_or_none
    )
    error = np.sqrt(np.mean(np.sum((projected.reshape(-1, 4, 2) - observed) ** 2, axis=-1), axis=-1))
    depth = pose.apply(world.reshape(-1, 3))[:, 2].reshape(-1, 4)
    return np.where(np.all(depth > 1e-6, axis=1), error, np.inf)


def _refine_lm(pose: Pose, world: np.ndarray, observed: np.ndarray, camera: CameraModel) -> Pose:
    """``solvePnPRefineLM`` of a camera pose on quads ``world`` (S, 4, 3) and their corners (S, 4, 2)."""
    try:
        rvec, tvec = cv2.solvePnPRefineLM(
            world.reshape(-1, 3),
            observed.reshape(-1, 2),
            camera.camera_matrix,
            camera.dist_or_none,
            pose.rvec.reshape(3, 1).copy(),
            pose.tvec.reshape(3, 1).copy(),
        )
    except cv2.error:
        return pose
    refined = Pose(rvec.reshape(3), tvec.reshape(3))
    return refined if refined.is_finite() else pose


def _decisive(frame: FrameObservations, k: int, ratio: float = DECISIVE_RATIO) -> bool:
    """Is marker ``k`` of ``frame`` alone enough to trust its better IPPE solution?"""
    return len(frame.hypotheses[k]) == 1 or bool(frame.ambiguity[k] >= ratio)


# ---------------------------------------------------------------------------- initialisation


def _locate_frame(problem: _Problem, index: int, placed: dict[int, Pose], ratio: float = DECISIVE_RATIO) -> Pose | None:
    """The frame's ``camera_from_world`` from the placed markers it shows (module doc), or None."""
    frame = problem.frames[index]
    seen = [k for k, marker_id in enumerate(frame.ids.tolist()) if marker_id in placed]
    if not seen:
        return None
    camera = problem.camera(frame)
    if len(seen) == 1:
        k = seen[0]
        if not _decisive(frame, k, ratio):
            return None
        return frame.hypotheses[k][0].compose(placed[int(frame.ids[k])].inverse())
    world = np.stack([placed[int(frame.ids[k])].apply(problem.square) for k in seen])  # (S, 4, 3)
    observed = frame.corners[seen]
    normalised = problem.normalised[index][seen]
    candidates = [h.compose(placed[int(frame.ids[k])].inverse()) for k in seen for h in frame.hypotheses[k]]
    rotation, translation = _rotations(candidates)
    errors = _normalised_errors_px(
        rotation[:, None], translation[:, None], world[None], normalised[None], problem.focal(frame)
    )  # (C, S)
    inliers = errors < LOOSE_PX
    counts = inliers.sum(axis=1)
    totals = np.where(inliers, errors, 0.0).sum(axis=1)
    best = int(np.lexsort((totals, -counts))[0])
    if counts[best] == 0:
        return None
    pose, mask = candidates[best], inliers[best]
    for _ in range(4):
        pose = _refine_lm(pose, world[mask], observed[mask], camera)
        refined_mask = _pixel_errors(pose, world, observed, camera) < INIT_INLIER_PX
        settled = not refined_mask.any() or np.array_equal(refined_mask, mask)
        mask = refined_mask
        if settled:
            break
    count = int(mask.sum())
    if count >= 2:
        return pose
    if count == 1:
        k = seen[int(np.flatnonzero(mask)[0])]
        if _decisive(frame, k, ratio):
            return pose
    return None


def _place_marker(
    problem: _Problem, marker_id: int, entries: list[tuple[int, int]], cameras: dict[int, Pose]
) -> tuple[Pose | None, int, str]:
    """A marker's ``world_from_marker`` from the located frames showing it (``entries``: frame, position in
    it): (pose or None, frames agreeing, why not placed)."""
    if len(entries) < MIN_FRAMES:
        return None, 0, f"seen in {len(entries)} located frame(s), {MIN_FRAMES} needed"
    scored = [entries[i] for i in _even(len(entries), _MAX_SCORED)]
    rotation, translation = _rotations([cameras[f] for f, _ in scored])
    normalised = np.stack([problem.normalised[f][k] for f, k in scored])
    focal = np.array([problem.focal(problem.frames[f]) for f, _ in scored])
    candidates = []
    for i in _even(len(entries), _MAX_CANDIDATES // 2):
        f, k = entries[i]
        world_from_camera = cameras[f].inverse()
        candidates += [world_from_camera.compose(h) for h in problem.frames[f].hypotheses[k]]
    cand_rotation, cand_translation = _rotations(candidates)
    world = np.einsum("cij,kj->cki", cand_rotation, problem.square) + cand_translation[:, None, :]  # (C, 4, 3)
    errors = _normalised_errors_px(
        rotation[None], translation[None], world[:, None], normalised[None], focal[None]
    )  # (C, E)
    inliers = errors < PLACE_INLIER_PX
    counts = inliers.sum(axis=1)
    totals = np.where(inliers, errors, 0.0).sum(axis=1)
    best = int(np.lexsort((totals, -counts))[0])
    if counts[best] < MIN_FRAMES:
        return (
            None,
            int(counts[best]),
            (
                f"its views disagree: the best pose is supported by {counts[best]} of {len(scored)} frames, "
                f"{MIN_FRAMES} needed"
            ),
        )
    pose = _refine_marker(
        problem,
        candidates[best],
        rotation[inliers[best]],
        translation[inliers[best]],
        normalised[inliers[best]],
        focal[inliers[best]],
    )
    world_refined = pose.apply(problem.square)
    support = int(
        (_normalised_errors_px(rotation, translation, world_refined[None], normalised, focal) < PLACE_INLIER_PX).sum()
    )
    if support < counts[best]:  # the refinement made it worse: keep the candidate
        pose, support = candidates[best], int(counts[best])
    return pose, support, ""


def _refine_marker(
    problem: _Problem,
    start: Pose,
    rotation: np.ndarray,
    translation: np.ndarray,
    normalised: np.ndarray,
    focal: np.ndarray,
) -> Pose:
    """A marker's pose refined on the frames that agree with it, the cameras held fixed (normalised errors)."""
    rotation0 = start.rotation

    def residuals(x: np.ndarray) -> np.ndarray:
        increment, _ = cv2.Rodrigues(x[:3])
        world = problem.square @ (increment @ rotation0).T + x[3:]
        in_camera = np.einsum("eij,kj->eki", rotation, world) + translation[:, None, :]
        projected = in_camera[..., :2] / np.maximum(in_camera[..., 2:], 1e-9)
        return ((projected - normalised) * focal[:, None, None]).ravel()

    try:
        solved = least_squares(residuals, np.concatenate([np.zeros(3), start.tvec]), loss="huber", f_scale=HUBER_PX)
    except (ValueError, np.linalg.LinAlgError):
        return start
    increment, _ = cv2.Rodrigues(solved.x[:3])
    pose = Pose.from_matrix(increment @ rotation0, solved.x[3:])
    return pose if pose.is_finite() else start


def _even(count: int, at_most: int) -> list[int]:
    """At most ``at_most`` indices of ``range(count)``, evenly spread."""
    if count <= at_most:
        return list(range(count))
    return sorted(set(np.linspace(0, count - 1, at_most).round().astype(int).tolist()))


@dataclass
class Initial:
    """The initialisation's result: the map and frame poses, and the markers it could not place (id -> why)."""

    reference_id: int
    world_from_marker: dict[int, Pose]
    camera_from_world: dict[int, Pose]
    unplaced: dict[int, str]
    rounds: int


def initialise(problem: _Problem, origin: int | None = None, progress: Progress | None = None) -> Initial:
    """Place the markers incrementally from the reference marker (module doc)."""
    counts = Counter(int(i) for frame in problem.frames for i in frame.ids.tolist())
    if origin is not None and origin not in counts:
        raise InputError(
            f"--origin {origin}: marker {origin} is never seen with another marker "
            f"(seen together: {_id_list(sorted(counts))})"
        )
    reference = origin if origin is not None else max(counts, key=lambda i: (counts[i], -i))
    placed: dict[int, Pose] = {reference: Pose.identity()}
    cameras: dict[int, Pose] = {}
    unplaced: dict[int, str] = {}
    rounds = 0
    ratio = DECISIVE_RATIO
    while True:
        rounds += 1
        cameras = {}
        for index in range(len(problem.frames)):
            pose = _locate_frame(problem, index, placed, ratio)
            if pose is not None:
                cameras[index] = pose
        entries: dict[int, list[tuple[int, int]]] = {}
        for index in cameras:
            for k, marker_id in enumerate(problem.frames[index].ids.tolist()):
                if marker_id not in placed:
                    entries.setdefault(marker_id, []).append((index, k))
        added: dict[int, Pose] = {}
        unplaced = {
            m: f"never seen in a frame located from the placed markers ({counts[m]} frame(s))"
            for m in counts
            if m not in placed
        }
        for marker_id, found in sorted(entries.items(), key=lambda item: -len(item[1])):
            pose, support, why = _place_marker(problem, marker_id, found, cameras)
            if pose is None:
                unplaced[marker_id] = why
                continue
            clash = _coincident(pose, {**placed, **added}, problem.length_m)
            if clash is not None:
                unplaced[marker_id] = f"lands on marker {clash} (a misread id?)"
                continue
            added[marker_id] = pose
            unplaced.pop(marker_id, None)
        if not added and len(placed) == 1 and ratio > 1.0:
            # no view of the reference is decisive (small or far markers): let each view's better solution
            # locate its frame; the placement's consensus over frames outvotes the flipped ones
            log.info("no decisive view of the reference marker %d: trying every view's better solution", reference)
            ratio = 1.0
            continue
        if not added:
            break
        placed.update(added)
        ratio = DECISIVE_RATIO
        if progress is not None:
            progress(f"initialisation round {rounds}: {len(placed)} marker(s) placed, {len(cameras)} frame(s) located")
        if len(placed) >= 3:
            located = {i: p for i, p in cameras.items()}
            adjusted = bundle_adjust(problem, placed, located, reference, max_nfev=15)
            placed = adjusted.world_from_marker
    return Initial(reference, placed, cameras, unplaced, rounds)


def _coincident(pose: Pose, placed: dict[int, Pose], length_m: float) -> int | None:
    """The placed marker whose centre is within half a side of ``pose``'s, if any."""
    for marker_id, other in placed.items():
        if np.linalg.norm(other.tvec - pose.tvec) < 0.5 * length_m:
            return marker_id
    return None


def _id_list(ids: Sequence[int], at_most: int = 12) -> str:
    shown = ", ".join(str(i) for i in ids[:at_most])
    return (shown + f", ... ({len(ids)} in all)") if len(ids) > at_most else (shown or "none")


# ---------------------------------------------------------------------------- bundle adjustment


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


def bundle_adjust(
    problem: _Problem,
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
    if observations is None:
        observations = [
            (f, k)
            for f in camera_from_world
            for k, marker_id in enumerate(problem.frames[f].ids.tolist())
            if marker_id in world_from_marker
        ]
    per_frame = Counter(f for f, _ in observations)
    observations = sorted((f, k) for f, k in observations if per_frame[f] >= 2 and f in camera_from_world)
    frames = sorted({f for f, _ in observations})
    markers = [reference] + sorted(m for m in world_from_marker if m != reference)
    frame_pos = {f: i for i, f in enumerate(frames)}
    marker_pos = {m: i for i, m in enumerate(markers)}
    n_frames, n_free = len(frames), len(markers) - 1
    obs_frame = np.array([frame_pos[f] for f, _ in observations], dtype=np.int64)
    obs_marker = np.array([marker_pos[int(problem.frames[f].ids[k])] for f, k in observations], dtype=np.int64)
    observed = (
        np.stack([problem.frames[f].corners[k] for f, k in observations]) if observations else np.zeros((0, 4, 2))
    )
    count = len(observations)
    # each frame's observations are contiguous (sorted by frame)
    bounds = np.searchsorted(obs_frame, np.arange(n_frames + 1))
    frame_rotation0, frame_translation0 = _rotations([camera_from_world[f] for f in frames])
    marker_rotation0, marker_translation0 = _rotations([world_from_marker[m] for m in markers])
    rotated_square = np.einsum("mij,kj->mki", marker_rotation0, problem.square)  # (M, 4, 3): R0_m s
    cams = [problem.camera(problem.frames[f]) for f in frames]
    x0 = np.concatenate(
        [
            np.hstack([np.zeros((n_frames, 3)), frame_translation0]).ravel(),
            np.hstack([np.zeros((n_free, 3)), marker_translation0[1:]]).ravel(),
        ]
    )

    # the Jacobian's structure: observation o's 8 rows x (6 frame columns, 6 marker columns unless the reference)
    rows = np.repeat(np.arange(8 * count).reshape(count, 8, 1), 6, axis=2)
    frame_cols = np.broadcast_to((6 * obs_frame)[:, None, None] + np.arange(6), (count, 8, 6))
    free = obs_marker > 0
    marker_cols = np.broadcast_to(
        (6 * n_frames + 6 * (obs_marker[free] - 1))[:, None, None] + np.arange(6), (int(free.sum()), 8, 6)
    )
    jac_rows = np.concatenate([rows.ravel(), rows[free].ravel()])
    jac_cols = np.concatenate([frame_cols.ravel(), marker_cols.ravel()])
    shape = (8 * count, 6 * (n_frames + n_free))
    corner_of_row = np.repeat(np.arange(4), 2)

    cache: dict[str, object] = {}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residuals (8 O,), frame-part Jacobian (O, 8, 6), marker-part Jacobian (O, 8, 6)) at ``x``."""
        key = x.tobytes()
        if cache.get("key") == key:
            return cache["value"]  # type: ignore[return-value]
        frame_x = x[: 6 * n_frames].reshape(n_frames, 6)
        marker_x = np.vstack([np.zeros((1, 6)), x[6 * n_frames :].reshape(n_free, 6)])
        marker_x[0, 3:] = marker_translation0[0]
        increments, d_increments = [], []
        for m in range(len(markers)):
            rotation, jacobian = cv2.Rodrigues(marker_x[m, :3])
            increments.append(rotation)
            d_increments.append(jacobian.reshape(3, 3, 3))  # [i] = d rotation / d x_i
        increments_arr = np.stack(increments)
        world = np.einsum("mij,mkj->mki", increments_arr, rotated_square) + marker_x[:, None, 3:]  # (M, 4, 3)
        # d world corner / d marker increment i: dR_i (R0 s)
        d_world = np.einsum("mipq,mkq->mkpi", np.stack(d_increments), rotated_square)  # (M, 4, 3, 3)
        residual = np.empty((count, 8))
        d_frame = np.empty((count, 8, 6))
        d_point = np.empty((count, 8, 3))
        for i in range(n_frames):
            lo, hi = bounds[i], bounds[i + 1]
            points = world[obs_marker[lo:hi]].reshape(-1, 3)
            pre = points @ frame_rotation0[i].T
            camera = cams[i]
            projected, jacobian = cv2.projectPoints(
                pre, frame_x[i, :3], frame_x[i, 3:], camera.camera_matrix, camera.dist_or_none
            )
            residual[lo:hi] = (projected.reshape(-1, 4, 2) - observed[lo:hi]).reshape(-1, 8)
            jacobian = jacobian.reshape(hi - lo, 8, -1)
            d_frame[lo:hi] = jacobian[:, :, :6]
            full_rotation = cv2.Rodrigues(frame_x[i, :3])[0] @ frame_rotation0[i]
            d_point[lo:hi] = jacobian[:, :, 3:6] @ full_rotation  # d pixel / d world point
        rotation_part = np.einsum("orp,orpi->ori", d_point, d_world[obs_marker][:, corner_of_row])
        d_marker = np.concatenate([rotation_part, d_point], axis=2)
        value = (residual.ravel(), d_frame, d_marker)
        cache["key"], cache["value"] = key, value
        return value

    def fun(x: np.ndarray) -> np.ndarray:
        return evaluate(x)[0]

    def jac(x: np.ndarray) -> sparse.csr_matrix:
        _, d_frame, d_marker = evaluate(x)
        data = np.concatenate([d_frame.ravel(), d_marker[free].ravel()])
        return sparse.csr_matrix((data, (jac_rows, jac_cols)), shape=shape)

    evaluations = 0
    x = x0
    if count and shape[1]:
        solved = least_squares(
            fun,
            x0,
            jac=jac,
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
    residual = fun(x) if count else np.zeros(0)
    frame_x = x[: 6 * n_frames].reshape(n_frames, 6)
    marker_x = x[6 * n_frames :].reshape(n_free, 6)
    cameras_out = {
        f: Pose.from_matrix(cv2.Rodrigues(frame_x[i, :3])[0] @ frame_rotation0[i], frame_x[i, 3:])
        for i, f in enumerate(frames)
    }
    markers_out = {reference: world_from_marker[reference]}
    for j, m in enumerate(markers[1:]):
        markers_out[m] = Pose.from_matrix(cv2.Rodrigues(marker_x[j, :3])[0] @ marker_rotation0[j + 1], marker_x[j, 3:])
    corner_errors = np.linalg.norm(residual.reshape(-1, 4, 2), axis=2) if count else np.zeros((0, 4))
    return Adjusted(
        world_from_marker=markers_out,
        camera_from_world=cameras_out,
        observations=observations,
        errors_px=np.sqrt(np.mean(corner_errors**2, axis=1)) if count else np.zeros(0),
        corner_errors_px=corner_errors,
        jacobian=jac(x) if count and shape[1] else None,
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


# ---------------------------------------------------------------------------- the whole solve


@dataclass
class MapSolution:
    """A solved map with what the report shows about it."""

    map: MarkerMap
    camera_from_world: dict[str, Pose]  # frame name -> pose, the frames the final adjustment used
    frame_order: list[str]
    observations_per_marker: dict[int, int]
    observation_errors: list[tuple[str, int, float]]  # (frame name, marker id, RMS corner error px)
    corner_errors_px: np.ndarray  # every used corner's reprojection distance
    dropped: list[tuple[str, int, float]]  # outlier observations: (frame name, marker id, RMS px at the drop)
    unplaced: dict[int, str]
    first_rms_px: float
    evaluations: int
    seconds: float
    frames_in: int

    @property
    def rms_px(self) -> float:
        """RMS of the used corners' reprojection distances."""
        errors = self.corner_errors_px
        return math.sqrt(float(np.mean(errors**2))) if errors.size else math.nan


def _rms(errors: np.ndarray) -> float:
    return math.sqrt(float(np.mean(errors**2))) if errors.size else math.nan


def build_map(
    frames: list[FrameObservations],
    cameras: list[CameraModel],
    length_m: float,
    *,
    origin: int | None = None,
    progress: Progress | None = None,
) -> MapSolution:
    """Initialise, adjust, drop outliers and adjust again, then the uncertainties (module doc).

    Raises :class:`~ar_anchor.errors.InputError` when fewer than two markers are ever seen together.
    """
    started = time.monotonic()
    together = {int(i) for frame in frames for i in frame.ids.tolist()}
    if len(together) < 2 or not frames:
        raise InputError(
            "fewer than two markers were ever seen together in one frame: a map needs frames showing two "
            "markers or more (check the video covers the markers, and --dictionary / --marker-length)"
        )
    problem = _Problem(frames, cameras, length_m)
    initial = initialise(problem, origin, progress)
    if len(initial.world_from_marker) < 2:
        reasons = "; ".join(f"{m}: {why}" for m, why in sorted(initial.unplaced.items())[:6])
        raise InputError(
            f"could place no marker beside the reference marker {initial.reference_id} ({reasons}); "
            "film the markers together from several viewpoints"
        )
    if progress is not None:
        progress(
            f"bundle adjustment: {len(initial.world_from_marker)} markers, {len(initial.camera_from_world)} frames"
        )
    adjusted = bundle_adjust(problem, initial.world_from_marker, initial.camera_from_world, initial.reference_id)
    first_rms = _rms(adjusted.corner_errors_px)
    evaluations = adjusted.evaluations
    unplaced = dict(initial.unplaced)
    dropped: list[tuple[str, int, float]] = []
    for _ in range(3):
        errors = adjusted.errors_px
        limit = max(OUTLIER_PX, 5.0 * float(np.median(errors))) if errors.size else OUTLIER_PX
        bad = errors > limit
        if not bad.any():
            break
        for (f, k), error in zip(np.array(adjusted.observations)[bad].tolist(), errors[bad].tolist()):
            dropped.append((frames[f].name, int(frames[f].ids[k]), float(error)))
        kept = [o for o, is_bad in zip(adjusted.observations, bad) if not is_bad]
        markers = dict(adjusted.world_from_marker)
        per_marker = Counter(int(frames[f].ids[k]) for f, k in kept)
        for marker_id in list(markers):
            if marker_id != initial.reference_id and per_marker[marker_id] < MIN_FRAMES:
                del markers[marker_id]
                unplaced[marker_id] = f"only {per_marker[marker_id]} observation(s) left after dropping outliers"
        kept = [(f, k) for f, k in kept if int(frames[f].ids[k]) in markers]
        if progress is not None:
            progress(f"dropped {int(bad.sum())} outlier observation(s) (> {limit:.2f} px); adjusting again")
        adjusted = bundle_adjust(problem, markers, adjusted.camera_from_world, initial.reference_id, observations=kept)
        evaluations += adjusted.evaluations
    if len(adjusted.world_from_marker) < 2:
        raise InputError("after dropping outlier observations fewer than two markers are left in the map")
    sigmas = marker_sigmas(adjusted)
    sigmas[initial.reference_id] = 0.0
    marker_map = MarkerMap(length_m, initial.reference_id, dict(sorted(adjusted.world_from_marker.items())), sigmas)
    names = {f: frames[f].name for f in adjusted.frames}
    observation_errors = [
        (frames[f].name, int(frames[f].ids[k]), float(e))
        for (f, k), e in zip(adjusted.observations, adjusted.errors_px)
    ]
    return MapSolution(
        map=marker_map,
        camera_from_world={names[f]: adjusted.camera_from_world[f] for f in adjusted.frames},
        frame_order=[names[f] for f in adjusted.frames],
        observations_per_marker=dict(sorted(Counter(m for _, m, _ in observation_errors).items())),
        observation_errors=observation_errors,
        corner_errors_px=adjusted.corner_errors_px.ravel(),
        dropped=dropped,
        unplaced={m: why for m, why in sorted(unplaced.items()) if m not in adjusted.world_from_marker},
        first_rms_px=first_rms,
        evaluations=evaluations,
        seconds=time.monotonic() - started,
        frames_in=len(frames),
    )
