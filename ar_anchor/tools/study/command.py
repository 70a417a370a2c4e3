"""``ar-anchor study NAME``: run one study (or all three) and write its figure, Markdown, JSON and
rerun recording."""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...errors import OutputError
from .figures import plot_jitter, plot_outliers, plot_ransac
from .jitter import run_jitter
from .options import (
    DEFAULT_OUT,
    FULL,
    QUICK,
    STUDIES,
    Defaults,
    camera_from_args,
    check,
    command_line,
    jitter_setup,
    outliers_settings,
    pnp_setup,
    ransac_settings,
)
from .pnp import PnPSetup, run_outliers, run_ransac
from .recording import PLOTS, StudyRecording, jitter_frame_logger, record_result
from .report import headline, jitter_markdown, outliers_markdown, ransac_markdown, seconds_text
from .stats import Progress

__all__ = ["run_study"]


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as err:
        raise OutputError(f"{path}: cannot write ({err.strerror})") from None


def _json_ready(value: Any) -> Any:
    """NaN and infinities as None (JSON has neither), floats to 6 significant digits."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return float(f"{value:.6g}") if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _meta(command: str, wall_time_s: float) -> dict[str, Any]:
    return {
        "command": command,
        "wall_time_s": wall_time_s,
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }


_WRITERS = {
    "outliers": (plot_outliers, outliers_markdown),
    "ransac": (plot_ransac, ransac_markdown),
    "jitter": (plot_jitter, jitter_markdown),
}


def _study(
    name: str, args: argparse.Namespace, out: Path, defaults: Defaults, progress: Progress | None
) -> dict[str, Any]:
    """Run one study and write its four files; returns the result (with ``meta``)."""
    camera = camera_from_args(args)
    command = command_line(args, name, out)
    start = time.perf_counter()
    if name == "jitter":
        setup, result = jitter_setup(args, defaults, camera), None
    else:
        setup = pnp_setup(args, camera)
        result = _run_pnp(name, setup, args, defaults, progress)
    from ...run.outputs import prepare_out_dir  # (imports the tracker: not on every CLI start)

    prepare_out_dir(out)
    recording = StudyRecording(out / f"{name}.rrd", name, PLOTS[name])
    try:
        if name == "jitter":
            result = run_jitter(setup, progress=progress, on_frame=jitter_frame_logger(recording, setup))
        result["meta"] = _meta(command, time.perf_counter() - start)
        png, text, views = _write_files(name, result, out)
        record_result(recording, name, setup, result, views)
        recording.documents(name, png, text)
    finally:
        recording.close()
    return result


def _run_pnp(
    name: str, setup: PnPSetup, args: argparse.Namespace, defaults: Defaults, progress: Progress | None
) -> dict[str, Any]:
    """The ``outliers`` or ``ransac`` study, its options checked first."""
    if name == "outliers":
        return run_outliers(setup, **outliers_settings(args, defaults, setup), progress=progress)
    return run_ransac(setup, **ransac_settings(args, defaults, setup), progress=progress)


def _write_files(name: str, result: dict[str, Any], out: Path) -> tuple[Path, str, Any]:
    """``<name>.png``, ``.md`` and ``.json``; returns the figure's path, the Markdown and the result's
    ``views`` (jitter: each distance's image, for the recording; not JSON), taken out of it."""
    png = out / f"{name}.png"
    plotter, writer = _WRITERS[name]
    plotter(result, png)
    text = writer(result)
    _write(out / f"{name}.md", text)
    views = result.pop("views", None)
    _write(out / f"{name}.json", json.dumps(_json_ready(result), indent=1) + "\n")
    return png, text, views


def run_study(args: argparse.Namespace) -> int:
    """``ar-anchor study NAME``: run the study (or all three), write its files, print where; 0 on success."""
    quiet = bool(getattr(args, "quiet", False))
    check(args.seed >= 0, f"--seed: must be >= 0, got {args.seed}")
    out = DEFAULT_OUT if args.out is None else Path(args.out)
    defaults = QUICK if args.quick else FULL

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    names = STUDIES if args.name == "all" else (args.name,)
    for name in names:
        result = _study(name, args, out, defaults, None if quiet else progress)
        if not quiet:
            print(headline(result))
            print(f"wrote {out / name}.png, .md, .json, .rrd ({seconds_text(result['meta']['wall_time_s'])})")
    return 0
