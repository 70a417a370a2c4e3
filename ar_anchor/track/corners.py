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

On a small marker, blur reaches from one edge to the next: the border is only one cell wide, and a
light inner cell next to it lifts the inner half of the profile across the outer edge, which moves that
edge point outward (by about a tenth of a pixel with 2 px cells and 0.6 px of blur), while a dark inner
cell does not. The sides would then follow the marker's bit pattern: bent lines whose fitted directions
are off by far more than the perspective that tells a far marker's two poses apart, so that the wrong
pose reprojects better in every frame. Each profile therefore also samples the inner cell next to it,
and the pull is measured on the marker itself and removed before the final fit: the edge points'
offsets from their side's line are regressed on that inner brightness (each side its own offset and
slope, one pull per marker) and every point moved back by its pull (see :func:`_without_inner_pull`).
On a lone 4 cm marker at 3 m (13 px, 0.6 px blur) the corners' bias falls from up to 0.18 px to 0.03 px
and their pose's reprojection error from 0.09 px to 0.02 px.

With a distortion model, edge points are undistorted before the lines are fitted and the corners
distorted back, so curved sides on a wide lens are handled exactly.

Each fitted corner is accepted or rejected by the quality of its own two sides, never by how far it
moves from the detected corner: where markers touch at their corners (chessboard-like sheets) the
detector's contour merges them and its corners land several pixels off, exactly where the edge fit
is most needed. A side is trusted when its edge points are many, spread over much of its length and
mostly on one line (the line is refitted without the points far from it, so a neighbour's edge near a
corner or an occluding blob does not pull it), with a small residual (against the marker's cleanest
side: the image's noise and blur), when its direction agrees with the detected side's and its edge is
about as strong as the marker's other sides' (dark inside, light outside: each profile's polarity is
checked too). A corner is refined when both its sides are trusted, they are not nearly parallel, and
it stays within a quarter of the marker's side of the detected corner (a sanity bound only); any other
corner keeps its detected position.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["FITTED", "NOT_TRIED", "REJECTED", "fit_corners_by_edges", "refine_corners_by_edges"]

_STEP_ALONG = 0.5  # px between edge samples along a side (larger on big markers, see _MAX_PER_SIDE)
_MAX_PER_SIDE = 40  # edge samples per side at most: more only costs time
_ACROSS = np.linspace(-1.0, 1.0, 17)  # profile samples across a side, in units of the half-width
_ACROSS_32 = _ACROSS.astype(np.float32)
_HALF_WIDTH_CELLS = 0.7  # profile half-width, in marker cells (the border is one cell wide) ...
_HALF_WIDTH_PX = (1.5, 4.0)  # ... clipped to this range of pixels
_SEARCH_CELLS, _SEARCH_PX = 1.0, (1.5, 6.0)  # the same for the first pass, which must find an edge the
# detector placed a few pixels off (where markers touch at their corners)
_ITERATIONS = 2  # re-centre each profile on its last edge estimate
_MIN_SIDE_PX = 6.0
_MIN_POINTS = 4  # edge points a side needs for its line
# what a side's line must satisfy to be trusted (see the module's docstring)
_TRIM_ITERATIONS = 1  # refits without the points farther than _TRIM_SIGMAS robust sigmas from the line
_TRIM_SIGMAS = 3.0
_MIN_POINT_FRACTION = 0.3  # inliers, of the profiles the side has
_MIN_INLIER_FRACTION = 0.6  # inliers, of the side's edge points
_MIN_COVERAGE = 0.4  # from the first inlier to the last: at least this fraction of the side's samples
_MAX_RMS_PX = 0.25  # inliers' RMS distance from the line: at most this, or this fraction of the
_MAX_RMS_HALF = 0.08  # profile's half-width, or this multiple of the marker's cleanest side's (the image's
_MAX_RMS_NOISE = 3.0  # noise and blur, as this marker shows them)
_MAX_TURN_DEG = 15.0  # the line's direction against the detected side's
_MIN_STRENGTH = 0.25  # the side's typical edge gradient, against the marker's strongest side
_MAX_OPPOSITE = 0.5  # a profile's strongest light-to-dark gradient, against its dark-to-light peak
# and what a corner must satisfy
_MIN_SIN = 0.2  # its two lines at least about 12 deg from parallel
_MAX_MOVE_SIDE = 0.25  # at most this fraction of the marker's side from the detected corner (or _MIN_MOVE_PX)
_MIN_MOVE_PX = 1.5
# the pull of the marker's light inner cells on its edge points (see _without_inner_pull)
_INNER_CELLS = 1.5  # where a profile's inner cell is sampled: this many cells inside its edge point
_INNER_RIDGE = 0.5  # the regression's ridge, in profiles' worth of a full-contrast step in the inner brightness
_INNER_MAX_CELLS = 0.1  # the largest correction: this fraction of a cell (at the marker's full contrast)
_INNER_SIGMAS = 2.0  # the pull is shrunk by (this many standard errors / the pull) squared: none within that
_INNER_REACH_PX = (1.0, 2.0)  # the pull is all taken where the inner cell starts within the first distance (px) of
# the profiles' inner end (cells up to about 3 px), none beyond the second (cells of about 6 px and more)

FITTED, REJECTED, NOT_TRIED = 1, 0, -1  # a corner's status (fit_corners_by_edges)


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
    (N, K, 2) float64 corners; a corner whose fit cannot be trusted keeps its input position.

    Every step runs on all markers and sides at once (arrays of shape (markers, sides, samples)):
    this runs on every marker of every frame.
    """
    return fit_corners_by_edges(grey, corners, cells, camera_matrix, dist)[0]


def fit_corners_by_edges(
    grey: np.ndarray,
    corners: np.ndarray,
    cells: int,
    camera_matrix: np.ndarray | None = None,
    dist: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_corners_by_edges`, and each corner's status: (N, K) int8, ``FITTED`` (moved to its
    sides' intersection), ``REJECTED`` (a fit was tried and not trusted: the input corner is kept) or
    ``NOT_TRIED`` (a marker too small to sample, or with non-finite corners)."""
    corners = np.asarray(corners, dtype=np.float64)
    sides = corners.shape[-2] if corners.ndim == 3 and corners.shape[-2] >= 3 else 4
    corners = corners.reshape(-1, sides, 2)
    out = corners.copy()
    status = np.full(corners.shape[:2], NOT_TRIED, np.int8)
    profiles = _Profiles.of(corners, cells)
    if profiles is None:
        return out, status
    quad = corners[profiles.index]
    points, keep, strength, inner, contrast = profiles.edge_points(grey)
    if camera_matrix is not None and dist is not None and np.any(np.asarray(dist) != 0):
        k_matrix = np.asarray(camera_matrix, np.float64)
        dist = np.asarray(dist, np.float64).reshape(-1)
        # the detected corners too: the fitted sides' directions are checked against theirs
        flat = np.concatenate([points.reshape(-1, 2), quad.reshape(-1, 2)])
        flat = cv2.undistortPoints(flat.reshape(-1, 1, 2), k_matrix, dist, P=k_matrix).reshape(-1, 2)
        points, plane_quad = flat[: points[..., 0].size].reshape(points.shape), flat[points[..., 0].size :]
        plane_quad = plane_quad.reshape(quad.shape)
    else:
        k_matrix = dist = None
        plane_quad = quad
    centre, direction, count, rms, extent, inliers = _fit_lines(points, keep)
    # the pull of light inner cells removed (it follows the bit pattern: it would bend the sides) on the markers
    # whose profiles reach their inner cells, and the sides of those whose points moved refitted
    near = np.flatnonzero(_inner_reach(profiles.cell, profiles.half) > 0)
    if near.size:
        shifted, moved = _without_inner_pull(
            points[near], inliers[near], centre[near], direction[near], profiles.normal[near], inner[near],
            contrast[near], profiles.cell[near], profiles.half[near],
        )  # fmt: skip
        if moved.any():  # (on the same inliers: the points moved by a small fraction of a cell at most)
            near = near[moved]
            points[near] = shifted[moved]
            line_centre, direction[near], _, squares = _principal_lines(points[near], inliers[near])
            centre[near] = np.where(np.isfinite(centre[near]), line_centre, np.nan)
            rms[near] = np.sqrt(squares / np.maximum(count[near], 1))
    trusted = _trusted_sides(profiles, plane_quad, direction, count, rms, extent, keep, strength)
    # corner k is where sides k - 1 and k meet
    before = (np.arange(sides) - 1) % sides
    centre_before, direction_before = centre[:, before], direction[:, before]
    refined = _intersect(centre_before, direction_before, centre, direction)
    sin = np.abs(direction_before[..., 0] * direction[..., 1] - direction_before[..., 1] * direction[..., 0])
    good = trusted[:, before] & trusted & (sin >= _MIN_SIN) & np.all(np.isfinite(refined), axis=2)
    if k_matrix is not None and good.any():
        rays = cv2.undistortPoints(refined[good].reshape(-1, 1, 2), k_matrix, np.zeros(5)).reshape(-1, 2)
        rays3 = np.column_stack([rays, np.ones(len(rays))])
        refined[good] = cv2.projectPoints(rays3, np.zeros(3), np.zeros(3), k_matrix, dist)[0].reshape(-1, 2)
        good &= np.all(np.isfinite(refined), axis=2)
    # a sanity bound only (the detector's corner can be several pixels off where markers touch)
    limit = np.maximum(_MIN_MOVE_PX, _MAX_MOVE_SIDE * profiles.cell * cells)
    with np.errstate(invalid="ignore"):
        good &= np.linalg.norm(refined - quad, axis=2) <= limit[:, None]
    out[profiles.index] = np.where(good[..., None], refined, quad)
    status[profiles.index] = np.where(good, FITTED, REJECTED)
    return out, status


def _trusted_sides(
    profiles: _Profiles,
    plane_quad: np.ndarray,
    direction: np.ndarray,
    count: np.ndarray,
    rms: np.ndarray,
    extent: np.ndarray,
    keep: np.ndarray,
    strength: np.ndarray,
) -> np.ndarray:
    """(M, K) bool: which sides' fitted lines (``direction``, from ``count`` inlier edge points ``rms`` from the
    line and spread over ``extent`` samples, of the points ``keep`` marks, with edge ``strength``) are trusted. A
    side is trusted when its line rests on many edge points spread along it, close to it, runs along the detected
    side (of ``plane_quad``, where the lines were fitted), and its edge is about as strong as the marker's other
    sides' (a side with no edge at all has only noise: weak and scattered)."""
    sides = plane_quad.shape[1]
    after = (np.arange(sides) + 1) % sides
    detected = plane_quad[:, after] - plane_quad
    turn = np.abs(np.einsum("mkd,mkd->mk", detected, direction)) / np.maximum(np.linalg.norm(detected, axis=2), 1e-12)
    valid = profiles.valid.sum(axis=-1)
    noise = np.min(np.where(count >= _MIN_POINTS, rms, np.inf), axis=1)
    rms_limit = np.maximum(np.maximum(_MAX_RMS_PX, _MAX_RMS_HALF * profiles.half), _MAX_RMS_NOISE * noise)
    trusted = (
        (count >= np.maximum(_MIN_POINTS, _MIN_POINT_FRACTION * valid))
        & (count >= _MIN_INLIER_FRACTION * keep.sum(axis=-1))
        & (extent >= _MIN_COVERAGE * (valid - 1))
        & (rms <= rms_limit[:, None])
        & (turn >= np.cos(np.radians(_MAX_TURN_DEG)))
    )
    with np.errstate(invalid="ignore"):
        strongest = np.max(np.where(trusted, strength, 0.0), axis=1)
        trusted &= strength >= _MIN_STRENGTH * strongest[:, None]
    return trusted


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

    @property
    def search(self) -> np.ndarray:
        """The first pass's half-width (M,): wider than ``half``."""
        return np.maximum(np.clip(_SEARCH_CELLS * self.cell, *_SEARCH_PX), self.half)

    def edge_points(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per profile, the centroid of the outward dark-to-light gradient and whether to trust it; per
        side, the typical (median) peak gradient of its trusted profiles (NaN where there is none); per
        profile, the brightness ``_INNER_CELLS`` cells inside its edge point (the inner cell next to the
        border there) and the grey-level step from its inner end to its outer end (the edge's contrast)."""
        # only the pixels the profiles can reach are converted to float (a whole 1080p frame costs 0.4 ms):
        # a profile's centre moves less than the search half-width from the side, and reaches a half-width beyond
        search = self.search
        reach = float((search + self.half).max()) + 2.0
        valid_base = self.base[self.valid]
        lo = np.maximum(np.floor(valid_base.min(axis=0) - reach), 0).astype(int)
        hi = np.minimum(np.ceil(valid_base.max(axis=0) + reach) + 1, (grey.shape[1], grey.shape[0])).astype(int)
        lo = np.minimum(lo, np.maximum(hi - 1, 0))  # a marker wholly outside the image still gets a pixel
        image = np.asarray(grey[lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float32)
        shape = self.base.shape[:3]
        centre = self.base - lo  # the profiles' centres on the crop before they move ...
        offsets = np.zeros(shape)  # ... by this much along the outward normal
        normal = self.normal.astype(np.float32)[:, :, None, None, :]  # (M, K, 1, 1, 2)
        for iteration in range(_ITERATIONS):
            half = search if iteration == 0 else self.half
            across = (half[:, None] * _ACROSS).astype(np.float32)[:, None, None, :]  # (M, 1, 1, A) px
            at = (centre + offsets[..., None] * self.normal[:, :, None, :]).astype(np.float32)[..., None, :]
            # sample positions (M, K, S, A); float32 is ample for pixel coordinates (and what remap takes)
            profile = cv2.remap(
                image,
                (at[..., 0] + across * normal[..., 0]).reshape(-1, _ACROSS.size),
                (at[..., 1] + across * normal[..., 1]).reshape(-1, _ACROSS.size),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            ).reshape(*shape, _ACROSS.size)
            signed = np.empty_like(profile)  # np.gradient's differences, without its overhead
            np.subtract(profile[..., 2:], profile[..., :-2], out=signed[..., 1:-1])
            signed[..., 1:-1] *= 0.5
            signed[..., 0] = profile[..., 1] - profile[..., 0]
            signed[..., -1] = profile[..., -1] - profile[..., -2]
            weights = np.maximum(signed, 0.0)  # dark inside to light outside only
            peak = weights.max(axis=-1)
            # noise adds small positive gradients everywhere, which would pull the centroid to the
            # window's centre: only the part of the profile above a fifth of its peak counts
            weights -= 0.2 * peak[..., None]
            np.maximum(weights, 0.0, out=weights)
            total = weights.sum(axis=-1)
            shift = (weights @ _ACROSS_32) * half[:, None, None] / np.maximum(total, 1e-12)
            offsets = offsets + np.where(total > 1e-6, shift, 0.0)
        keep = self.valid & (total > 1e-6) & (np.abs(offsets) < search[:, None, None])
        # polarity: a profile that also crosses a strong light-to-dark edge (past a corner where markers
        # touch, a neighbour's or an occluder's edge) does not see this side's edge alone
        # (outside the edge only: inside, the marker's own bits can lie within a small marker's profile)
        keep &= -signed[..., _ACROSS.size // 2 :].min(axis=-1) <= _MAX_OPPOSITE * peak
        # a profile with a weak edge (an occluded or washed-out stretch of the side) is no evidence
        typical = _masked_median(peak, keep)
        keep &= ~(peak < 0.5 * typical[..., None])  # a side without any trusted profile keeps none anyway
        # the inner cell next to each edge point (inside the quad: within the crop, which covers the markers)
        inner_at = centre + (offsets - _INNER_CELLS * self.cell[:, None, None])[..., None] * self.normal[:, :, None, :]
        inner = cv2.remap(
            image,
            inner_at[..., 0].astype(np.float32).reshape(1, -1),
            inner_at[..., 1].astype(np.float32).reshape(1, -1),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(shape)
        contrast = profile[..., -1] - profile[..., 0]  # light outside, dark inside
        edges = self.base + offsets[..., None] * self.normal[:, :, None, :]
        return edges, keep, typical, inner.astype(np.float64), contrast


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median over the last axis of the entries where ``mask`` holds (NaN where none does).

    By sorting with the masked entries pushed to the end (``np.nanmedian`` goes through masked
    arrays for inputs this small and costs ten times as much)."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=-1).reshape(-1, values.shape[-1])
    count = mask.sum(axis=-1).reshape(-1)
    rows = np.arange(len(count))
    low = ordered[rows, np.maximum((count - 1) // 2, 0)]
    high = ordered[rows, count // 2]
    return np.where(count > 0, 0.5 * (low + high), np.nan).reshape(values.shape[:-1])


def _principal_lines(points: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Total least-squares line through each side's masked points: (centre, unit direction, unit normal,
    the points' sum of squared distances from it)."""
    count = np.maximum(mask.sum(axis=-1), 1)[..., None]
    masked = points * mask[..., None]
    centre = masked.sum(axis=-2) / count
    # scatter matrix about the centre, from the raw second moments (pixel coordinates: no cancellation)
    moments = np.einsum("...sd,...se->...de", masked, points)
    moments -= count[..., None] * centre[..., :, None] * centre[..., None, :]
    sxx, sxy, syy = moments[..., 0, 0], moments[..., 0, 1], moments[..., 1, 1]
    # principal axis of [[sxx, sxy], [sxy, syy]]: at angle 0.5 atan2(2 sxy, sxx - syy)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    cos, sin = np.cos(angle), np.sin(angle)
    direction = np.stack([cos, sin], axis=-1)
    normal = np.stack([-sin, cos], axis=-1)
    squares = 0.5 * (sxx + syy) - np.hypot(0.5 * (sxx - syy), sxy)  # the smaller eigenvalue
    return centre, direction, normal, np.maximum(squares, 0.0)


def _fit_lines(points: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per side (points (M, K, S, 2), ``keep`` (M, K, S)): a total least-squares line, refitted without the
    points farther than a few robust sigmas from it (so a neighbour's edge near a corner, or an occluder's,
    does not pull it), with what tells whether to trust it.

    Returns (centre, direction, count, rms, extent, inliers): the line (centre NaN for a side with fewer
    than ``_MIN_POINTS`` points), how many points it keeps, their RMS distance from it, how many sample
    steps lie from the first of them to the last (the samples are evenly spaced along the side), and which
    points it keeps."""
    inliers = keep
    centre, direction, normal, squares = _principal_lines(points, inliers)
    for _ in range(_TRIM_ITERATIONS):
        residual = np.abs(np.einsum("...sd,...d->...s", points - centre[..., None, :], normal))
        scale = 1.4826 * _masked_median(residual, inliers) + 0.02
        trimmed = keep & (residual <= _TRIM_SIGMAS * scale[..., None])
        inliers = np.where((trimmed.sum(axis=-1) >= _MIN_POINTS)[..., None], trimmed, inliers)
        centre, direction, normal, squares = _principal_lines(points, inliers)
    count = inliers.sum(axis=-1)
    rms = np.sqrt(squares / np.maximum(count, 1))
    last = keep.shape[-1] - 1 - np.argmax(inliers[..., ::-1], axis=-1)
    extent = last - np.argmax(inliers, axis=-1)
    centre = np.where((count >= _MIN_POINTS)[..., None], centre, np.nan)
    return centre, direction, count, rms, extent, inliers


def _without_inner_pull(
    points: np.ndarray,
    inliers: np.ndarray,
    centre: np.ndarray,
    direction: np.ndarray,
    outward: np.ndarray,
    inner: np.ndarray,
    contrast: np.ndarray,
    cell: np.ndarray,
    half: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Edge points (M, K, S, 2) with the outward pull of the light inner cells next to them removed, and
    which markers' points moved (M,).

    Per marker, the points' outward offsets from their side's line are regressed on ``inner`` (the
    brightness inside each point, see :meth:`_Profiles.edge_points`): each side its own offset and slope
    (a side's real position and direction, which the pull must not absorb), one pull per grey level for
    the whole marker (``beta``, px per grey level: the same blur and cell size on every side), with a
    small ridge so that a marker whose inner brightness hardly varies along its sides gets none. Only a
    clear pull is taken (shrunk by the square of ``_INNER_SIGMAS`` standard errors over the pull: none
    within that many standard errors, all but a few per cent of a pull measured to a tenth), and only where
    the profiles reach the inner cells (``_INNER_REACH_PX``: on bigger markers the fit would move points by
    its noise alone, and this would be the only change). The
    pull is never negative and at most ``_INNER_MAX_CELLS`` cells at the marker's full contrast; every
    point then moves inward by ``beta`` times its inner brightness above the marker's darkest (a point
    next to a dark cell stays where it is). ``inliers``: the points of the sides' first lines (centre,
    direction); ``outward``: each side's outward normal (M, K, 2), for the sense of the fitted normals."""
    weight = (inliers & np.all(np.isfinite(centre), axis=-1)[..., None]).astype(np.float64)
    relative = points - np.where(np.isfinite(centre), centre, 0.0)[..., None, :]
    normal = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
    normal *= np.where(np.einsum("mkd,mkd->mk", normal, outward) < 0, -1.0, 1.0)[..., None]  # outward
    along = np.einsum("mksd,mkd->mks", relative, direction)
    offset = np.einsum("mksd,mkd->mks", relative, normal)
    brightness = np.where(np.isfinite(inner), inner, 0.0)

    def detrended(values: np.ndarray) -> np.ndarray:  # minus each side's weighted least-squares line in ``along``
        s0, s1, s2 = weight.sum(-1), (weight * along).sum(-1), (weight * along * along).sum(-1)
        v0, v1 = (weight * values).sum(-1), (weight * along * values).sum(-1)
        det = s0 * s2 - s1 * s1
        solvable = det > 1e-9 * np.maximum(s0 * s2, 1e-12)
        det = np.where(solvable, det, 1.0)
        intercept, slope = (s2 * v0 - s1 * v1) / det, (s0 * v1 - s1 * v0) / det
        return np.where(solvable[..., None], values - intercept[..., None] - slope[..., None] * along, 0.0)

    brightness_left, offset_left = detrended(brightness), detrended(np.where(np.isfinite(offset), offset, 0.0))
    full = _masked_median(contrast.reshape(len(contrast), -1), weight.reshape(len(weight), -1) > 0)  # (M,)
    full = np.where(np.isfinite(full) & (full > 0), full, 1.0)
    spread = (weight * brightness_left**2).sum(axis=(1, 2)) + _INNER_RIDGE * full**2
    beta = (weight * brightness_left * offset_left).sum(axis=(1, 2)) / spread
    # only a clear pull counts (on a big marker the inner cells are beyond the blur's reach: the fit would
    # only move points by its noise)
    residual = offset_left - beta[:, None, None] * brightness_left
    dof = np.maximum(weight.sum(axis=(1, 2)) - 2 * weight.shape[1] - 1, 1.0)
    error = np.sqrt((weight * residual**2).sum(axis=(1, 2)) / dof / spread)
    clear = np.clip(1.0 - (_INNER_SIGMAS * error / np.maximum(beta, 1e-12)) ** 2, 0.0, 1.0)
    # ... and only where the profiles reach the inner cells: their inner end (``half`` inside the edge) within
    # a blur's reach of the inner cell (one cell inside)
    beta = np.clip(beta * clear * _inner_reach(cell, half), 0.0, _INNER_MAX_CELLS * cell / full)
    darkest = np.min(np.where(weight > 0, brightness, np.inf), axis=(1, 2))
    darkest = np.where(np.isfinite(darkest), darkest, 0.0)
    pull = beta[:, None, None] * np.maximum(brightness - darkest[:, None, None], 0.0)
    return points - pull[..., None] * normal[:, :, None, :], beta > 0


def _inner_reach(cell: np.ndarray, half: np.ndarray) -> np.ndarray:
    """How much of a marker's inner pull to take (0..1), by how far its inner cells start beyond the
    profiles' inner end: all of it within ``_INNER_REACH_PX[0]``, none beyond ``_INNER_REACH_PX[1]``."""
    low, high = _INNER_REACH_PX
    return np.clip((high - (cell - half)) / (high - low), 0.0, 1.0)


def _intersect(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Where lines (p, u) and (q, v) meet, elementwise; NaN when they are within about 3 deg of parallel."""
    det = -u[..., 0] * v[..., 1] + u[..., 1] * v[..., 0]  # det [u, -v]
    d = q - p
    s = (-d[..., 0] * v[..., 1] + d[..., 1] * v[..., 0]) / np.where(np.abs(det) < 0.05, np.nan, det)
    return p + s[..., None] * u
