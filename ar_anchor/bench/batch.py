"""``ar-anchor bench batch``: many recordings replayed one after the other (a loop of ``ar-anchor replay``
processes, as a shell script would) against ``ar-anchor batch`` on local processes and on a local Ray.

The clips: the demo scene (lone markers 0 and 7 and the 2x2 board ``desk`` of ``configs/demo.toml``) seen by
a hand-held camera (0.35-1.2 m, a different seed per clip) at 640x480, :data:`CLIP_FRAMES` frames at
:data:`FPS` fps each (``--frames``), rendered and encoded to H.264 once (PyAV, CRF 18, as ``bench run``).
Every variant is a real process started with :mod:`subprocess` and timed from outside (start-up included):

* ``sequential``: ``ar-anchor -q replay CLIP`` for each clip in turn;
* ``batch``: ``ar-anchor -q batch CLIPS/ --jobs N`` (N: the usable cores), each worker on one OpenCV thread;
* ``batch, OpenCV threads kept``: the same with ``AR_ANCHOR_BATCH_KEEP_OPENCV_THREADS=1`` (each worker keeps
  OpenCV's default thread count): what one thread per worker saves or costs;
* ``batch --ray``: the same tasks on a local Ray of N CPUs (started and stopped by the command; skipped with a
  note when Ray is not installed).

Each batch's ``poses.csv`` files are compared with the sequential replays' (byte for byte). Target (issue 22):
``batch`` at least :data:`TARGET_SPEEDUP` times faster than the sequential loop.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..camera import CameraModel
from ..config import demo_config
from ..config.document import demo_toml
from ..synthetic import Trajectory, demo_scene
from .report import fmt, load_average, machine_info, machine_lines, report_head, write_json
from .run import _cli
from .speed.scenes import encode_scene

__all__ = ["CLIPS", "CLIP_FRAMES", "TARGET_SPEEDUP", "batch_markdown", "run_batch_benchmark", "write_batch_report"]

CLIPS = 12
CLIP_FRAMES = 300  # 10 s at FPS
FPS = 30.0
SIZE = (640, 480)
FOCAL_PX = 500.0
TARGET_SPEEDUP = 1.7
KEEP_THREADS = "AR_ANCHOR_BATCH_KEEP_OPENCV_THREADS"


def _usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _render(folder: Path, clips: int, frames: int, step: Callable[[str], None]) -> dict[str, Any]:
    """``clips`` clips (see the module doc) in ``folder``, with the camera YAML and the demo config beside it."""
    folder.mkdir(parents=True)
    camera = CameraModel.from_fov(*SIZE, FOCAL_PX)
    config = demo_config()
    started = time.perf_counter()
    for k in range(clips):
        step(f"render and encode clip {k + 1} of {clips}")
        trajectory = Trajectory(
            kind="handheld", near_m=0.35, far_m=1.2, look_at=(-0.01, 0.0, 0.0), seed=k, duration_s=frames / FPS
        )
        scene = demo_scene(config, camera, frames=frames, trajectory=trajectory, fps=FPS, seed=k)
        encode_scene(folder / f"clip{k:02d}.mp4", scene)
    camera_file, config_file = folder.parent / "camera.yml", folder.parent / "demo.toml"
    camera.to_yaml(camera_file)
    config_file.write_text(demo_toml())
    return {
        "clips": clips,
        "frames": frames,
        "size": f"{SIZE[0]}x{SIZE[1]}",
        "video_mb": sum(p.stat().st_size for p in folder.glob("*.mp4")) / 1e6,
        "render_s": time.perf_counter() - started,
        "camera": camera_file,
        "config": config_file,
    }


def _timed(command: list[str], what: str, env: dict[str, str] | None = None) -> float:
    """Run ``command`` to its end; its wall time (s). RuntimeError naming ``what`` when it fails."""
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        tail = " ".join(done.stderr.strip().splitlines()[-2:])
        raise RuntimeError(f"{what} failed ({done.returncode}): {tail}")
    return wall


def _same_poses(out: Path, reference: Path, names: list[str]) -> int:
    """How many of ``names`` have a ``poses.csv`` under ``out`` identical to the one under ``reference``."""
    same = 0
    for name in names:
        a, b = out / name / "poses.csv", reference / name / "poses.csv"
        same += a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()
    return same


def run_batch_benchmark(
    *, clips: int = CLIPS, frames: int = CLIP_FRAMES, progress: Callable[[int, int, str], None] | None = None
) -> dict[str, Any]:
    """The clips rendered once, then the sequential loop, ``batch``, ``batch`` with OpenCV's threads kept and
    ``batch --ray`` (see the module doc); the results as ``batch.json`` holds them."""
    try:
        import ray  # noqa: F401

        has_ray = True
    except ImportError:
        has_ray = False
    jobs = _usable_cpus()
    results: dict[str, Any] = {"meta": machine_info(), "notes": [], "jobs": jobs, "target_speedup": TARGET_SPEEDUP}
    steps = clips + clips + 2 + has_ray
    counter = iter(range(steps))

    def step(name: str) -> None:
        if progress:
            progress(next(counter, steps - 1), steps, name)

    with tempfile.TemporaryDirectory(prefix="ar_anchor_bench_batch_") as name:
        tmp = Path(name)
        videos = tmp / "clips"
        clip = _render(videos, clips, frames, step)
        common = ["--camera", str(clip.pop("camera")), "--config", str(clip.pop("config"))]
        results["clips"] = clip
        names = [f"clip{k:02d}" for k in range(clips)]
        sequential = 0.0
        for k, clip_name in enumerate(names):
            step(f"sequential replay {k + 1} of {clips}")
            command = _cli("replay", str(videos / f"{clip_name}.mp4"), *common, "--out", str(tmp / "seq" / clip_name))
            sequential += _timed(command, f"replay of {clip_name}")
        variants: dict[str, Any] = {"sequential": {"wall_s": sequential, "command": "ar-anchor replay CLIP (each)"}}
        runs = [
            ("batch", [], None),
            ("batch, OpenCV threads kept", [], {**os.environ, KEEP_THREADS: "1"}),
        ]
        if has_ray:
            runs.append(("batch --ray", ["--ray"], None))
        else:
            results["notes"].append("Ray is not installed (pip install 'ar-anchor[cluster]'): batch --ray not measured")
        for label, extra, env in runs:
            step(label)
            out = tmp / label.replace(" ", "_").replace(",", "")
            command = _cli("batch", str(videos), *common, "--out", str(out), "--jobs", str(jobs), *extra)
            wall = _timed(command, label, env)
            variants[label] = {
                "wall_s": wall,
                "speedup": sequential / wall if wall > 0 else None,
                "same_poses": _same_poses(out, tmp / "seq", names),
                "command": f"ar-anchor batch clips/ --jobs {jobs}" + (" --ray" if extra else ""),
            }
        results["variants"] = variants
    results["meta"]["load_average_end"] = load_average()
    speedup = variants["batch"]["speedup"]
    results["verdict"] = None if speedup is None else speedup >= TARGET_SPEEDUP
    return results


def batch_markdown(results: dict[str, Any], command: str) -> str:
    """``batch.md`` from :func:`run_batch_benchmark`'s results."""
    clip, variants = results["clips"], results["variants"]
    total_frames = clip["clips"] * clip["frames"]
    lines = report_head(
        "Batch: a loop of replays against `ar-anchor batch`, local and on Ray",
        f"Produced by `{command}`: real `ar-anchor` processes timed from outside (see `ar_anchor/bench/batch.py`).",
        results.get("notes", []),
    )
    lines += [
        "",
        f"{clip['clips']} synthetic clips (the demo scene, a hand-held camera at 0.35-1.2 m, a seed each), "
        f"{clip['frames']} frames each at {FPS:g} fps ({clip['frames'] / FPS:g} s), {clip['size']}, H.264 "
        f"({clip['video_mb']:.1f} MB in all; rendered and encoded in {clip['render_s']:.0f} s). Default replay "
        f"(offline: three passes). {results['jobs']} workers / Ray CPUs. Wall time: the whole command, start-up "
        "included (the sequential loop: the sum of its processes).",
        "",
        "| variant | wall s | frames/s | speedup over the loop | poses.csv identical to the loop's |",
        "|---|---|---|---|---|",
    ]
    for label, run in variants.items():
        same = "-" if "same_poses" not in run else f"{run['same_poses']} of {clip['clips']}"
        speedup = "1" if label == "sequential" else fmt(run.get("speedup"))
        lines.append(
            f"| {label} | {fmt(run['wall_s'], 1)} | {fmt(total_frames / run['wall_s'], 1)} | {speedup} | {same} |"
        )
    verdict = results.get("verdict")
    meta = results["meta"]
    lines += [
        "",
        f"- **batch over the loop: {fmt(variants['batch'].get('speedup'))}x** (target >= {TARGET_SPEEDUP:g}x): "
        + ("-" if verdict is None else "**pass**" if verdict else "**FAIL**")
        + ".",
    ]
    lines += machine_lines(meta)
    return "\n".join(lines)


def write_batch_report(
    out_dir: Path,
    *,
    quick: bool = False,
    frames: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    command: str,
) -> dict[str, Any]:
    """Run the benchmark; write ``batch.md`` and ``batch.json`` to ``out_dir``. ``quick``: 4 clips of 60 frames."""
    clips = 4 if quick else CLIPS
    frames = frames or (60 if quick else CLIP_FRAMES)
    results = run_batch_benchmark(clips=clips, frames=frames, progress=progress)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "batch.json", results)
    (out_dir / "batch.md").write_text(batch_markdown(results, command))
    return results
