"""What a map run leaves behind: the layout in both formats :func:`ar_anchor.boards.read_layout` reads (the
ArUco marker map YAML and our own TOML, each written atomically and read back before it replaces
anything), the markdown report, and the tracker config snippet that uses the map as a board.

Numbers are written with Python's shortest round-trip repr, so a layout read back equals the map exactly.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ...boards import read_layout
from ...errors import ConfigError, OutputError, printable
from .model import MarkerMap
from .solve import MapSolution

__all__ = [
    "board_snippet",
    "format_report",
    "format_summary",
    "layout_toml",
    "layout_yaml",
    "write_layout_toml",
    "write_layout_yaml",
]


def _number(value: float) -> str:
    """A float as both TOML and OpenCV's YAML read it back exactly."""
    text = repr(float(value))
    return "0.0" if text == "-0.0" else text


def _point(point: Sequence[float]) -> str:
    return "[" + ", ".join(_number(v) for v in point) + "]"


def layout_yaml(marker_map: MarkerMap) -> str:
    """The ArUco marker map (``MarkerMap::saveToFile``'s layout: ``aruco_bc_*`` keys, metres)."""
    corners = marker_map.all_corners()
    lines = [
        "%YAML:1.0",
        "---",
        f"aruco_bc_nmarkers: {len(corners)}",
        "aruco_bc_mInfoType: 1",
        "aruco_bc_markers:",
    ]
    for marker_id, quad in corners.items():
        lines.append(f"   - {{ id: {marker_id}, corners: [ " + ", ".join(_point(p) for p in quad) + " ] }")
    return "\n".join(lines) + "\n"


def layout_toml(marker_map: MarkerMap, header: str = "") -> str:
    """Our own layout TOML: ``[[markers]]`` with ``id`` and ``corners`` (TL, TR, BR, BL; metres)."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    for marker_id, quad in marker_map.all_corners().items():
        lines += ["", "[[markers]]", f"id = {marker_id}", "corners = [" + ", ".join(_point(p) for p in quad) + "]"]
    return "\n".join(lines).lstrip("\n") + "\n"


def _write_checked(path: Path, text: str, option: str, expected: MarkerMap) -> None:
    """Write ``text`` to ``path`` atomically; it must read back (:func:`read_layout`) as ``expected``."""
    if path.is_dir():
        raise OutputError(f"{option} {printable(path)}: is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{option} {printable(path)}: cannot create its folder ({err.strerror})") from None
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        try:
            temporary.write_text(text, encoding="utf-8")
        except OSError as err:
            raise OutputError(f"{option} {printable(path)}: cannot write ({err.strerror})") from None
        try:
            layout = read_layout(temporary)
        except ConfigError as err:  # our own file must read back
            raise OutputError(f"{option} {printable(path)}: written file does not read back ({err})") from None
        if [m for m, _ in layout] != expected.ids:
            raise OutputError(f"{option} {printable(path)}: written file reads back with other markers")
        try:
            os.replace(temporary, path)
        except OSError as err:
            raise OutputError(f"{option} {printable(path)}: cannot write ({err.strerror})") from None
    finally:
        if temporary.exists():
            temporary.unlink(missing_ok=True)


def write_layout_yaml(path: str | os.PathLike[str], marker_map: MarkerMap, option: str = "--out") -> None:
    """The ArUco marker map YAML at ``path`` (atomically, read back first)."""
    _write_checked(Path(path), layout_yaml(marker_map), option, marker_map)


def write_layout_toml(
    path: str | os.PathLike[str], marker_map: MarkerMap, header: str = "", option: str = "--out"
) -> None:
    """Our layout TOML at ``path`` (atomically, read back first); ``header``: comment lines on top."""
    _write_checked(Path(path), layout_toml(marker_map, header), option, marker_map)


def board_snippet(layout_name: str, dictionary: str, name: str = "map") -> str:
    """The tracker TOML that tracks the map as one rigid board (the layout path is relative to the config)."""
    return (
        "[detector]\n"
        f'dictionary = "{dictionary}"\n'
        "\n"
        "[[boards]]\n"
        f'name = "{name}"\n'
        'kind = "custom"\n'
        f'layout = "{layout_name}"  # relative to this config file\n'
    )


def _percentile(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else math.nan


def format_summary(solution: MapSolution) -> str:
    """One line: markers, frames, reprojection error."""
    errors = solution.corner_errors_px
    sigmas = {m: s for m, s in solution.map.sigma_mm.items() if math.isfinite(s)}
    worst = max(sigmas, key=lambda m: sigmas[m]) if sigmas else None
    return (
        f"{len(solution.map.ids)} markers from {len(solution.frame_order)} frames; reprojection RMS "
        f"{solution.rms_px:.3f} px, median {_percentile(errors, 50):.3f} px, p95 {_percentile(errors, 95):.3f} px"
        + (f"; largest position uncertainty {sigmas[worst]:.2f} mm (marker {worst})" if worst is not None else "")
    )


def format_report(
    solution: MapSolution,
    *,
    sources: Sequence[str],
    dictionary: str,
    frames_considered: int,
    frames_read: int,
    step: int,
    outputs: Sequence[tuple[str, Path]],
    layout_name: str,
    frame_label: Callable[[str], str] | None = None,
) -> str:
    """The markdown report: inputs, frames, markers (observations, uncertainty), errors, outliers, usage."""
    marker_map = solution.map
    errors = solution.corner_errors_px
    label = frame_label or (lambda name: name)
    lines = [
        "# ar-anchor map",
        "",
        f"- date: {_dt.datetime.now().astimezone().isoformat(timespec='seconds')}",
        "- inputs: " + ", ".join(f"`{printable(s)}`" for s in sources),
        f"- dictionary {dictionary}, marker side {marker_map.length_m * 1000:g} mm",
        f"- frames: {frames_read} read, {frames_considered} searched"
        + (f" (one in {step})" if step > 1 else "")
        + f", {solution.frames_in} with two markers or more, {len(solution.frame_order)} used in the adjustment",
        f"- map frame: marker {marker_map.reference_id}'s (its centre, x right, y up, z out of the marker)",
        f"- map size: {marker_map.extent_m:.3f} m (diagonal of the box holding every corner)",
        f"- solve: {solution.evaluations} evaluations, {solution.seconds:.1f} s",
        "",
        "## Reprojection error",
        "",
        "Every used corner, reprojected from the adjusted map and that frame's adjusted camera pose:",
        "",
        "| corners | RMS px | median px | p95 px | max px | first solve RMS px |",
        "|---:|---:|---:|---:|---:|---:|",
        f"| {errors.size} | {solution.rms_px:.3f} | {_percentile(errors, 50):.3f} | {_percentile(errors, 95):.3f} "
        f"| {float(errors.max()) if errors.size else math.nan:.3f} | {solution.first_rms_px:.3f} |",
        "",
        "## Markers",
        "",
        "Position: the marker's centre in the map frame. sigma: 1-sigma 3D uncertainty of that position relative "
        "to the reference marker (from J^T J at the solution, scaled by the residual variance; frame poses "
        "eliminated).",
        "",
        "| id | observations | RMS px | x m | y m | z m | sigma mm |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    lines += _marker_rows(solution)
    if solution.unplaced:
        lines += ["", "Not mapped:", ""]
        lines += [f"- marker {m}: {why}" for m, why in solution.unplaced.items()]
    lines += ["", "## Outliers", ""]
    if solution.dropped:
        lines.append(
            f"{len(solution.dropped)} observation(s) dropped after a first solve (misread ids, smeared corners):"
        )
        lines.append("")
        for name, marker_id, error in solution.dropped[:30]:
            lines.append(f"- {label(name)}: marker {marker_id}, {error:.2f} px")
        if len(solution.dropped) > 30:
            lines.append(f"- ... and {len(solution.dropped) - 30} more")
    else:
        lines.append("none dropped")
    lines += ["", "## Files", ""]
    lines += [f"- {what}: `{printable(path)}`" for what, path in outputs]
    lines += [
        "",
        "## Tracking the map as one board",
        "",
        "In a tracker config (`ar-anchor replay VIDEO --config map.toml ...`), beside the layout file:",
        "",
        "```toml",
        board_snippet(layout_name, dictionary).rstrip("\n"),
        "```",
        "",
    ]
    return "\n".join(lines)


def _marker_rows(solution: MapSolution) -> list[str]:
    """The markers table's rows: id, observations, RMS error, centre, uncertainty."""
    marker_map = solution.map
    rows = []
    per_marker: dict[int, list[float]] = {}
    for _, marker_id, error in solution.observation_errors:
        per_marker.setdefault(marker_id, []).append(error)
    for marker_id in marker_map.ids:
        centre = marker_map.world_from_marker[marker_id].tvec
        marker_errors = np.asarray(per_marker.get(marker_id, []))
        rms = math.sqrt(float(np.mean(marker_errors**2))) if marker_errors.size else math.nan
        sigma = marker_map.sigma_mm.get(marker_id, math.nan)
        reference = " (reference)" if marker_id == marker_map.reference_id else ""
        rows.append(
            f"| {marker_id}{reference} | {solution.observations_per_marker.get(marker_id, 0)} | {rms:.3f} "
            f"| {centre[0]:+.4f} | {centre[1]:+.4f} | {centre[2]:+.4f} | {sigma:.2f} |"
        )
    return rows
