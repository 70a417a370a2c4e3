"""The compiled kernels of the hot path, and the one place that decides whether they are used.

The pose stage's polish (:func:`~ar_anchor.track.marker_poses.refine_poses`) loops over poses and
Levenberg-Marquardt steps; numpy pays its dispatch on every small array operation there, so that loop
is compiled: a C extension (``ar_anchor/track/_lm.c``, built by ``pip install``; ``setup.py``) that
runs the numpy version's steps, acceptance and stopping rules (results agree to rounding:
``tests/track/test_marker_poses.py``), without the GIL.

Why C and not numba: numba's import and the first call of a cached kernel cost 0.6-0.9 s of start-up
(measured, docs/benchmarks.md), more than the whole start-up budget; the extension loads in a
millisecond. A machine that cannot compile it (the extension is optional) runs the numpy version, as
does ``AR_ANCHOR_NO_COMPILED=1``, and any camera whose distortion model the kernel does not implement
(the 14-coefficient sensor tilt).
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np

__all__ = ["compiled_refine", "distortion12"]

log = logging.getLogger(__name__)

_MODULE: Any = None
_TRIED = False


def compiled_refine() -> Any:
    """The compiled polish (``_lm.refine``), or None: not built, or disabled (``AR_ANCHOR_NO_COMPILED``)."""
    global _MODULE, _TRIED
    if not _TRIED:
        _TRIED = True
        if os.environ.get("AR_ANCHOR_NO_COMPILED", "") not in ("", "0"):
            return None
        try:
            from . import _lm  # type: ignore[attr-defined]

            _MODULE = _lm
        except ImportError as err:
            log.info("the compiled pose polish is not built (%s): numpy instead (slower, the same poses)", err)
    return None if _MODULE is None else _MODULE.refine


def distortion12(dist: np.ndarray | None) -> np.ndarray | None:
    """The camera's distortion as the kernel's 12 coefficients (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4), or
    None for a model it does not implement (the 14-coefficient sensor tilt)."""
    out = np.zeros(12)
    if dist is None:
        return out
    values = np.asarray(dist, np.float64).reshape(-1)
    if values.size > 12 and np.any(values[12:] != 0.0):
        return None
    out[: min(values.size, 12)] = values[:12]
    return out
