"""Speed benchmark: ``ar-anchor bench speed``.

Three pipelines are timed on the very same synthetic frames, rendered beforehand (rendering is never
timed) at 720p and 1080p with a moving camera:

``opencv``
    The plain loop a newcomer writes: ``cv2.aruco.ArucoDetector`` with OpenCV's default
    ``DetectorParameters`` on the grey image (the BGR -> grey conversion counts as detection), then
    ``cv2.solvePnP(..., SOLVEPNP_IPPE_SQUARE)`` per marker.
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

Modules: :mod:`.scenes` (the clips), :mod:`.measure` (the pipelines taking turns, their statistics),
:mod:`.memory`, :mod:`.end_to_end`, :mod:`.run` (:func:`run_speed_benchmark`) and :mod:`.report`
(``speed.md`` and ``speed.json``).
"""

from __future__ import annotations

from .measure import ONE_THREAD_PIPELINES, PIPELINES
from .report import speed_markdown, write_speed_report
from .run import run_speed_benchmark
from .scenes import SCENES, SIZES, render_clip, speed_config, speed_scene

__all__ = [
    "ONE_THREAD_PIPELINES",
    "PIPELINES",
    "SCENES",
    "SIZES",
    "render_clip",
    "run_speed_benchmark",
    "speed_config",
    "speed_markdown",
    "speed_scene",
    "write_speed_report",
]
