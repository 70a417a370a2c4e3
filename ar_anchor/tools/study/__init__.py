"""``ar-anchor study``: the PnP textbook's experiments, reproduced with our own code.

Three studies, each writing ``<name>.png`` (figure), ``<name>.md`` (table and the facts it shows),
``<name>.json`` (settings, every raw number, summary) and ``<name>.rrd`` (rerun recording) to ``--out``:

``outliers``
    Points 4-8 m ahead of a 1920x1080 camera (fx = fy = 1480), 0.5 px pixel noise, a quarter of the
    correspondences replaced by uniform random pixels: plain ``solvePnP`` against ``solvePnPRansac``
    (2 px, 300 iterations) followed by ``solvePnPRefineLM`` on its inliers, over many seeds.
    The points are drawn in the camera frame (a uniform pixel and a uniform depth in 4-8 m, so every
    point is in view) and expressed in the world frame with the inverse of the true pose
    ``camera_from_world`` (rvec (0.10, -0.30, 0.05), tvec (0.20, -0.10, 0.50)); the true pose maps
    them back into view.
``ransac``
    The same problem over a grid of contamination x inlier threshold: median translation error,
    inlier recall (share of the honest points RANSAC keeps) and the share of seeds that succeed.
``jitter``
    A lone 5 cm marker and a 2x2 board of the same markers, seen by a static synthetic camera
    (1280x720, fx = 1000) at 0.3-3 m; each distance's view is rendered once (blur included) and each of
    its frames adds fresh Gaussian sensor noise. The tracker (as configured: ROI tracking on by default) runs
    on those frames; its per-frame raw pose and its output give the spread of the distance ``||t||``
    and of the orientation for both pipelines, the flipped-frame rate and the ambiguity onset.

A seed fixes one problem: its points, pixel noise and the order in which points get contaminated
are drawn in a fixed sequence, so the same seed at a higher contamination replaces a superset of
the same points (common random numbers across the grid).

Modules: :mod:`.pnp` (the ``outliers`` and ``ransac`` experiments), :mod:`.jitter` (the
``jitter`` experiment), :mod:`.stats` (summary statistics they share), :mod:`.figures`
(matplotlib), :mod:`.report` (Markdown), :mod:`.recording` (rerun), :mod:`.options` (the command
line), :mod:`.limits` (the range of every number, checked before the first study runs), :mod:`.files`
(``--out`` and the files written under partial names until complete), :mod:`.interrupt` (Ctrl-C and
SIGTERM, never lost) and :mod:`.command` (``ar-anchor study``: run, write the four files).

An interrupted or failed study leaves none of its four files: they are written as
``.<name>.<pid>.partial.<suffix>`` (the recording as ``.<name>.rrd.<pid>.tmp``), renamed into place
together once all are complete and removed otherwise; files of studies completed before stay.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ...lazy import lazy_exports

if TYPE_CHECKING:  # imported on first use (below): the command line's options must not load matplotlib
    from .command import run_study
    from .jitter import JitterSetup, run_jitter
    from .options import DEFAULT_OUT, STUDIES, configure_parser
    from .pnp import (
        Correspondences,
        PnPSetup,
        PnPTrial,
        make_correspondences,
        run_outliers,
        run_ransac,
        solve_trial,
    )

__all__ = [
    "DEFAULT_OUT",
    "STUDIES",
    "Correspondences",
    "JitterSetup",
    "PnPSetup",
    "PnPTrial",
    "configure_parser",
    "make_correspondences",
    "run_jitter",
    "run_outliers",
    "run_ransac",
    "run_study",
    "solve_trial",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".command": ["run_study"],
        ".jitter": ["JitterSetup", "run_jitter"],
        ".options": ["DEFAULT_OUT", "STUDIES", "configure_parser"],
        ".pnp": [
            "Correspondences",
            "PnPSetup",
            "PnPTrial",
            "make_correspondences",
            "run_outliers",
            "run_ransac",
            "solve_trial",
        ],
    },
    globals(),
)
