"""``real.md`` and ``real.json``: the run scored and reported, and a few lines for the terminal."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2

from ... import __version__
from ...boards import read_layout
from ...camera import CameraModel
from ...config import TrackerConfig
from ..report import FLIP_DEG, fmt, write_json
from .inputs import RealInputs
from .run import RealRun, run_real, score_real_run
from .scoring import MIN_COMMON_FRAMES

__all__ = ["real_markdown", "real_summary", "write_real_report"]


def write_real_report(
    out_dir: str | os.PathLike[str],
    inputs: RealInputs,
    config: TrackerConfig,
    *,
    command: str = "ar-anchor bench real",
    progress: Callable[[int, int | None], None] | None = None,
) -> dict[str, Any]:
    """Run :func:`~ar_anchor.bench.real.run.run_real` on ``inputs`` with ``config`` (already carrying the
    dictionary / length overrides), score it, write ``real.md`` and ``real.json`` to ``out_dir`` and return
    the results."""
    camera = CameraModel.from_yaml(inputs.camera)
    layout = read_layout(inputs.layout) if inputs.layout is not None else None
    run = run_real(inputs.video, camera, config, progress=progress)
    results = score_real_run(run, layout)
    results["meta"] = _meta(inputs, config, run, command)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "real.json", results)
    (out / "real.md").write_text(real_markdown(results))
    return results


def _meta(inputs: RealInputs, config: TrackerConfig, run: RealRun, command: str) -> dict[str, Any]:
    return {
        "command": command,
        "video": _shown(inputs.video),
        "camera": _shown(inputs.camera),
        "layout": _shown(inputs.layout) if inputs.layout is not None else None,
        "dictionary": config.detector.dictionary,
        "marker_length_m": config.markers.length_m,
        "config": str(config.source) if getattr(config, "source", None) else "defaults",
        "resolution": list(run.resolution),
        "flip_deg": FLIP_DEG,
        "min_common_frames": MIN_COMMON_FRAMES,
        "ar_anchor": __version__,
        "opencv": cv2.__version__,
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def real_markdown(results: Mapping[str, Any]) -> str:
    """The report of scored results (with their ``meta``)."""
    meta, speed, det = results["meta"], results["speed"], results["detection"]
    layout = meta.get("layout")
    lines = _introduction(meta, speed) + _consistency(results["rows"], layout) + _detection(det) + _speed(speed)
    return "\n".join(lines)


def _introduction(meta: Mapping[str, Any], speed: Mapping[str, Any]) -> list[str]:
    """Title, inputs, what is measured and the blind spot."""
    layout = meta.get("layout")
    lines = [
        "# Real video: rigid-sheet consistency (no ground truth)",
        "",
        f"Produced by: `{meta['command']}`",
        "",
        f"Video `{meta['video']}` ({speed['frames']} frames, {meta['resolution'][0]}x{meta['resolution'][1]}), "
        f"camera `{meta['camera']}`, {meta['dictionary']}, markers {1000 * meta['marker_length_m']:g} mm"
        + (f", layout `{layout}`" if layout else "")
        + f"; tracker config: {meta['config']}. ar_anchor {meta['ar_anchor']}, OpenCV {meta['opencv']}, "
        f"{meta['date']}.",
        "",
        "## What is measured",
        "",
        "The markers are printed on one rigid sheet, so each pair's relative pose `marker_a_from_marker_b` "
        "(from `camera_from_a` and `camera_from_b` in the same frame) should be constant. Each pair-frame is "
        "compared with that pair's mean over the video (rotation: chordal mean; translation: median). "
        f"A **flip** is a pair-frame more than {FLIP_DEG:g} deg from the pair's mean: one of the two markers "
        "is on the wrong planar (IPPE) solution, or badly wrong. The RMS columns are over the other "
        "pair-frames (rotation in degrees, translation in mm from the pair's median). Pairs seen together "
        f"in fewer than {MIN_COMMON_FRAMES} frames are not scored. Marker-frames: (marker, frame) poses scored.",
        "",
        "**Blind spot**: a flip of all markers together (every marker on its mirror solution at once, as "
        "a lone sheet seen face-on can do) keeps the relative poses consistent and is not counted"
        + (
            "; so is a pair that is wrong most of the time (it pulls its own mean), which the columns "
            "against the printed layout do catch."
            if layout
            else ". Give `--layout` (the printed marker map) to compare with the true relative poses as well."
        ),
        "",
        "## Relative pose consistency",
        "",
    ]
    return lines


def _consistency(rows: Sequence[Mapping[str, Any]], layout: str | None) -> list[str]:
    """The relative-pose consistency table (with the columns against the layout when there is one)."""
    header = "| poses | pair-frames | flips % | rel. rot RMS deg | rel. trans RMS mm | marker-frames |"
    rule = "|---|---:|---:|---:|---:|---:|"
    if layout:
        header += " vs layout: flips % | rot RMS deg | trans RMS mm | pair mean offset deg | distance ratio |"
        rule += "---:|---:|---:|---:|---:|"
    lines = [header, rule]
    for row in rows:
        cells = [
            row["label"],
            str(row["pair_frames"]),
            fmt(row["flip_pct"]),
            fmt(row["rel_rot_rms_deg"]),
            fmt(row["rel_trans_rms_mm"], 1),
            str(row["marker_frames"]),
        ]
        if layout:
            vs = row["vs_layout"]
            cells += [fmt(vs["flip_pct"]), fmt(vs["rel_rot_rms_deg"]), fmt(vs["rel_trans_rms_mm"], 1)]
            cells += [fmt(vs["mean_offset_rms_deg"]), fmt(vs["distance_ratio"], 3)]
        lines.append("| " + " | ".join(cells) + " |")
    if layout:
        lines += [
            "",
            "The *vs layout* columns compare each pair-frame with the pair's relative pose in the printed "
            "layout instead of its mean (same flip threshold, same pairs). *Pair mean offset*: RMS over pairs "
            "of the angle between the pair's mean and the layout; *distance ratio*: median measured / printed "
            "centre distance. Both are about the sheet as much as the tracker: a sheet that is not flat, or "
            "printed at another scale than the layout (or than --marker-length), offsets every pair-frame and "
            "leaves less of the flip margin, so read the layout columns next to these two.",
        ]
    return lines


def _detection(det: Mapping[str, Any]) -> list[str]:
    """Marker-frames measured by ar_anchor and found by plain OpenCV, and the worst frames."""
    lines = [
        "",
        "## Detection",
        "",
        "| | marker-frames | frames with a marker |",
        "|---|---:|---:|",
        f"| ar_anchor (raw pose measured) | {det['ours_marker_frames']} | {det['ours_frames_with_markers']} |",
        f"| plain OpenCV | {det['plain_marker_frames']} | {det['plain_frames_with_markers']} |",
        "",
        f"Plain OpenCV found {det['plain_not_ours']} marker-frames that ar_anchor did not measure "
        f"(in {det['frames_plain_not_ours']} frames); ar_anchor measured {det['ours_not_plain']} that plain "
        f"OpenCV did not find (in {det['frames_ours_not_plain']} frames).",
    ]
    if det["worst_frames"]:
        lines += ["", "Worst frames (plain OpenCV found, ar_anchor did not):", ""]
        lines += ["| frame | missed ids | plain found |", "|---:|---|---:|"]
        for w in det["worst_frames"]:
            lines.append(f"| {w['frame']} | {', '.join(map(str, w['missed_ids']))} | {w['plain_found']} |")
    return lines


def _speed(speed: Mapping[str, Any]) -> list[str]:
    """Frames per second of the tracker and of plain OpenCV."""
    return [
        "",
        "## Speed",
        "",
        f"Tracker: {fmt(speed['tracker_fps'], 1)} frames/s ({fmt(speed['tracker_ms_per_frame'], 2)} ms/frame, "
        f"Tracker.process only); plain OpenCV: {fmt(speed['plain_fps'], 1)} frames/s; whole run (decode, both, "
        f"collection) {fmt(speed['wall_s'], 1)} s.",
        "",
    ]


def real_summary(results: Mapping[str, Any]) -> str:
    """A few lines for the terminal."""
    lines = []
    for row in results["rows"]:
        if row["key"] not in ("output", "raw", "plain_opencv"):
            continue
        text = (
            f"{row['label']}: {row['pair_frames']} pair-frames, flips {fmt(row['flip_pct'])} %, "
            f"rel. rot RMS {fmt(row['rel_rot_rms_deg'])} deg, rel. trans RMS {fmt(row['rel_trans_rms_mm'], 1)} mm, "
            f"{row['marker_frames']} marker-frames"
        )
        if "vs_layout" in row:
            vs = row["vs_layout"]
            text += f" (vs layout: flips {fmt(vs['flip_pct'])} %, rot {fmt(vs['rel_rot_rms_deg'])} deg)"
        lines.append(text)
    det, speed = results["detection"], results["speed"]
    lines.append(
        f"detection: {det['ours_marker_frames']} marker-frames measured vs {det['plain_marker_frames']} plain OpenCV; "
        f"{det['plain_not_ours']} found by plain OpenCV only; tracker {fmt(speed['tracker_fps'], 1)} frames/s"
    )
    return "\n".join(lines)


def _shown(path: Path) -> str:
    """A path as the report shows it: relative to the working folder (a report names no machine's
    absolute paths), unless it is on another drive."""
    try:
        return os.path.relpath(path)
    except ValueError:
        return str(path)
