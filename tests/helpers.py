"""The test suite's shared helpers: the fuzz / fault-injection harness (property budgets, in-process
CLI runs, time limits), CLI subprocess checks, and geometry fixtures used by several test modules.

Example budgets: every property test declares its CI budget with :func:`fuzz_settings`; under
``HYPOTHESIS_PROFILE=long`` the budget is multiplied by ``FUZZ_SCALE`` (default 20), which is the
documented longer run (docs/fault-campaign.md).
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import functools
import io
import logging
import math
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import settings

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose, look_at, matrix_from_rvec
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene

PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
SCALE = int(os.environ.get("FUZZ_SCALE", "20")) if PROFILE == "long" else 1


@functools.cache
def parsed_module(path: Path) -> ast.Module:
    """The syntax tree of a source file, parsed once per test process (the structure tests of tests/test_layers.py
    and tests/test_rooms.py each read every module of the package: six parses of each, 7 s of CPU, before)."""
    return ast.parse(path.read_text(), filename=str(path))


# Exit codes of ar_anchor.cli.main (docs/troubleshooting.md)
EXIT_CODES = {0, 1, 2, 130}


def examples(ci_budget: int) -> int:
    """The example count of a property test: its CI budget, scaled up under the long profile."""
    return ci_budget * SCALE


def fuzz_settings(ci_budget: int, **kwargs) -> settings:
    return settings(max_examples=examples(ci_budget), deadline=None, **kwargs)


@dataclass(frozen=True)
class CliResult:
    code: int
    stdout: str
    stderr: str
    system_exit: bool  # argparse ended the call with SystemExit (usage error, --help, --version)

    def describe(self) -> str:
        return f"exit {self.code} (SystemExit: {self.system_exit})\nstdout: {self.stdout!r}\nstderr: {self.stderr!r}"


def run_main(argv: Sequence[str], cwd: Path | None = None) -> CliResult:
    """``ar_anchor.cli.main.main(argv)`` in-process (in ``cwd`` when given), stdout/stderr captured, SystemExit
    turned into its code.

    main() changes process-wide state (the "ar_anchor" logger's handler, the SIGTERM handler);
    both are restored so that other tests see what they saw before.
    """
    from ar_anchor.cli.main import main

    logger = logging.getLogger("ar_anchor")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    saved_sigterm = signal.getsignal(signal.SIGTERM)
    out, err = io.StringIO(), io.StringIO()
    system_exit = False
    try:
        with (
            working_directory(cwd) if cwd is not None else contextlib.nullcontext(),
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
        ):
            try:
                code = main(list(argv))
            except SystemExit as exc:
                system_exit = True
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    finally:
        logger.handlers[:] = saved[0]
        logger.setLevel(saved[1])
        logger.propagate = saved[2]
        signal.signal(signal.SIGTERM, saved_sigterm)
    return CliResult(code, out.getvalue(), err.getvalue(), system_exit)


@contextlib.contextmanager
def working_directory(path: Path):
    """``path`` as the current directory within the block (``contextlib.chdir`` is Python 3.11+; we support 3.10)."""
    previous = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(previous)


def assert_clean_exit(result: CliResult, allowed: set[int] = EXIT_CODES) -> None:
    """An exit code of the documented set, and nothing that betrays a bug on the user's screen."""
    assert isinstance(result.code, int) and result.code in allowed, result.describe()
    for text in (result.stdout, result.stderr):
        assert "Traceback" not in text, result.describe()
        assert "internal error" not in text, result.describe()  # main()'s catch-all for unexpected exceptions


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("ar-anchor: error:")]


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class Hang(BaseException):
    """Raised by :func:`time_limit` (a BaseException, so that no ``except Exception`` can swallow it)."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Fail a call that takes longer than ``seconds`` (main thread; Python-level code only)."""

    def expired(_signum: int, _frame: object) -> None:
        raise Hang(f"took longer than {seconds} s: a hang?")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(text: str) -> None:
    """Count an outcome in Hypothesis' statistics (``--hypothesis-show-statistics``); no-op outside @given."""
    from hypothesis import event
    from hypothesis.errors import InvalidArgument

    try:
        event(f"outcome: {text}")
    except InvalidArgument:
        pass


# ============================================================================ CLI subprocesses

TIMEOUT_S = 60


RERUN = Path(sys.executable).with_name("rerun")


POSES_HEADER = (
    "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
    "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
)


def study_args(argv: list[str]) -> argparse.Namespace:
    """``ar-anchor study`` options parsed as the command would, quiet."""
    from ar_anchor.tools.study import configure_parser

    parser = argparse.ArgumentParser(allow_abbrev=False)
    configure_parser(parser)
    args = parser.parse_args(argv)
    args.quiet = True
    return args


def cli(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "ar_anchor", *args]


def describe(result: subprocess.CompletedProcess[str]) -> str:
    return f"exit {result.returncode}\nstdout: {result.stdout!r}\nstderr: {result.stderr!r}"


def assert_no_traceback(result: subprocess.CompletedProcess[str]) -> None:
    assert "Traceback" not in result.stderr and "Traceback" not in result.stdout, describe(result)
    assert "internal error" not in result.stderr, describe(result)


def verify_rrd(path: Path) -> None:
    assert path.is_file() and path.stat().st_size > 0, f"{path} missing or empty"
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found: {path} not verified")
    result = subprocess.run(
        [str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=TIMEOUT_S, check=False
    )
    assert result.returncode == 0, result.stdout + result.stderr


def count_decoded_frames(path: Path) -> int:
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    assert capture.isOpened(), f"{path}: cannot be opened"
    count = 0
    try:
        while capture.read()[0]:
            count += 1
    finally:
        capture.release()
    return count


# ============================================================================ geometry fixtures


def mirrored(pose: Pose) -> Pose:
    """The other IPPE solution of a square: its normal mirrored through the line of sight."""
    sight = pose.tvec / np.linalg.norm(pose.tvec)
    normal = pose.rotation[:, 2]
    axis = np.cross(normal, sight if normal @ sight > 0 else -sight)
    angle = 2.0 * math.asin(min(np.linalg.norm(axis), 1.0))
    turn = matrix_from_rvec(axis / np.linalg.norm(axis) * angle)
    return Pose.from_matrix(turn @ pose.rotation, pose.tvec)


LENGTH = 0.05


def random_view(rng: np.random.Generator, near: float, far: float, tilt_deg: float = 50.0) -> Pose:
    """camera_from_world looking at the origin from a random direction, with a random roll."""
    distance = rng.uniform(near, far)
    az, el = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2))
    eye = distance * np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    look = np.array([*rng.uniform(-0.03, 0.03, 2), 0.0])
    roll = Pose(np.array([0.0, 0.0, rng.uniform(-math.pi, math.pi)]), np.zeros(3))
    return roll.compose(look_at(eye, look))


def distorted_camera() -> CameraModel:
    k = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
    return CameraModel(k, np.array([-0.32, 0.12, 0.0005, -0.0004, 0.0]), 640, 480)


def corner_view(camera: CameraModel) -> tuple[SyntheticSource, Pose]:
    """A 20 cm marker placed in the image's top-left corner region, where barrel distortion bends its sides."""
    scene = SyntheticScene(camera=camera, markers=(PlacedMarker(5, 0.2, Pose.identity()),), frames=1, seed=1)
    # the camera looks at a point right of and below the marker, so the marker lands top-left
    camera_from_world = look_at((0.22, -0.16, 0.6), (0.22, -0.16, 0.0))
    return SyntheticSource(scene), camera_from_world


def orbit_pairs(frames: int) -> tuple[CameraModel, list]:
    """A demo scene seen from near, orbiting (a board and lone markers, coming and going): each frame with
    the tracker's result, and the scene's camera, for the recording's tests."""
    from ar_anchor.config import demo_config
    from ar_anchor.sources.synthetic import SyntheticSource
    from ar_anchor.synthetic import demo_scene
    from ar_anchor.synthetic.trajectory import Trajectory
    from ar_anchor.track.tracker import Tracker

    config = demo_config()
    trajectory = Trajectory("orbit", look_at=(-0.01, 0.0, 0.0), near_m=0.3)
    scene = demo_scene(config, CameraModel.from_fov(480, 360, 70.0), frames=frames, trajectory=trajectory)
    tracker = Tracker(config, scene.camera)
    with SyntheticSource(scene) as source:
        return scene.camera, [(frame, tracker.process(frame)) for frame in source]
