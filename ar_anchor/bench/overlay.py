"""Overlay rendering cost: ``ar-anchor bench overlay``.

The median time of :meth:`~ar_anchor.render.overlay.OverlayRenderer.annotate` per frame for one model
(the cube, or icospheres of growing triangle counts) on one marker, at 720p and 1080p.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import CameraModel
from ..config import TrackerConfig
from ..geometry import Pose
from ..lazy import import_held
from ..targets import TargetId, TrackState

__all__ = ["OVERLAY_TRIANGLES", "run_overlay_benchmark", "write_overlay_report"]

OVERLAY_TRIANGLES = (12, 368, 1_280, 5_120, 20_480)


def _sphere_mesh_file(directory: Path, triangles: int) -> Path:
    """An icosphere of about ``triangles`` faces (20 * 4^k), as a PLY file for the mesh overlay."""
    trimesh = import_held("trimesh")  # not inside its imports: a Ctrl-C there would be swallowed
    import_held("trimesh.creation")

    subdivisions = max(0, round(math.log(max(triangles, 20) / 20, 4)))
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    path = directory / f"sphere_{len(mesh.faces)}.ply"
    mesh.export(path)
    return path


def run_overlay_benchmark(frames: int = 60, progress: Callable[[int, int, str], None] | None = None) -> list[dict]:
    """Median ``OverlayRenderer.annotate`` time per frame: one model of a given size on one marker,
    seen from 0.5 m so it covers about a fifth of the frame's height, at 720p and 1080p."""
    import tempfile  # noqa: PLC0415

    from ..config import OverlayConfig  # noqa: PLC0415
    from ..render.overlay import OverlayRenderer  # noqa: PLC0415
    from ..track.detection import MarkerDetections  # noqa: PLC0415
    from ..track.results import FrameResult, TargetResult  # noqa: PLC0415

    rows = []
    sizes = [(1280, 720, 1000.0), (1920, 1080, 1480.0)]
    cases = [("cube", 12), *[("mesh", n) for n in OVERLAY_TRIANGLES[1:]]]
    with tempfile.TemporaryDirectory() as tmp:
        for i, (kind, triangles) in enumerate(cases):
            if progress is not None:
                progress(i, len(cases), f"{kind} {triangles}")
            path = "" if kind == "cube" else str(_sphere_mesh_file(Path(tmp), triangles))
            overlay = OverlayConfig(target=TargetId.marker(0), kind=kind, path=path, size_m=0.1)
            config = dataclasses.replace(TrackerConfig(), overlays=(overlay,))
            row: dict[str, Any] = {"model": kind, "triangles": 12 if kind == "cube" else None}
            for width, height, focal in sizes:
                camera = CameraModel.from_fov(width, height, focal)
                renderer = OverlayRenderer(config, camera)
                if kind == "mesh":
                    row["triangles"] = int(len(renderer._meshes[path].faces))
                image = np.full((height, width, 3), 128, np.uint8)
                times = []
                for k in range(frames):
                    angle = 2 * math.pi * k / frames
                    pose = Pose(
                        np.array([math.pi + 0.4 * math.cos(angle), 0.4 * math.sin(angle), 0.0]), np.array([0, 0, 0.5])
                    )
                    target = TargetResult(TargetId.marker(0), TrackState.TRACKED, pose, pose, 0.1, 3.0, 0.05)
                    result = FrameResult(k, 0, MarkerDetections.empty(), {target.target: target}, camera=camera)
                    start = time.perf_counter()
                    renderer.annotate(image, result)
                    times.append((time.perf_counter() - start) * 1e3)
                row[f"{height}p_ms"] = float(np.median(times[5:]))
            rows.append(row)
    return rows


def write_overlay_report(
    out_dir: Path, frames: int = 60, progress=None, command: str = "ar-anchor bench overlay"
) -> list:
    """Run :func:`run_overlay_benchmark`; write ``overlay.md`` and ``overlay.json`` to ``out_dir``; the rows."""
    start = time.perf_counter()
    rows = run_overlay_benchmark(frames, progress)
    wall = time.perf_counter() - start
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "overlay.json").write_text(json.dumps({"command": command, "rows": rows}, indent=2) + "\n")
    lines = [
        "# Overlay rendering cost",
        "",
        f"Produced by `{command}` in {wall:.0f} s: median time of `OverlayRenderer.annotate` per frame (one model "
        f"on one marker 0.5 m away, 10 cm across, turning; {frames} frames; one thread; no lens distortion).",
        "",
        "| model | triangles | 720p ms | 1080p ms |",
        "|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| {row['model']} | {row['triangles']} | {row['720p_ms']:.2f} | {row['1080p_ms']:.2f} |")
    (out_dir / "overlay.md").write_text("\n".join(lines) + "\n")
    return rows
