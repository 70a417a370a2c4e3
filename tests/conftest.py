from __future__ import annotations

import compileall
import os
import signal
import sys
from pathlib import Path

import pytest

# numpy's OpenBLAS on one thread in this process and the workers it starts, as the ``ar-anchor`` command runs
# it (ar_anchor.cli.main._one_blas_thread): the package's code in-process as in a run, and no BLAS pool
# spinning beside each test (the suite's CPU time fell by 6 %, measured on 2 cores: docs/development.md)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ar_anchor.camera import CameraModel  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def pytest_configure(config: pytest.Config) -> None:
    """A suite started in the background (``pytest &`` in a script) has SIGINT ignored, and every process a
    test starts would inherit that: the tests that interrupt a run with Ctrl-C would then test nothing but
    the ignoring. Such a test starts its process as a user's terminal would, with SIGINT at its default."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if not hasattr(config, "workerinput"):  # once, in the process that starts the workers
        _compile_the_package()


def _compile_the_package() -> None:
    """The package's bytecode, compiled once before the tests start their ~200 ``ar-anchor`` processes.

    Where ``PYTHONDONTWRITEBYTECODE`` is set (some CI images and containers set it), Python never caches the
    bytecode of an editable install, and each of those processes would compile the whole package again
    (about 0.3 s of CPU each, measured on a 2-frame demo). The ``__pycache__`` folders are what any
    ``pip install .`` or ordinary import writes (and are ignored by git); a stale one is recompiled.
    """
    if sys.dont_write_bytecode or os.environ.get("PYTHONDONTWRITEBYTECODE"):
        compileall.compile_dir(REPO / "ar_anchor", quiet=1, workers=0)


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
