"""What the studies share: the progress callback, and summary statistics in which a failed solve
(None) counts as +inf, worse than any error."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["Progress", "finite", "spread"]

Progress = Callable[[str], None]


def _failures_last(values: Sequence[float | None]) -> np.ndarray:
    """Errors with failed solves as +inf (a failure is worse than any error)."""
    return np.array([math.inf if v is None else v for v in values], dtype=np.float64)


def spread(values: Sequence[float | None]) -> dict[str, float | int | None]:
    """Median, 10th and 90th percentile and maximum (failures count as +inf), and the failure count."""
    array = _failures_last(values)
    if array.size == 0:
        return {"median": None, "p10": None, "p90": None, "max": None, "failed": 0}
    return {
        "median": _percentile(array, 50),
        "p10": _percentile(array, 10),
        "p90": _percentile(array, 90),
        "max": finite(np.max(array)),
        "failed": int(np.sum(~np.isfinite(array))),
    }


def _percentile(array: np.ndarray, q: float) -> float | None:
    """Percentile of errors with failures as +inf; None when it falls among the failures."""
    with np.errstate(invalid="ignore"):  # inf - inf between two failures: NaN, i.e. a failure
        value = float(np.percentile(array, q))
    return value if math.isfinite(value) else None


def finite(value: float) -> float | None:
    """``value`` as a float, or None when it is NaN or infinite."""
    value = float(value)
    return value if math.isfinite(value) else None
