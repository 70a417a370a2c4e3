"""``ar-anchor bench run``: the CLI's own end-to-end runs, timed from outside.

Three measurements, each a real ``ar-anchor`` process started with :mod:`subprocess` exactly as a
user would start it (default settings unless stated):

* **replay**: ``ar-anchor replay`` of a 1920x1080 H.264 clip (one 5 cm marker, the camera orbiting
  at 0.6 m, rendered with sensor noise and blur, encoded once with PyAV) with a cube overlay and
  rerun logging: frames per second from its ``summary.json`` (frames / wall time of the run) and
  from the process's own wall time (start-up included). It runs three times, taking turns with a
  plain OpenCV loop in a process of its own (:mod:`ar_anchor.bench.speed.plain_loop`: PyAV decode,
  ``detectMarkers``, IPPE per marker, no outputs): replay, plain, replay, plain, ...; the medians of
  three and their ratio. The replay section shows the median replay run.
* **chessboard.avi**: ``ar-anchor replay`` of the real video with default outputs (found under
  ``$AR_ANCHOR_REALDATA``; skipped with a note when absent): frames / process wall time, the run's own
  fps and the tracker's detect, pose and filter medians from ``summary.json``.
* **50 markers**: ``ar-anchor replay`` (default outputs) of the synthetic 720p 50-marker clip of
  ``bench speed``, encoded to H.264 first: frames / process wall time and the same figures.
* **live latency**: ``ar-anchor live --device synthetic --width 1920 --height 1080 --fps 30``:
  per-stage times and the latency from frame capture (the frame delivered by the device) to pose,
  from ``summary.json``.
* **memory**: the same live run for ``--minutes`` (10 by default), its resident set size sampled
  from ``/proc/<pid>/status`` every few seconds; stopped with SIGINT as a user would (which also
  checks that an interrupted run exits 130 with its outputs complete). Growth is measured after a
  warm-up minute.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import CameraModel
from .report import fmt, load_average, machine_info, machine_lines, report_head
from .speed import speed_scene
from .speed.live import LIVE_SIZE as SIZE
from .speed.live import SAMPLE_S, live_run, stages
from .speed.real_clip import chessboard_files
from .speed.scenes import FIFTY_MARKER_M, FIFTY_SIZE, encode_scene, fifty_markers_scene

__all__ = ["ALTERNATIONS", "RUN_PARTS", "run_run_benchmark", "write_run_report"]

FX = 1480.0
WARMUP_S = 60.0
# the live scene of one 5 cm marker (the synthetic camera renders what the config tracks)
ONE_MARKER_CONFIG = "[markers]\nlength_m = 0.05\nids = [0]\n"
RUN_PARTS: tuple[str, ...] = ("1080p", "live", "chessboard", "50markers")  # what ``--clips`` takes
ALTERNATIONS = 3  # replay and plain-loop runs each, taking turns


def _camera() -> CameraModel:
    width, height = SIZE
    k = np.array([[FX, 0.0, (width - 1) / 2], [0.0, FX, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return CameraModel(k, np.zeros(5), width, height)


def _encode_clip(path: Path, frames: int) -> None:
    """The one-marker 1080p clip of ``bench speed``, encoded to H.264 (CRF 18) with PyAV."""
    encode_scene(path, speed_scene("one", _camera(), frames))


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ar_anchor", "-q", *args]


def _timed(command: list[str], what: str) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run ``command`` to its end; the finished process and its wall time (s), start-up included."""
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        tail = " ".join(done.stderr.strip().splitlines()[-2:])
        raise RuntimeError(f"{what} failed ({done.returncode}): {tail}")
    return done, wall


def _replay_run(args: list[str], out: Path, shown: str) -> dict[str, Any]:
    """One ``ar-anchor replay`` process (``args`` after ``replay``), timed from outside, with its ``summary.json``."""
    _, wall = _timed(_cli("replay", *args, "--out", str(out)), shown)
    summary = json.loads((out / "summary.json").read_text())
    rrd = out / "recording.rrd"
    return {
        "command": shown,
        "frames": summary["frames"],
        "rrd_mb": rrd.stat().st_size / 1e6 if rrd.exists() else None,
        "fps_run": summary["fps"],
        "fps_process": summary["frames"] / wall,
        "process_wall_s": wall,
        "image_logging": summary.get("image_logging"),
        "stages": stages(summary),
    }


def _plain_run(video: Path, camera_file: Path, dictionary: str, length_m: float) -> dict[str, Any]:
    """One plain-loop process (:mod:`ar_anchor.bench.speed.plain_loop`), timed from outside."""
    script = Path(__file__).resolve().parent / "speed" / "plain_loop.py"
    command = [sys.executable, str(script), str(video), str(camera_file), dictionary, f"{length_m:g}"]
    done, wall = _timed(command, "the plain loop")
    inner = json.loads(done.stdout.strip().splitlines()[-1])
    return {**inner, "process_wall_s": wall, "fps_process": inner["frames"] / wall}


def _median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run of median process wall time (of an odd number of runs)."""
    return sorted(runs, key=lambda run: run["process_wall_s"])[len(runs) // 2]


def _replay(tmp: Path, frames: int, progress: Callable[[str], None]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The 1080p clip: replay and the plain loop, :data:`ALTERNATIONS` runs each taking turns; the median
    replay run (as before) and the comparison."""
    video, camera_file, config = tmp / "clip_1080p.mp4", tmp / "camera_1080p.yml", tmp / "cube.toml"
    _encode_clip(video, frames)
    _camera().to_yaml(camera_file)
    config.write_text('[markers]\nlength_m = 0.05\n\n[[overlays]]\ntarget = "marker:*"\nkind = "cube"\n')
    shown = "ar-anchor replay clip_1080p.mp4 --camera camera_1080p.yml --config cube.toml"
    replays, plains = [], []
    for index in range(ALTERNATIONS):
        progress(f"replay {index + 1} of {ALTERNATIONS}")
        args = [str(video), "--camera", str(camera_file), "--config", str(config)]
        replays.append(_replay_run(args, tmp / f"replay_{index}", shown))
        progress(f"plain loop {index + 1} of {ALTERNATIONS}")
        plains.append(_plain_run(video, camera_file, "DICT_4X4_50", 0.05))
    replay = {**_median_run(replays), "video_mb": video.stat().st_size / 1e6, "runs": len(replays)}
    replay_wall = float(np.median([r["process_wall_s"] for r in replays]))
    plain_wall = float(np.median([r["process_wall_s"] for r in plains]))
    comparison = {
        "replay_command": shown,
        "plain_command": "python ar_anchor/bench/speed/plain_loop.py clip_1080p.mp4 camera_1080p.yml DICT_4X4_50 0.05",
        "plain_decode": "PyAV (thread_type AUTO, bgr24 frames, as ar-anchor replay decodes)",
        "frames": replay["frames"],
        "replay_wall_s": [r["process_wall_s"] for r in replays],
        "plain_wall_s": [r["process_wall_s"] for r in plains],
        "replay_fps_process": [r["fps_process"] for r in replays],
        "plain_fps_process": [r["fps_process"] for r in plains],
        "plain_markers": [r["markers"] for r in plains],
        "replay_wall_median_s": replay_wall,
        "plain_wall_median_s": plain_wall,
        "replay_fps_median": float(np.median([r["fps_process"] for r in replays])),
        "plain_fps_median": float(np.median([r["fps_process"] for r in plains])),
        "ratio_replay_over_plain_wall": replay_wall / plain_wall if plain_wall > 0 else None,
    }
    return replay, comparison


def _replay_chessboard(tmp: Path) -> dict[str, Any]:
    """``ar-anchor replay chessboard.avi`` with default outputs, or the note saying why it was skipped."""
    files = chessboard_files()
    if isinstance(files, str):
        return {"skipped": files}
    video, camera_file = files
    shown = (
        "ar-anchor replay chessboard.avi --camera intrinsics.yml --dictionary DICT_ARUCO_ORIGINAL --marker-length 0.034"
    )
    args = [str(video), "--camera", str(camera_file), "--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034"]
    return {**_replay_run(args, tmp / "chessboard", shown), "video": str(video)}


def _replay_fifty(tmp: Path, frames: int) -> dict[str, Any]:
    """The 720p 50-marker clip of ``bench speed``, encoded to H.264, replayed with default outputs."""
    width, height, fx = FIFTY_SIZE
    camera = CameraModel.from_fov(width, height, fx)
    video, camera_file = tmp / "clip_50markers_720p.mp4", tmp / "camera_720p.yml"
    encode_scene(video, fifty_markers_scene(camera, frames))
    camera.to_yaml(camera_file)
    shown = f"ar-anchor replay clip_50markers_720p.mp4 --camera camera_720p.yml --marker-length {FIFTY_MARKER_M:g}"
    args = [str(video), "--camera", str(camera_file), "--marker-length", f"{FIFTY_MARKER_M:g}"]
    return {**_replay_run(args, tmp / "fifty", shown), "video_mb": video.stat().st_size / 1e6}


def _memory(run: dict[str, Any]) -> dict[str, Any]:
    samples = run["rss_mb"]
    after = [rss for t, rss in samples if t >= WARMUP_S]
    if not after:
        return {"warmup_s": WARMUP_S, "growth_mb": None}
    base = after[0]
    return {
        "warmup_s": WARMUP_S,
        "rss_after_warmup_mb": base,
        "peak_after_warmup_mb": max(after),
        "final_mb": after[-1],
        "growth_mb": max(after) - base,
        "samples": len(samples),
    }


def run_run_benchmark(
    *,
    minutes: float = 10.0,
    replay_frames: int = 600,
    live_seconds: float = 30.0,
    parts: tuple[str, ...] = RUN_PARTS,
    progress: Callable | None = None,
) -> dict[str, Any]:
    """The ``parts`` of :data:`RUN_PARTS`: the 1080p replay against the plain loop, live latency (and, when
    ``minutes`` > 0, memory over a long live run), chessboard.avi and the 50-marker clip replayed."""
    results: dict[str, Any] = {"meta": machine_info(), "notes": []}
    results["meta"]["parts"] = list(parts)
    steps = 2 * ALTERNATIONS * ("1080p" in parts) + ("chessboard" in parts) + ("50markers" in parts)
    steps += (2 + (minutes > 0)) * ("live" in parts)
    done = iter(range(steps))

    def step(name: str) -> None:
        if progress:
            progress(next(done), steps, name)

    with tempfile.TemporaryDirectory(prefix="ar_anchor_bench_run_") as name:
        tmp = Path(name)
        if "1080p" in parts:
            results["replay"], results["replay_vs_plain"] = _replay(
                tmp, replay_frames, lambda what: step(f"1080p H.264 clip, {replay_frames} frames: {what}")
            )
        if "chessboard" in parts:
            step("replay of chessboard.avi")
            results["chessboard"] = _replay_chessboard(tmp)
            if "skipped" in results["chessboard"]:
                results["notes"].append(results["chessboard"]["skipped"])
        if "50markers" in parts:
            step(f"replay of a {replay_frames}-frame 720p clip of 50 markers")
            results["fifty"] = _replay_fifty(tmp, replay_frames)
        if "live" in parts:
            _live_parts(results, tmp, live_seconds, minutes, step)
    results["meta"]["load_average_end"] = load_average()
    return results


def _live_parts(
    results: dict[str, Any], tmp: Path, live_seconds: float, minutes: float, step: Callable[[str], None]
) -> None:
    """Live latency (the default scene, one marker) and, when ``minutes`` > 0, the long run's memory."""
    step(f"live synthetic 1080p for {live_seconds:g} s")
    results["live"] = live_run(tmp, live_seconds, "live")
    step(f"live synthetic 1080p, one marker, for {live_seconds:g} s")
    results["live_one"] = live_run(tmp, live_seconds, "live_one", ONE_MARKER_CONFIG)
    if minutes > 0:
        step(f"live synthetic 1080p for {minutes:g} min (memory)")
        long_run = live_run(tmp, minutes * 60.0, "long")
        results["long_live"] = {k: v for k, v in long_run.items() if k != "rss_mb"}
        results["long_live"]["rss_mb"] = [[round(t, 1), round(rss, 1)] for t, rss in long_run["rss_mb"]]
        results["memory"] = _memory(long_run)


def run_markdown(results: dict[str, Any], command: str) -> str:
    """``run.md`` from :func:`run_run_benchmark`'s results: replay fps (and against the plain loop), the real
    and the 50-marker replays, live latency per stage, memory, machine (the parts that ran)."""
    lines = report_head(
        "End-to-end runs: replay throughput, live latency, memory",
        f"Produced by `{command}`: real `ar-anchor` processes, default settings (see `ar_anchor/bench/run.py`).",
        results.get("notes", []),
    )
    if "replay" in results:
        lines += _replay_lines(results["replay"], results.get("replay_vs_plain"))
    if "chessboard" in results and "skipped" not in results["chessboard"]:
        lines += _replay_section("Replay: chessboard.avi (real video, 640x480, 18 markers), default outputs",
                                 results["chessboard"])  # fmt: skip
    if "fifty" in results:
        lines += _replay_section("Replay: synthetic 720p H.264, 50 markers, default outputs", results["fifty"])
    if "live" in results:
        lines += _live_lines(results)
    if "memory" in results:
        lines += _memory_lines(results["memory"], results["long_live"])
    meta = results["meta"]
    lines += machine_lines(meta)
    return "\n".join(lines)


def _replay_lines(replay: dict[str, Any], versus: dict[str, Any] | None) -> list[str]:
    """The 1080p replay (its median run) and, when measured, the alternating runs against the plain loop."""
    lines = [
        "",
        "## Replay: 1920x1080 H.264, cube overlay, rerun logging",
        "",
        f"`{replay['command']}` ({replay['frames']} frames, {replay['video_mb']:.1f} MB video, recording "
        f"{fmt(replay['rrd_mb'], 1)} MB; camera images {replay['image_logging']})"
        + (f"; the median of {replay['runs']} runs:" if replay.get("runs", 1) > 1 else ":"),
        "",
        f"- **{replay['fps_run']:.1f} fps** over the run (frames / the run's wall time in `summary.json`);",
        f"- {replay['fps_process']:.1f} fps counting the whole process ({replay['process_wall_s']:.1f} s, "
        "start-up and the final flush included).",
    ]
    if not versus:
        return lines
    runs = len(versus["replay_wall_s"])
    lines += [
        "",
        f"### Against a plain OpenCV loop, {runs} runs each, taking turns",
        "",
        f"Replay (the command above) and the plain loop (`{versus['plain_command']}`: a separate Python process, "
        f"decode with {versus['plain_decode']}, grey, `detectMarkers` with default `DetectorParameters`, "
        "`solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)` per marker, no outputs) ran in turn: replay, plain, replay, "
        f"plain, ... Whole-process fps = {versus['frames']} frames / process wall time (start-up included).",
        "",
        "| | runs (s) | median wall s | median fps |",
        "|---|---|---|---|",
        f"| replay | {', '.join(fmt(x, 1) for x in versus['replay_wall_s'])} | {fmt(versus['replay_wall_median_s'])} "
        f"| {fmt(versus['replay_fps_median'], 1)} |",
        f"| plain loop | {', '.join(fmt(x, 1) for x in versus['plain_wall_s'])} | "
        f"{fmt(versus['plain_wall_median_s'])} | {fmt(versus['plain_fps_median'], 1)} |",
        "",
        f"**Replay / plain loop wall time: {fmt(versus['ratio_replay_over_plain_wall'])}x** (median / median; "
        "above 1: replay is slower). The plain loop found "
        f"{', '.join(str(m) for m in versus['plain_markers'])} marker poses.",
    ]
    return lines


def _replay_section(title: str, run: dict[str, Any]) -> list[str]:
    """A replay with default outputs: whole-process fps, the run's own fps, the tracker's stage medians."""
    stages = run["stages"]

    def median(stage: str) -> str:
        return fmt(stages.get(stage, {}).get("median"))

    return [
        "",
        f"## {title}",
        "",
        f"`{run['command']}` ({run['frames']} frames"
        + (f", {run['video_mb']:.1f} MB video" if run.get("video_mb") else "")
        + f"; recording {fmt(run.get('rrd_mb'), 1)} MB, camera images {run.get('image_logging')}):",
        "",
        f"- **{run['fps_process']:.1f} fps** for the whole process: {run['frames']} frames / "
        f"{run['process_wall_s']:.1f} s (start-up and the final flush included);",
        f"- {run['fps_run']:.1f} fps over the run (`summary.json`);",
        f"- tracker medians from `summary.json`: detect {median('detect')} + pose {median('pose')} + filter "
        f"{median('filter')} ms per frame.",
    ]


def _live_lines(results: dict[str, Any]) -> list[str]:
    """The two live runs, stage by stage."""
    live, one = results["live"], results["live_one"]
    lines = [
        "",
        "## Live: `ar-anchor live --device synthetic --width 1920 --height 1080 --fps 30`",
        "",
        "Two scenes: the default one (lone markers 0 and 7 and the 2x2 board `desk`: seven targets) and one "
        "5 cm marker (the same command with `--config` holding `[markers] ids = [0]`). Each runs "
        f"{live['seconds']:g} s, then gets SIGINT.",
        "",
        "| | default scene (7 targets) | one marker |",
        "|---|---|---|",
        f"| exit code, status | {live['exit_code']}, {live['status']} | {one['exit_code']}, {one['status']} |",
        f"| frames tracked (fps) | {live['frames']} ({fmt(live['fps'], 1)}) | {one['frames']} ({fmt(one['fps'], 1)}) |",
        f"| dropped by the camera queue (tracker busy) | {live['live'].get('dropped_queue', 0)} | "
        f"{one['live'].get('dropped_queue', 0)} |",
        f"| tracked but not logged (logger busy) | {live['frames_not_logged']} | {one['frames_not_logged']} |",
    ]
    for stage in live["stages"]:
        name = f"**{stage}**" if stage == "capture_to_pose" else stage
        a, b = live["stages"][stage], one["stages"].get(stage, {})
        lines.append(
            f"| {name} ms, median / p95 | {fmt(a.get('median'))} / {fmt(a.get('p95'))} | "
            f"{fmt(b.get('median'))} / {fmt(b.get('p95'))} |"
        )
    lines += [
        "",
        "*capture_to_pose*: from the frame's arrival (the device delivered it) to its pose (detect + pose + "
        "filter done); *wait*: arrival to the tracker taking it; *render*, *log*: the output thread's overlay "
        "drawing and rerun logging of that frame (off the tracker's thread).",
    ]
    return lines


def _memory_lines(memory: dict[str, Any], long_live: dict[str, Any]) -> list[str]:
    """The long live run's resident set size."""
    return [
        "",
        f"## Memory: the same live run for {long_live['seconds'] / 60:g} minutes",
        "",
        f"{long_live['frames']} frames tracked; stopped with SIGINT: exit {long_live['exit_code']}, "
        f"status `{long_live['status']}`. Resident set size sampled every {SAMPLE_S:g} s:",
        "",
        f"- after the {memory['warmup_s']:g} s warm-up: {fmt(memory.get('rss_after_warmup_mb'), 1)} MB; "
        f"peak after it: {fmt(memory.get('peak_after_warmup_mb'), 1)} MB; at the end: "
        f"{fmt(memory.get('final_mb'), 1)} MB;",
        f"- **growth after warm-up: {fmt(memory.get('growth_mb'), 1)} MB**.",
    ]


def write_run_report(
    out_dir: Path,
    *,
    quick: bool = False,
    minutes: float | None = None,
    progress: Callable | None = None,
    command: str,
    parts: tuple[str, ...] | None = None,
    frames: int | None = None,
) -> dict[str, Any]:
    """Run the benchmark; write ``run.md`` and ``run.json`` to ``out_dir``. ``parts``: of :data:`RUN_PARTS`
    (default all); ``frames``: of the encoded synthetic clips (default 600, ``quick`` 150)."""
    minutes = (0.0 if quick else 10.0) if minutes is None else minutes
    results = run_run_benchmark(
        minutes=minutes,
        replay_frames=frames or (150 if quick else 600),
        live_seconds=10.0 if quick else 30.0,
        parts=RUN_PARTS if parts is None else parts,
        progress=progress,
    )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "run.json").write_text(json.dumps(results, indent=2) + "\n")
    (out_dir / "run.md").write_text(run_markdown(results, command))
    return results
