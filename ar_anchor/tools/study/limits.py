"""The ranges every number of ``ar-anchor study`` must lie in, checked where it enters.

Each limit has a physical reason (a marker must cover a few pixels and fit in the image, noise below
the grey-level range, a field of view a lens can have) or bounds the time of a single OpenCV call,
which no Ctrl-C can interrupt (one RANSAC solve, one render of the jitter scene). A value outside its
range is an :class:`~ar_anchor.errors.InputError` (exit 2) that names the option and the range.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from ...camera import CameraModel
from ...errors import InputError, printable
from ...geometry import marker_corners_in_marker
from ...synthetic import Trajectory
from .jitter import SETTLE_FRAMES, JitterSetup

__all__ = [
    "MAX_VALUES",
    "MAX_VIEW_M",
    "MIN_MARKER_PX",
    "RANGES",
    "check_camera",
    "check_distances",
    "distance_range",
    "in_range",
]

# option: (lowest, highest, unit); both ends allowed
RANGES: dict[str, tuple[float, float, str]] = {
    "--seed": (0, 1_000_000, ""),  # the jitter study seeds OpenCV's generator with seed * 1000 + distance
    "--seeds": (1, 100_000, ""),
    "--points": (6, 1000, ""),  # one RANSAC solve costs points x iterations and cannot be interrupted
    "--iterations": (1, 5000, ""),
    "--pixel-noise": (0.0, 100.0, " px"),
    "--threshold": (0.001, 1000.0, " px"),
    "--thresholds": (0.001, 1000.0, " px"),
    "--frames": (SETTLE_FRAMES + 2, 100_000, ""),  # the first SETTLE_FRAMES are the filter's settling time
    "--marker-m": (0.001, 1.0, " m"),
    "--sensor-noise": (0.0, 100.0, " grey levels"),
    "--blur": (0.0, 10.0, " px"),
}
MAX_VALUES = 100  # values of a list option (--distances, --thresholds, --contaminations)
MIN_MARKER_PX = 8  # a marker's side below this many pixels cannot be decoded
MAX_VIEW_M = 50.0  # widest view of the jitter scene (a 2 m wall, tiled beyond): bounds one render's time
MAX_SIDE_PX = {"jitter": 4096, "pnp": 16384}  # image sides: the jitter study renders every pixel
MIN_SIDE_PX = 64
FOV_DEG = (1.0, 170.0)


def in_range(option: str, value: float, *, what: str = "must be", why: str = "") -> None:
    """An :class:`InputError` unless ``value`` lies in ``option``'s range (:data:`RANGES`); ``why`` is
    added to the message in brackets."""
    low, high, unit = RANGES[option]
    if not (math.isfinite(value) and low <= value <= high):
        reason = f" ({why})" if why else ""
        raise InputError(f"{option}: {what} in [{low:g}, {high:g}]{unit}{reason}, got {value:g}")


def check_camera(camera: CameraModel, source: object, study: str) -> None:
    """An :class:`InputError` naming ``--camera FILE`` unless the camera suits the study (``jitter`` or
    ``pnp``): image sides, principal point inside the image, no skew, a field of view of 1-170 deg,
    and a distortion model that can be inverted over the whole image."""
    where = f"--camera: camera file {printable(source)}"
    width, height = camera.size
    low, high = MIN_SIDE_PX, MAX_SIDE_PX[study]
    if not (low <= width <= high and low <= height <= high):
        raise InputError(f"{where}: image {width}x{height}; the {study} study needs sides of {low}-{high} px")
    k = camera.camera_matrix
    if not (0.0 <= k[0, 2] <= width and 0.0 <= k[1, 2] <= height):
        raise InputError(f"{where}: principal point ({k[0, 2]:g}, {k[1, 2]:g}) lies outside the {width}x{height} image")
    if abs(k[0, 1]) > 1e-6 * k[0, 0]:
        raise InputError(f"{where}: skew {k[0, 1]:g}; the studies need a camera without skew (K[0][1] = 0)")
    for axis, focal, side in (("horizontal", k[0, 0], width), ("vertical", k[1, 1], height)):
        fov = math.degrees(2.0 * math.atan(side / (2.0 * focal)))
        if not FOV_DEG[0] <= fov <= FOV_DEG[1]:
            raise InputError(
                f"{where}: {axis} field of view {fov:.3g} deg (focal length {focal:g} px over {side} px); "
                f"the studies need {FOV_DEG[0]:g}-{FOV_DEG[1]:g} deg"
            )
    if camera.has_distortion and not _distortion_inverts(camera):
        raise InputError(
            f"{where}: the distortion model folds over (pixels no point projects to) and cannot be inverted "
            "over the whole image"
        )


def _distortion_inverts(camera: CameraModel) -> bool:
    """Pixels on a grid over the image (edges included) go to rays and back within 0.01 px."""
    width, height = camera.size
    u, v = np.meshgrid(np.linspace(0, width - 1, 33), np.linspace(0, height - 1, 33))
    pixels = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
    k = camera.camera_matrix
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        rays = cv2.undistortPointsIter(pixels, k, camera.dist_coeffs, None, None, criteria)
    else:  # OpenCV 5 folded the criteria into undistortPoints
        rays = cv2.undistortPoints(pixels, k, camera.dist_coeffs, R=None, P=None, criteria=criteria)
    rays = rays.reshape(-1, 2)
    if not np.all(np.isfinite(rays)):
        return False
    back = camera.project(np.column_stack([rays, np.ones(len(rays))]))
    return bool(np.all(np.isfinite(back)) and np.abs(back - pixels.reshape(-1, 2)).max() < 0.01)


def _fits(setup: JitterSetup, distance_m: float) -> bool:
    """At ``distance_m``, the lone marker and the board lie wholly in the image, in front of the camera."""
    scene, aim = setup.scene()
    points = [m.world_from_target.apply(marker_corners_in_marker(m.length_m)) for m in scene.markers]
    for placed in scene.boards:
        width, height = placed.board.size_m
        outline = np.array([[0, 0, 0], [width, 0, 0], [width, height, 0], [0, height, 0]], float)
        points.append(placed.world_from_target.apply(outline))
    trajectory = Trajectory(
        kind="static", near_m=distance_m, azimuth_deg=setup.tilt_deg, elevation_deg=0.0, roll_deg=0.0, look_at=aim
    )
    in_camera = trajectory.camera_from_world(0.0).apply(np.concatenate(points))
    if np.any(in_camera[:, 2] <= 1e-3):
        return False
    pixels = setup.camera.project(in_camera)
    width, height = setup.camera.size
    return bool(np.all((pixels >= 0) & (pixels <= np.array([width - 1.0, height - 1.0]))))


def distance_range(setup: JitterSetup) -> tuple[float, float] | None:
    """The distances (m) at which the jitter study can run: the nearest at which marker and board fit in
    the image, the farthest at which the marker still covers :data:`MIN_MARKER_PX` and the view is at
    most :data:`MAX_VIEW_M` wide; None when no distance satisfies both."""
    k, (width, _) = setup.camera.camera_matrix, setup.camera.size
    far = min(k[0, 0] * setup.marker_m / MIN_MARKER_PX, MAX_VIEW_M * k[0, 0] / width)
    if not _fits(setup, far):
        return None
    near, fits = 1e-3, far
    for _ in range(50):  # bisection: the view only shrinks toward the aim point as the camera backs off
        middle = math.sqrt(near * fits)
        if _fits(setup, middle):
            fits = middle
        else:
            near = middle
        if fits / near < 1.001:
            break
    return fits, far


def _three_digits(value: float, rounding: Callable[[float], int]) -> float:
    """``value`` rounded to three significant digits by ``rounding`` (up or down: a range shown stays inside)."""
    scale = 10.0 ** (math.floor(math.log10(value)) - 2)
    return rounding(value / scale) * scale


def check_distances(setup: JitterSetup, distances: Sequence[float], text: str) -> None:
    """An :class:`InputError` naming ``--distances`` unless every distance lies in :func:`distance_range`."""
    if not all(d > 0 for d in distances):
        raise InputError(f"--distances: must all be > 0 m, got {text}")
    camera = setup.camera
    scene = (
        f"the {setup.marker_m * 100:g} cm marker and its board in the {camera.width}x{camera.height} image "
        f"(fx {camera.camera_matrix[0, 0]:g})"
    )
    allowed = distance_range(setup)
    if allowed is None:
        raise InputError(
            f"--distances: no distance shows {scene} whole with the marker at least {MIN_MARKER_PX} px wide; "
            "use a larger --marker-m or another --camera"
        )
    near, far = allowed
    outside = [d for d in distances if not near <= d <= far]
    if outside:
        shown = f"{_three_digits(near, math.ceil):g}-{_three_digits(far, math.floor):g}"
        raise InputError(
            f"--distances: {', '.join(f'{d:g}' for d in outside)} m outside {shown} m, where "
            f"{scene} fit whole and the marker covers at least {MIN_MARKER_PX} px (with a view at most "
            f"{MAX_VIEW_M:g} m wide)"
        )
