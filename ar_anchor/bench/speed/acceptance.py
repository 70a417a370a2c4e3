"""``ar-anchor bench speed``: issue 33's acceptance, measured as real processes with plain OpenCV in the
same run.

Parts (``--clips`` picks some; :data:`PARTS`):

``chessboard``
    chessboard.avi (real, 640x480, 18 markers; from ``$AR_ANCHOR_REALDATA``, skipped with a note when
    absent) looped losslessly (:func:`~.remux.loop_video`) to at least ``chessboard_frames`` frames. Each
    round runs ``ar-anchor replay --causal``, the same with ``--no-recording``, the default (offline)
    ``ar-anchor replay`` and the plain loop, the order rotating from round to round.
``50markers``
    The synthetic 720p 50-marker clip (:func:`~.scenes.fifty_markers_scene`) encoded to H.264: ``replay
    --causal`` and the plain loop in turns.
``1080p``
    The synthetic 1080p one-marker clip (``speed_scene("one")``, 800 frames) encoded to H.264: the same.
``startup``
    ``replay --causal --max-frames 1`` of a short 1080p one-marker clip: start to the first pose row in
    ``poses.csv``, and to the exit; ``ar-anchor --help``; ``python -c pass`` for scale.
``live``
    ``ar-anchor live --device synthetic --width 1920 --height 1080 --fps 30`` (default scene), run for
    ``live_seconds`` then interrupted, as ``ar-anchor bench run`` runs it: capture-to-pose median and p95
    from its ``summary.json``; each run beside one with ``--no-recording``, taking turns.

Every replay runs with default outputs (poses.csv, summary.json, recording.rrd) and nothing but the
options the clip needs (``--camera``, and ``--dictionary`` / ``--marker-length``). The plain loop is
:mod:`.plain_loop` with ``--subpix``: PyAV decode as the replay decodes, ``ArucoDetector`` with
``CORNER_REFINE_SUBPIX``, ``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` per marker, no outputs. Each quantity
is the median over ``repeats`` rounds; each ratio is a ratio of those medians.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from ...camera import CameraModel
from ..report import load_average, machine_info
from .live import live_run
from .processes import cli, first_pose_run, plain_run, replay_run, wall_run
from .real_clip import chessboard_files
from .remux import loop_video
from .rows import acceptance_rows, found_comparison, median, summarise_clip
from .scenes import FIFTY, FIFTY_MARKER_M, FIFTY_SIZE, MARKER_M, encode_scene, fifty_markers_scene, speed_scene

__all__ = ["DEFAULTS", "PARTS", "QUICK", "run_speed_acceptance"]

PARTS: tuple[str, ...] = ("chessboard", FIFTY, "1080p", "startup", "live")
SIZE_1080P = (1920, 1080, 1480.0)  # width, height, fx: as bench run's 1080p clip
STARTUP_FRAMES = 5
NO_RECORDING = "replay --causal --no-recording"
LIVE_FPS = 30
DEFAULTS: dict[str, Any] = {
    "chessboard_frames": 1000,
    "fifty_frames": 300,
    "one_frames": 800,
    "repeats": 3,
    "help_runs": 5,
    "live_runs": 3,
    "live_seconds": 20.0,
}
QUICK: dict[str, Any] = {
    "chessboard_frames": 300,
    "fifty_frames": 60,
    "one_frames": 120,
    "repeats": 1,
    "help_runs": 1,
    "live_runs": 1,
    "live_seconds": 8.0,
}


def run_speed_acceptance(
    parts: Sequence[str] = PARTS,
    *,
    chessboard_frames: int = DEFAULTS["chessboard_frames"],
    fifty_frames: int = DEFAULTS["fifty_frames"],
    one_frames: int = DEFAULTS["one_frames"],
    repeats: int = DEFAULTS["repeats"],
    help_runs: int = DEFAULTS["help_runs"],
    live_runs: int = DEFAULTS["live_runs"],
    live_seconds: float = DEFAULTS["live_seconds"],
    realdata: Path | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Measure the ``parts`` (of :data:`PARTS`); the results: ``meta`` (machine, versions, load, settings,
    wall time), ``notes`` (skipped parts), ``parts`` (each part's runs and medians) and ``rows`` (the
    acceptance rows, :func:`~.rows.acceptance_rows`)."""
    unknown = [p for p in parts if p not in PARTS]
    if unknown or repeats < 1:
        raise ValueError(f"unknown speed part {unknown[0]!r} (any of {', '.join(PARTS)})" if unknown else "repeats < 1")
    meta = {**machine_info(), **_versions()}
    settings = {
        "parts": list(parts),
        "chessboard_frames": chessboard_frames,
        "fifty_frames": fifty_frames,
        "one_frames": one_frames,
        "repeats": repeats,
        "help_runs": help_runs,
        "live_runs": live_runs,
        "live_seconds": live_seconds,
    }
    steps = _Steps(parts, repeats, help_runs, live_runs, progress)
    notes: list[str] = []
    results: dict[str, Any] = {}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ar_anchor_speed_") as name:
        tmp = Path(name)
        if "chessboard" in parts:
            results["chessboard"] = _chessboard(tmp, chessboard_frames, repeats, realdata, steps)
            if "skipped" in results["chessboard"]:
                notes.append(results["chessboard"]["skipped"])
        if FIFTY in parts:
            results[FIFTY] = _fifty(tmp, fifty_frames, repeats, steps)
        if "1080p" in parts:
            results["1080p"] = _one_1080p(tmp, one_frames, repeats, steps)
        if "startup" in parts:
            results["startup"] = _startup(tmp, repeats, help_runs, steps)
        if "live" in parts:
            results["live"] = _live(tmp, live_runs, live_seconds, steps)
    meta["wall_time_s"] = time.perf_counter() - start
    meta["load_average_end"] = load_average()
    return {"meta": {**meta, **settings}, "notes": notes, "parts": results, "rows": acceptance_rows(results)}


def _versions() -> dict[str, str | None]:
    """rerun-sdk's and PyAV's versions, from the installed packages (neither is imported here)."""
    out: dict[str, str | None] = {}
    for key, package in (("rerun", "rerun-sdk"), ("pyav", "av")):
        try:
            out[key] = metadata.version(package)
        except metadata.PackageNotFoundError:
            out[key] = None
    return out


class _Steps:
    """Progress reports numbered from 0 of the run's known total."""

    def __init__(
        self,
        parts: Sequence[str],
        repeats: int,
        help_runs: int,
        live_runs: int,
        progress: Callable[[int, int, str], None] | None,
    ) -> None:
        per_part = {
            "chessboard": 1 + 4 * repeats,
            FIFTY: 1 + 2 * repeats,
            "1080p": 1 + 2 * repeats,
            "startup": 2 + repeats,
            "live": 2 * live_runs,
        }
        self.total = sum(per_part[p] for p in parts)
        self.progress, self.done = progress, 0

    def __call__(self, name: str) -> None:
        if self.progress is not None:
            self.progress(min(self.done, self.total - 1), self.total, name)
        self.done += 1


def _rounds(
    label: str,
    runs: dict[str, Callable[[int], dict[str, Any]]],
    repeats: int,
    step: Callable[[str], None],
) -> dict[str, list[dict[str, Any]]]:
    """``repeats`` rounds of every run in ``runs`` (name -> run of round i), the order rotating by one each
    round (round 0: as given; round 1: from the second; ...); each name's runs in round order."""
    names = list(runs)
    out: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    for index in range(repeats):
        for offset in range(len(names)):
            name = names[(index + offset) % len(names)]
            step(f"{label}: {name} {index + 1} of {repeats}")
            out[name].append(runs[name](index))
    return out


def _clip_part(
    label: str,
    video: Path,
    replay_args: list[str],
    plain_args: tuple[Path, str, float],
    repeats: int,
    tmp: Path,
    step: Callable[[str], None],
    *,
    offline: bool,
    no_recording: bool = False,
) -> dict[str, Any]:
    """A clip's rounds (``replay --causal``, the same with ``--no-recording`` when ``no_recording``, the
    offline replay when ``offline``, the plain loop), the per-frame marker comparison of each round, the
    medians and the ratios."""
    slug = video.stem
    runs: dict[str, Callable[[int], dict[str, Any]]] = {
        "replay --causal": lambda i: replay_run(video, replay_args, tmp / f"{slug}_causal_{i}", causal=True),
    }
    if no_recording:
        runs[NO_RECORDING] = lambda i: replay_run(
            video, [*replay_args, "--no-recording"], tmp / f"{slug}_norec_{i}", causal=True
        )
    if offline:
        runs["replay (offline)"] = lambda i: replay_run(video, replay_args, tmp / f"{slug}_offline_{i}", causal=False)
    runs["plain loop"] = lambda i: plain_run(video, *plain_args)
    done = _rounds(label, runs, repeats, step)
    causal, plain = done["replay --causal"], done["plain loop"]
    found = [found_comparison(c.pop("_measured"), p["_ids"]) for c, p in zip(causal, plain)]
    for run in [*done.get("replay (offline)", []), *done.get(NO_RECORDING, [])]:
        run.pop("_measured")
    same_ids = all(p["_ids"] == plain[0]["_ids"] for p in plain)
    for run in plain:
        run.pop("_ids")
    part: dict[str, Any] = {
        "label": label,
        "frames": causal[0]["frames"],
        "video_mb": video.stat().st_size / 1e6,
        "replay_args": replay_args,
        "causal": causal,
        "plain": plain,
        "found": max(found, key=lambda f: f["frames_fewer"]),  # the round where the tracker fell shortest
        "found_fewer_per_round": [f["frames_fewer"] for f in found],
        "plain_ids_same_every_round": same_ids,
    }
    if offline:
        part["offline"] = done["replay (offline)"]
    if no_recording:
        part["causal_no_recording"] = done[NO_RECORDING]
    part["summary"] = summarise_clip(part)
    return part


def _chessboard(
    tmp: Path, min_frames: int, repeats: int, realdata: Path | None, step: Callable[[str], None]
) -> dict[str, Any]:
    """chessboard.avi looped to ``min_frames``: causal, offline and plain runs; or the skip note."""
    files = chessboard_files(realdata)
    if isinstance(files, str):
        return {"skipped": files.replace("chessboard clip skipped", "chessboard part skipped")}
    video, camera_file = files
    step(f"chessboard.avi looped to >= {min_frames} frames (packets copied)")
    looped = tmp / "chessboard_loop.avi"
    frames = loop_video(video, looped, min_frames)
    args = ["--camera", str(camera_file), "--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034"]
    part = _clip_part(
        f"chessboard.avi x{frames // 149 if frames % 149 == 0 else '?'} ({frames} frames, 640x480)",
        looped,
        args,
        (camera_file, "DICT_ARUCO_ORIGINAL", 0.034),
        repeats,
        tmp,
        step,
        offline=True,
        no_recording=True,
    )
    return {**part, "source": str(video), "looped_frames": frames}


def _encoded(tmp: Path, name: str, camera: CameraModel, scene: Any) -> tuple[Path, Path]:
    """The scene rendered and encoded to H.264 (CRF 18, as ``bench run`` encodes its clips) and its camera."""
    video, camera_file = tmp / f"{name}.mp4", tmp / f"{name}.yml"
    encode_scene(video, scene)
    camera.to_yaml(camera_file)
    return video, camera_file


def _fifty(tmp: Path, frames: int, repeats: int, step: Callable[[str], None]) -> dict[str, Any]:
    width, height, fx = FIFTY_SIZE
    camera = CameraModel.from_fov(width, height, fx)
    step(f"720p 50 markers: rendering and encoding {frames} frames")
    video, camera_file = _encoded(tmp, "fifty_720p", camera, fifty_markers_scene(camera, frames))
    length = f"{FIFTY_MARKER_M:g}"
    return _clip_part(
        f"720p 50 markers (synthetic, H.264, {frames} frames)",
        video,
        ["--camera", str(camera_file), "--marker-length", length],
        (camera_file, "DICT_4X4_50", FIFTY_MARKER_M),
        repeats,
        tmp,
        step,
        offline=False,
    )


def _camera_1080p() -> CameraModel:
    width, height, fx = SIZE_1080P
    return CameraModel.from_fov(width, height, fx)


def _one_1080p(tmp: Path, frames: int, repeats: int, step: Callable[[str], None]) -> dict[str, Any]:
    camera = _camera_1080p()
    step(f"1080p one marker: rendering and encoding {frames} frames")
    video, camera_file = _encoded(tmp, "one_1080p", camera, speed_scene("one", camera, frames))
    return _clip_part(
        f"1080p one marker (synthetic, H.264, {frames} frames)",
        video,
        ["--camera", str(camera_file), "--marker-length", f"{MARKER_M:g}"],
        (camera_file, "DICT_4X4_50", MARKER_M),
        repeats,
        tmp,
        step,
        offline=False,
    )


def _startup(tmp: Path, repeats: int, help_runs: int, step: Callable[[str], None]) -> dict[str, Any]:
    """Start to the first pose and to the exit of ``replay --causal --max-frames 1`` (``repeats`` runs), then
    ``--help`` and ``python -c pass`` (``help_runs`` runs each, taking turns)."""
    import sys

    camera = _camera_1080p()
    step(f"start-up: a {STARTUP_FRAMES}-frame 1080p one-marker clip")
    video, camera_file = _encoded(tmp, "startup_1080p", camera, speed_scene("one", camera, STARTUP_FRAMES))
    args = ["--camera", str(camera_file), "--marker-length", f"{MARKER_M:g}"]
    firsts = []
    for index in range(repeats):
        step(f"start-up: replay --max-frames 1, {index + 1} of {repeats}")
        firsts.append(first_pose_run(video, args, tmp / f"startup_{index}"))
    step(f"start-up: ar-anchor --help and python -c pass, {help_runs} each")
    helps, pythons = [], []
    for _ in range(help_runs):
        helps.append(wall_run(cli("--help"), "ar-anchor --help"))
        pythons.append(wall_run([sys.executable, "-c", "pass"], "python -c pass"))
    return {
        "label": "1080p one marker, 5-frame H.264 clip",
        "command": "ar-anchor replay clip.mp4 --camera clip.yml --marker-length 0.05 --causal --max-frames 1",
        "runs": firsts,
        "help_s": helps,
        "python_s": pythons,
        "summary": {
            "first_pose_s": median(r["first_pose_s"] for r in firsts),
            "exit_s": median(r["exit_s"] for r in firsts),
            "help_s": median(helps),
            "python_s": median(pythons),
        },
    }


def _live(tmp: Path, runs: int, seconds: float, step: Callable[[str], None]) -> dict[str, Any]:
    """``runs`` live synthetic 1080p runs of ``seconds`` each (``bench run``'s live run, the default scene),
    each beside one with ``--no-recording`` (taking turns: which goes first alternates)."""
    done: list[dict[str, Any]] = []
    bare: list[dict[str, Any]] = []
    for index in range(runs):
        order = [False, True] if index % 2 == 0 else [True, False]
        for without in order:
            label = " --no-recording" if without else ""
            step(f"live --device synthetic 1920x1080{label}, {seconds:g} s, {index + 1} of {runs}")
            extra = ("--no-recording",) if without else ()
            run = live_run(tmp, seconds, f"live_{'norec_' if without else ''}{index}", extra=extra)
            run.pop("rss_mb", None)
            (bare if without else done).append(run)

    def stage(run: dict[str, Any], key: str) -> float | None:
        value = run["stages"].get("capture_to_pose", {}).get(key)
        return None if value is None else float(value)

    return {
        "label": "live synthetic 1920x1080 @ 30 fps, default scene (7 targets)",
        "command": f"ar-anchor live --device synthetic --width 1920 --height 1080 --fps {LIVE_FPS}",
        "seconds": seconds,
        "runs": done,
        "runs_no_recording": bare,
        "summary": {
            "capture_to_pose_median_ms": median(stage(r, "median") for r in done),
            "capture_to_pose_p95_ms": median(stage(r, "p95") for r in done),
            "fps": median(r["fps"] for r in done),
            "dropped_queue": median(r["live"].get("dropped_queue") for r in done),
            "no_recording_median_ms": median(stage(r, "median") for r in bare),
            "no_recording_p95_ms": median(stage(r, "p95") for r in bare),
            "frames_not_logged": median(r.get("frames_not_logged") for r in done),
        },
    }
