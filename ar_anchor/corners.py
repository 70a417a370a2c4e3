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
    """
    corners = np.asarray(corners, dtype=np.float64)
    sides = corners.shape[-2] if corners.ndim == 3 and corners.shape[-2] >= 3 else 4
    corners = corners.reshape(-1, sides, 2)
    out = corners.copy()
    profiles = _Profiles.of(corners, cells)
    if profiles is None:
        return out
    image = np.asarray(grey, dtype=np.float32)
    points, keep = profiles.edge_points(image)
    if camera_matrix is not None and dist is not None and np.any(np.asarray(dist) != 0):
        k_matrix = np.asarray(camera_matrix, np.float64)
        dist = np.asarray(dist, np.float64).reshape(-1)
        points = cv2.undistortPoints(points.reshape(-1, 1, 2), k_matrix, dist, P=k_matrix).reshape(-1, 2)
    else:
        k_matrix = dist = None
    for m in np.unique(profiles.marker):
        lines = []
        for k in range(sides):
            side = (profiles.marker == m) & (profiles.side == k) & keep
            if side.sum() < _MIN_POINTS:
                break
            lines.append(_fit_line(points[side]))
        if len(lines) < sides:
            continue
        refined = np.array([_intersect(lines[k - 1], lines[k]) for k in range(sides)])  # corner k: sides k-1, k
        if not np.all(np.isfinite(refined)):
            continue
        if k_matrix is not None:
            rays = cv2.undistortPoints(refined.reshape(-1, 1, 2), k_matrix, np.zeros(5)).reshape(-1, 2)
            rays3 = np.column_stack([rays, np.ones(sides)])
            refined = cv2.projectPoints(rays3, np.zeros(3), np.zeros(3), k_matrix, dist)[0].reshape(sides, 2)
        limit = max(1.5, 0.5 * profiles.cell[m])
        if np.all(np.isfinite(refined)) and np.linalg.norm(refined - corners[m], axis=1).max() <= limit:
            out[m] = refined
    return out


class _Profiles:
    """Every intensity profile across every side of every marker, to be sampled in one ``remap``."""

    def __init__(self, base, normal, half, marker, side, cell) -> None:
        self.base, self.normal, self.half = base, normal, half
        self.marker, self.side, self.cell = marker, side, cell

    @classmethod
    def of(cls, corners: np.ndarray, cells: int) -> _Profiles | None:
        base, normal, half, marker, side = [], [], [], [], []
        cell = np.zeros(len(corners))
        for m, quad in enumerate(corners):
            if not np.all(np.isfinite(quad)):
                continue
            end = np.roll(quad, -1, axis=0)  # side k runs from corner k to corner k + 1
            lengths = np.linalg.norm(end - quad, axis=1)
            if lengths.min() < _MIN_SIDE_PX:
                continue
            cell[m] = float(lengths.mean()) / cells
            along = (end - quad) / lengths[:, None]
            # outward normal: corners run clockwise in the image (y down), so (dy, -dx) points outward
            outward = np.column_stack([along[:, 1], -along[:, 0]])
            width = float(np.clip(_HALF_WIDTH_CELLS * cell[m], *_HALF_WIDTH_PX))
            margin = 0.5 * cell[m] + 1.0  # keep away from the corners, where the neighbouring side's edge is
            for k in range(len(quad)):
                span = lengths[k] - 2 * margin
                count = int(min(_MAX_PER_SIDE, np.floor(span / _STEP_ALONG) + 1)) if span > 0 else 0
                if count < _MIN_POINTS:
                    break
                positions = margin + np.linspace(0.0, span, count)
                base.append(quad[k] + positions[:, None] * along[k])
                normal.append(np.repeat(outward[k][None], count, axis=0))
                half.append(np.full(count, width))
                marker.append(np.full(count, m))
                side.append(np.full(count, k))
        if not base:
            return None
        return cls(*(np.concatenate(a) for a in (base, normal, half, marker, side)), cell)

    def edge_points(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per profile, the centroid of the outward dark-to-light gradient, and whether to trust it."""
        offsets = np.zeros(len(self.base))
        across = _ACROSS[None, :] * self.half[:, None]  # (P, S) pixels from the profile's centre
        for _ in range(_ITERATIONS):
            centres = self.base + offsets[:, None] * self.normal
            samples = centres[:, None, :] + across[..., None] * self.normal[:, None, :]
            profile = cv2.remap(
                image,
                samples[..., 0].astype(np.float32),
                samples[..., 1].astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            gradient = np.clip(np.gradient(profile, axis=1), 0.0, None)  # dark inside to light outside only
            peak = gradient.max(axis=1)
            # noise adds small positive gradients everywhere, which would pull the centroid to the
            # window's centre: only the part of the profile above a fifth of its peak counts
            weights = np.clip(gradient - 0.2 * peak[:, None], 0.0, None)
            total = weights.sum(axis=1)
            shift = (weights * across).sum(axis=1) / np.maximum(total, 1e-12)
            offsets = offsets + np.where(total > 1e-6, shift, 0.0)
        keep = (total > 1e-6) & (np.abs(offsets) < self.half)
        # a profile with a weak edge (an occluded or washed-out stretch of the side) is no evidence
        groups = self.marker * 64 + self.side
        for group in np.unique(groups):
            members = groups == group
            good = members & keep
            if good.any():
                keep[members] &= peak[members] >= 0.5 * np.median(peak[good])
        return self.base + offsets[:, None] * self.normal, keep


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least-squares line (a point on it, unit direction), refitted once without outliers."""
    for _ in range(2):
        centre = points.mean(axis=0)
        _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
        direction = vt[0]
        residual = np.abs((points - centre) @ vt[1])
        scale = 1.4826 * np.median(residual) + 0.02
        inliers = residual <= 3.0 * scale
        if inliers.all() or inliers.sum() < _MIN_POINTS:
            break
        points = points[inliers]
    return centre, direction


def _intersect(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Where two lines meet; NaN when they are within about 3 deg of parallel."""
    (p, u), (q, v) = a, b
    matrix = np.column_stack([u, -v])
    if abs(np.linalg.det(matrix)) < 0.05:
        return np.full(2, np.nan)
    s = np.linalg.solve(matrix, q - p)
    return p + s[0] * u
