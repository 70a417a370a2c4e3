"""Speed benchmark: ``ar-anchor bench speed`` (issue 33's acceptance) and ``ar-anchor bench speed --stages``.

``ar-anchor bench speed`` (:mod:`.acceptance`, report :mod:`.report`) measures issue 33's acceptance as real
processes, plain OpenCV in the same run, runs taking turns, medians of three rounds: chessboard.avi looped to
over 1000 frames (:mod:`.remux`), the synthetic 720p 50-marker and 1080p one-marker clips encoded to H.264,
the start-up to the first pose and ``--help``, and live latency at 1080p. Each acceptance line is a row with
its value, target and pass or fail (:mod:`.rows`); the processes are :mod:`.processes`, the plain loop
:mod:`.plain_loop` (``--subpix``: ``CORNER_REFINE_SUBPIX`` + ``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)``).

``ar-anchor bench speed --stages`` (:mod:`.stages_run`, report :mod:`.stages_report`) times four pipelines
in one process on the very same frames, held in memory beforehand (rendering and decoding are never timed):
synthetic clips at 720p and 1080p with a moving camera (one marker, eight markers, a 2x2 board), a synthetic
720p scene of 50 small markers seen by a hand-held camera, and the real ``chessboard.avi`` (18 markers, no
truth; skipped with a note when the real data is absent):

``opencv``
    The plain loop a newcomer writes: ``cv2.aruco.ArucoDetector`` with OpenCV's default
    ``DetectorParameters`` on the grey image (the BGR -> grey conversion counts as detection), then
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` per marker (its first solution).
``opencv_subpix``
    The same with ``cornerRefinementMethod = CORNER_REFINE_SUBPIX``.
``tracker_full``
    :class:`~ar_anchor.track.tracker.Tracker` with ROI tracking off (full-frame detection every frame).
``tracker_roi``
    :class:`~ar_anchor.track.tracker.Tracker` with the default detector settings (ROI tracking on).

The pipelines take turns frame by frame (the order rotates every frame), so a background load that
comes and goes on a shared machine hits all of them alike. Every pipeline first runs a throw-away
instance over a few frames (warm-up); the measured instance then starts fresh at frame 0, so its
accuracy includes the filter's start. The default pass runs with OpenCV's own thread count; a second
pass repeats the loops with ``cv2.setNumThreads(1)`` (the one-core comparison).

Then one clip (1080p, one marker) goes through the whole chain a session runs, one stage after the
other: decode (the rendered frames encoded once to H.264 and read back by
:class:`~ar_anchor.sources.files.VideoFileSource`), track, overlay (the default cube on
``marker:*``) and rerun logging (default recording settings, to a temporary ``.rrd``).

Every clip reports each stage per frame and per marker found, the markers found per frame by each
pipeline, the tracker / plain-loop ratios of the same run, and each pipeline's tracemalloc peak.

Modules of ``--stages``: :mod:`.scenes` (the clips, shared with the acceptance and ``bench run``),
:mod:`.real_clip` (chessboard.avi), :mod:`.measure` (the pipelines taking turns, their statistics),
:mod:`.memory`, :mod:`.end_to_end`, :mod:`.stages_run` (:func:`run_stages_benchmark`) and
:mod:`.stages_report` (``speed_stages.md`` and ``speed_stages.json``).
"""

from __future__ import annotations

from .acceptance import PARTS, run_speed_acceptance
from .measure import ONE_THREAD_PIPELINES, PIPELINES
from .report import speed_markdown, write_speed_report
from .scenes import CLIP_NAMES, EXTRA_CLIPS, SCENES, SIZES, render_clip, speed_config, speed_scene, split_clips
from .stages_report import stages_markdown, write_stages_report
from .stages_run import run_stages_benchmark

__all__ = [
    "CLIP_NAMES",
    "EXTRA_CLIPS",
    "ONE_THREAD_PIPELINES",
    "PARTS",
    "PIPELINES",
    "SCENES",
    "SIZES",
    "render_clip",
    "run_speed_acceptance",
    "run_stages_benchmark",
    "speed_config",
    "speed_markdown",
    "speed_scene",
    "split_clips",
    "stages_markdown",
    "write_speed_report",
    "write_stages_report",
]
