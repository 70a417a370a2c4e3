"""``ar-anchor calibrate``: camera calibration from ChArUco views (image folder or glob, video, device).

Pipeline
--------
1. **Detect** every considered frame with ``cv2.aruco.CharucoDetector.detectBoard``. A view needs
   at least ``max(6, 25 %)`` of the board's chessboard corners, spread over two rows and two columns.
2. **Sharpness**: :func:`edge_width_px` estimates the blur of the board's edges, in pixels (the sigma
   of a Gaussian edge): ``contrast / (sqrt(2 pi) * peak derivative)``, with the derivative taken
   along each of the board's two axes as seen in the image (all ChArUco edges are parallel to one of
   them) and the worse axis kept, so motion blur along either axis counts. It does not depend on
   the board's size in the image or on its contrast (sharp renders and photos measure 0.8-1.1 px).
   A view is *blurry* when its width exceeds ``max(1.8 px, 1.6 x the 25th percentile`` of the
   widths of all detected views) -- relative to the sharpest quarter, so a soft lens is not
   rejected wholesale and a clip that is mostly motion-blurred still has a sharp reference.
3. **Distinct views**: a view *duplicates* a kept one when they share at least half of their corners,
   the mean displacement of the shared corners is below 2 % of the image diagonal, and the corner
   counts are within ``max(2, 15 %)`` of each other.
4. **Selection** (files): all sharp views compete for ``--max-views`` places, greedily by coverage:
   each pick maximises ``sum(1 / (1 + n))`` over the cells of a 16x12 grid its corners touch (``n``:
   kept views already touching that cell), so views adding unseen image regions come first.
   Videos are sampled (every ``k``-th frame, at most about ``10 x --max-views`` candidates).
   Devices keep views online: a frame is kept when it is sharp (against the running reference),
   distinct from every kept view and at least 0.5 s (capture time) after the last kept one, until ``--max-views``
   views or ``--duration-s`` (Ctrl-C stops the capture and calibrates with what was kept).
5. **Calibration**: ``cv2.calibrateCameraExtended`` on ``CharucoBoard.matchImagePoints`` points,
   5-parameter distortion (k1, k2, p1, p2, k3). The model falls back to ``CALIB_FIX_K3`` only when
   the 5-parameter fit fails, or its radial polynomial folds over (stops increasing) before the
   image corners -- *not* merely because there are few views: with OpenCV's four tutorial views,
   fixing k3 moves fx from 457 to 326 px at the same RMS (k3 trades off against the focal length
   when corners stay near the centre), 28 % away from OpenCV's own calibration of them.
6. **Outliers**: views whose RMS reprojection error exceeds ``max(3 x median, median + 0.5 px)`` are
   dropped, worst first, never below ``--min-views``, and the camera is calibrated once more.
7. **Uncertainty**: a bootstrap over views: 100 times (a fixed seed; at most 15 s), as many views as
   were used are drawn with replacement and calibrated again; each parameter's standard deviation
   over these fits, or OpenCV's own estimate when larger, is its reported ``+-``. OpenCV's estimate
   alone assumes every corner's error is independent and is optimistic for real views (errors shared
   by a view's corners: a board not quite flat, rolling shutter, blur); on 10-20 rendered views with
   such errors it held the truth within 3 sigma for 50-59 % of fx fy cx cy (up to 13 sigma off), the
   bootstrap's for 99-100 % (at most 3.1 sigma, RMS 1.0 sigma). One warning says when the
   uncertainty itself is unreliable: fewer than 8 views, board orientations within 15 degrees of each
   other (focal length and distance trade off), resampled fits failing or too few of them in time.
8. **Coverage**: an 8x6 grid of image cells; a warning when fewer than half hold a corner, when the
   outer third of a side holds none, or when no corner reaches that side's outermost cells.

Outputs: the OpenCV YAML camera file (``camera_matrix``, ``distortion_coefficients``,
``image_width``, ``image_height``, ``rms``, ``date``, ``board``, ``views``, ``coverage``, ``model``,
``std_intrinsics`` (fx fy cx cy k1 k2 p1 p2 k3, one standard deviation), ``std_intrinsics_method`` and,
when it is unreliable, ``std_intrinsics_unreliable``),
written atomically, and a rerun recording (entity tree below).

Rerun entity tree (timelines ``view``: position in the selection, ``frame``: source frame index):
``views/image`` each selected view (JPEG) with ``corners`` (detected) and ``reprojected``;
``metrics/view_error_px/first_fit|final`` per-view RMS; ``coverage`` the heat map with all corners;
``events`` rejections and the report (TextLog).

Modules: :mod:`.views` (the board, detection, sharpness, distinct views, selection),
:mod:`.solve` (calibration, outliers, coverage; the run's :class:`CalibrationReport`),
:mod:`.gather` (frames from files or a device; :func:`calibrate_source`), :mod:`.report`
(camera YAML, terminal report), :mod:`.recording` (the rerun recording) and :mod:`.command`
(``ar-anchor calibrate``).
"""

from __future__ import annotations

from .command import run_calibrate
from .gather import calibrate_source
from .report import format_report, write_camera_yaml
from .solve import (
    CalibrationReport,
    CalibrationResult,
    Coverage,
    Uncertainty,
    bootstrap_uncertainty,
    calibrate_views,
    coverage_of,
)
from .views import CharucoSpec, Rejection, View, ViewDetector, edge_width_px, is_duplicate, select_views

__all__ = [
    "CalibrationReport",
    "CalibrationResult",
    "CharucoSpec",
    "Coverage",
    "Rejection",
    "Uncertainty",
    "View",
    "ViewDetector",
    "bootstrap_uncertainty",
    "calibrate_source",
    "calibrate_views",
    "coverage_of",
    "edge_width_px",
    "format_report",
    "is_duplicate",
    "run_calibrate",
    "select_views",
    "write_camera_yaml",
]
