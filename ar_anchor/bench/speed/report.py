"""``speed.md`` and ``speed.json`` (``ar-anchor bench speed``): issue 33's acceptance, row by row, then each
part's runs."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..report import fmt, write_json
from .acceptance import DEFAULTS, PARTS, QUICK, run_speed_acceptance
from .rows import median

__all__ = ["speed_markdown", "write_speed_report"]


def write_speed_report(
    out_dir: Path,
    quick: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench speed",
    *,
    parts: Sequence[str] | None = None,
    frames: int | None = None,
    repeats: int | None = None,
    realdata: Path | None = None,
    **settings: Any,
) -> dict[str, Any]:
    """Run the acceptance benchmark, write ``speed.md`` and ``speed.json`` to ``out_dir``, return the results.

    ``quick``: :data:`~.acceptance.QUICK` settings (shorter clips, one round, one short live run) instead of
    :data:`~.acceptance.DEFAULTS`; ``parts``: of :data:`~.acceptance.PARTS` (default all); ``frames``: the
    synthetic clips' length (both); ``repeats``: rounds; ``settings``: any other of
    :func:`~.acceptance.run_speed_acceptance`'s settings.
    """
    chosen = {**(QUICK if quick else DEFAULTS), **settings}
    if frames is not None:
        chosen["fifty_frames"] = chosen["one_frames"] = frames
    if repeats is not None:
        chosen["repeats"] = repeats
    results = run_speed_acceptance(PARTS if parts is None else parts, realdata=realdata, progress=progress, **chosen)
    results["meta"]["command"] = command
    results["meta"]["quick"] = quick
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "speed.json", results)
    (out_dir / "speed.md").write_text(speed_markdown(results, command))
    return results


def _value(row: Mapping[str, Any]) -> str:
    value, unit = row["value"], row["unit"]
    if value is None:
        return "-"
    if unit == "x":
        return f"{value:.2f}x"
    if unit == "frames":
        return f"{value:.0f}"
    if unit == "s":
        return f"{value:.2f} s"
    if unit == "fps":
        return f"{value:.1f} fps"
    return f"{value:.1f} {unit}"


def _target(row: Mapping[str, Any]) -> str:
    op, bound, unit = row["op"], row["bound"], row["unit"]
    shown = {"x": f"{bound:g}x", "frames": f"{bound:g}", "s": f"{bound:g} s", "fps": f"{bound:g} fps"}
    return f"{op.replace('==', '=')} {shown.get(unit, f'{bound:g} {unit}')}"


def _verdict(passed: bool | None) -> str:
    return "-" if passed is None else ("**pass**" if passed else "**FAIL**")


def speed_markdown(results: Mapping[str, Any], command: str) -> str:
    """The report of :func:`~.acceptance.run_speed_acceptance`'s ``results``."""
    meta, rows, parts = results["meta"], results["rows"], results["parts"]
    passed = [r for r in rows if r["passed"]]
    failed = [r for r in rows if r["passed"] is False]
    lines = [
        "# Speed: the targets, plain OpenCV in the same run",
        "",
        f"Produced by `{command}` in {meta['wall_time_s']:.0f} s"
        + (" (quick mode: shorter clips, one round: not the acceptance's numbers)" if meta.get("quick") else "")
        + f". {_machine(meta)}",
    ]
    for note in results.get("notes", []):
        lines += ["", f"Note: {note}."]
    lines += [
        "",
        f"## Acceptance: {len(passed)} of {len(rows)} rows pass" + (f", {len(failed)} fail" if failed else ""),
        "",
        f"Every value is the median over {_n(meta['repeats'], 'round')}, the runs of a round taking turns (the order "
        "rotating from round to round); a ratio is the ratio of two such medians of this run. Whole-process "
        "times run from starting the process to its exit.",
        "",
        "| row | clip | what | measured | target | | how |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['id']} | {row['clip']} | {row['what']} | {_value(row)} | {_target(row)} | "
            f"{_verdict(row['passed'])} | {row['how']} |"
        )
    lines += _how(meta)
    for key in PARTS:
        part = parts.get(key)
        if part is None or "skipped" in part:
            continue
        if "causal" in part:
            lines += _clip_section(part)
        elif key == "startup":
            lines += _startup_section(part)
        elif key == "live":
            lines += _live_section(part)
    lines += [
        "",
        "## Covered elsewhere",
        "",
        "- Memory flat over 10 minutes: `ar-anchor bench run` (its long live run, "
        "[run.md](run.md#memory-the-same-live-run-for-10-minutes)).",
        "- chessboard.avi through rigid_sheet.py (relative poses of the markers on the one sheet): "
        "`ar-anchor bench real` ([real.md](real.md)); every scene of `ar-anchor bench stability` "
        "([stability.md](stability.md)).",
        "- Where the time goes, stage by stage: `ar-anchor bench profile` ([profile.md](profile.md)); the tracker "
        "and plain loops in one process on the same frames, with accuracy against truth: `ar-anchor bench speed "
        "--stages` ([speed_stages.md](speed_stages.md)).",
        "",
    ]
    return "\n".join(lines)


def _machine(meta: Mapping[str, Any]) -> str:
    return (
        f"Machine: {meta['processor']}, {meta['cpu_count']} CPUs ({meta['usable_cpus']} usable), {meta['system']}; "
        f"Python {meta['python']}, OpenCV {meta['opencv']} ({meta['opencv_threads']} threads), NumPy "
        f"{meta['numpy']}, rerun-sdk {meta.get('rerun')}, PyAV {meta.get('pyav')}. Load average (1, 5, 15 min) "
        f"at the start {_load(meta.get('load_average_start'))}, at the end {_load(meta.get('load_average_end'))}."
    )


def _load(value: Any) -> str:
    return "-" if not value else " / ".join(f"{v:.2f}" for v in value)


def _how(meta: Mapping[str, Any]) -> list[str]:
    return [
        "",
        "How each row is taken:",
        "",
        "- *tracker per frame* (1a, 2a): the sum of the detect, pose and filter medians (`latency_ms`) of "
        "`summary.json` of a `replay --causal` process with default outputs (poses.csv, summary.json, "
        "recording.rrd). *plain*: `ar_anchor/bench/speed/plain_loop.py --subpix` as a process of its own: PyAV "
        "decode (`thread_type` AUTO, BGR, as replay decodes), grey + `ArucoDetector.detectMarkers` with "
        "`CORNER_REFINE_SUBPIX`, `solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)` per marker, no outputs; its per-frame "
        "cost is the sum of its detect and pose medians (the tracker's statistic; decode not included). The "
        "*how* column also gives the ratio against the plain loop's wall time per frame (its loop's wall time "
        "/ frames, decode included: the lenient one).",
        "- *whole process fps* (1b, 2b): frames / the `replay --causal` process's wall time from start to exit "
        "(start-up, the recording's final flush included). 3: that fps over the plain loop process's, measured "
        "the same way (its Python start-up and imports included).",
        "- 1c: the default replay (offline: three passes, the video decoded twice) process's wall time over "
        "the `--causal` one's. 1d: the tracker per frame (as 1a) with default outputs over the same replay with "
        "`--no-recording` (poses.csv and summary.json only), in the same rounds: what the recording costs the "
        "tracker.",
        "- 4a: from starting `ar-anchor replay CLIP --causal --max-frames 1` to its first row in poses.csv (the "
        "first frame tracked and its pose written; the file polled every 2 ms); the process's exit is given "
        "beside it. 4b: `python -m ar_anchor --help`, start to exit, median of "
        f"{_n(meta.get('help_runs') or 0, 'run')} (`python -c pass` beside it: the interpreter's own start-up).",
        "- 5: `ar-anchor bench run`'s live run: `summary.json`'s capture-to-pose median and p95 (frame delivered "
        "by the device to its pose), median over the runs. 5c, 5d: those medians over the same of as many "
        "runs with `--no-recording`, taking turns.",
        "- 6: per frame, the markers the tracker measured (poses.csv rows `tracked` or `ambiguous`) against "
        "the ids the plain loop found; the round where the tracker fell shortest. *missed*: marker-frames the "
        "plain loop found and the tracker did not; *extra*: the other way round.",
    ]


def _clip_section(part: Mapping[str, Any]) -> list[str]:
    s = part["summary"]
    stage = s["tracker_stage_ms"]
    lines = [
        "",
        f"## {part['label']}",
        "",
        f"`ar-anchor replay VIDEO {' '.join(_short(a) for a in part['replay_args'])}` ({part['video_mb']:.1f} MB "
        f"video; camera images {part['causal'][0].get('image_logging')}); medians of "
        f"{_n(len(part['causal']), 'round')}:",
        "",
        "| | process wall s (runs) | median wall s | fps (whole process) | fps (run, summary.json) | per frame |",
        "|---|---|---|---|---|---|",
        f"| replay --causal | {_runs(part['causal'])} | {fmt(s['causal_wall_s'])} | {fmt(s['causal_fps_process'], 1)} "
        f"| {fmt(s['causal_fps_run'], 1)} | detect {fmt(stage['detect'])} + pose {fmt(stage['pose'])} + filter "
        f"{fmt(stage['filter'])} = {fmt(s['tracker_ms'])} ms |",
    ]
    if "causal_no_recording" in part:
        bare = part["causal_no_recording"]
        lines.append(
            f"| replay --causal --no-recording | {_runs(bare)} | {fmt(s['no_recording_wall_s'])} | "
            f"{fmt(s['no_recording_fps_process'], 1)} | {fmt(median(r.get('fps_run') for r in bare), 1)} | "
            f"detect + pose + filter {fmt(s['no_recording_tracker_ms'])} ms |"
        )
    if "offline" in part:
        fps_run = [r.get("fps_run") for r in part["offline"]]
        lines.append(
            f"| replay (offline) | {_runs(part['offline'])} | {fmt(s['offline_wall_s'])} | "
            f"{fmt(s['offline_fps_process'], 1)} | {fmt(median(fps_run), 1)} | |"
        )
    lines.append(
        f"| plain SUBPIX loop | {_runs(part['plain'])} | {fmt(s['plain_wall_s'])} | {fmt(s['plain_fps_process'], 1)} "
        f"| | detect + pose {fmt(s['plain_detect_pose_ms'])} ms (decode {fmt(s['plain_decode_ms'])}); loop wall "
        f"/ frame {fmt(s['plain_loop_ms_per_frame'])} ms |"
    )
    found = part["found"]
    lines += [
        "",
        f"Tracker / plain per frame: {fmt(s['tracker_over_plain_detect_pose'])}x (against detect + pose), "
        f"{fmt(s['tracker_over_plain_loop'])}x (against the loop's wall time per frame). Whole process: replay "
        f"--causal / plain fps {fmt(s['causal_fps_over_plain_fps'])}x. Markers per frame: the tracker measured "
        f"fewer than plain OpenCV found in {found['frames_fewer']} of {found['frames']} frames (per round: "
        f"{', '.join(str(n) for n in part['found_fewer_per_round'])}); marker-frames plain "
        f"{found['plain_marker_frames']}, tracker {found['tracker_marker_frames']}, missed "
        f"{found['missed_marker_frames']}, extra {found['extra_marker_frames']}.",
    ]
    return lines


def _startup_section(part: Mapping[str, Any]) -> list[str]:
    s = part["summary"]
    return [
        "",
        f"## Start-up ({part['label']})",
        "",
        f"`{part['command']}`: to the first pose row {', '.join(fmt(r['first_pose_s']) for r in part['runs'])} s "
        f"(median {fmt(s['first_pose_s'])}), to the exit {', '.join(fmt(r['exit_s']) for r in part['runs'])} s "
        f"(median {fmt(s['exit_s'])}). `ar-anchor --help`: {', '.join(fmt(v) for v in part['help_s'])} s (median "
        f"{fmt(s['help_s'])}); `python -c pass`: median {fmt(s['python_s'])} s.",
    ]


def _live_section(part: Mapping[str, Any]) -> list[str]:
    lines = [
        "",
        f"## Live: `{part['command']}`",
        "",
        f"{_n(len(part['runs']), 'run')} of {part['seconds']:g} s each (counted from when the run's outputs "
        f"appear), then interrupted (SIGINT) as `ar-anchor bench run` does; {part['label']}.",
        "",
        "| run | frames tracked (fps) | dropped by the camera queue | capture-to-pose median / p95 ms | detect / "
        "pose / filter / log median ms | frames not logged |",
        "|---|---|---|---|---|---|",
    ]
    runs = [(str(i), run) for i, run in enumerate(part["runs"], 1)]
    runs += [(f"{i} --no-recording", run) for i, run in enumerate(part.get("runs_no_recording", []), 1)]
    for index, run in runs:
        st = run["stages"]

        def med(name: str, stages: Mapping[str, Any] = st) -> str:
            return fmt(stages.get(name, {}).get("median"))

        lines.append(
            f"| {index} | {run['frames']} ({fmt(run['fps'], 1)}) | {run['live'].get('dropped_queue', 0)} | "
            f"{med('capture_to_pose')} / {fmt(st.get('capture_to_pose', {}).get('p95'))} | {med('detect')} / "
            f"{med('pose')} / {med('filter')} / {med('log')} | {run.get('frames_not_logged', 0)} |"
        )
    return lines


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}" + ("" if count == 1 else "s")


def _runs(runs: Sequence[Mapping[str, Any]]) -> str:
    return ", ".join(fmt(r["process_wall_s"]) for r in runs)


def _short(arg: str) -> str:
    """An argument as the report shows it: a path by its file name."""
    return Path(arg).name if "/" in arg else arg
