"""Real-video benchmark without ground truth: ``ar-anchor bench real``.

Markers printed on one rigid sheet keep their relative pose. For every pair of markers ``a``, ``b``
seen in the same frame, ``marker_a_from_marker_b = inv(camera_from_a) @ camera_from_b`` is compared
with that pair's mean over the video (rotation: the chordal mean, the SVD projection of the summed
rotation matrices; translation: the per-axis median). A pair-frame whose relative rotation is more
than ``flip_deg`` (10 deg) from the pair's mean is a **flip** (one of the two markers is on the wrong
planar solution, or badly wrong); the RMS of the other pair-frames' rotation (deg) and translation
(mm) differences measures noise. Pairs seen together in fewer than 10 frames are not scored.

Blind spot: a flip of *all* markers together (every marker on its mirror solution at once) keeps the
relative poses consistent and is not seen. With a printed layout (``--layout``, an ArUco marker map),
each pair is also compared with its true relative pose from the layout, which a video-wide mean cannot
give (a pair that is wrong most of the time pulls its own mean).

The figures are the ones ``../shared/tools/rigid_sheet.py`` computes (its ``score``), computed here
the same way (exact agreement on the same poses is tested), and the plain OpenCV baseline is its
``plain`` (default ``ArucoDetector`` + ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker).

Reusable pieces: :func:`score_rigid_sheet`, :func:`score_against_layout`, :func:`read_poses_csv`
(:mod:`.scoring`); :func:`plain_opencv_poses` (and :class:`PlainOpenCV` per frame), :func:`run_real`
(tracker and baseline over one video), :func:`score_real_run` (:mod:`.run`); :func:`real_inputs`
(:mod:`.inputs`); :func:`write_real_report` (:mod:`.report`).
"""

from __future__ import annotations

from ..report import FLIP_DEG
from .inputs import DEFAULT_DICTIONARY, DEFAULT_MARKER_LENGTH_M, RealInputs, default_realdata_root, real_inputs
from .report import real_markdown, real_summary, write_real_report
from .run import PlainOpenCV, RealRun, detection_comparison, plain_opencv_poses, run_real, score_real_run
from .scoring import (
    MIN_COMMON_FRAMES,
    PoseTable,
    layout_relative_poses,
    read_poses_csv,
    score_against_layout,
    score_rigid_sheet,
)

__all__ = [
    "DEFAULT_DICTIONARY",
    "DEFAULT_MARKER_LENGTH_M",
    "FLIP_DEG",
    "MIN_COMMON_FRAMES",
    "PlainOpenCV",
    "PoseTable",
    "RealInputs",
    "RealRun",
    "default_realdata_root",
    "detection_comparison",
    "layout_relative_poses",
    "plain_opencv_poses",
    "read_poses_csv",
    "real_inputs",
    "real_markdown",
    "real_summary",
    "run_real",
    "score_against_layout",
    "score_real_run",
    "score_rigid_sheet",
    "write_real_report",
]
