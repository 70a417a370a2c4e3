"""What a run tells the user on the terminal: a progress bar, the live status line, the summary table,
the list of outputs and the exit code."""

from __future__ import annotations

import argparse
import sys
import time
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
    """Print the run's summary (unless -q) and its output files (names escaped: :func:`~ar_anchor.errors.printable`);
    the exit code (0 when the run completed)."""
    if not args.quiet:
        print(format_summary(outputs.summary))
    files = "poses.csv, summary.json, recording.rrd" + (", raw.mkv" if outputs.raw_video else "")
    files += ", frames.csv" if (outputs.out_dir / "frames.csv").is_file() else ""  # (a replay of images)
    print(f"outputs: {printable(outputs.out_dir)}/ ({files})")
    video = outputs.summary.get("video_out")
    if video:
        print(f"annotated video: {printable(video['path'])} ({video['frames']} frames)")
    status = outputs.summary.get("status")
    return EXIT_OK if status == "completed" else EXIT_FAILURE


def format_summary(summary: dict[str, Any]) -> str:
    """The run's summary as a small fixed-width table: one row per target, the markers drawn as part of a
    board folded into its row (``board:charuco (17 markers)``: see :func:`_folded_members`)."""
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
    folded = _folded_members(summary["targets"])
    shown = {name: entry for name, entry in summary["targets"].items() if name not in folded}
    names = {name: _row_name(name, folded) for name in shown}
    width = max([12, *(len(text) for text in names.values())])
    header = f"{'target':<{width}} {'detected':>9} {'tracked/ambig/gap':>18}"
    if truth:
        header += f" {'in view':>8} {'rate':>6} {'rot med/p95 deg':>17} {'trans med/p95 %':>17}"
    lines.append(header)
    lines.append("-" * len(header))
    for name, entry in shown.items():
        states = entry.get("states", {})
        gap = states.get("predicted", 0) + states.get("interpolated", 0)  # (replay: interpolated, live: predicted)
        state_text = f"{states.get('tracked', 0)}/{states.get('ambiguous', 0)}/{gap}"
        row = f"{names[name]:<{width}} {entry['frames_measured']:>9} {state_text:>18}"
        if truth:
            rate = entry.get("detection_rate_in_view")
            rot, trans = entry["rotation_error_deg"], entry["translation_error_pct"]

            def pair(d: dict[str, float | None]) -> str:
                return "-" if d["median"] is None else f"{d['median']:.2f} / {d['p95']:.2f}"

            row += f" {entry['frames_in_view']:>8} {'-' if rate is None else f'{100 * rate:.0f}%':>6}"
            row += f" {pair(rot):>17} {pair(trans):>17}"
        lines.append(row)
    return "\n".join(lines)


def _folded_members(targets: dict[str, Any]) -> dict[str, str]:
    """The markers folded under a board in the table: marker -> board, for every marker drawn as part of one
    board (summary.json's ``member_of``) in each of its frames, when that board has a row. (Their own rows
    stay in poses.csv and summary.json; a marker also seen on its own, or in two boards, keeps its row.)"""
    folded = {}
    for name, entry in targets.items():
        member_of = entry.get("member_of") or {}
        rows = sum(entry.get("states", {}).values())
        if len(member_of) == 1:
            board, frames = next(iter(member_of.items()))
            if frames == rows and board in targets:
                folded[name] = board
    return folded


def _row_name(name: str, folded: dict[str, str]) -> str:
    """A target's name in the table; a board's with how many markers are folded under it."""
    count = sum(1 for board in folded.values() if board == name)
    marker_s = "marker" if count == 1 else "markers"
    return printable(name) + (f" ({count} {marker_s})" if count else "")
