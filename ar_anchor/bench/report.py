"""What every benchmark report shares: the thresholds, strict JSON, the machine's description and
the Markdown number formats.

``FLIP_DEG`` and ``SETTLE_FRAMES`` are defined here once; :mod:`~ar_anchor.bench.stability`,
:mod:`~ar_anchor.bench.speed` and :mod:`~ar_anchor.bench.real` (and the study) use the same values.
"""

from __future__ import annotations

import json
import math
import os
import platform
from pathlib import Path
from typing import Any

import cv2
import numpy as np

__all__ = [
    "FLIP_DEG",
    "SETTLE_FRAMES",
    "fmt",
    "fmt_sig",
    "load_average",
    "machine_info",
    "report_head",
    "strict_json",
    "write_json",
]

FLIP_DEG = 10.0  # a rotation error (or a disagreement) above this is a flip: the wrong planar solution
SETTLE_FRAMES = 30  # jitter is measured after the first second (the filter's convergence), for both pipelines


def strict_json(value: Any, *, significant: int | None = None) -> Any:
    """``value`` ready for strict JSON: NaN and infinities as None, NumPy scalars as Python ones, dict
    keys as strings, tuples as lists. ``significant``: round floats to that many significant digits
    (None: keep them whole)."""
    if isinstance(value, float):
        if not math.isfinite(value):
            return None
        return float(f"{value:.{significant}g}") if significant is not None else value
    if isinstance(value, dict):
        return {str(k): strict_json(v, significant=significant) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v, significant=significant) for v in value]
    if isinstance(value, np.generic):
        return strict_json(value.item(), significant=significant)
    return value


def write_json(path: Path, value: Any) -> None:
    """``value`` as strict JSON (see :func:`strict_json`), indented, with a final newline."""
    path.write_text(json.dumps(strict_json(value), indent=2) + "\n")


def load_average() -> list[float] | None:
    """The 1, 5 and 15 minute load averages (None where the system has none)."""
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def machine_info() -> dict[str, Any]:
    """The machine a benchmark ran on: processor, CPUs (all and usable), system, Python, NumPy and
    OpenCV versions, OpenCV's thread count and the load average at this moment."""
    processor = platform.processor()
    if not processor:
        try:
            with open("/proc/cpuinfo") as handle:
                names = (line.split(":", 1)[1].strip() for line in handle if line.startswith("model name"))
                processor = next(names, "")
        except OSError:
            processor = ""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "processor": processor or platform.machine(),
        "machine": platform.machine(),
        "system": f"{platform.system()} {platform.release()}",
        "cpu_count": os.cpu_count(),
        "usable_cpus": usable,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "load_average_start": load_average(),
    }


def report_head(title: str, produced: str, notes: Any = ()) -> list[str]:
    """A benchmark report's first lines: its ``# title``, the line saying what produced it, and one
    ``Note:`` paragraph per note (the run's skipped parts and caveats)."""
    lines = [f"# {title}", "", produced]
    for note in notes:
        lines += ["", f"Note: {note}."]
    return lines


def machine_lines(meta: dict[str, Any]) -> list[str]:
    """A benchmark report's last section: the machine (:func:`machine_info`) and its load at the start and end."""
    return [
        "",
        "## Machine",
        "",
        f"{meta['processor']}, {meta['usable_cpus']} usable CPUs, Python {meta['python']}, OpenCV {meta['opencv']} "
        f"({meta['opencv_threads']} threads). Load average at the start {meta['load_average_start']}, at the end "
        f"{meta.get('load_average_end')}.",
        "",
    ]


def fmt(value: Any, digits: int = 2) -> str:
    """A table cell: floats with ``digits`` decimals, other values as they print, "-" for None and
    non-finite floats."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def fmt_sig(value: Any, significant: int = 3) -> str:
    """Small errors with significant digits (0.000621, 0.0140, 0.833); "-" for None and non-finite."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:#.{significant}g}".rstrip(".")
