"""``ar-anchor calibrate``'s uncertainty: the bootstrap over views covers the true camera where OpenCV's
own estimate does not, and one warning says when the views are too few or too alike to trust it.

The views are rendered exactly as in ``test_calibrate`` (its :class:`BoardRenderer`), for a small
640x480 camera, and each is then warped by its own small random affine map (about 0.003 of the image
size): an error shared by all of a view's corners, as a board that is not quite flat or a rolling
shutter gives real views. OpenCV's estimate treats every corner's error as independent, so it shrinks
with the number of corners per view; the truth does not.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.tools.calibrate import (
    CharucoSpec,
    View,
    ViewDetector,
    bootstrap_uncertainty,
    calibrate_source,
    calibrate_views,
)
from ar_anchor.tools.calibrate.gather import quality_warnings
from ar_anchor.tools.calibrate.solve import coverage_of, orientation_spread_deg

from .test_calibrate import COLS, ROWS, SQUARE_M, BoardRenderer, _rotation, board_poses, spec

SIZE = (640, 480)
TRUE_K = np.array([[520.0, 0.0, 322.0], [0.0, 517.0, 236.0], [0.0, 0.0, 1.0]])
TRUE_DIST = np.array([-0.25, 0.08, 0.0005, -0.001, 0.0])
WARP_SIGMA = 0.003  # per view: the affine map's 2x2 part is the identity plus this much noise
RESAMPLES = 40


@pytest.fixture(scope="module")
def renderer() -> BoardRenderer:
    return BoardRenderer(CameraModel(TRUE_K, TRUE_DIST, *SIZE))


def warped_views(
    renderer: BoardRenderer, poses: list[tuple[np.ndarray, np.ndarray]], seed: int, warp: float = WARP_SIGMA
) -> list[View]:
    """The views of ``poses``, each rendered with noise and blur, then warped by its own affine map."""
    rng = np.random.default_rng(100 + seed)
    detector = ViewDetector(spec())
    centre = np.array([SIZE[0] / 2, SIZE[1] / 2])
    views = []
    for index, (rotation, tvec) in enumerate(poses):
        image = renderer.render(rotation, tvec, rng)
        linear = np.eye(2) + rng.normal(0.0, warp, (2, 2))
        affine = np.column_stack([linear, centre - linear @ centre])
        image = cv2.warpAffine(image, affine, SIZE, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        found = detector.detect(image, f"view_{index:02d}.png", index)
        if isinstance(found, View):
            views.append(found)
    return views


def intrinsics(camera: CameraModel) -> np.ndarray:
    k = camera.camera_matrix
    return np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])


def test_bootstrap_covers_the_true_camera_where_opencvs_estimate_does_not(renderer):
    # given, for each of three seeds, ten views of a known camera, each with an error of its own
    truth = intrinsics(CameraModel(TRUE_K, TRUE_DIST, *SIZE))
    z_reported, z_opencv = [], []
    for seed in range(3):
        views = warped_views(renderer, board_poses(renderer, 10, seed=seed), seed)
        assert len(views) >= 8, f"seed {seed}: {len(views)} views detected"
        # when the camera is calibrated and the bootstrap estimates its uncertainty
        result = calibrate_views(spec(), views, SIZE, min_views=6)
        uncertainty = bootstrap_uncertainty(spec(), result, SIZE, resamples=RESAMPLES)
        assert uncertainty.ran == RESAMPLES and uncertainty.failed == 0
        assert not uncertainty.distrust, uncertainty.distrust
        error = intrinsics(result.camera) - truth
        z_reported.append(error / np.array(uncertainty.std[:4]))
        z_opencv.append(error / np.array(result.std[:4]))
        # and it stays useful: fx and fy known to better than 2 %
        assert max(uncertainty.std[0] / truth[0], uncertainty.std[1] / truth[1]) < 0.02, uncertainty.std
    z_reported, z_opencv = np.abs(z_reported), np.abs(z_opencv)
    # then fx, fy, cx, cy are within 3 sigma of the truth in every run (measured: at most 1.9 over 8 seeds)
    assert z_reported.max() < 3.0, np.round(z_reported, 2)
    # while OpenCV's own estimate misses them by more than 3 sigma (measured: up to 12 sigma)
    assert z_opencv.max() > 3.0, np.round(z_opencv, 2)


def test_same_views_give_the_same_uncertainty(renderer):
    views = warped_views(renderer, board_poses(renderer, 8, seed=7), 7)
    result = calibrate_views(spec(), views, SIZE, min_views=6)
    first = bootstrap_uncertainty(spec(), result, SIZE, resamples=20)
    again = bootstrap_uncertainty(spec(), result, SIZE, resamples=20)
    assert first.bootstrap_std == again.bootstrap_std
    other_seed = bootstrap_uncertainty(spec(), result, SIZE, resamples=20, seed=1)
    assert other_seed.bootstrap_std != first.bootstrap_std


def test_the_bootstrap_stops_at_its_time_budget_and_says_so(renderer):
    views = warped_views(renderer, board_poses(renderer, 8, seed=5), 5)
    result = calibrate_views(spec(), views, SIZE, min_views=6)
    messages: list[str] = []
    uncertainty = bootstrap_uncertainty(spec(), result, SIZE, resamples=50, budget_s=0.0, progress=messages.append)
    assert uncertainty.ran == 0 and uncertainty.planned == 50
    assert messages == [
        f"uncertainty: 0/50 resampled calibrations of {len(views)} views (0.0 s, stopped at the 0 s budget)"
    ]
    # the report falls back on OpenCV's estimate and says the uncertainty is unreliable
    assert uncertainty.std[:4] == result.std[:4]
    assert any(d.startswith("only 0 calibrations on resampled views succeeded") for d in uncertainty.distrust)
    assert uncertainty.describe().startswith("OpenCV's estimate from the residuals")


def test_few_views_and_parallel_views_are_flagged(renderer):
    # given four views (fewer than eight)
    poses = board_poses(renderer, 12, seed=3)
    # (the first five poses render the very same first four detected views as the first eight did: view_02
    # is not detected; the views are rendered in order from one generator, so fewer poses change none of them)
    few = warped_views(renderer, poses[:5], 3, warp=0.0)[:4]
    assert len(few) == 4
    result = calibrate_views(spec(), few, SIZE, min_views=4)
    uncertainty = bootstrap_uncertainty(spec(), result, SIZE, resamples=30)
    # then the uncertainty is flagged as unreliable, for that reason only
    assert [d.split(" (")[0] for d in uncertainty.distrust] == ["only 4 view(s)"]
    warnings = quality_warnings(result, coverage_of(result.views, SIZE), uncertainty)
    flagged = [w for w in warnings if "uncertainty (+-) is itself unreliable" in w]
    assert len(flagged) == 1 and "only 4 view(s) (at least 8" in flagged[0]
    # given ten views of a board that keeps one orientation (tilted 30 degrees), moved over the image
    tilted = _rotation((1.0, 0.3, 0.0), 30.0)
    centre = np.array([COLS * SQUARE_M / 2, ROWS * SQUARE_M / 2, 0.0])
    parallel = [(tilted, tvec + (rotation - tilted) @ centre) for rotation, tvec in poses[:10]]
    views = warped_views(renderer, parallel, 3, warp=0.0)
    assert len(views) >= 8
    result = calibrate_views(spec(), views, SIZE, min_views=6)
    uncertainty = bootstrap_uncertainty(spec(), result, SIZE, resamples=30)
    # then the orientations' spread is measured near zero and flagged
    assert result.orientation_spread_deg < 3.0
    assert any(d.startswith("the board's orientations differ by at most") for d in uncertainty.distrust)
    # while the varied views of the first test are not
    assert orientation_spread_deg(np.array([[0, 0, 1.0], [math.sin(0.5), 0, math.cos(0.5)]])) == pytest.approx(
        math.degrees(0.5)
    )


@pytest.mark.realdata
def test_opencvs_four_tutorial_views_are_too_few_and_cover_its_calibration(realdata):
    # given OpenCV's four ChArUco calibration photos and OpenCV's own calibration of that camera
    folder = realdata / "opencv_contrib"
    storage = cv2.FileStorage(str(folder / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ)
    reference = storage.getNode("camera_matrix").mat()
    storage.release()
    board = CharucoSpec.parse("5x7", 0.04, 0.02, "DICT_6X6_250")
    # when they are calibrated
    report = calibrate_source(str(folder / "img_0[0-3].jpg"), board, min_views=4)
    uncertainty = report.uncertainty
    assert uncertainty is not None and uncertainty.ran == uncertainty.planned
    # then one warning says the uncertainty is unreliable: four views, nearly parallel
    # (measured: the board's orientations differ by at most 4 degrees)
    flagged = [w for w in report.warnings if "uncertainty (+-) is itself unreliable" in w]
    assert len(flagged) == 1
    assert "only 4 view(s)" in flagged[0] and "orientations differ by at most" in flagged[0]
    # and the reference lies within 2 sigma (measured: fx 457.3 +-15.8 vs 452.5, fy 461.3 +-15.0 vs 456.8)
    k = report.camera.camera_matrix
    for got, want, sigma in (
        (k[0, 0], reference[0, 0], uncertainty.std[0]),
        (k[1, 1], reference[1, 1], uncertainty.std[1]),
    ):
        assert abs(got - want) < 2 * sigma, (got, want, sigma)
