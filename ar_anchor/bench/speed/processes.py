"""The processes ``ar-anchor bench speed`` times from outside: ``ar-anchor replay`` (default outputs), the
plain OpenCV loop (:mod:`.plain_loop`, SUBPIX corners), the start-up to the first pose, ``ar-anchor --help``
and ``python -c pass``.

Every wall time is taken around :func:`subprocess.run` (or :class:`subprocess.Popen` to its exit): from
before the process is started to after it has exited, its start-up, imports and final flush included.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...targets import TargetId

__all__ = [
    "MEASURED_STATES",
    "PLAIN_LOOP",
    "cli",
    "first_pose_run",
    "measured_markers",
    "plain_run",
    "replay_run",
    "timed",
    "wall_run",
]

PLAIN_LOOP = Path(__file__).resolve().parent / "plain_loop.py"
MEASURED_STATES = ("tracked", "ambiguous")  # poses.csv states of a target measured in that frame
TRACKER_STAGES = ("detect", "pose", "filter")
_POLL_S = 0.002


def cli(*args: str) -> list[str]:
    """``ar-anchor -q ARGS`` as this interpreter runs it (``python -m ar_anchor``)."""
    return [sys.executable, "-m", "ar_anchor", "-q", *args]


def timed(command: Sequence[str], what: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run ``command`` to its end; the finished process and its wall time (s), start-up included;
    :class:`RuntimeError` naming ``what`` when it fails."""
    start = time.perf_counter()
    done = subprocess.run(list(command), capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        tail = " ".join(done.stderr.strip().splitlines()[-2:])
        raise RuntimeError(f"{what} failed ({done.returncode}): {tail}")
    return done, wall


def measured_markers(poses_csv: Path) -> dict[int, set[int]]:
    """The markers the tracker measured in each frame (``state`` tracked or ambiguous in ``poses.csv``):
    frame index -> marker ids (frames without a measured marker are absent)."""
    out: dict[int, set[int]] = {}
    with open(poses_csv, newline="") as handle:
        for row in csv.DictReader(handle):
            marker_id = TargetId.parse(row["target"]).marker_id
            if marker_id is not None and row["state"] in MEASURED_STATES:
                out.setdefault(int(row["frame"]), set()).add(marker_id)
    return out


def replay_run(video: Path, args: Sequence[str], out: Path, *, causal: bool) -> dict[str, Any]:
    """One ``ar-anchor replay VIDEO ARGS --out OUT`` process (``--causal`` when ``causal``; default outputs:
    poses.csv, summary.json, recording.rrd), timed from outside: its frames, process wall time and fps,
    the run's own fps (``summary.json``), the tracker's stage medians (``summary.json``'s ``latency_ms``)
    and, under the private key ``_measured``, the markers it measured per frame."""
    command = cli("replay", str(video), *args, *(["--causal"] if causal else []), "--out", str(out))
    _, wall = timed(command, f"ar-anchor replay{' --causal' if causal else ''} {video.name}")
    summary = json.loads((out / "summary.json").read_text())
    latency = summary.get("latency_ms", {})
    stages = {stage: latency.get(f"{stage}_ms", {}).get("median") for stage in TRACKER_STAGES}
    known = [v for v in stages.values() if v is not None]
    rrd = out / "recording.rrd"
    return {
        "mode": "causal" if causal else "offline",
        "frames": summary["frames"],
        "process_wall_s": wall,
        "fps_process": summary["frames"] / wall if wall > 0 else None,
        "fps_run": summary.get("fps"),
        "tracker_ms": {**stages, "total": sum(known) if len(known) == len(TRACKER_STAGES) else None},
        "stage_medians_ms": {k.removesuffix("_ms"): v.get("median") for k, v in latency.items()},
        "image_logging": summary.get("image_logging"),
        "rrd_mb": rrd.stat().st_size / 1e6 if rrd.exists() else None,
        "_measured": measured_markers(out / "poses.csv"),
    }


def plain_run(video: Path, camera_file: Path, dictionary: str, length_m: float) -> dict[str, Any]:
    """One plain-loop process (:mod:`.plain_loop` with ``--subpix --ids``), timed from outside: its own
    JSON (per-frame stage medians, loop wall time) with the process wall time and fps, its loop's wall
    time per frame and, under the private key ``_ids``, the markers it found per frame."""
    command = [sys.executable, str(PLAIN_LOOP), str(video), str(camera_file), dictionary, f"{length_m:g}"]
    done, wall = timed([*command, "--subpix", "--ids"], "the plain loop")
    inner = json.loads(done.stdout.strip().splitlines()[-1])
    ids = inner.pop("ids")
    frames = inner["frames"]
    return {
        **inner,
        "process_wall_s": wall,
        "fps_process": frames / wall if wall > 0 else None,
        "loop_ms_per_frame": 1e3 * inner["loop_wall_s"] / frames if frames else None,
        "_ids": ids,
    }


def wall_run(command: Sequence[str], what: str) -> float:
    """The wall time (s) of one run of ``command``, start to exit."""
    return timed(command, what)[1]


def first_pose_run(video: Path, args: Sequence[str], out: Path) -> dict[str, float | None]:
    """``ar-anchor replay VIDEO ARGS --causal --max-frames 1 --out OUT``: the time from starting the process
    to its first row in ``poses.csv`` (the first frame's pose written; polled every 2 ms) and to its exit."""
    command = cli("replay", str(video), *args, "--causal", "--max-frames", "1", "--out", str(out))
    poses = out / "poses.csv"
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first: float | None = None
    try:
        while process.poll() is None:
            if first is None and _has_row(poses):
                first = time.perf_counter() - start
            time.sleep(_POLL_S)
        exit_s = time.perf_counter() - start
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    if process.returncode != 0:
        raise RuntimeError(f"ar-anchor replay --max-frames 1 failed ({process.returncode}): {stderr.strip()[-200:]}")
    if first is None and _has_row(poses):
        first = exit_s  # written in the process's last 2 ms: no earlier than its exit as seen from here
    return {"first_pose_s": first, "exit_s": exit_s}


def _has_row(poses: Path) -> bool:
    """``poses.csv`` holds its header and at least one whole row."""
    try:
        return poses.read_bytes().count(b"\n") >= 2
    except OSError:
        return False
