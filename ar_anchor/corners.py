"""Sub-pixel marker corners from the marker's four edges.

A marker's outer border is a dark square on a light quiet zone: its four sides are straight edges
(straight in the undistorted image). Instead of refining each corner from the few pixels around it
(``cornerSubPix``, whose window must stay small on a far marker and then keeps a bias of several
tenths of a pixel), every side is sampled along its whole length: at points every half pixel, the
intensity profile across the side locates the edge (the centroid of the dark-to-light gradient),
a line is fitted through those edge points, and each corner is the intersection of its two sides.
Dozens of edge points per side average their noise away; on the synthetic benchmark scenes the
corners' RMS error falls from 0.36-0.57 px (OpenCV's sub-pixel refinement) to 0.02-0.09 px on
15-30 px markers.

With a distortion model, edge points are undistorted before the lines are fitted and the corners
distorted back, so curved sides on a wide lens are handled exactly.

The refinement keeps a marker's detected corners whenever it cannot trust its own result: too few
edge points on a side, nearly parallel sides, or a corner that would move further than half a
marker cell.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["refine_corners_by_edges"]

_STEP_ALONG = 0.5  # px between edge samples along a side (larger on big markers, see _MAX_PER_SIDE)
_MAX_PER_SIDE = 40  # edge samples per side at most: more only costs time
_ACROSS = np.linspace(-1.0, 1.0, 17)  # profile samples across a side, in units of the half-width
_HALF_WIDTH_CELLS = 0.7  # profile half-width, in marker cells (the border is one cell wide) ...
_HALF_WIDTH_PX = (1.5, 4.0)  # ... clipped to this range of pixels
_ITERATIONS = 2  # re-centre each profile on its last edge estimate
_MIN_SIDE_PX = 6.0
_MIN_POINTS = 4  # edge points a side needs for its line


def refine_corners_by_edges(
    grey: np.ndarray,
    corners: np.ndarray,
    cells: int,
    camera_matrix: np.ndarray | None = None,
    dist: np.ndarray | None = None,
) -> np.ndarray:
    """Refine markers' corners from their edges.

    Parameters
    ----------
    grey : (H, W) uint8 or float image.
    corners : (N, 4, 2) detected corners, clockwise in the image (OpenCV's TL, TR, BR, BL); any
        convex dark polygon on a light background works the same, as (N, K, 2) with K >= 3.
    cells : marker cells per side, border included (``dictionary.markerSize + 2``).
    camera_matrix, dist : the camera's model; with a non-zero ``dist``, lines are fitted in the
        undistorted image.

    Returns
    -------
    (N, K, 2) float64 corners; a marker whose refinement fails keeps its input corners.

    Every step runs on all markers and sides at once (arrays of shape (markers, sides, samples)):
    this runs on every marker of every frame.
    """
    corners = np.asarray(corners, dtype=np.float64)
    sides = corners.shape[-2] if corners.ndim == 3 and corners.shape[-2] >= 3 else 4
    corners = corners.reshape(-1, sides, 2)
    out = corners.copy()
    profiles = _Profiles.of(corners, cells)
    if profiles is None:
        return out
    points, keep = profiles.edge_points(grey)
    if camera_matrix is not None and dist is not None and np.any(np.asarray(dist) != 0):
        k_matrix = np.asarray(camera_matrix, np.float64)
        dist = np.asarray(dist, np.float64).reshape(-1)
        points = cv2.undistortPoints(points.reshape(-1, 1, 2), k_matrix, dist, P=k_matrix).reshape(points.shape)
    else:
        k_matrix = dist = None
    centre, direction = _fit_lines(points, keep)  # (M, K, 2) each; NaN where a side has too few points
    # corner k is where sides k - 1 and k meet
    refined = _intersect(np.roll(centre, 1, axis=1), np.roll(direction, 1, axis=1), centre, direction)
    good = np.all(np.isfinite(refined), axis=(1, 2))
    if k_matrix is not None and good.any():
        flat = refined[good].reshape(-1, 1, 2)
        rays = cv2.undistortPoints(flat, k_matrix, np.zeros(5)).reshape(-1, 2)
        rays3 = np.column_stack([rays, np.ones(len(rays))])
        distorted = cv2.projectPoints(rays3, np.zeros(3), np.zeros(3), k_matrix, dist)[0]
        refined[good] = distorted.reshape(-1, sides, 2)
        good &= np.all(np.isfinite(refined), axis=(1, 2))
    limit = np.maximum(1.5, 0.5 * profiles.cell)
    moved = np.linalg.norm(refined - corners[profiles.index], axis=2).max(axis=1)
    good &= moved <= limit
    out[profiles.index[good]] = refined[good]
    return out


class _Profiles:
    """Every intensity profile across every side of every marker that can be refined, to be sampled in
    one ``remap``: arrays of shape (M markers, K sides, S samples along a side), ``valid`` marking the
    samples that exist (a shorter side has fewer)."""

    def __init__(self, index, base, normal, half, valid, cell) -> None:
        self.index, self.base, self.normal, self.half, self.valid, self.cell = index, base, normal, half, valid, cell

    @classmethod
    def of(cls, corners: np.ndarray, cells: int) -> _Profiles | None:
        finite = np.all(np.isfinite(corners), axis=(1, 2))
        ends = np.roll(corners, -1, axis=1)  # side k runs from corner k to corner k + 1
        lengths = np.linalg.norm(ends - corners, axis=2)  # (N, K)
        lengths = np.where(finite[:, None], lengths, 0.0)
        cell = lengths.mean(axis=1) / cells
        margin = 0.5 * cell + 1.0  # keep away from the corners, where the neighbouring side's edge is
        span = lengths - 2 * margin[:, None]
        with np.errstate(invalid="ignore"):
            count = np.where(span > 0, np.minimum(_MAX_PER_SIDE, np.floor(span / _STEP_ALONG) + 1), 0).astype(int)
        usable = finite & (lengths.min(axis=1) >= _MIN_SIDE_PX) & (count.min(axis=1) >= _MIN_POINTS)
        if not usable.any():
            return None
        index = np.flatnonzero(usable)
        quad, end, lengths, count = corners[index], ends[index], lengths[index], count[index]
        cell, margin, span = cell[index], margin[index], span[index]
        along = (end - quad) / lengths[..., None]
        # outward normal: corners run clockwise in the image (y down), so (dy, -dx) points outward
        normal = np.stack([along[..., 1], -along[..., 0]], axis=-1)
        samples = int(count.max())
        step = np.arange(samples)
        fraction = step / np.maximum(count - 1, 1)[..., None]  # linspace(0, span, count) as fractions
        valid = step < count[..., None]
        positions = margin[:, None, None] + np.where(valid, fraction, 0.0) * span[..., None]
        base = quad[:, :, None, :] + positions[..., None] * along[:, :, None, :]
        half = np.clip(_HALF_WIDTH_CELLS * cell, *_HALF_WIDTH_PX)
        return cls(index, base, normal, half, valid, cell)

    def edge_points(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per profile, the centroid of the outward dark-to-light gradient, and whether to trust it."""
        # only the pixels the profiles can reach are converted to float (a whole 1080p frame costs 0.4 ms):
        # a profile's centre moves less than its half-width from the side, and reaches a half-width beyond
        reach = 2.0 * float(self.half.max()) + 2.0
        valid_base = self.base[self.valid]
        lo = np.maximum(np.floor(valid_base.min(axis=0) - reach), 0).astype(int)
        hi = np.minimum(np.ceil(valid_base.max(axis=0) + reach) + 1, (grey.shape[1], grey.shape[0])).astype(int)
        lo = np.minimum(lo, np.maximum(hi - 1, 0))  # a marker wholly outside the image still gets a pixel
        image = np.asarray(grey[lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float32)
        origin = lo.astype(np.float64)
        shape = self.base.shape[:3]
        normal = np.broadcast_to(self.normal[:, :, None, :], (*shape, 2))
        half = np.broadcast_to(self.half[:, None, None], shape)
        offsets = np.zeros(shape)
        across = _ACROSS * half[..., None]  # (M, K, S, A) pixels from the profile's centre
        for _ in range(_ITERATIONS):
            centres = self.base - origin + offsets[..., None] * normal
            samples = centres[..., None, :] + across[..., None] * normal[..., None, :]
            profile = cv2.remap(
                image,
                samples[..., 0].reshape(-1, _ACROSS.size).astype(np.float32),
                samples[..., 1].reshape(-1, _ACROSS.size).astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            ).reshape(across.shape)
            gradient = np.clip(np.gradient(profile, axis=-1), 0.0, None)  # dark inside to light outside only
            peak = gradient.max(axis=-1)
            # noise adds small positive gradients everywhere, which would pull the centroid to the
            # window's centre: only the part of the profile above a fifth of its peak counts
            weights = np.clip(gradient - 0.2 * peak[..., None], 0.0, None)
            total = weights.sum(axis=-1)
            shift = (weights * across).sum(axis=-1) / np.maximum(total, 1e-12)
            offsets = offsets + np.where(total > 1e-6, shift, 0.0)
        keep = self.valid & (total > 1e-6) & (np.abs(offsets) < half)
        # a profile with a weak edge (an occluded or washed-out stretch of the side) is no evidence
        typical = _masked_median(peak, keep)
        keep &= ~(peak < 0.5 * typical[..., None])  # a side without any trusted profile keeps none anyway
        return self.base + offsets[..., None] * normal, keep


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median over the last axis of the entries where ``mask`` holds (NaN where none does).

    By sorting with the masked entries pushed to the end (``np.nanmedian`` goes through masked
    arrays for inputs this small and costs ten times as much)."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=-1)
    count = mask.sum(axis=-1)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    high = np.take_along_axis(ordered, np.maximum(count // 2, 0)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, 0.5 * (low + high), np.nan)


def _principal_lines(points: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total least-squares line through each side's masked points: (centre, unit direction, unit normal)."""
    count = mask.sum(axis=-1)
    weights = mask / np.maximum(count, 1)[..., None]
    centre = np.einsum("...s,...sd->...d", weights, points)
    delta = (points - centre[..., None, :]) * mask[..., None]
    sxx = np.einsum("...s,...s->...", delta[..., 0], delta[..., 0])
    sxy = np.einsum("...s,...s->...", delta[..., 0], delta[..., 1])
    syy = np.einsum("...s,...s->...", delta[..., 1], delta[..., 1])
    # principal axis of [[sxx, sxy], [sxy, syy]]: at angle 0.5 atan2(2 sxy, sxx - syy)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    direction = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    normal = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
    return centre, direction, normal


def _fit_lines(points: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per side (points (M, K, S, 2), ``keep`` (M, K, S)): a total least-squares line, refitted once
    without the points farther than 3 robust sigmas from it (when enough remain). NaN for a side with
    fewer than ``_MIN_POINTS`` points."""
    centre, direction, normal = _principal_lines(points, keep)
    residual = np.abs(np.einsum("...sd,...d->...s", points - centre[..., None, :], normal))
    scale = 1.4826 * _masked_median(residual, keep) + 0.02
    inliers = keep & (residual <= 3.0 * scale[..., None])
    refit = (inliers.sum(axis=-1) >= _MIN_POINTS) & (inliers.sum(axis=-1) < keep.sum(axis=-1))
    if refit.any():
        centre2, direction2, _ = _principal_lines(points, inliers)
        centre = np.where(refit[..., None], centre2, centre)
        direction = np.where(refit[..., None], direction2, direction)
    few = keep.sum(axis=-1) < _MIN_POINTS
    centre[few] = np.nan
    return centre, direction


def _intersect(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Where lines (p, u) and (q, v) meet, elementwise; NaN when they are within about 3 deg of parallel."""
    det = -u[..., 0] * v[..., 1] + u[..., 1] * v[..., 0]  # det [u, -v]
    d = q - p
    s = (-d[..., 0] * v[..., 1] + d[..., 1] * v[..., 0]) / np.where(np.abs(det) < 0.05, np.nan, det)
    return p + s[..., None] * u
