from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from ar_anchor.camera import CameraModel

REPO = Path(__file__).resolve().parents[1]


def pytest_configure(config: pytest.Config) -> None:
    """A suite started in the background (``pytest &`` in a script) has SIGINT ignored, and every process a
    test starts would inherit that: the tests that interrupt a run with Ctrl-C would then test nothing but
    the ignoring. Such a test starts its process as a user's terminal would, with SIGINT at its default."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def camera() -> CameraModel:
    return CameraModel.default_synthetic()


@pytest.fixture(scope="session")
def realdata() -> Path:
    """The folder of real marker recordings named by $AR_ANCHOR_REALDATA; skips the test when it is absent."""
    root = Path(os.environ.get("AR_ANCHOR_REALDATA", REPO.parent / "shared" / "realdata"))
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(
            f"real data not found at {root}: set AR_ANCHOR_REALDATA to a folder of the public marker "
            "recordings (OpenCV contrib's ArUco samples, the ArUco library's test data); see docs/development.md"
        )
    return root


# ---------------------------------------------------------------------------- hypothesis profiles
# ci (default): a fixed, modest example budget, derandomized, so the fuzz/property suite is
# repeatable and runs in bounded time. long: the longer hunt, e.g.
#   HYPOTHESIS_PROFILE=long pytest tests/test_fuzz_*.py tests/test_media_faults.py tests/test_security.py
# Each test's own @settings(max_examples=...) is its ci budget; FUZZ_SCALE multiplies it under "long"
# (see tests/fuzzing.py: examples()).
from hypothesis import HealthCheck, settings  # noqa: E402

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
settings.register_profile(
    "long",
    derandomize=False,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
