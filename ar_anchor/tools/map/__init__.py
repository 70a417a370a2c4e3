"""``ar-anchor map``: a map of markers that sit rigidly together (a sheet, a wall, a room), learned from
one or more videos or image folders by bundle adjustment.

Pipeline
--------
1. **Observe** (:mod:`.observe`): every ``--step``-th frame is searched with the tracker's own
   :class:`~ar_anchor.track.detection.Detector` (edge-fitted corners, the one dictionary); every marker
   gets both IPPE solutions (:func:`~ar_anchor.track.pose.solve_marker`). Frames with two markers or more
   are kept.
2. **Initialise** (:mod:`.solve`): from the reference marker (the most seen, or ``--origin``), markers are
   placed incrementally; each frame's camera pose comes from all placed markers it shows (RANSAC across
   markers, then ``solvePnPRefineLM``), a new marker's pose from the consensus of its IPPE solutions over
   the located frames showing it. No single frame decides anything: the planar flip of one view is
   outvoted by the others.
3. **Bundle adjustment** (:mod:`.solve`): ``scipy.optimize.least_squares`` with a sparse analytic
   Jacobian and a Huber loss over every frame's pose and every marker's pose (the reference fixed: the
   map frame); observations still off after a first solve are dropped and the map solved again.
4. **Uncertainty** (:mod:`.solve`): each marker's 1-sigma position uncertainty from the normal matrix.
5. **Outputs** (:mod:`.report`, :mod:`.recording`): the ArUco marker map YAML and our layout TOML (both
   read by :func:`ar_anchor.boards.read_layout`, so the map is a ``kind = "custom"`` board), a markdown
   report and a rerun recording.

Modules: :mod:`.model` (observations, the map, similarity alignment), :mod:`.observe`, :mod:`.solve`,
:mod:`.report`, :mod:`.recording` and :mod:`.command` (``ar-anchor map``).
"""

from __future__ import annotations

from .command import run_map
from .model import FrameObservations, MarkerMap, Similarity, aligned_errors, rms_m, similarity_align
from .observe import Observed, observe_sources
from .report import board_snippet, format_report, layout_toml, layout_yaml, write_layout_toml, write_layout_yaml
from .solve import MapSolution, build_map

__all__ = [
    "FrameObservations",
    "MapSolution",
    "MarkerMap",
    "Observed",
    "Similarity",
    "aligned_errors",
    "board_snippet",
    "build_map",
    "format_report",
    "layout_toml",
    "layout_yaml",
    "observe_sources",
    "rms_m",
    "run_map",
    "similarity_align",
    "write_layout_toml",
    "write_layout_yaml",
]
