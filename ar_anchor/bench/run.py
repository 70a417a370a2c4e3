"""``ar-anchor bench run``: the CLI's own end-to-end runs, timed from outside.

Three measurements, each a real ``ar-anchor`` process started with :mod:`subprocess` exactly as a
user would start it (default settings unless stated):

* **replay**: ``ar-anchor replay`` of a 1920x1080 H.264 clip (one 5 cm marker, the camera orbiting
  at 0.6 m, rendered with sensor noise and blur, encoded once with PyAV) with a cube overlay and
  rerun logging: frames per second from its ``summary.json`` (frames / wall time of the run) and
  from the process's own wall time (start-up included).
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
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import CameraModel
from .report import fmt, load_average, machine_info
from .speed import render_clip, speed_scene

__all__ = ["run_run_benchmark", "write_run_report"]

SIZE = (1920, 1080)
FX = 1480.0
LIVE_FPS = 30.0
WARMUP_S = 60.0
# the live scene of one 5 cm marker (the synthetic camera renders what the config tracks)
ONE_MARKER_CONFIG = "[markers]\nlength_m = 0.05\nids = [0]\n"
SAMPLE_S = 5.0


def _camera() -> CameraModel:
    width, height = SIZE
    k = np.array([[FX, 0.0, (width - 1) / 2], [0.0, FX, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return CameraModel(k, np.zeros(5), width, height)


def _encode_clip(path: Path, frames: int) -> None:
    """The one-marker 1080p clip of ``bench speed``, encoded to H.264 (CRF 18) with PyAV."""
    import av

    scene = speed_scene("one", _camera(), frames)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=int(scene.fps))
        stream.width, stream.height = SIZE
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}

        def encode(image: np.ndarray) -> None:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                container.mux(packet)

        render_clip(scene, on_frame=encode, keep=False)
        for packet in stream.encode():
            container.mux(packet)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ar_anchor", "-q", *args]


def _rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _stages(summary: dict[str, Any]) -> dict[str, Any]:
    return {stage.removesuffix("_ms"): values for stage, values in summary.get("latency_ms", {}).items()}


def _replay(tmp: Path, frames: int) -> dict[str, Any]:
    video, camera_file, config = tmp / "clip_1080p.mp4", tmp / "camera_1080p.yml", tmp / "cube.toml"
    _encode_clip(video, frames)
    _camera().to_yaml(camera_file)
    config.write_text('[markers]\nlength_m = 0.05\n\n[[overlays]]\ntarget = "marker:*"\nkind = "cube"\n')
    out = tmp / "replay"
    command = _cli("replay", str(video), "--camera", str(camera_file), "--config", str(config), "--out", str(out))
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"replay failed ({done.returncode}): {done.stderr.strip()}")
    summary = json.loads((out / "summary.json").read_text())
    return {
        "command": "ar-anchor replay clip_1080p.mp4 --camera camera_1080p.yml --config cube.toml",
        "frames": summary["frames"],
        "video_mb": video.stat().st_size / 1e6,
        "rrd_mb": (out / "recording.rrd").stat().st_size / 1e6,
        "fps_run": summary["fps"],
        "fps_process": summary["frames"] / wall,
        "process_wall_s": wall,
        "image_logging": summary.get("image_logging"),
        "stages": _stages(summary),
    }


def _live(tmp: Path, seconds: float, name: str, config: str | None = None) -> dict[str, Any]:
    """A live synthetic 1080p run for ``seconds`` after the camera opened, then SIGINT. ``config``: a
    tracker TOML (the synthetic scene holds the markers and boards it names)."""
    out = tmp / name
    width, height = SIZE
    command = _cli(
        "live", "--device", "synthetic", "--width", str(width), "--height", str(height), "--fps", str(LIVE_FPS)
    )
    command += ["--out", str(out)]
    if config is not None:
        path = tmp / f"{name}.toml"
        path.write_text(config)
        command += ["--config", str(path)]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples: list[tuple[float, float]] = []
    started: float | None = None
    try:
        while process.poll() is None:
            now = time.monotonic()
            if started is None and (out / "poses.csv").exists():
                started = now  # the camera's clip is rendered and frames flow
            if started is not None:
                rss = _rss_mb(process.pid)
                if rss is not None:
                    samples.append((now - started, rss))
                if now - started >= seconds:
                    process.send_signal(signal.SIGINT)
                    break
            time.sleep(SAMPLE_S if started is not None else 0.5)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    summary = json.loads((out / "summary.json").read_text())
    return {
        "exit_code": process.returncode,
        "status": summary["status"],
        "seconds": seconds,
        "frames": summary["frames"],
        "fps": summary["fps"],
        "live": summary.get("live", {}),
        "frames_not_logged": summary.get("frames_not_logged", 0),
        "stages": _stages(summary),
        "rss_mb": samples,
        "stderr_tail": stderr.strip().splitlines()[-3:],
    }


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
    *, minutes: float = 10.0, replay_frames: int = 600, live_seconds: float = 30.0, progress: Callable | None = None
) -> dict[str, Any]:
    """Replay throughput, live latency and (when ``minutes`` > 0) memory over a long live run."""
    results: dict[str, Any] = {"meta": machine_info()}
    steps = ["replay", "live latency", "live latency, one marker"] + (["memory"] if minutes > 0 else [])
    with tempfile.TemporaryDirectory(prefix="ar_anchor_bench_run_") as name:
        tmp = Path(name)
        if progress:
            progress(0, len(steps), f"replay of a {replay_frames}-frame 1080p H.264 clip")
        results["replay"] = _replay(tmp, replay_frames)
        if progress:
            progress(1, len(steps), f"live synthetic 1080p for {live_seconds:g} s")
        results["live"] = _live(tmp, live_seconds, "live")
        if progress:
            progress(2, len(steps), f"live synthetic 1080p, one marker, for {live_seconds:g} s")
        results["live_one"] = _live(tmp, live_seconds, "live_one", ONE_MARKER_CONFIG)
        if minutes > 0:
            if progress:
                progress(3, len(steps), f"live synthetic 1080p for {minutes:g} min (memory)")
            long_run = _live(tmp, minutes * 60.0, "long")
            results["long_live"] = {k: v for k, v in long_run.items() if k != "rss_mb"}
            results["long_live"]["rss_mb"] = [[round(t, 1), round(rss, 1)] for t, rss in long_run["rss_mb"]]
            results["memory"] = _memory(long_run)
    results["meta"]["load_average_end"] = load_average()
    return results


def run_markdown(results: dict[str, Any], command: str) -> str:
    """``run.md`` from :func:`run_run_benchmark`'s results: replay fps, live latency per stage, memory, machine."""
    meta, replay, live = results["meta"], results["replay"], results["live"]
    lines = [
        "# End-to-end runs: replay throughput, live latency, memory",
        "",
        f"Produced by `{command}`: real `ar-anchor` processes, default settings (see `ar_anchor/bench/run.py`).",
        "",
        "## Replay: 1920x1080 H.264, cube overlay, rerun logging",
        "",
        f"`{replay['command']}` ({replay['frames']} frames, {replay['video_mb']:.1f} MB video, recording "
        f"{replay['rrd_mb']:.1f} MB; camera images {replay['image_logging']}):",
        "",
        f"- **{replay['fps_run']:.1f} fps** over the run (frames / the run's wall time in `summary.json`);",
        f"- {replay['fps_process']:.1f} fps counting the whole process ({replay['process_wall_s']:.1f} s, "
        "start-up and the final flush included).",
        "",
        "## Live: `ar-anchor live --device synthetic --width 1920 --height 1080 --fps 30`",
        "",
        "Two scenes: the default one (lone markers 0 and 7 and the 2x2 board `desk`: seven targets) and one "
        "5 cm marker (the same command with `--config` holding `[markers] ids = [0]`). Each runs "
        f"{live['seconds']:g} s, then gets SIGINT.",
        "",
        "| | default scene (7 targets) | one marker |",
        "|---|---|---|",
    ]
    one = results["live_one"]
    lines.append(f"| exit code, status | {live['exit_code']}, {live['status']} | {one['exit_code']}, {one['status']} |")
    lines.append(
        f"| frames tracked (fps) | {live['frames']} ({fmt(live['fps'], 1)}) | {one['frames']} ({fmt(one['fps'], 1)}) |"
    )
    lines.append(
        f"| dropped by the camera queue (tracker busy) | {live['live'].get('dropped_queue', 0)} | "
        f"{one['live'].get('dropped_queue', 0)} |"
    )
    lines.append(f"| tracked but not logged (logger busy) | {live['frames_not_logged']} | {one['frames_not_logged']} |")
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
    if "memory" in results:
        memory, long_live = results["memory"], results["long_live"]
        lines += [
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
    lines += [
        "",
        "## Machine",
        "",
        f"{meta['processor']}, {meta['usable_cpus']} usable CPUs, Python {meta['python']}, OpenCV {meta['opencv']} "
        f"({meta['opencv_threads']} threads). Load average at the start {meta['load_average_start']}, at the end "
        f"{meta['load_average_end']}.",
        "",
    ]
    return "\n".join(lines)


def write_run_report(
    out_dir: Path, *, quick: bool = False, minutes: float | None = None, progress: Callable | None = None, command: str
) -> dict[str, Any]:
    """Run the benchmark; write ``run.md`` and ``run.json`` to ``out_dir``."""
    minutes = (0.0 if quick else 10.0) if minutes is None else minutes
    results = run_run_benchmark(
        minutes=minutes,
        replay_frames=150 if quick else 600,
        live_seconds=10.0 if quick else 30.0,
        progress=progress,
    )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "run.json").write_text(json.dumps(results, indent=2) + "\n")
    (out_dir / "run.md").write_text(run_markdown(results, command))
    return results
