"""Issue 33's acceptance as rows: each measured value (a median over the runs, or a ratio of two
medians of the same run), its target and whether it passes. Pure functions of the measured parts, so
that the arithmetic is tested apart from the timing.

A part's record (see :mod:`.acceptance`) holds its runs: ``causal`` (and, for chessboard.avi, ``offline``)
replays as :func:`~.processes.replay_run` returns them, ``plain`` loops as :func:`~.processes.plain_run`
returns them, and ``found``, the per-frame marker comparison of :func:`found_comparison`.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "TARGETS",
    "acceptance_rows",
    "check",
    "found_comparison",
    "median",
    "ratio",
    "summarise_clip",
]

_OPS: dict[str, Callable[[float, float], bool]] = {"<=": operator.le, ">=": operator.ge, "==": operator.eq}

# row id -> (operator, bound, unit): issue 33's acceptance
TARGETS: dict[str, tuple[str, float, str]] = {
    "1a": ("<=", 1.5, "x"),
    "1b": (">=", 60.0, "fps"),
    "1c": ("<=", 1.6, "x"),
    "1d": ("<=", 1.1, "x"),
    "2a": ("<=", 2.0, "x"),
    "2b": (">=", 30.0, "fps"),
    "3": (">=", 1.2, "x"),
    "4a": ("<=", 0.8, "s"),
    "4b": ("<=", 0.3, "s"),
    "5a": ("<=", 8.0, "ms"),
    "5b": ("<=", 15.0, "ms"),
    "5c": ("<=", 1.1, "x"),
    "5d": ("<=", 1.1, "x"),
    "6": ("==", 0.0, "frames"),
}


def median(values: Iterable[float | None]) -> float | None:
    """The median of the values given (None ones left out); None when there is none."""
    kept = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.median(kept)) if kept else None


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b``; None when either is missing or ``b`` is not positive."""
    if a is None or b is None or not b > 0:
        return None
    return a / b


def check(value: float | None, op: str, bound: float) -> bool | None:
    """Does ``value`` meet ``op bound`` (``<=``, ``>=``, ``==``)? None when it was not measured."""
    if value is None or not math.isfinite(value):
        return None
    return bool(_OPS[op](value, bound))


def found_comparison(tracker: Mapping[int, set[int]], plain: Sequence[Sequence[int]]) -> dict[str, int]:
    """Markers found per frame, the tracker (``tracker``: frame -> ids measured) against the plain loop
    (``plain``: ids per frame, in order): frames compared (the plain loop's), frames where the tracker found
    fewer, marker-frames the plain loop found and the tracker did not (``missed``) and the other way round
    (``extra``), and each side's marker-frames."""
    fewer = missed = extra = tracker_total = plain_total = 0
    for index, ids in enumerate(plain):
        mine, theirs = tracker.get(index, set()), set(ids)
        fewer += len(mine) < len(theirs)
        missed += len(theirs - mine)
        extra += len(mine - theirs)
        tracker_total += len(mine)
        plain_total += len(theirs)
    beyond = sum(1 for index in tracker if index >= len(plain))  # frames the plain loop never saw
    return {
        "frames": len(plain),
        "frames_fewer": fewer,
        "missed_marker_frames": missed,
        "extra_marker_frames": extra,
        "tracker_marker_frames": tracker_total,
        "plain_marker_frames": plain_total,
        "tracker_frames_beyond_plain": beyond,
    }


def summarise_clip(part: Mapping[str, Any]) -> dict[str, Any]:
    """The medians over a clip's runs: the causal (and offline) replays' process wall time, process fps and
    tracker per frame (the sum of ``summary.json``'s detect, pose and filter medians); the plain loop's
    process wall time and fps, its detect + pose per frame (the sum of its detect and pose medians: the same
    statistic as the tracker's) and its loop wall time per frame (decode included); and the ratios of those
    medians."""
    causal, plain = part.get("causal", []), part.get("plain", [])
    offline = part.get("offline", [])
    out: dict[str, Any] = {
        "causal_wall_s": median(r["process_wall_s"] for r in causal),
        "causal_fps_process": median(r["fps_process"] for r in causal),
        "causal_fps_run": median(r.get("fps_run") for r in causal),
        "tracker_ms": median(r["tracker_ms"].get("total") for r in causal),
        "tracker_stage_ms": {
            stage: median(r["tracker_ms"].get(stage) for r in causal) for stage in ("detect", "pose", "filter")
        },
        "plain_wall_s": median(r["process_wall_s"] for r in plain),
        "plain_fps_process": median(r["fps_process"] for r in plain),
        "plain_detect_pose_ms": median(_sum(r.get("detect_ms"), r.get("pose_ms")) for r in plain),
        "plain_loop_ms_per_frame": median(r.get("loop_ms_per_frame") for r in plain),
        "plain_decode_ms": median(r.get("decode_ms") for r in plain),
    }
    out["tracker_over_plain_detect_pose"] = ratio(out["tracker_ms"], out["plain_detect_pose_ms"])
    out["tracker_over_plain_loop"] = ratio(out["tracker_ms"], out["plain_loop_ms_per_frame"])
    out["causal_fps_over_plain_fps"] = ratio(out["causal_fps_process"], out["plain_fps_process"])
    bare = part.get("causal_no_recording", [])
    if bare:
        out["no_recording_tracker_ms"] = median(r["tracker_ms"].get("total") for r in bare)
        out["no_recording_fps_process"] = median(r["fps_process"] for r in bare)
        out["no_recording_wall_s"] = median(r["process_wall_s"] for r in bare)
        out["recording_over_no_recording"] = ratio(out["tracker_ms"], out["no_recording_tracker_ms"])
    if offline:
        out["offline_wall_s"] = median(r["process_wall_s"] for r in offline)
        out["offline_fps_process"] = median(r["fps_process"] for r in offline)
        out["offline_over_causal_wall"] = ratio(out["offline_wall_s"], out["causal_wall_s"])
    return out


def _sum(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a + b


def _row(row_id: str, clip: str, what: str, value: float | None, how: str, **extra: Any) -> dict[str, Any]:
    op, bound, unit = TARGETS[row_id]
    return {
        "id": row_id,
        "clip": clip,
        "what": what,
        "value": value,
        "unit": unit,
        "target": f"{op} {bound:g}",
        "op": op,
        "bound": bound,
        "passed": check(value, op, bound),
        "how": how,
        **extra,
    }


def acceptance_rows(parts: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The acceptance rows of the parts measured (a part absent or skipped gives no row): each with its
    id, clip, what it measures, value, unit, target, pass (True / False / None: not measured) and how it
    was taken."""
    rows: list[dict[str, Any]] = []
    chess = _measured(parts, "chessboard")
    if chess is not None:
        s = chess["summary"]
        rows.append(
            _row(
                "1a", chess["label"], "tracker detect + pose + filter per frame / plain SUBPIX + IPPE detect + pose",
                s["tracker_over_plain_detect_pose"],
                f"{_ms(s['tracker_ms'])} / {_ms(s['plain_detect_pose_ms'])}; against the plain loop's wall time per "
                f"frame (decode included, {_ms(s['plain_loop_ms_per_frame'])}): {_x(s['tracker_over_plain_loop'])}",
                tracker_over_plain_loop=s["tracker_over_plain_loop"],
            )
        )  # fmt: skip
        rows.append(
            _row("1b", chess["label"], "`replay --causal` whole process fps (default outputs)",
                 s["causal_fps_process"], f"{chess['frames']} frames / {_s(s['causal_wall_s'])} s process wall")
        )  # fmt: skip
        rows.append(
            _row("1c", chess["label"], "default (offline) replay wall / `replay --causal` wall",
                 s.get("offline_over_causal_wall"), f"{_s(s.get('offline_wall_s'))} s / {_s(s['causal_wall_s'])} s")
        )  # fmt: skip
        if "recording_over_no_recording" in s:
            rows.append(
                _row("1d", chess["label"], "tracker detect + pose + filter per frame, `replay --causal` with default "
                     "outputs / with `--no-recording`", s["recording_over_no_recording"],
                     f"{_ms(s['tracker_ms'])} / {_ms(s['no_recording_tracker_ms'])}; whole process "
                     f"{_fps(s['causal_fps_process'])} / {_fps(s['no_recording_fps_process'])} fps")
            )  # fmt: skip
    fifty = _measured(parts, "50markers")
    if fifty is not None:
        s = fifty["summary"]
        rows.append(
            _row(
                "2a", fifty["label"], "tracker detect + pose + filter per frame / plain SUBPIX + IPPE detect + pose",
                s["tracker_over_plain_detect_pose"],
                f"{_ms(s['tracker_ms'])} / {_ms(s['plain_detect_pose_ms'])}; against the plain loop's wall time per "
                f"frame (decode included, {_ms(s['plain_loop_ms_per_frame'])}): {_x(s['tracker_over_plain_loop'])}",
                tracker_over_plain_loop=s["tracker_over_plain_loop"],
            )
        )  # fmt: skip
        rows.append(
            _row("2b", fifty["label"], "`replay --causal` whole process fps (default outputs)",
                 s["causal_fps_process"], f"{fifty['frames']} frames / {_s(s['causal_wall_s'])} s process wall")
        )  # fmt: skip
    one = _measured(parts, "1080p")
    if one is not None:
        s = one["summary"]
        rows.append(
            _row(
                "3", one["label"], "`replay --causal` process fps / plain decode + detect + IPPE loop process fps",
                s["causal_fps_over_plain_fps"],
                f"{_fps(s['causal_fps_process'])} / {_fps(s['plain_fps_process'])} fps ({one['frames']} frames / "
                f"process wall {_s(s['causal_wall_s'])} s and {_s(s['plain_wall_s'])} s)",
            )
        )  # fmt: skip
    startup = _measured(parts, "startup")
    if startup is not None:
        s = startup["summary"]
        rows.append(
            _row("4a", startup["label"], "start-up to the first frame's pose in poses.csv", s["first_pose_s"],
                 f"`replay --causal --max-frames 1`; the process exits after {_s(s['exit_s'])} s")
        )  # fmt: skip
        rows.append(
            _row("4b", "-", "`ar-anchor --help` wall", s["help_s"],
                 f"`python -m ar_anchor --help`; `python -c pass`: {_s(s['python_s'])} s")
        )  # fmt: skip
    rows += _live_rows(parts)
    rows += _found_rows(parts)
    return rows


def _live_rows(parts: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Rows 5a-5d of the live part: capture-to-pose median and p95, and each over the same with
    ``--no-recording``."""
    rows: list[dict[str, Any]] = []
    live = _measured(parts, "live")
    if live is not None:
        s = live["summary"]
        runs = len(live["runs"])
        how = f"median over {runs} run{'s' * (runs != 1)} of {live['seconds']:g} s; {_fps(s['fps'])} fps tracked"
        rows.append(_row("5a", live["label"], "capture-to-pose latency, median", s["capture_to_pose_median_ms"], how))
        rows.append(_row("5b", live["label"], "capture-to-pose latency, p95", s["capture_to_pose_p95_ms"], how))
        if s.get("no_recording_median_ms") is not None:
            for row_id, key, what in (("5c", "median", "median"), ("5d", "p95", "p95")):
                mine, bare = s[f"capture_to_pose_{key}_ms"], s[f"no_recording_{key}_ms"]
                rows.append(
                    _row(row_id, live["label"], f"capture-to-pose {what}, recording on / `--no-recording`",
                         ratio(mine, bare), f"{_ms(mine)} / {_ms(bare)}; {how}")
                )  # fmt: skip
    return rows


def _found_rows(parts: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Row 6 of each clip whose markers were counted against plain OpenCV's."""
    rows: list[dict[str, Any]] = []
    for key in ("chessboard", "50markers", "1080p"):
        part = _measured(parts, key)
        if part is None or "found" not in part:
            continue
        found = part["found"]
        rows.append(
            _row(
                "6", part["label"], "frames where the tracker measured fewer markers than plain OpenCV found",
                float(found["frames_fewer"]),
                f"{found['frames']} frames; marker-frames plain {found['plain_marker_frames']}, tracker "
                f"{found['tracker_marker_frames']}; missed {found['missed_marker_frames']}, extra "
                f"{found['extra_marker_frames']}",
            )
        )  # fmt: skip
    return rows


def _measured(parts: Mapping[str, Any], key: str) -> Mapping[str, Any] | None:
    part = parts.get(key)
    return None if part is None or "skipped" in part else part


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} ms"


def _s(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _fps(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _x(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}x"
