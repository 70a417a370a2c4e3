"""Start-up times of ``ar-anchor`` (docs/benchmarks.md, "Start-up"): the wall time of ``--help`` and
``demo --help``, and of a one-frame replay and demo from exec to the first frame's result (the moment
``Tracker.process`` first returns) and to the end of the process.

    python bench/startup.py                    # this checkout, 11 runs of each
    python bench/startup.py --runs 21 --trees /path/to/old/checkout .   # two checkouts, taking turns

Each tree is put first on PYTHONPATH (its ``ar_anchor`` is the one imported); the runs of the trees
alternate, so that a busy machine slows both alike. Medians, with the range. The replay reads
chessboard.avi from the real data (``$AR_ANCHOR_REALDATA`` or ``../shared/realdata``); without it, only
``--help`` and the demo are timed. Standard library only.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# run in the child: note when Tracker.process first returns (time.time(), into $STARTUP_FIRST_FRAME), then
# run the command line as `ar-anchor` does; the hook is installed before ar_anchor is imported
_CHILD = """
import importlib.abc, importlib.machinery, os, sys, time
out = os.environ["STARTUP_FIRST_FRAME"]
class Hook(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "ar_anchor.track.tracker":
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        run = spec.loader.exec_module
        def exec_module(module):
            run(module)
            process, done = module.Tracker.process, []
            def first(self, *args, **kwargs):
                result = process(self, *args, **kwargs)
                if not done:
                    done.append(True)
                    with open(out, "w") as file:
                        file.write(repr(time.time()))
                return result
            module.Tracker.process = first
        spec.loader.exec_module = exec_module
        return spec
sys.meta_path.insert(0, Hook())
sys.argv = ["ar-anchor", *sys.argv[1:]]
from ar_anchor.cli.main import main
sys.exit(main())
"""


def _commands(out: Path, realdata: Path) -> dict[str, list[str]]:
    commands = {"--help": ["--help"], "demo --help": ["demo", "--help"]}
    clip = realdata / "aruco_testdata" / "chessboard"
    if (clip / "chessboard.avi").is_file():
        commands["replay, 1 frame"] = [
            "replay",
            str(clip / "chessboard.avi"),
            "--camera",
            str(clip / "intrinsics.yml"),
            "--dictionary",
            "DICT_ARUCO_ORIGINAL",
            "--marker-length",
            "0.034",
            "--causal",
            "--max-frames",
            "1",
            "-q",
            "--out",
            str(out / "replay"),
        ]
    else:
        print(f"note: {clip / 'chessboard.avi'} not found: the replay is not timed", file=sys.stderr)
    commands["demo, 1 frame"] = ["demo", "--max-frames", "1", "-q", "--out", str(out / "demo")]
    return commands


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=11, help="runs of each command in each tree (default 11)")
    parser.add_argument("--trees", nargs="+", type=Path, default=[REPO], help="checkouts to time (default: this one)")
    args = parser.parse_args()
    realdata = Path(os.environ.get("AR_ANCHOR_REALDATA", REPO.parent / "shared" / "realdata"))
    trees = [tree.resolve() for tree in args.trees]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        marker = out / "first_frame"
        commands = _commands(out, realdata)
        wall: dict[tuple[str, Path], list[float]] = {(c, t): [] for c in commands for t in trees}
        first: dict[tuple[str, Path], list[float]] = {(c, t): [] for c in commands for t in trees}
        for run in range(args.runs):
            for name, argv in commands.items():
                for tree in trees if run % 2 == 0 else trees[::-1]:
                    env = {**os.environ, "PYTHONPATH": str(tree), "STARTUP_FIRST_FRAME": str(marker)}
                    marker.unlink(missing_ok=True)
                    began, start = time.time(), time.perf_counter()
                    # run in the temporary folder: `python -c` puts its folder first on sys.path, before PYTHONPATH
                    command = [sys.executable, "-c", _CHILD, *argv]
                    result = subprocess.run(command, env=env, cwd=out, capture_output=True)
                    wall[name, tree].append(time.perf_counter() - start)
                    if result.returncode != 0:
                        print(result.stderr.decode(errors="replace"), file=sys.stderr)
                        return 1
                    if marker.exists():
                        first[name, tree].append(float(marker.read_text()) - began)
    bytecode = "not written (PYTHONDONTWRITEBYTECODE)" if sys.flags.dont_write_bytecode else "cached"
    print(f"{args.runs} runs each, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, bytecode {bytecode}\n")
    print("| command | tree | exec to the first frame's result | whole process |")
    print("|---|---|---|---|")
    for name in commands:
        for tree in trees:
            times, firsts = wall[name, tree], first[name, tree]
            to_first = f"{statistics.median(firsts):.2f} s ({min(firsts):.2f}-{max(firsts):.2f})" if firsts else "-"
            whole = f"{statistics.median(times):.2f} s ({min(times):.2f}-{max(times):.2f})"
            print(f"| `{name}` | {tree.name} | {to_first} | {whole} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
