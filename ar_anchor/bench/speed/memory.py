"""Memory figures of the speed benchmark: peak and current resident set size, handing freed memory
back to the OS, and a fresh tracker's Python-side allocation peak."""

from __future__ import annotations

import gc
import math
import os
import resource
import sys
import tracemalloc
from collections.abc import Callable, Sequence
from typing import Any

from ...sources.base import Frame

__all__ = [
    "loop_peak_mb",
    "maxrss_mb",
    "release_freed_memory",
    "reset_peak_rss",
    "rss_now_mb",
]


def maxrss_mb() -> float:
    """Peak resident set size of this process (since start, or since :func:`reset_peak_rss`)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024  # bytes on macOS, KiB on Linux


def rss_now_mb() -> float:
    """Current resident set size (Linux ``/proc/self/statm``; NaN elsewhere)."""
    try:
        with open("/proc/self/statm") as handle:
            pages = int(handle.read().split()[1])
    except (OSError, ValueError, IndexError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / (1024 * 1024)


def release_freed_memory() -> None:
    """Hand freed heap memory back to the OS (glibc keeps big freed blocks, e.g. the clips' frames)."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def reset_peak_rss() -> bool:
    """Reset the peak RSS (Linux >= 4.0: ``/proc/self/clear_refs`` 5 resets VmHWM and ``ru_maxrss``)."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
    except OSError:
        return False
    return True


def loop_peak_mb(make: Callable[[], Any], frames: Sequence[Frame]) -> float:
    """Peak of Python-side allocations (numpy arrays included, OpenCV's own C++ buffers not) of a fresh loop
    from ``make()`` (anything with ``step(frame)``: a pipeline of :mod:`.measure`) stepping over ``frames``;
    the frames themselves were allocated before and do not count."""
    gc.collect()
    tracemalloc.start()
    try:
        loop = make()
        for frame in frames:
            loop.step(frame)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak / 1e6
