"""Start-up: a command imports only what it needs (docs/benchmarks.md, "Start-up", has the times).

``ar-anchor --help`` (any command's) builds the whole parser and must not load OpenCV, numpy, rerun, trimesh,
PyAV, scipy and the like. Each check runs ``main`` in a fresh interpreter and reads ``sys.modules`` after it.
"""

from __future__ import annotations

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
