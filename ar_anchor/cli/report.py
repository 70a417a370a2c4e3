"""What a run tells the user on the terminal: a progress bar, the live status line, the summary table,
the list of outputs and the exit code."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..errors import EXIT_FAILURE, EXIT_OK, printable


class Progress:
    """A tqdm bar on a terminal (frames, fps, ETA), nothing otherwise."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(desc=desc, unit="frame", leave=False, dynamic_ncols=True)

    def __call__(self, done: int, total: int | None, _result: object = None) -> None:
        if self.bar is None:
            return
        if total is not None and self.bar.total != total:
            self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class LiveStatus:
    """One status line for live runs, rewritten about twice a second on a terminal."""

    def __init__(self, enabled: bool, stats: Any) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.stats = stats
        self.start = time.monotonic()
        self.last = 0.0
        self.latency_ms = 0.0

    def __call__(self, done: int, _total: int | None, result: Any = None) -> None:
        if result is not None and result.latency_ms:
            self.latency_ms = (
                0.9 * self.latency_ms + 0.1 * sum(result.latency_ms.values())
                if done > 1
                else sum(result.latency_ms.values())
            )
        now = time.monotonic()
        if not self.enabled or now - self.last < 0.5:
            return
        self.last = now
        elapsed = now - self.start
        counts = self.stats.as_dict()
        tracked = 0 if result is None else sum(1 for t in result.targets.values() if t.measured)
        sys.stderr.write(
            f"\rlive {elapsed:6.1f} s | {done} frames, {done / max(elapsed, 1e-9):5.1f} fps | "
            f"dropped {counts['dropped_queue']} | targets {tracked} | tracker {self.latency_ms:5.1f} ms   "
        )
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def finish(args: argparse.Namespace, outputs: Any) -> int:
    """Print the run's summary (unless -q) and, as the last line, every file it wrote (names escaped:
    :func:`~ar_anchor.errors.printable`), unless ``--export`` is to run first (:func:`export_after_run`
    prints the line then, exports included); the exit code (0 when the run completed)."""
    if not args.quiet:
        print(format_summary(outputs.summary))
    if not (getattr(args, "export", False) or getattr(args, "export_images", False)):
        print(outputs_line(outputs.out_dir, outputs.summary))
    status = outputs.summary.get("status")
    return EXIT_OK if status == "completed" else EXIT_FAILURE


def run_files(out_dir: Path, summary: dict[str, Any]) -> list[str]:
    """The files a run wrote into ``out_dir``, in order: ``poses.csv``, ``summary.json``, every part of the
    recording (``recording.rrd``, ``recording.part2.rrd``, ...: ``[recording] part_minutes``), ``raw.mkv``
    with its timestamps (``--record``) and ``frames.csv`` (a replay of images); those that exist."""
    names = ["poses.csv", "summary.json", *summary.get("recording_parts", ["recording.rrd"])]
    names += ["raw.mkv", "raw.mkv.timestamps.csv", "frames.csv"]
    return [name for name in names if (out_dir / name).is_file()]


def outputs_line(out_dir: Path, summary: dict[str, Any] | None = None, exported: Sequence[str] = ()) -> str:
    """``outputs: OUT/ (poses.csv, summary.json, recording.rrd, recording.part2.rrd, ...)``, then the exports
    (``exported``: their names in ``out_dir``) and the annotated video (``--video-out``, anywhere) when
    there are: the run's last line, every file it wrote. ``summary``: the run's (default: read from
    ``out_dir``'s ``summary.json``)."""
    out_dir = Path(out_dir)
    if summary is None:
        try:
            summary = json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            summary = {}
    names = [*run_files(out_dir, summary), *exported]
    line = f"outputs: {printable(out_dir)}/ ({', '.join(printable(name) for name in names)})"
    video = summary.get("video_out")
    if video:
        line += f"; annotated video: {printable(video['path'])} ({video['frames']} frames)"
    return line


def format_summary(summary: dict[str, Any]) -> str:
    """The run's summary as a small fixed-width table."""
    fps = summary.get("fps")
    lines = [
        f"{summary['frames']} frames in {summary['wall_time_s']:.1f} s ({fps:.1f} fps)"
        if fps
        else f"{summary['frames']} frames",
        f"markers found in {summary['frames_with_markers']} of {summary['frames']} frames, "
        f"a pose in {summary['frames_with_pose']}"
        + (f" ({summary['dictionary_hint']})" if summary.get("dictionary_hint") else ""),
    ]
    truth = summary.get("ground_truth")
    header = f"{'target':<12} {'detected':>9} {'tracked/ambig/gap':>18}"
    if truth:
        header += f" {'in view':>8} {'rate':>6} {'rot med/p95 deg':>17} {'trans med/p95 %':>17}"
    lines.append(header)
    lines.append("-" * len(header))
    for name, entry in summary["targets"].items():
        states = entry.get("states", {})
        gap = states.get("predicted", 0) + states.get("interpolated", 0)  # (replay: interpolated, live: predicted)
        state_text = f"{states.get('tracked', 0)}/{states.get('ambiguous', 0)}/{gap}"
        row = f"{printable(name):<12} {entry['frames_measured']:>9} {state_text:>18}"
        if truth:
            rate = entry.get("detection_rate_in_view")
            rot, trans = entry["rotation_error_deg"], entry["translation_error_pct"]

            def pair(d: dict[str, float | None]) -> str:
                return "-" if d["median"] is None else f"{d['median']:.2f} / {d['p95']:.2f}"

            row += f" {entry['frames_in_view']:>8} {'-' if rate is None else f'{100 * rate:.0f}%':>6}"
            row += f" {pair(rot):>17} {pair(trans):>17}"
        lines.append(row)
    return "\n".join(lines)
