"""Measurements of the tracker: `ar-anchor bench` (stability, real video, speed, run) and
`ar-anchor study`, each writing Markdown + JSON."""
