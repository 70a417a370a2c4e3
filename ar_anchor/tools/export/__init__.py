"""Exports of a finished run for robotics tools: ``poses_ext.csv`` (quaternions and 4x4 matrices), TUM
trajectories (``tum/<target>.txt``) and a ROS 2 bag (``run.mcap``). See ``docs/outputs-and-viewer.md``.

:func:`export_run` is the entry point (``ar-anchor export RUN_DIR``, and ``--export`` after a run).
"""

from __future__ import annotations

from .run import FORMATS, ExportResult, export_run, parse_formats

__all__ = ["FORMATS", "ExportResult", "export_run", "parse_formats"]
