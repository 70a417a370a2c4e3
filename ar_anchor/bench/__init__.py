"""Measurements of the tracker: `ar-anchor bench` (stability, boards, overlay, speed, run, real video)
and `ar-anchor study`, each writing Markdown + JSON.

``stability/`` (synthetic ground truth: raw IPPE vs the tracker), ``boards.py`` (a board vs a lone
marker), ``overlay.py`` (rendering cost), ``speed/`` (plain OpenCV vs the tracker, per frame and end to
end), ``run.py`` (the CLI's own processes timed from outside), ``real/`` (real video, no truth);
``report.py`` holds what their reports share (thresholds, strict JSON, the machine, number formats).
"""
