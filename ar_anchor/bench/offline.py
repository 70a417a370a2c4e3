"""``ar-anchor bench offline``: what the offline replay (issue 20) costs against the causal one, and what
it gains on real video.

Two measurements, each a real ``ar-anchor replay`` process started with :mod:`subprocess` as a user
would start it:

* **long synthetic replay**: the demo scene (lone markers 0 and 7 and the 2x2 board ``desk`` of
  ``configs/demo.toml``, the demo's 1280x720 camera, sensor noise 2, blur 0.6 px) seen by a hand-held
  camera (sway, tremor, a quick turn every 2.5 s on average, 0.35-1.2 m) for ``--minutes`` minutes
  (default 10) at 30 fps, rendered and encoded to H.264 (CRF 18, PyAV, as ``bench run``) once. It is
  replayed with ``--causal`` and without (the offline default), taking turns: causal, offline, causal,
  ... (3 runs each; ``--quick``: 1). Each run: the process's wall time (start-up included) and its
  resident set size sampled from ``/proc/<pid>/status`` every :data:`SAMPLE_S` s; growth = the peak
  after the warm-up minus the size at the end of the warm-up (:func:`warmup_s`: 60 s, or a quarter of
  the run when that is shorter). From ``summary.json``: the spool's size and the states summed over
  the targets (the offline run's live-filter states beside its own).
* **chessboard.avi** (under ``$AR_ANCHOR_REALDATA``; skipped with a note when absent): replayed causal
  and offline (``--dictionary DICT_ARUCO_ORIGINAL --marker-length 0.034``), each ``poses.csv`` scored
  with the rigid-sheet pair consistency of :mod:`ar_anchor.bench.real` (pair flips > 10 deg, relative
  rotation and translation RMS), over all rows with a pose and over ``tracked`` rows only.

Targets (issue 20): offline / causal wall time <= 1.5, offline growth < 100 MB, and on chessboard.avi
offline pair flips and relative rotation RMS <= causal's.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import CameraModel
from ..config import demo_config
from ..config.document import demo_toml
from ..synthetic import Trajectory, demo_scene
from .real.scoring import read_poses_csv, score_rigid_sheet
from .report import fmt, load_average, machine_info, machine_lines, report_head, write_json
from .run import _cli
from .speed.live import rss_mb
from .speed.real_clip import chessboard_files
from .speed.scenes import encode_scene

__all__ = [
    "MAX_GROWTH_MB",
    "MAX_RATIO",
    "MODES",
    "SAMPLE_S",
    "offline_markdown",
    "offline_verdicts",
    "rss_growth",
    "run_offline_benchmark",
    "warmup_s",
    "write_offline_report",
]

MODES: tuple[str, ...] = ("causal", "offline")
SAMPLE_S = 0.5
WARMUP_S = 60.0
LEVEL_S = 10.0  # sustained growth: RSS medians over this many seconds (a spike of a second or two does not count)
FPS = 30.0
MAX_RATIO = 1.5  # issue 20: offline replay at most 1.5x the causal replay's time ...
MAX_GROWTH_MB = 100.0  # ... within flat memory
STATE_SETS: dict[str, tuple[str, ...] | None] = {"all rows": None, "tracked only": ("tracked",)}
CLIP_NAME = "demo_handheld_720p.mp4"
CHESSBOARD_ARGS = ("--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034")


def warmup_s(wall_s: float) -> float:
    """The warm-up of a run of ``wall_s`` seconds: :data:`WARMUP_S`, or a quarter of the run when shorter."""
    return min(WARMUP_S, wall_s / 4.0)


def _clip(tmp: Path, minutes: float) -> dict[str, Any]:
    """The long clip (see the module doc) encoded to ``tmp``, with its camera YAML and the demo config."""
    camera = CameraModel.default_synthetic()
    frames = max(2, int(round(minutes * 60.0 * FPS)))
    trajectory = Trajectory(
        kind="handheld", near_m=0.35, far_m=1.2, look_at=(-0.01, 0.0, 0.0), seed=0, duration_s=frames / FPS
    )
    scene = demo_scene(demo_config(), camera, frames=frames, trajectory=trajectory, fps=FPS)
    video, camera_file, config = tmp / CLIP_NAME, tmp / "camera_720p.yml", tmp / "demo.toml"
    started = time.perf_counter()
    encode_scene(video, scene)
    camera.to_yaml(camera_file)
    config.write_text(demo_toml())
    width, height = camera.size
    return {
        "video": video,
        "args": [str(video), "--camera", str(camera_file), "--config", str(config)],
        "frames": frames,
        "minutes": frames / FPS / 60.0,
        "size": f"{width}x{height}",
        "video_mb": video.stat().st_size / 1e6,
        "encode_s": time.perf_counter() - started,
        "command": f"ar-anchor replay {CLIP_NAME} --camera camera_720p.yml --config demo.toml",
    }


def _watched(command: list[str], what: str) -> tuple[float, list[tuple[float, float]]]:
    """Run ``command`` to its end, its RSS sampled every :data:`SAMPLE_S` s: (wall s, [(t s, MB)])."""
    samples: list[tuple[float, float]] = []
    with tempfile.TemporaryFile("w+") as errors:  # (a pipe left unread could fill and stall the run)
        started = time.monotonic()
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=errors, text=True)
        try:
            while process.poll() is None:
                rss = rss_mb(process.pid)
                if rss is not None:
                    samples.append((time.monotonic() - started, rss))
                try:
                    process.wait(timeout=SAMPLE_S)  # (returns as soon as it ends: the wall time is not rounded up)
                except subprocess.TimeoutExpired:
                    pass
            wall = time.monotonic() - started
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        errors.seek(0)
        stderr = errors.read()
    if process.returncode != 0:
        tail = " ".join(stderr.strip().splitlines()[-2:])
        raise RuntimeError(f"{what} failed ({process.returncode}): {tail}")
    return wall, samples


def rss_growth(wall: float, samples: list[tuple[float, float]]) -> dict[str, Any]:
    """Peak and growth after the warm-up (see :func:`warmup_s`) of one run's RSS samples ``[(t s, MB)]``:
    growth = the peak after the warm-up minus the first sample after it (None without samples after it);
    sustained growth: the same with medians over :data:`LEVEL_S` seconds (the highest minus the first)."""
    warmup = warmup_s(wall)
    after = [rss for t, rss in samples if t >= warmup]
    result: dict[str, Any] = {
        "warmup_s": warmup,
        "samples": len(samples),
        "peak_mb": max((rss for _, rss in samples), default=None),
    }
    if after:
        result.update(rss_after_warmup_mb=after[0], peak_after_warmup_mb=max(after), final_mb=after[-1])
        result["growth_mb"] = max(after) - after[0]
        window = max(1, int(round(LEVEL_S / SAMPLE_S)))
        levels = [float(np.median(after[i : i + window])) for i in range(0, max(1, len(after) - window + 1))]
        result["sustained_growth_mb"] = max(levels) - levels[0]
    else:
        result["growth_mb"] = result["sustained_growth_mb"] = None
    return result


def _summed_states(summary: dict[str, Any], key: str) -> dict[str, int] | None:
    """``summary.json``'s per-target ``key`` (``states`` or ``causal_states``) summed over the targets."""
    total: dict[str, int] = {}
    found = False
    for entry in summary.get("targets", {}).values():
        if key in entry:
            found = True
            for state, count in entry[key].items():
                total[state] = total.get(state, 0) + int(count)
    return total if found else None


def _replay(args: list[str], out: Path, mode: str) -> dict[str, Any]:
    """One ``ar-anchor replay`` process (``--causal`` for the causal mode), timed and watched from outside."""
    command = _cli("replay", *args, "--out", str(out), *(["--causal"] if mode == "causal" else []))
    wall, samples = _watched(command, f"the {mode} replay")
    summary = json.loads((out / "summary.json").read_text())
    return {
        "mode": mode,
        "wall_s": wall,
        "frames": summary["frames"],
        "fps_process": summary["frames"] / wall if wall > 0 else None,
        "memory": rss_growth(wall, samples),
        "rss_mb": [[round(t, 1), round(rss, 1)] for t, rss in samples],
        "offline": summary.get("offline"),
        "states": _summed_states(summary, "states"),
        "causal_states": _summed_states(summary, "causal_states"),
    }


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _long_replay(tmp: Path, minutes: float, runs: int, step: Callable[[str], None]) -> dict[str, Any]:
    """The long synthetic clip replayed ``runs`` times in each mode, taking turns; medians and the ratio."""
    step(f"render and encode the {minutes:g}-minute clip")
    clip = _clip(tmp, minutes)
    done: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
    for index in range(runs):
        for mode in MODES:
            step(f"{mode} replay {index + 1} of {runs}")
            run = _replay(clip["args"], tmp / f"{mode}_{index}", mode)
            done[mode].append(run)
            # the temporary folder holds six runs: keep only what the report reads (a recording's parts
            # each carry the whole source video again)
            written = tmp / f"{mode}_{index}"
            run["recording_mb"] = sum(part.stat().st_size for part in written.glob("recording*.rrd")) / 1e6
            for path in [*written.glob("recording*.rrd"), written / "poses.csv"]:
                path.unlink(missing_ok=True)
    result: dict[str, Any] = {key: value for key, value in clip.items() if key not in ("video", "args")}
    result["runs"] = runs
    for mode in MODES:
        walls = [run["wall_s"] for run in done[mode]]
        growths = [run["memory"]["growth_mb"] for run in done[mode] if run["memory"]["growth_mb"] is not None]
        result[mode] = {
            "wall_s": walls,
            "wall_median_s": _median(walls),
            "growth_mb": growths,
            "sustained_growth_mb": [run["memory"].get("sustained_growth_mb") for run in done[mode]],
            "growth_median_mb": _median(growths),
            "growth_max_mb": max(growths, default=None),
            "runs": done[mode],
        }
    causal, offline = result["causal"]["wall_median_s"], result["offline"]["wall_median_s"]
    result["ratio_offline_over_causal"] = offline / causal if causal else None
    return result


def _chessboard(tmp: Path, step: Callable[[str], None]) -> dict[str, Any]:
    """chessboard.avi replayed causal and offline, each ``poses.csv`` scored (all rows, tracked only)."""
    files = chessboard_files()
    if isinstance(files, str):
        return {"skipped": files}
    video, camera_file = files
    result: dict[str, Any] = {
        "video": str(video),
        "command": "ar-anchor replay chessboard.avi --camera intrinsics.yml " + " ".join(CHESSBOARD_ARGS),
    }
    for mode in MODES:
        step(f"{mode} replay of chessboard.avi")
        out = tmp / f"chessboard_{mode}"
        run = _replay([str(video), "--camera", str(camera_file), *CHESSBOARD_ARGS], out, mode)
        scores = {name: score_rigid_sheet(read_poses_csv(out / "poses.csv", states=states))
                  for name, states in STATE_SETS.items()}  # fmt: skip
        result[mode] = {key: run[key] for key in ("wall_s", "frames", "states", "causal_states", "offline")}
        result[mode]["scores"] = scores
    return result


def run_offline_benchmark(
    *, minutes: float = 10.0, runs: int = 3, progress: Callable[[int, int, str], None] | None = None
) -> dict[str, Any]:
    """The long synthetic replay (``minutes`` > 0; ``runs`` per mode, taking turns) and chessboard.avi,
    causal against offline (see the module doc); the results as ``offline.json`` holds them."""
    results: dict[str, Any] = {"meta": machine_info(), "notes": []}
    steps = (1 + 2 * runs) * (minutes > 0) + 2
    counter = iter(range(steps))

    def step(name: str) -> None:
        if progress:
            progress(next(counter, steps - 1), steps, name)

    with tempfile.TemporaryDirectory(prefix="ar_anchor_bench_offline_") as name:
        tmp = Path(name)
        if minutes > 0:
            results["long"] = _long_replay(tmp, minutes, runs, step)
        results["chessboard"] = _chessboard(tmp, step)
        if "skipped" in results["chessboard"]:
            results["notes"].append(results["chessboard"]["skipped"])
    results["meta"]["load_average_end"] = load_average()
    results["verdicts"] = offline_verdicts(results)
    return results


def offline_verdicts(results: dict[str, Any]) -> dict[str, bool | None]:
    """Issue 20's targets, each True / False (None: not measured)."""
    long, board = results.get("long"), results.get("chessboard", {})
    verdicts: dict[str, bool | None] = {"time_ratio": None, "offline_growth": None, "chessboard": None}
    if long:
        ratio, growth = long["ratio_offline_over_causal"], long["offline"]["growth_max_mb"]
        verdicts["time_ratio"] = None if ratio is None else ratio <= MAX_RATIO
        verdicts["offline_growth"] = None if growth is None else growth < MAX_GROWTH_MB
    if "causal" in board and "offline" in board:
        ok = True
        for name in STATE_SETS:
            causal, offline = board["causal"]["scores"][name], board["offline"]["scores"][name]
            ok &= _not_above(offline["flip_pct"], causal["flip_pct"])
            ok &= _not_above(offline["rel_rot_rms_deg"], causal["rel_rot_rms_deg"])
        verdicts["chessboard"] = ok
    return verdicts


def _not_above(value: float | None, reference: float | None) -> bool:
    """``value <= reference``, NaN / None as "nothing to compare" (True)."""
    if value is None or reference is None or not np.isfinite(value) or not np.isfinite(reference):
        return True
    return value <= reference


def _verdict(value: bool | None) -> str:
    return "-" if value is None else ("**pass**" if value else "**FAIL**")


def offline_markdown(results: dict[str, Any], command: str) -> str:
    """``offline.md`` from :func:`run_offline_benchmark`'s results: the long replay's time and memory, the
    states, chessboard.avi's scores, the verdicts and the machine."""
    lines = report_head(
        "Offline replay against the causal one: cost, memory, real video",
        f"Produced by `{command}`: real `ar-anchor replay` processes (see `ar_anchor/bench/offline.py`).",
        results.get("notes", []),
    )
    verdicts = results.get("verdicts", {})
    if results.get("long"):
        lines += _long_lines(results["long"], verdicts)
    board = results.get("chessboard", {})
    if "causal" in board:
        lines += _chessboard_lines(board, verdicts)
    meta = results["meta"]
    lines += machine_lines(meta)
    return "\n".join(lines)


def _long_lines(long: dict[str, Any], verdicts: dict[str, Any]) -> list[str]:
    """The long synthetic replay: wall times, memory, spool, states."""
    causal, offline = long["causal"], long["offline"]
    spool = [(run.get("offline") or {}).get("spool_mb") for run in offline["runs"]]
    lines = [
        "",
        f"## Long synthetic replay: {long['minutes']:g} minutes at {long['size']}, H.264",
        "",
        f"`{long['command']}` (and the same with `--causal`): {long['frames']} frames at {FPS:g} fps, "
        f"{long['video_mb']:.1f} MB video (rendered and encoded in {long['encode_s']:.0f} s). The demo scene "
        "(lone markers 0 and 7, the 2x2 board `desk`: seven targets) seen by a hand-held camera at 0.35-1.2 m "
        "(sway, tremor, quick turns), sensor noise 2, blur 0.6 px; encoded with PyAV's libx264 (CRF 18). "
        f"{long['runs']} run(s) per mode, taking turns (causal, offline, causal, ...). Wall time: the whole "
        f"process (start-up included). RSS sampled every {SAMPLE_S:g} s from `/proc/<pid>/status`; growth = "
        f"peak after the warm-up minus the RSS at its end (warm-up {WARMUP_S:g} s, or a quarter of the run when "
        f"shorter); sustained growth: the same over {LEVEL_S:g} s medians of the samples (spikes of a second or "
        "two left out).",
        "",
        "| | causal (`--causal`) | offline (default) |",
        "|---|---|---|",
        f"| wall s per run | {', '.join(fmt(x, 1) for x in causal['wall_s'])} | "
        f"{', '.join(fmt(x, 1) for x in offline['wall_s'])} |",
        f"| median wall s (fps) | {fmt(causal['wall_median_s'], 1)} ({_fps(long, causal)}) | "
        f"{fmt(offline['wall_median_s'], 1)} ({_fps(long, offline)}) |",
        f"| RSS growth after warm-up MB per run | {', '.join(fmt(x, 1) for x in causal['growth_mb'])} | "
        f"{', '.join(fmt(x, 1) for x in offline['growth_mb'])} |",
        f"| sustained growth MB per run ({LEVEL_S:g} s medians) | "
        f"{', '.join(fmt(x, 1) for x in causal.get('sustained_growth_mb', []))} | "
        f"{', '.join(fmt(x, 1) for x in offline.get('sustained_growth_mb', []))} |",
        f"| peak RSS MB per run | {', '.join(fmt(r['memory']['peak_mb'], 0) for r in causal['runs'])} | "
        f"{', '.join(fmt(r['memory']['peak_mb'], 0) for r in offline['runs'])} |",
        f"| spool MB (`summary.json`) | - | {', '.join(fmt(x, 1) for x in spool)} |",
        f"| recording MB (all parts) | {_recording(causal)} | {_recording(offline)} |",
        "",
        f"- **Offline / causal wall time: {fmt(long['ratio_offline_over_causal'])}x** (median / median; "
        f"target <= {MAX_RATIO:g}x): {_verdict(verdicts.get('time_ratio'))}.",
        f"- **Offline RSS growth: {fmt(offline['growth_max_mb'], 1)} MB** (the largest of its runs; target < "
        f"{MAX_GROWTH_MB:g} MB): {_verdict(verdicts.get('offline_growth'))}; causal: "
        f"{fmt(causal['growth_max_mb'], 1)} MB. Sustained growth ({LEVEL_S:g} s medians, the largest of the "
        f"runs): offline {fmt(_largest(offline.get('sustained_growth_mb')), 1)} MB, causal "
        f"{fmt(_largest(causal.get('sustained_growth_mb')), 1)} MB.",
    ]
    return lines + _state_lines(causal["runs"][0], offline["runs"][0])


def _largest(values: list[float | None] | None) -> float | None:
    return max((v for v in values or [] if v is not None), default=None)


def _recording(mode: dict[str, Any]) -> str:
    return ", ".join(fmt(run.get("recording_mb"), 0) for run in mode["runs"])


def _fps(long: dict[str, Any], mode: dict[str, Any]) -> str:
    wall = mode["wall_median_s"]
    return fmt(long["frames"] / wall, 1) + " fps" if wall else "-"


def _state_lines(causal: dict[str, Any], offline: dict[str, Any]) -> list[str]:
    """Target-frames per state, summed over the targets: the causal run, the offline run's live filter
    (its ``causal_states``) and the offline answer."""
    columns = [("causal replay", causal["states"]), ("offline run: live filter", offline["causal_states"]),
               ("offline run: offline", offline["states"])]  # fmt: skip
    states = sorted({s for _, counts in columns if counts for s in counts if any(c and c.get(s) for _, c in columns)})
    lines = [
        "",
        "Target-frames per state, summed over the targets (`summary.json`; the first run of each mode):",
        "",
        "| state | " + " | ".join(name for name, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    for state in states:
        lines.append(f"| {state} | " + " | ".join(fmt((c or {}).get(state)) for _, c in columns) + " |")
    return lines


def _chessboard_lines(board: dict[str, Any], verdicts: dict[str, Any]) -> list[str]:
    """chessboard.avi: the rigid-sheet scores of both modes over each state set."""
    lines = [
        "",
        "## chessboard.avi: rigid-sheet pair consistency",
        "",
        f"`{board['command']}` (and the same with `--causal`), each `poses.csv` scored by "
        "`ar_anchor.bench.real.score_rigid_sheet` (as `../shared/tools/rigid_sheet.py`): for every pair of "
        "markers seen together in at least 10 frames, marker_a_from_marker_b per frame against the pair's mean; "
        "more than 10 deg off is a flip, the RMS of the rest measures noise.",
        "",
        "| rows | mode | marker-frames | pair-frames | pair flips (%) | rel. rotation RMS deg | "
        "rel. translation RMS mm |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in STATE_SETS:
        for mode in MODES:
            s = board[mode]["scores"][name]
            lines.append(
                f"| {name} | {mode} | {s['marker_frames']} | {s['pair_frames']} | {s['flips']} "
                f"({fmt(s['flip_pct'])} %) | {fmt(s['rel_rot_rms_deg'], 3)} | {fmt(s['rel_trans_rms_mm'], 2)} |"
            )
    lines += [
        "",
        f"States (target-frames): causal {_states_text(board['causal']['states'])}; offline "
        f"{_states_text(board['offline']['states'])}.",
        "",
        "- Offline pair flips (% of pair-frames) and relative rotation RMS <= causal's (both row sets): "
        f"{_verdict(verdicts.get('chessboard'))}.",
    ]
    return lines


def _states_text(states: dict[str, int] | None) -> str:
    return ", ".join(f"{state} {count}" for state, count in (states or {}).items() if count) or "-"


def write_offline_report(
    out_dir: Path,
    *,
    quick: bool = False,
    minutes: float | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    command: str,
) -> dict[str, Any]:
    """Run the benchmark; write ``offline.md`` and ``offline.json`` to ``out_dir``. ``minutes``: the long
    clip (default 10, ``quick`` 1; 0: chessboard.avi only); ``quick``: one run per mode, else three."""
    minutes = (1.0 if quick else 10.0) if minutes is None else minutes
    results = run_offline_benchmark(minutes=minutes, runs=1 if quick else 3, progress=progress)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "offline.json", results)
    (out_dir / "offline.md").write_text(offline_markdown(results, command))
    return results
