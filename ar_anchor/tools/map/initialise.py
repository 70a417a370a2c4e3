"""Map initialisation: place the markers one by one from the reference marker, flip-robustly.

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
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from ...camera import CameraModel
from ...errors import InputError
from ...geometry import Pose
from .adjust import bundle_adjust
from .model import FrameObservations
from .problem import HUBER_PX, Problem, Progress, rotations

__all__ = ["DECISIVE_RATIO", "MIN_FRAMES", "Initial", "initialise"]

log = logging.getLogger(__name__)

DECISIVE_RATIO = 3.0  # a lone placed marker locates a frame only when its worse IPPE solution is this much worse
LOOSE_PX = 12.0  # initialisation: a candidate camera pose's inlier markers, before refinement
INIT_INLIER_PX = 5.0  # initialisation: inlier markers after refinement (the map is not adjusted yet)
PLACE_INLIER_PX = 6.0  # initialisation: frames agreeing with a candidate marker pose
MIN_FRAMES = 3  # a marker is placed when at least this many frames agree on its pose
_MAX_CANDIDATES = 48  # initialisation: candidate poses tried per marker (frames sampled evenly)
_MAX_SCORED = 400  # initialisation: frames a candidate is scored against (sampled evenly)


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


def _locate_frame(problem: Problem, index: int, placed: dict[int, Pose], ratio: float = DECISIVE_RATIO) -> Pose | None:
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
    rotation, translation = rotations(candidates)
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
    problem: Problem, marker_id: int, entries: list[tuple[int, int]], cameras: dict[int, Pose]
) -> tuple[Pose | None, int, str]:
    """A marker's ``world_from_marker`` from the located frames showing it (``entries``: frame, position in
    it): (pose or None, frames agreeing, why not placed)."""
    if len(entries) < MIN_FRAMES:
        return None, 0, f"seen in {len(entries)} located frame(s), {MIN_FRAMES} needed"
    scored = [entries[i] for i in _even(len(entries), _MAX_SCORED)]
    rotation, translation = rotations([cameras[f] for f, _ in scored])
    normalised = np.stack([problem.normalised[f][k] for f, k in scored])
    focal = np.array([problem.focal(problem.frames[f]) for f, _ in scored])
    candidates = []
    for i in _even(len(entries), _MAX_CANDIDATES // 2):
        f, k = entries[i]
        world_from_camera = cameras[f].inverse()
        candidates += [world_from_camera.compose(h) for h in problem.frames[f].hypotheses[k]]
    cand_rotation, cand_translation = rotations(candidates)
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
    problem: Problem,
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


def initialise(problem: Problem, origin: int | None = None, progress: Progress | None = None) -> Initial:
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
