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

PLAIN_EVERY_S = 5.0  # a piped run's progress: a plain line this often (seconds)


class PlainProgress:
    """Progress where stderr is no terminal (piped, redirected to a log): a plain line every
    :data:`PLAIN_EVERY_S` seconds (``replay: 120 of 450 frames, 24.1 fps, 5.0 s``), none for a run shorter."""

    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.start = time.monotonic()
        self.last = self.start

    def __call__(self, done: int, total: int | None, _result: object = None) -> None:
        now = time.monotonic()
        if now - self.last < PLAIN_EVERY_S:
            return
        self.last = now
        elapsed = now - self.start
        frames = f"{done} of {total} frames" if total is not None else f"{done} frames"
        try:
            sys.stderr.write(f"{self.desc}: {frames}, {done / max(elapsed, 1e-9):.1f} fps, {elapsed:.1f} s\n")
            sys.stderr.flush()
        except (OSError, ValueError):  # a reader gone away: the run goes on
            pass


class Progress:
    """A tqdm bar on a terminal (frames, fps, ETA); elsewhere a plain line every few seconds
    (:class:`PlainProgress`); nothing when not ``enabled`` (-q)."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        self.plain: PlainProgress | None = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(desc=desc, unit="frame", leave=False, dynamic_ncols=True)
        elif enabled:
            self.plain = PlainProgress(desc)

    def __call__(self, done: int, total: int | None, _result: object = None) -> None:
        if self.plain is not None:
            self.plain(done, total)
        if self.bar is None:
            return
        if total is not None and self.bar.total != total:
            self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class LiveStatus:
    """One status line for live runs, rewritten about twice a second on a terminal (piped: a plain line every
    few seconds)."""

    def __init__(self, enabled: bool, stats: Any) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.plain = PlainProgress("live") if enabled and not self.enabled else None  # piped: a line now and then
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
        if self.plain is not None:
            self.plain(done, None)
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
    images = summary.get("images_out")
    if images:
        count = images["images"]
        line += f"; annotated images: {printable(images['folder'])}/ ({count} image{'' if count == 1 else 's'})"
    return line


FEW_FRAMES = 30  # a run of at most this many frames (or of stills) says where each target was


def format_summary(summary: dict[str, Any]) -> str:
    """The run's summary as a small fixed-width table, its columns explained below it: one row per target, the
    markers drawn as part of a board folded into its row (``board:charuco (17 markers)``: see
    :func:`_folded_members`); for a run of a few frames (or of independent stills) where each target was
    (:func:`format_where`)."""
    fps = summary.get("fps")
    lines = [
        f"{summary['frames']} frames in {summary['wall_time_s']:.1f} s ({fps:.1f} fps)"
        if fps
        else f"{summary['frames']} frames",
        _markers_line(summary),
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
    if summary["targets"]:
        lines += _legend(bool(truth))
    if summary["targets"] and (
        summary["frames"] <= FEW_FRAMES or str(summary.get("decided_with", "")).endswith("(independent stills)")
    ):
        lines += ["", *format_where(summary)]
    return "\n".join(lines)


def _markers_line(summary: dict[str, Any]) -> str:
    """How many frames had markers, and a pose; frames whose markers all shared an id with another (none of
    them used: which is which cannot be told) are said as such, not as frames without markers."""
    frames, found = summary["frames"], summary["frames_with_markers"]
    only_duplicated = summary.get("frames_with_only_duplicated_ids", 0)
    hint = f" ({summary['dictionary_hint']})" if summary.get("dictionary_hint") else ""
    line = f"markers found in {found} of {frames} frames, a pose in {summary['frames_with_pose']}{hint}"
    if not summary.get("frames_with_duplicated_ids"):
        return line
    ids = summary.get("duplicated_ids") or []
    named = f"id {ids[0]}" if len(ids) == 1 else f"ids {', '.join(str(i) for i in ids)}"
    appeared = "appeared" if len(ids) == 1 else "each appeared"
    was = "was" if len(ids) == 1 else "were"
    if only_duplicated:
        seen = found + only_duplicated
        which = "every one" if only_duplicated == frames else f"{only_duplicated} of them"
        return (
            f"markers detected in {seen} of {frames} frames, but in {which} {named} {appeared} more than once "
            f"and {was} not used: give each marker its own id\n"
            f"markers used in {found} of {frames} frames, a pose in {summary['frames_with_pose']}{hint}"
        )
    return (
        f"{line}; {named} {appeared} more than once in {summary['frames_with_duplicated_ids']} frame(s) and "
        f"{was} not used there: give each marker its own id"
    )


def _legend(truth: bool) -> list[str]:
    """What the table's columns mean, in words."""
    lines = [
        "columns: detected = frames with a measured pose; tracked/ambig/gap = frames whose pose was tracked",
        "  (flip decided) / ambiguous (two poses fit about equally: the likelier shown) / a gap filled (not measured)",
    ]
    if truth:
        lines += [
            "  in view = frames the target was in view (ground truth); rate = detected / in view",
            "  rot med/p95 deg = rotation error to the ground truth, degrees: median / 95th percentile over frames",
            "  trans med/p95 % = position error, % of the true distance: median / 95th percentile over frames",
        ]
    return lines


def format_where(summary: dict[str, Any]) -> list[str]:
    """Where each target was: its last state, its distance from the camera (m) and its tilt to the line of sight
    (deg; 0 faces the camera), the median over the frames it had a pose in (the value itself for one frame)."""
    frames = summary["frames"]
    folded = _folded_members(summary["targets"])
    shown = {name: entry for name, entry in summary["targets"].items() if name not in folded}
    names = {name: _row_name(name, folded) for name in shown}
    width = max([12, *(len(text) for text in names.values())])
    header = f"{'target':<{width}} {'last state':<11} {'distance m':>10} {'tilt deg':>9}  seen in"
    lines = [header, "-" * len(header)]
    for name, entry in shown.items():
        distance = (entry.get("distance_m") or {}).get("median")
        tilt = (entry.get("tilt_deg") or {}).get("median")
        if distance is None:
            continue
        tilt_text = "-" if tilt is None else f"{tilt:.1f}"
        lines.append(
            f"{names[name]:<{width}} {entry.get('last_state', ''):<11} {distance:>10.3f} {tilt_text:>9}  "
            f"{entry['frames_measured']} of {frames} frames"
        )
    if len(lines) == 2:
        return []
    what = "in that frame" if frames == 1 else "median over the frames it had a pose in"
    lines += [
        f"distance = camera to the target's origin (a marker's centre), {what};",
        "  tilt = angle between the target's face normal and the line of sight (0 = facing the camera, 90 = edge-on)",
    ]
    return lines


def _folded_members(targets: dict[str, Any]) -> dict[str, str]:
    """The markers folded under a board in the table: marker -> board, for every marker drawn as part of one
    board (summary.json's ``member_of``) in each frame it was measured in, when that board has a row. Its gap
    rows (``predicted``, ``interpolated``: not seen that frame) do not count. (Their own rows stay in poses.csv
    and summary.json; a marker also seen on its own, or in two boards, keeps its row.)"""
    folded = {}
    for name, entry in targets.items():
        member_of = entry.get("member_of") or {}
        if len(member_of) == 1:
            board, frames = next(iter(member_of.items()))
            if frames == entry.get("frames_measured") and board in targets:
                folded[name] = board
    return folded


def _row_name(name: str, folded: dict[str, str]) -> str:
    """A target's name in the table; a board's with how many markers are folded under it."""
    count = sum(1 for board in folded.values() if board == name)
    marker_s = "marker" if count == 1 else "markers"
    return printable(name) + (f" ({count} {marker_s})" if count else "")
