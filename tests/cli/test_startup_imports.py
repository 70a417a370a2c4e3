"""Start-up: a command imports only what it needs (docs/benchmarks.md, "Start-up", has the times).

``ar-anchor --help`` (any command's) builds the whole parser and must not load OpenCV, numpy, rerun, trimesh,
PyAV, scipy and the like. A run loads no trimesh (the default overlays need none), no PyAV without a video,
and rerun only in the thread that opens the outputs while the first frame is tracked, never in the main
thread before it. Each check runs ``main`` in a fresh interpreter and reads what it imported.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# what the parser must never load: the libraries that make start-up slow, and the tracker's own modules
HEAVY = (
    "cv2",
    "numpy",
    "rerun",
    "trimesh",
    "av",
    "scipy",
    "filterpy",
    "tqdm",
    "matplotlib",
    "ray",
    "fpdf",
    "mcap",
    "mcap_ros2",
    "ar_anchor.track",
    "ar_anchor.run",
    "ar_anchor.viz",
    "ar_anchor.sources",
    "ar_anchor.config",
)


def loaded_after_main(argv: list[str], modules: tuple[str, ...], cwd: Path = REPO) -> list[str]:
    """Which of ``modules`` are imported once ``main(argv)`` has returned (or exited), in a new interpreter."""
    code = (
        "import sys\n"
        "from ar_anchor.cli.main import main\n"
        "try:\n"
        f"    main({argv!r})\n"
        "except SystemExit:\n"
        "    pass\n"
        f"print('LOADED', sorted(m for m in {modules!r} if m in sys.modules))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=120, check=False
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("LOADED ")]
    assert result.returncode == 0 and lines, f"exit {result.returncode}\n{result.stdout[-2000:]}\n{result.stderr}"
    return eval(lines[-1].removeprefix("LOADED "))  # noqa: S307 - our own print of a list of names


def test_the_subprocess_imports_this_tree():
    code = "import ar_anchor; print(ar_anchor.__file__)"
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert Path(result.stdout.strip()).resolve() == REPO / "ar_anchor" / "__init__.py"


@pytest.mark.parametrize(
    "argv",
    [["--help"], ["--version"], ["demo", "--help"], ["replay", "--help"], ["live", "--help"], ["study", "--help"]],
    ids=" ".join,
)
def test_help_loads_nothing_heavy(argv):
    assert loaded_after_main(argv, HEAVY) == []


def test_the_check_sees_a_heavy_import():
    # the check itself can fail: a parser that imported OpenCV would be caught
    assert loaded_after_main(["--help"], ("argparse", "ar_anchor.cli.main")) == ["ar_anchor.cli.main", "argparse"]


def imports_during_main(argv: list[str], modules: tuple[str, ...], cwd: Path) -> dict[str, str]:
    """Which of ``modules`` ``main(argv)`` imports, each with the name of the thread that imported it first."""
    code = (
        "import sys, threading\n"
        "seen = {}\n"
        "class Watch:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name in {modules!r} and name not in seen:\n"
        "            seen[name] = threading.current_thread().name\n"
        "        return None\n"
        "sys.meta_path.insert(0, Watch())\n"
        "from ar_anchor.cli.main import main\n"
        f"code = main({argv!r})\n"
        "print('SEEN', seen, code)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300, check=False
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("SEEN ")]
    assert result.returncode == 0 and lines, f"exit {result.returncode}\n{result.stdout[-2000:]}\n{result.stderr}"
    seen, code_text = lines[-1].removeprefix("SEEN ").rsplit(" ", 1)
    assert code_text == "0", result.stderr
    return eval(seen)  # noqa: S307 - our own print of a dict of names


RUN_HEAVY = ("rerun", "trimesh", "av", "scipy", "filterpy", "tqdm", "matplotlib", "ray", "fpdf", "mcap")


@pytest.mark.slow
def test_a_demo_loads_no_rerun_trimesh_or_pyav_in_the_tracker_process(tmp_path):
    seen = imports_during_main(["-q", "demo", "--frames", "2", "--out", "out"], RUN_HEAVY, cwd=tmp_path)
    assert seen == {}  # (rerun: in the output process only)
    assert (tmp_path / "out" / "recording.rrd").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.realdata
def test_a_video_replay_loads_pyav_but_no_rerun_or_trimesh_in_the_tracker_process(realdata, tmp_path):
    clip = realdata / "aruco_testdata" / "chessboard"
    argv = ["-q", "replay", str(clip / "chessboard.avi"), "--camera", str(clip / "intrinsics.yml")]
    argv += ["--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034", "--causal", "--max-frames", "3"]
    seen = imports_during_main([*argv, "--out", "out"], RUN_HEAVY, cwd=tmp_path)
    assert seen == {"av": "MainThread"}  # (rerun: in the output process only)


@pytest.mark.parametrize(("given", "expected"), [(None, "1"), ("4", "4")])
def test_the_command_gives_numpys_blas_one_thread_unless_the_user_chose(given, expected):
    # given an environment without OPENBLAS_NUM_THREADS, or with the user's own
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    code = (
        "import os, sys\n"
        "from ar_anchor.cli.main import main\n"
        "try:\n"
        "    main(['--version'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print('BLAS', os.environ.get('OPENBLAS_NUM_THREADS'), 'numpy' in sys.modules)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    # then numpy, not loaded yet, will start OpenBLAS with one thread (or the user's count)
    assert f"BLAS {expected} False" in result.stdout, result.stdout + result.stderr


def test_a_process_that_loaded_numpy_already_keeps_its_blas():
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    code = (
        "import os, numpy\n"
        "from ar_anchor.cli.main import _one_blas_thread\n"
        "_one_blas_thread()\n"
        "print('BLAS', os.environ.get('OPENBLAS_NUM_THREADS'))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert "BLAS None" in result.stdout, result.stdout + result.stderr
