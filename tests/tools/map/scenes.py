"""Known layouts for the map tests: observations projected from exact poses (fast), the room of 20
markers on four walls with a camera walking a loop through it, and the truth they are scored against."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose, look_at, marker_corners_in_marker
from ar_anchor.tools.map import FrameObservations
from ar_anchor.track.marker_poses import solve_markers
from ar_anchor.track.pose import MarkerPose

# a 640x480 webcam with barrel distortion (the chessboard video's camera is stronger still)
WEBCAM = CameraModel(
    np.array([[650.0, 0.0, 321.5], [0.0, 648.0, 238.0], [0.0, 0.0, 1.0]]),
    np.array([-0.3, 0.12, 0.001, -0.0008, 0.0]),
    640,
    480,
)

# the room: 4 m x 3 m, walls at x = +-2 and z = +-1.5, markers of 20 cm facing into the room
ROOM_HALF = (2.0, 1.5)
ROOM_MARKER_M = 0.2
ROOM_CENTRE = np.array([0.0, 1.4, 0.0])


def truth_corners(markers: dict[int, Pose], length_m: float) -> dict[int, np.ndarray]:
    """Each marker's corners (4, 3) in the world."""
    return {marker_id: pose.apply(marker_corners_in_marker(length_m)) for marker_id, pose in markers.items()}


def sheet_markers(cols: int = 4, rows: int = 2, length_m: float = 0.05, gap_m: float = 0.03) -> dict[int, Pose]:
    """A planar sheet of markers, ids 0.., row-major, a little bent out of plane so no two are coplanar."""
    step = length_m + gap_m
    markers = {}
    for k in range(cols * rows):
        row, col = divmod(k, cols)
        centre = np.array([col * step, -row * step, 0.004 * math.sin(k)])
        markers[k] = Pose(np.array([0.02 * math.cos(k), 0.02 * math.sin(2 * k), 0.05 * k]), centre)
    return markers


def sheet_cameras(count: int, rng: np.random.Generator, target: np.ndarray) -> list[Pose]:
    """Cameras 0.35-0.7 m from ``target``, looking at it from up to about 35 degrees off its normal."""
    cameras = []
    for _ in range(count):
        direction = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5), 1.0])
        eye = target + direction / np.linalg.norm(direction) * rng.uniform(0.35, 0.7)
        aim = target + rng.normal(0.0, 0.02, 3)
        cameras.append(look_at(eye, aim, up=(rng.normal(0, 0.2), 1.0, 0.0)))
    return cameras


def observe(
    markers: dict[int, Pose],
    cameras: list[Pose],
    camera: CameraModel,
    length_m: float,
    *,
    noise_px: float,
    rng: np.random.Generator,
) -> list[FrameObservations]:
    """Each camera's view of the markers fully in its image, corners with Gaussian noise, as the map
    pipeline observes them (both IPPE solutions per marker)."""
    frames = []
    for index, camera_from_world in enumerate(cameras):
        ids, corners, hypotheses, ambiguity = [], [], [], []
        seen, quads = [], []  # the markers fully in the image and their noisy corners: solved in one call
        for marker_id, world_from_marker in markers.items():
            world = world_from_marker.apply(marker_corners_in_marker(length_m))
            if np.any(camera_from_world.apply(world)[:, 2] < 0.05):
                continue
            pixels, _ = cv2.projectPoints(
                world, camera_from_world.rvec, camera_from_world.tvec, camera.camera_matrix, camera.dist_or_none
            )
            pixels = pixels.reshape(4, 2)
            if np.any(pixels < 2) or np.any(pixels > np.array(camera.size) - 3):
                continue
            seen.append(marker_id)
            quads.append(pixels + rng.normal(0.0, noise_px, (4, 2)))
        solved_all = (
            solve_markers(np.array(seen), np.array(quads), np.full(len(seen), length_m), camera) if seen else []
        )
        for marker_id, pixels, solved in zip(seen, quads, solved_all):
            if isinstance(solved, MarkerPose):
                ids.append(marker_id)
                corners.append(pixels)
                hypotheses.append(tuple(h.pose for h in solved.hypotheses))
                ambiguity.append(solved.ambiguity)
        if len(ids) >= 2:
            frames.append(FrameObservations(0, index, np.array(ids), np.stack(corners), tuple(hypotheses), ambiguity))
    return frames


def room_markers(per_wall: int = 5) -> dict[int, Pose]:
    """``per_wall`` markers on each of the four walls (ids 0 .. 4 per_wall - 1 around the room), between 1.1 and
    1.7 m high, facing into the room (marker z: the wall's inward normal, y: up)."""
    half_x, half_z = ROOM_HALF
    walls = [  # (a point of the wall, its direction left to right seen from inside, inward normal, half width)
        (np.array([0.0, 0.0, -half_z]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), half_x),
        (np.array([half_x, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0]), half_z),
        (np.array([0.0, 0.0, half_z]), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]), half_x),
        (np.array([-half_x, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]), half_z),
    ]
    markers = {}
    up = np.array([0.0, 1.0, 0.0])
    for w, (origin, right, normal, half) in enumerate(walls):
        for k in range(per_wall):
            along = (-0.8 + 1.6 * k / (per_wall - 1)) * half
            height = 1.1 + 0.6 * ((k * 7 + w * 3) % 5) / 4
            rotation = np.column_stack([right, up, normal])
            markers[w * per_wall + k] = Pose.from_matrix(rotation, origin + along * right + height * up)
    return markers


def room_path(frames: int) -> list[Pose]:
    """A camera walking a loop through the room, turning once around while looking at the walls (its
    position opposite where it looks, so it sees a good stretch of wall), with a small sway."""
    poses = []
    for i in range(frames):
        s = i / frames
        heading = 2.0 * math.pi * s
        outward = np.array([math.cos(heading), 0.0, math.sin(heading)])
        eye = ROOM_CENTRE - 0.7 * outward + np.array([0.1 * math.sin(5 * heading), 0.15 * math.sin(3 * heading), 0.0])
        aim = ROOM_CENTRE + 3.0 * outward + np.array([0.0, -0.1 + 0.2 * math.sin(2 * heading), 0.0])
        poses.append(look_at(eye, aim, up=(0.05 * math.sin(7 * heading), 1.0, 0.0)))
    return poses
