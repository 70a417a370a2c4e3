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

from ...errors import printable
from . import interrupt
from .figures import plot_jitter, plot_outliers, plot_ransac
from .files import StudyFiles, check_out, create_out
from .jitter import run_jitter
from .limits import in_range
from .options import (
    FULL,
    QUICK,
    STUDIES,
    Defaults,
    camera_from_args,
    command_line,
    jitter_setup,
    outliers_settings,
    pnp_setup,
    ransac_settings,
)
from .pnp import run_outliers, run_ransac
from .recording import PLOTS, StudyRecording, jitter_frame_logger, record_result
from .report import headline, jitter_markdown, outliers_markdown, ransac_markdown, seconds_text
from .stats import Progress

__all__ = ["run_study"]


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

Plan = tuple[str, Any, dict[str, Any]]  # (study, its setup, its settings: empty for jitter)


def _plan(name: str, args: argparse.Namespace, defaults: Defaults) -> Plan:
    """One study's setup and settings from the options, every number checked (nothing runs yet)."""
    if name == "jitter":
        return name, jitter_setup(args, defaults, camera_from_args(args, "jitter")), {}
    setup = pnp_setup(args, camera_from_args(args, "pnp"))
    settings = outliers_settings if name == "outliers" else ransac_settings
    return name, setup, settings(args, defaults, setup)


def _study(plan: Plan, args: argparse.Namespace, out: Path, progress: Progress | None) -> dict[str, Any]:
    """Run one study and write its four files: under partial names, renamed into place together when all
    are complete, removed when the study is interrupted or fails. Returns the result (with ``meta``)."""
    name, setup, settings = plan
    command = command_line(args, name, out)
    start = time.perf_counter()
    result = None
    if name == "outliers":
        result = run_outliers(setup, **settings, progress=progress)
    elif name == "ransac":
        result = run_ransac(setup, **settings, progress=progress)
    files = StudyFiles(out, name)
    recording = StudyRecording(out / f"{name}.rrd", name, PLOTS[name])
    try:
        if result is None:
            result = run_jitter(setup, progress=progress, on_frame=jitter_frame_logger(recording, setup))
        result["meta"] = _meta(command, time.perf_counter() - start)
        text, views = _write_files(name, result, files)
        interrupt.check()  # a Ctrl-C that matplotlib's cleanup swallowed
        record_result(recording, name, setup, result, views)
        recording.documents(name, files.partial["png"], text)
        recording.flush()
        with interrupt.held():  # the four files become final together
            recording.close()
            files.commit()
    except BaseException:
        with interrupt.held(raise_after=False):
            recording.discard()
            files.discard()
        raise
    return result


def _write_files(name: str, result: dict[str, Any], files: StudyFiles) -> tuple[str, Any]:
    """``<name>.png``, ``.md`` and ``.json`` (partial); returns the Markdown and the result's ``views``
    (jitter: each distance's image, for the recording; not JSON), taken out of it."""
    plotter, writer = _WRITERS[name]
    try:
        plotter(result, files.partial["png"])
    except OSError as err:
        raise files.error("png", err) from None
    text = writer(result)
    files.write_text("md", text)
    views = result.pop("views", None)
    files.write_text("json", json.dumps(_json_ready(result), indent=1) + "\n")
    return text, views


def run_study(args: argparse.Namespace) -> int:
    """``ar-anchor study NAME``: run the study (or all three), write its files, print where; 0 on success.

    Every option is checked before the first study starts; Ctrl-C or SIGTERM ends the run within a
    second (KeyboardInterrupt) and leaves the interrupted study's files out (those of a study that
    completed before stay)."""
    quiet = bool(getattr(args, "quiet", False))
    in_range("--seed", args.seed)
    out = check_out(args.out)
    defaults = QUICK if args.quick else FULL

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    plans = [_plan(name, args, defaults) for name in (STUDIES if args.name == "all" else (args.name,))]
    create_out(out)
    with interrupt.interruptible():
        for plan in plans:
            result = _study(plan, args, out, None if quiet else progress)
            if not quiet:
                print(headline(result))
                where = printable(out / plan[0])
                print(f"wrote {where}.png, .md, .json, .rrd ({seconds_text(result['meta']['wall_time_s'])})")
            interrupt.check()
    if not quiet and len(plans) > 1:  # the last line: every file written
        names = [f"{plan[0]}{ext}" for plan in plans for ext in (".png", ".md", ".json", ".rrd")]
        print(f"outputs: {printable(out)}/ ({', '.join(names)})")
    return 0
