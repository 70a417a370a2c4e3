"""Fixtures shared by the calibration tests of several modules: the rendered ChArUco views (rendered once per
test process, not once per module: ~4 s of CPU each time) and a calibration of six of them.

Both are read-only: tests copy the views they need (:func:`tests.tools.test_calibrate.copy_views`) and only read
the report.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.tools.test_calibrate import VIEWS, BoardRenderer, board_poses, copy_views, spec


@pytest.fixture(scope="session")
def views_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """18 rendered views as PNG files (read-only: copy them with ``copy_views`` to change a folder)."""
    folder = tmp_path_factory.mktemp("charuco_views")
    renderer = BoardRenderer()
    rng = np.random.default_rng(5)
    for index, (rotation, tvec) in enumerate(board_poses(renderer, VIEWS)):
        assert cv2.imwrite(str(folder / f"view_{index:02d}.png"), renderer.render(rotation, tvec, rng))
    return folder


@pytest.fixture(scope="session")
def six_view_report(views_dir: Path, tmp_path_factory: pytest.TempPathFactory):
    """``calibrate_source`` of the first 6 rendered views (computed once; tests only read it)."""
    from ar_anchor.tools.calibrate import calibrate_source

    return calibrate_source(str(copy_views(views_dir, tmp_path_factory.mktemp("six_shots"), 6)), spec())
