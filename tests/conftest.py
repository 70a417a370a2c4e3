from __future__ import annotations

import os
from pathlib import Path

import pytest

from ar_anchor.camera import CameraModel

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def camera() -> CameraModel:
    return CameraModel.default_synthetic()


@pytest.fixture(scope="session")
def realdata() -> Path:
    """../shared/realdata (or $AR_ANCHOR_REALDATA); skips the test when it is absent."""
    root = Path(os.environ.get("AR_ANCHOR_REALDATA", REPO.parent / "shared" / "realdata"))
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(f"real data not found at {root} (set AR_ANCHOR_REALDATA)")
    return root
