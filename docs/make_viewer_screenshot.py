r"""The docs' screenshots of the rerun web viewer: a recording made here, then ``ar-anchor view --screenshot``.

Usage (the project's venv active, Chromium installed: ``apt install chromium``)::

    python docs/make_viewer_screenshot.py --make demo --layout overlay --frame 10 \
        --out docs/images/overlay_viewer_demo.png
    python docs/make_viewer_screenshot.py --make real --layout overlay --out docs/images/overlay_viewer_real.png
    python docs/make_viewer_screenshot.py --recording run/ --out shot.png --frame 120

``--make demo`` records ``ar-anchor demo --frames 60``; ``--make real`` replays the ArUco library's
``chessboard.avi`` from the real data (``--realdata DIR``, default ``$AR_ANCHOR_REALDATA``); ``--recording``
takes an existing recording (a run's folder: all its parts). The shot itself is ``ar-anchor view RECORDING
--screenshot`` (:mod:`ar_anchor.viz.screenshot`); this script adds the recording, a ``--crop`` and a size
limit (``--max-kb``: smaller, then fewer colour levels). Exit status: ``ar-anchor view``'s (0 written, 1 the
viewer failed, 2 bad arguments or no Chromium).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2


def ar_anchor() -> str:
    found = shutil.which("ar-anchor", path=str(Path(sys.executable).parent)) or shutil.which("ar-anchor")
    if found is None:
        sys.exit("make_viewer_screenshot: ar-anchor is not on PATH: activate the project's venv")
    return found


def make_recording(kind: str, out_dir: Path, realdata: Path) -> Path:
    """Record ``kind`` (``demo``: the synthetic demo, 60 frames; ``real``: chessboard.avi) into ``out_dir``."""
    if kind == "demo":
        args = ["demo", "--frames", "60"]
    else:
        data = realdata / "aruco_testdata" / "chessboard"
        args = ["replay", str(data / "chessboard.avi"), "--camera", str(data / "intrinsics.yml")]
        args += ["--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034"]
    print(f"recording: ar-anchor {' '.join(args)} --out {out_dir}", flush=True)
    subprocess.run([ar_anchor(), "-q", *args, "--out", str(out_dir)], check=True)
    return out_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--recording", type=Path, help="an existing recording (.rrd, or a run's folder)")
    source.add_argument("--make", choices=("demo", "real"), help="record the demo (60 frames) or chessboard.avi")
    parser.add_argument("--out", type=Path, required=True, metavar="PNG", help="the screenshot to write")
    parser.add_argument("--crop", help="keep X,Y,W,H of the window (pixels)")
    parser.add_argument("--max-kb", type=int, default=300, help="largest PNG, kilobytes (default 300)")
    parser.add_argument("--realdata", type=Path, default=Path(os.environ.get("AR_ANCHOR_REALDATA", "realdata")))
    passed = ("--frame", "--layout", "--size", "--timeout", "--chromium")  # ar-anchor view's, passed on
    for option in passed:
        parser.add_argument(option, help=f"ar-anchor view {option}")
    args = parser.parse_args(argv)
    view_options = [text for option in passed if (value := getattr(args, option[2:])) for text in (option, value)]
    with tempfile.TemporaryDirectory(prefix="viewer_shot_") as tmp:
        work = Path(tmp)
        recording = args.recording or make_recording(args.make, work / "run", args.realdata)
        raw = work / "raw.png"
        command = [ar_anchor(), "view", str(recording), "--screenshot", str(raw), *view_options]
        code = subprocess.run(command, check=False).returncode
        if code != 0:
            return code
        from ar_anchor.viz.screenshot import encode_png

        image = cv2.imread(str(raw))
        if args.crop:
            x, y, w, h = (int(v) for v in args.crop.split(","))
            image = image[y : y + h, x : x + w]
        png = encode_png(image, args.max_kb * 1000)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(png)
    print(f"wrote {args.out} ({len(png) // 1000} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
