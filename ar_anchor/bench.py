"""Benchmarks on synthetic ground truth: ``ar-anchor bench stability``.

Every scenario is rendered once and tracked once; each frame's result carries both the raw
per-frame solution (``raw``, the lower-error IPPE solution) and the tracker's output (``pose``),
so the two pipelines are compared on the very same frames.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .camera import CameraModel
from .config import BoardConfig, TrackerConfig
from .geometry import Pose, angle_between_deg, pose_errors
from .sources.synthetic import PlacedBoard, PlacedMarker, SyntheticScene, SyntheticSource, Trajectory
from .tracker import Tracker

__all__ = ["Scenario", "ScenarioRun", "evaluate", "run_scenario", "stability_scenarios", "write_stability_report"]

FLIP_DEG = 10.0
SETTLE_FRAMES = 30  # jitter is measured after the first second (the filter's convergence), for both pipelines


@dataclass(frozen=True)
class Scenario:
    """One synthetic clip: a lone marker seen by a static or moving camera."""

    name: str
    marker_m: float
    distance_m: float
    motion: str = "static"  # static | wobble | orbit | fast | sweep
    tilt_deg: float = 0.0
    noise: float = 2.0
    blur: float = 0.6
    frames: int = 150
    far_m: float | None = None  # sweep: the far end
    hidden: tuple[tuple[int, int], ...] = ()
    seed: int = 0

    @property
    def moving(self) -> bool:
        return self.motion != "static"

    def trajectory(self) -> Trajectory:
        seconds = self.frames / 30.0
        if self.motion == "static":
            return Trajectory(
                kind="static", near_m=self.distance_m, azimuth_deg=self.tilt_deg, elevation_deg=0.0, roll_deg=0.0
            )
        if self.motion == "wobble":  # nearly fronto-parallel, small hand-held motion
            return Trajectory(
                kind="orbit",
                near_m=self.distance_m,
                azimuth_deg=self.tilt_deg + 4.0,
                elevation_deg=3.0,
                roll_deg=2.0,
                cycles=1.0,
            )
        if self.motion == "orbit":  # about 45 deg/s at the peak
            return Trajectory(
                kind="orbit",
                near_m=self.distance_m,
                azimuth_deg=35.0,
                elevation_deg=15.0,
                roll_deg=10.0,
                cycles=seconds * 45.0 / (2 * math.pi * 35.0),
            )
        if self.motion == "fast":  # 90 deg/s at the peak
            return Trajectory(
                kind="orbit",
                near_m=self.distance_m,
                azimuth_deg=45.0,
                elevation_deg=5.0,
                roll_deg=0.0,
                cycles=seconds * 90.0 / (2 * math.pi * 45.0),
            )
        if self.motion == "sweep":
            return Trajectory(
                kind="sweep",
                near_m=self.distance_m,
                far_m=self.far_m or self.distance_m * 4,
                azimuth_deg=30.0,
                elevation_deg=15.0,
                roll_deg=10.0,
                cycles=1.0,
            )
        raise ValueError(f"unknown motion {self.motion!r}")

    def scene(self, camera: CameraModel, dictionary: str = "DICT_4X4_50") -> SyntheticScene:
        return SyntheticScene(
            camera=camera,
            dictionary=dictionary,
            markers=(PlacedMarker(0, self.marker_m, Pose.identity()),),
            trajectory=self.trajectory(),
            frames=self.frames,
            seed=self.seed,
            noise_sigma=self.noise,
            blur_sigma=self.blur,
            hidden=self.hidden,
        )


@dataclass
class ScenarioRun:
    """Per-frame records of one scenario (NaN / None where there is nothing)."""

    scenario: Scenario
    truth: list[Pose | None] = field(default_factory=list)
    raw: list[Pose | None] = field(default_factory=list)
    output: list[Pose | None] = field(default_factory=list)
    state: list[str] = field(default_factory=list)  # "" when no output
    delta_px: list[float] = field(default_factory=list)  # worse - better IPPE reprojection error
    track_ms: list[float] = field(default_factory=list)


def run_scenario(scenario: Scenario, config: TrackerConfig, camera: CameraModel) -> ScenarioRun:
    """Render and track a scenario with ``config`` (its filter on)."""
    source = SyntheticSource(scenario.scene(camera, config.detector.dictionary))
    config = config.with_overrides(marker_length_m=scenario.marker_m, filter_enabled=True)
    config = dataclasses.replace(config, markers=dataclasses.replace(config.markers, lengths_m={}))
    tracker = Tracker(config, camera)
    run = ScenarioRun(scenario)
    for frame in source:
        start = time.perf_counter()
        result = tracker.process(frame)
        run.track_ms.append((time.perf_counter() - start) * 1e3)
        target = result.targets.get("marker:0")
        run.truth.append((frame.truth or {}).get("marker:0"))
        run.raw.append(target.raw if target is not None else None)
        run.output.append(target.pose if target is not None else None)
        run.state.append(target.state if target is not None else "")
        hyps = target.hypotheses if target is not None else ()
        run.delta_px.append(hyps[1].reproj_px - hyps[0].reproj_px if len(hyps) == 2 else math.nan)
    return run


def _mean_rotation(rotations: Sequence[np.ndarray]) -> np.ndarray:
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    mean = u @ vt
    if np.linalg.det(mean) < 0:
        mean = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return mean


def _series_metrics(poses: list[Pose | None], truth: list[Pose | None], moving: bool) -> dict[str, Any]:
    pairs = [(p, t) for p, t in zip(poses, truth) if p is not None and t is not None]
    if not pairs:
        return {"frames": 0}
    rot, trans = np.array([pose_errors(p, t) for p, t in pairs]).T
    out: dict[str, Any] = {
        "frames": len(pairs),
        "flipped_pct": 100.0 * float(np.mean(rot > FLIP_DEG)),
        "rot_median_deg": float(np.median(rot)),
        "rot_p95_deg": float(np.percentile(rot, 95)),
        "trans_median_pct": float(np.median(trans)),
    }
    twitches = sum(
        1
        for a, b in zip(poses, poses[1:])
        if a is not None
        and b is not None
        and angle_between_deg(a.rotation, b.rotation) > FLIP_DEG
        and np.linalg.norm(a.tvec - b.tvec) < 0.01
    )
    out["twitches"] = twitches
    settled = [p for p in poses[SETTLE_FRAMES:] if p is not None]
    if not moving and len(settled) > 1:
        mean = _mean_rotation([p.rotation for p in settled])
        out["jitter_deg"] = float(np.sqrt(np.mean([angle_between_deg(p.rotation, mean) ** 2 for p in settled])))
    if moving:
        lags = []
        for lag in range(0, 7):
            errors = [
                angle_between_deg(poses[i].rotation, truth[i - lag].rotation)
                for i in range(lag, len(poses))
                if poses[i] is not None and truth[i - lag] is not None
            ]
            lags.append(float(np.median(errors)) if errors else math.inf)
        out["lag_frames"] = int(np.argmin(lags))
    return out


def evaluate(run: ScenarioRun, config: TrackerConfig | None = None) -> dict[str, Any]:
    """Metrics of the raw pipeline and of the tracker on one scenario."""
    config = config or TrackerConfig()
    moving = run.scenario.moving
    result: dict[str, Any] = {
        "scenario": dataclasses.asdict(run.scenario),
        "raw": _series_metrics(run.raw, run.truth, moving),
        "tracker": _series_metrics(run.output, run.truth, moving),
    }
    states = [s for s in run.state if s]
    errors = [
        angle_between_deg(p.rotation, t.rotation) if p is not None and t is not None else math.nan
        for p, t in zip(run.output, run.truth)
    ]
    tracked_errors = [e for e, s in zip(errors, run.state) if s == "tracked" and math.isfinite(e)]
    first_output = next((i for i, s in enumerate(run.state) if s), None)
    first_tracked = next((i for i, s in enumerate(run.state) if s == "tracked"), None)
    deltas = np.array([d for d in run.delta_px if math.isfinite(d)])
    result["tracker"].update(
        {
            "tracked_pct": 100.0 * states.count("tracked") / len(states) if states else 0.0,
            "ambiguous_pct": 100.0 * states.count("ambiguous") / len(states) if states else 0.0,
            "predicted_pct": 100.0 * states.count("predicted") / len(states) if states else 0.0,
            "wrong_tracked_pct": 100.0 * float(np.mean(np.array(tracked_errors) > FLIP_DEG)) if tracked_errors else 0.0,
            "frames_to_commit": None if first_tracked is None or first_output is None else first_tracked - first_output,
            "track_ms_median": float(np.median(run.track_ms)) if run.track_ms else None,
        }
    )
    result["detected_pct"] = 100.0 * sum(p is not None for p in run.raw) / max(len(run.raw), 1)
    result["delta_median_px"] = float(np.median(deltas)) if deltas.size else None
    result["delta_p90_px"] = float(np.percentile(deltas, 90)) if deltas.size else None
    # decidable: the wrong solution at some point reprojects worse than the margin, or fails validation
    # outright (then there is only one solution: no delta at all)
    measured = [d for d, s in zip(run.delta_px, run.state) if s and s != "predicted"]
    single = sum(1 for d in measured if not math.isfinite(d))
    result["decidable"] = bool(
        deltas.size == 0
        or np.percentile(deltas, 90) > config.filter.decide_margin_px
        or single > 0.1 * max(len(measured), 1)
    )
    return result


def stability_scenarios(quick: bool = False) -> list[Scenario]:
    """The benchmark grid: sizes 3-12 cm, 0.3-4 m, tilts down to fronto-parallel, static and moving, noise, dropouts."""
    frames = 90 if quick else 150
    grid = [
        Scenario("static 12cm 0.5m tilt30", 0.12, 0.5, "static", tilt_deg=30, frames=frames),
        Scenario("static 6cm 1m tilt20", 0.06, 1.0, "static", tilt_deg=20, frames=frames),
        Scenario("static 6cm 1m fronto", 0.06, 1.0, "static", tilt_deg=0, frames=frames),
        Scenario("static 4cm 3m tilt15", 0.04, 3.0, "static", tilt_deg=15, frames=frames),
        Scenario("static 4cm 3.5m fronto", 0.04, 3.5, "static", tilt_deg=0, frames=frames),
        Scenario("static 12cm 4m tilt20", 0.12, 4.0, "static", tilt_deg=20, frames=frames),
        Scenario("static 3cm 0.3m tilt40 noise4", 0.03, 0.3, "static", tilt_deg=40, noise=4.0, frames=frames),
        Scenario("wobble 5cm 0.6m fronto", 0.05, 0.6, "wobble", frames=frames),
        Scenario("wobble 4cm 2m fronto", 0.04, 2.0, "wobble", frames=frames),
        Scenario("orbit 6cm 1m", 0.06, 1.0, "orbit", frames=frames),
        Scenario("orbit 4cm 2m", 0.04, 2.0, "orbit", frames=frames),
        Scenario("fast 8cm 0.8m 90deg/s", 0.08, 0.8, "fast", frames=frames),
        Scenario("sweep 6cm 0.4-3m", 0.06, 0.4, "sweep", far_m=3.0, frames=frames),
        Scenario(
            "orbit 6cm 1m dropouts",
            0.06,
            1.0,
            "orbit",
            frames=frames,
            hidden=((frames // 3, frames // 3 + 6), (2 * frames // 3, 2 * frames // 3 + 20)),
        ),
    ]
    return grid[::2] if quick else grid


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def stability_table(results: list[dict[str, Any]]) -> str:
    """Markdown table: raw vs tracker per scenario."""
    header = (
        "| scenario | det % | Δ median px | flipped % raw / trk | rot med deg raw / trk | rot p95 deg raw / trk "
        "| trans med % raw / trk | jitter deg raw / trk | lag frames raw / trk | twitches raw / trk "
        "| tracked / ambiguous / predicted % | wrong tracked % | frames to commit |"
    )
    lines = [header, "|" + "|".join(["---"] * 13) + "|"]
    for r in results:
        raw, trk = r["raw"], r["tracker"]

        def pair(key: str, digits: int = 2, raw: dict = raw, trk: dict = trk) -> str:
            return f"{_fmt(raw.get(key), digits)} / {_fmt(trk.get(key), digits)}"

        states = " / ".join(_fmt(trk.get(k), 0) for k in ("tracked_pct", "ambiguous_pct", "predicted_pct"))
        name = r["scenario"]["name"] + ("" if r["decidable"] else " (undecidable)")
        lines.append(
            f"| {name} | {_fmt(r['detected_pct'], 0)} | {_fmt(r['delta_median_px'], 3)} | {pair('flipped_pct', 1)} "
            f"| {pair('rot_median_deg')} | {pair('rot_p95_deg', 1)} | {pair('trans_median_pct')} "
            f"| {pair('jitter_deg', 3)} | {pair('lag_frames', 0)} | {pair('twitches', 0)} "
            f"| {states} "
            f"| {_fmt(trk.get('wrong_tracked_pct'), 1)} | {_fmt(trk.get('frames_to_commit'), 0)} |"
        )
    return "\n".join(lines)


def write_stability_report(
    out_dir: Path,
    *,
    quick: bool = False,
    config: TrackerConfig | None = None,
    camera: CameraModel | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench stability",
) -> list[dict[str, Any]]:
    """Run the grid, write ``stability.md`` and ``stability.json`` to ``out_dir``, return the results."""
    config = config or TrackerConfig()
    camera = camera or CameraModel.default_synthetic()
    scenarios = stability_scenarios(quick)
    results = []
    start = time.perf_counter()
    for i, scenario in enumerate(scenarios):
        if progress is not None:
            progress(i, len(scenarios), scenario.name)
        results.append(evaluate(run_scenario(scenario, config, camera), config))
    wall = time.perf_counter() - start
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": command,
        "wall_time_s": wall,
        "camera": f"{camera.width}x{camera.height} fx={camera.camera_matrix[0, 0]:g}",
        "python": platform.python_version(),
        "machine": platform.machine(),
        "frames_per_scenario": scenarios[0].frames,
    }
    (out_dir / "stability.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2) + "\n")
    text = [
        "# Stability benchmark: raw per-frame IPPE vs. the tracker",
        "",
        f"Produced by `{command}` in {wall:.0f} s ({meta['camera']}, 30 fps, {meta['frames_per_scenario']} frames "
        "per scenario, sensor noise 2 grey levels unless stated, blur 0.6 px).",
        "",
        "*flipped*: frames whose rotation error exceeds 10 deg. *Δ*: how much worse the wrong IPPE solution "
        "reprojects (px, median over frames); a scenario is *undecidable* when even its 90th percentile stays "
        "below the filter's decision margin (corner-detector bias level), so no amount of evidence can decide: "
        "the tracker then says `ambiguous` and holds its best guess. *jitter*: RMS orientation around the mean "
        "(static scenes, after the first second, for both pipelines). *lag*: shift in frames that best aligns "
        "output with truth (moving scenes). "
        "*twitches*: consecutive outputs more than 10 deg apart with less than 1 cm of motion.",
        "",
        stability_table(results),
        "",
    ]
    (out_dir / "stability.md").write_text("\n".join(text))
    return results


# ---------------------------------------------------------------------------- boards vs a lone marker

BOARD_DISTANCES_M = (2.5, 3.0, 3.5, 4.0)


def _board_vs_marker_scene(camera: CameraModel, distance_m: float, tilt_deg: float, frames: int) -> SyntheticScene:
    """A lone 4 cm marker (id 0) beside a 2x2 grid board of the same 4 cm markers (ids 10-13, 4 cm
    gaps: a 12 cm board), both seen by one static camera: the same frames for both."""
    board = BoardConfig(name="grid2x2", cols=2, rows=2, marker_length_m=0.04, separation_m=0.04, first_id=10)
    flip_yz = np.diag([1.0, -1.0, -1.0])  # board frame: y down, z into the wall
    return SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(0, 0.04, Pose(np.zeros(3), np.array([-0.09, 0.0, 0.0]))),),
        boards=(PlacedBoard(board, Pose.from_matrix(flip_yz, np.array([-0.02, 0.06, 0.0]))),),
        trajectory=Trajectory(kind="static", near_m=distance_m, azimuth_deg=tilt_deg, elevation_deg=5.0, roll_deg=0.0),
        frames=frames,
        seed=int(distance_m * 10),
        noise_sigma=2.0,
        blur_sigma=0.6,
    )


def run_board_comparison(
    config: TrackerConfig, camera: CameraModel, distance_m: float, tilt_deg: float = 15.0, frames: int = 150
) -> dict[str, Any]:
    """Track the lone-marker-plus-board scene; metrics of the marker (raw) and of the board (raw and tracked)."""
    scene = _board_vs_marker_scene(camera, distance_m, tilt_deg, frames)
    config = dataclasses.replace(
        config,
        detector=dataclasses.replace(config.detector, dictionary=scene.dictionary),
        markers=dataclasses.replace(config.markers, length_m=0.04, lengths_m={}, ids=(0,)),
        boards=tuple(b.board for b in scene.boards),
        filter=dataclasses.replace(config.filter, enabled=True),
    )
    tracker = Tracker(config, camera)
    series: dict[str, dict[str, list[Pose | None]]] = {
        name: {"raw": [], "output": [], "truth": []} for name in ("marker:0", "board:grid2x2")
    }
    states: list[str] = []
    for frame in SyntheticSource(scene):
        result = tracker.process(frame)
        for name, data in series.items():
            target = result.targets.get(name)
            data["raw"].append(target.raw if target is not None else None)
            data["output"].append(target.pose if target is not None else None)
            data["truth"].append((frame.truth or {}).get(name))
        board = result.targets.get("board:grid2x2")
        states.append(board.state if board is not None else "")
    marker, board = series["marker:0"], series["board:grid2x2"]
    out = {
        "distance_m": distance_m,
        "tilt_deg": tilt_deg,
        "frames": frames,
        "marker_raw": _series_metrics(marker["raw"], marker["truth"], moving=False),
        "marker_tracked": _series_metrics(marker["output"], marker["truth"], moving=False),
        "board_raw": _series_metrics(board["raw"], board["truth"], moving=False),
        "board_tracked": _series_metrics(board["output"], board["truth"], moving=False),
        "board_tracked_pct": 100.0 * states.count("tracked") / max(len(states), 1),
    }
    jitter_marker = out["marker_raw"].get("jitter_deg", math.nan)
    jitter_board = out["board_tracked"].get("jitter_deg", math.nan)
    out["jitter_ratio"] = jitter_marker / jitter_board if jitter_board and jitter_board > 0 else math.nan
    return out


def write_board_report(
    out_dir: Path,
    *,
    config: TrackerConfig | None = None,
    camera: CameraModel | None = None,
    frames: int = 150,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench boards",
) -> list[dict[str, Any]]:
    """Lone 4 cm marker vs a 2x2 board of 4 cm markers at 2.5-4 m: ``boards.md`` and ``boards.json``."""
    config = config or TrackerConfig()
    # a 1080p camera (66 deg across): a 4 cm marker is 15 px wide at 4 m; the detector is told to look
    # for markers that small (min_perimeter_rate), as a user tracking far markers would
    camera = camera or CameraModel.from_fov(1920, 1080, 1480.0)
    config = dataclasses.replace(config, detector=dataclasses.replace(config.detector, min_perimeter_rate=0.02))
    start = time.perf_counter()
    results = []
    for i, distance in enumerate(BOARD_DISTANCES_M):
        if progress is not None:
            progress(i, len(BOARD_DISTANCES_M), f"{distance:g} m")
        results.append(run_board_comparison(config, camera, distance, frames=frames))
    wall = time.perf_counter() - start
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": command,
        "wall_time_s": wall,
        "camera": f"{camera.width}x{camera.height} fx={camera.camera_matrix[0, 0]:g}",
        "frames_per_distance": frames,
    }
    (out_dir / "boards.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2) + "\n")
    lines = [
        "# Boards vs a lone marker: the same frames",
        "",
        f"Produced by `{command}` in {wall:.0f} s ({meta['camera']}, detector min_perimeter_rate 0.02, "
        f"30 fps, {frames} frames per distance, static camera 15 deg off-axis, sensor noise 2 grey levels, "
        "blur 0.6 px). One scene holds a lone 4 cm marker and a 2x2 grid board of 4 cm markers (4 cm gaps, "
        "12 cm across) side by side, so both are measured on the same frames.",
        "",
        "*jitter*: RMS orientation around the mean after the first second. *flipped*: frames more than 10 deg "
        "off the truth. *ratio*: lone marker raw jitter / board tracked jitter (target: >= 10).",
        "",
        "| distance | marker det % | marker raw jitter deg | marker raw flipped % | board raw jitter deg "
        "| board tracked jitter deg | ratio | board flipped % raw / trk | board rot med deg | board tracked % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        mr, br, bt = r["marker_raw"], r["board_raw"], r["board_tracked"]
        lines.append(
            f"| {r['distance_m']:g} m | {_fmt(100.0 * mr.get('frames', 0) / r['frames'], 0)} "
            f"| {_fmt(mr.get('jitter_deg'), 3)} | {_fmt(mr.get('flipped_pct'), 1)} | {_fmt(br.get('jitter_deg'), 3)} "
            f"| {_fmt(bt.get('jitter_deg'), 3)} | {_fmt(r['jitter_ratio'], 1)} "
            f"| {_fmt(br.get('flipped_pct'), 1)} / {_fmt(bt.get('flipped_pct'), 1)} | {_fmt(bt.get('rot_median_deg'))} "
            f"| {_fmt(r['board_tracked_pct'], 0)} |"
        )
    (out_dir / "boards.md").write_text("\n".join(lines) + "\n")
    return results


# ---------------------------------------------------------------------------- overlay rendering cost

OVERLAY_TRIANGLES = (12, 368, 1_280, 5_120, 20_480)


def _sphere_mesh_file(directory: Path, triangles: int) -> Path:
    """An icosphere of about ``triangles`` faces (20 * 4^k), as a PLY file for the mesh overlay."""
    import trimesh  # noqa: PLC0415

    subdivisions = max(0, round(math.log(max(triangles, 20) / 20, 4)))
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    path = directory / f"sphere_{len(mesh.faces)}.ply"
    mesh.export(path)
    return path


def run_overlay_benchmark(frames: int = 60, progress: Callable[[int, int, str], None] | None = None) -> list[dict]:
    """Median ``OverlayRenderer.annotate`` time per frame: one model of a given size on one marker,
    seen from 0.5 m so it covers about a fifth of the frame's height, at 720p and 1080p."""
    import tempfile  # noqa: PLC0415

    from .config import OverlayConfig  # noqa: PLC0415
    from .detection import MarkerDetections  # noqa: PLC0415
    from .overlay import OverlayRenderer  # noqa: PLC0415
    from .tracker import FrameResult, TargetResult  # noqa: PLC0415

    rows = []
    sizes = [(1280, 720, 1000.0), (1920, 1080, 1480.0)]
    cases = [("cube", 12), *[("mesh", n) for n in OVERLAY_TRIANGLES[1:]]]
    with tempfile.TemporaryDirectory() as tmp:
        for i, (kind, triangles) in enumerate(cases):
            if progress is not None:
                progress(i, len(cases), f"{kind} {triangles}")
            path = "" if kind == "cube" else str(_sphere_mesh_file(Path(tmp), triangles))
            overlay = OverlayConfig(target="marker:0", kind=kind, path=path, size_m=0.1)
            config = dataclasses.replace(TrackerConfig(), overlays=(overlay,))
            row: dict[str, Any] = {"model": kind, "triangles": 12 if kind == "cube" else None}
            for width, height, focal in sizes:
                camera = CameraModel.from_fov(width, height, focal)
                renderer = OverlayRenderer(config, camera)
                if kind == "mesh":
                    row["triangles"] = int(len(renderer._meshes[path].faces))
                image = np.full((height, width, 3), 128, np.uint8)
                times = []
                for k in range(frames):
                    angle = 2 * math.pi * k / frames
                    pose = Pose(
                        np.array([math.pi + 0.4 * math.cos(angle), 0.4 * math.sin(angle), 0.0]), np.array([0, 0, 0.5])
                    )
                    target = TargetResult("marker:0", "tracked", pose, pose, 0.1, 3.0, 0.05)
                    result = FrameResult(k, 0, MarkerDetections.empty(), {"marker:0": target}, camera=camera)
                    start = time.perf_counter()
                    renderer.annotate(image, result)
                    times.append((time.perf_counter() - start) * 1e3)
                row[f"{height}p_ms"] = float(np.median(times[5:]))
            rows.append(row)
    return rows


def write_overlay_report(
    out_dir: Path, frames: int = 60, progress=None, command: str = "ar-anchor bench overlay"
) -> list:
    start = time.perf_counter()
    rows = run_overlay_benchmark(frames, progress)
    wall = time.perf_counter() - start
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "overlay.json").write_text(json.dumps({"command": command, "rows": rows}, indent=2) + "\n")
    lines = [
        "# Overlay rendering cost",
        "",
        f"Produced by `{command}` in {wall:.0f} s: median time of `OverlayRenderer.annotate` per frame (one model "
        f"on one marker 0.5 m away, 10 cm across, turning; {frames} frames; one thread; no lens distortion).",
        "",
        "| model | triangles | 720p ms | 1080p ms |",
        "|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| {row['model']} | {row['triangles']} | {row['720p_ms']:.2f} | {row['1080p_ms']:.2f} |")
    (out_dir / "overlay.md").write_text("\n".join(lines) + "\n")
    return rows
