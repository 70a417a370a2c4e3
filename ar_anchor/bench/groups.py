"""``ar-anchor bench groups``: the lone-marker filter against learned rigid groups (issue 23), on the
hand-held webcam scenes of a 6-marker sheet (:func:`~ar_anchor.bench.stability.scenarios.handheld_scenarios`:
motion blur, rolling shutter, compression, quick turns, a hand, 5-60 fps, 2-3 m away).

Each scene is rendered once and every frame goes to three trackers: the default one (each marker tracked
alone), one with ``[groups] learn = true``, no layout given, and, for reference, one given the sheet's
exact layout as a board (each member: the board's pose composed with its place on the sheet: the joint
solve's own floor in the scene). Per member of the sheet, from the frame its group formed (the learner's
first group holding it) to the end, the trackers' outputs against truth:

* **wrong frames**: rotation error above :data:`~ar_anchor.bench.report.FLIP_DEG` (a flip), % of the frames
  with an output, and **wrong tracked**: such frames said ``tracked``;
* **jitter**: frame-to-frame change of the error (RMS over consecutive output frames), rotation (deg) and
  position (mm): the noise of the output around the truth, a slowly varying bias aside.

Acceptance (issue 23), per member: wrong-frame rate with groups <= without, 0 wrong ``tracked`` frames,
and at distance (the 2-3 m scene) jitter at least :data:`JITTER_RATIO` times lower.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import CameraModel
from ..config import BoardConfig, TrackerConfig
from ..geometry import Pose, angle_between_deg, marker_corners_in_marker
from ..sources.synthetic import SyntheticSource
from ..synthetic.scene import marker_sheet
from ..targets import TargetId
from ..track.tracker import Tracker
from .report import FLIP_DEG, fmt, load_average, machine_info, machine_lines, report_head, write_json
from .stability.scenarios import Scenario, handheld_scenarios

__all__ = [
    "FAR_SCENE",
    "JITTER_RATIO",
    "groups_markdown",
    "run_groups_benchmark",
    "run_scene",
    "scene_failures",
    "score_member",
    "write_groups_report",
]

JITTER_RATIO = 3.0
FAR_SCENE = "hh 720p far 4cm 2-3m sheet6"


def _sheet_scenes(quick: bool) -> list[Scenario]:
    scenes = [s for s in handheld_scenarios() if s.sheet]
    if quick:
        scenes = [s for s in scenes if s.name in (FAR_SCENE, "hh vga h264 sheet6 30fps")]
    return scenes


def score_member(output: list[Pose | None], truth: list[Pose | None], state: list[str], start: int) -> dict[str, Any]:
    """One member's outputs from frame ``start`` on against truth (see the module doc)."""
    rows = [(k, p, t, s) for k, (p, t, s) in enumerate(zip(output, truth, state)) if k >= start and p and t]
    if not rows:
        return {"frames": 0}
    wrong = [angle_between_deg(p.rotation, t.rotation) > FLIP_DEG for _, p, t, _ in rows]
    steps_deg, steps_mm = [], []
    for (k0, p0, t0, _), (k1, p1, t1, _) in zip(rows, rows[1:]):
        if k1 != k0 + 1:
            continue
        e0, e1 = t0.rotation.T @ p0.rotation, t1.rotation.T @ p1.rotation
        steps_deg.append(angle_between_deg(e0, e1))
        steps_mm.append(1e3 * float(np.linalg.norm((p1.tvec - t1.tvec) - (p0.tvec - t0.tvec))))
    return {
        "frames": len(rows),
        "wrong_pct": 100.0 * float(np.mean(wrong)),
        "wrong_tracked": int(sum(w and s == "tracked" for w, (_, _, _, s) in zip(wrong, rows))),
        "jitter_deg": float(np.sqrt(np.mean(np.square(steps_deg)))) if steps_deg else math.nan,
        "jitter_mm": float(np.sqrt(np.mean(np.square(steps_mm)))) if steps_mm else math.nan,
    }


def run_scene(scenario: Scenario, config: TrackerConfig, camera: CameraModel) -> dict[str, Any]:
    """One scene rendered once, every frame tracked without and with learned groups; each member scored from
    the frame it joined a group (:func:`score_member`)."""
    camera = scenario.camera_model(camera)
    lone_config = scenario.tracker_config(config)
    # the camera's rolling-shutter readout, as its user would configure it ([pose] rolling_shutter_s)
    lone_config = dataclasses.replace(
        lone_config, pose=dataclasses.replace(lone_config.pose, rolling_shutter_s=scenario.rolling_shutter_s)
    )
    group_config = dataclasses.replace(lone_config, groups=dataclasses.replace(lone_config.groups, learn=True))
    sheet_from_marker = _sheet_layout(scenario)
    board = BoardConfig(
        name="sheet",
        kind="custom",
        layout=tuple(
            (i, tuple(tuple(float(v) for v in p) for p in pose.apply(marker_corners_in_marker(scenario.marker_m))))
            for i, pose in sheet_from_marker.items()
        ),
        dictionary=lone_config.detector.dictionary,
    )
    layout_config = dataclasses.replace(lone_config, boards=(board,))
    trackers = {
        "lone": Tracker(lone_config, camera),
        "groups": Tracker(group_config, camera),
        "layout": Tracker(layout_config, camera),
    }
    names = [TargetId.marker(i) for i in scenario.marker_ids]
    series: dict[str, dict[TargetId, dict[str, list]]] = {
        v: {n: {"output": [], "truth": [], "state": []} for n in names} for v in trackers
    }
    joined: dict[TargetId, int] = {}
    started = time.perf_counter()
    for frame in SyntheticSource(scenario.scene(camera, config.detector.dictionary)):
        truth = frame.truth or {}
        for variant, tracker in trackers.items():
            result = tracker.process(frame)
            sheet = result.targets.get(TargetId.board("sheet"))
            for name in names:
                target = result.targets.get(name)
                if variant == "layout":  # each member from the exact layout's joint pose, where it has one
                    offset = sheet_from_marker[name.marker_id]
                    target = None if sheet is None else dataclasses.replace(sheet, pose=sheet.pose.compose(offset))
                series[variant][name]["output"].append(target.pose if target is not None else None)
                series[variant][name]["truth"].append(truth.get(name))
                series[variant][name]["state"].append(str(target.state) if target is not None else "")
        learner = trackers["groups"].groups
        assert learner is not None
        for marker_id in learner.member_of:
            joined.setdefault(TargetId.marker(marker_id), frame.index)
    members = {}
    for name in names:
        start = joined.get(name)
        if start is None:
            members[str(name)] = {"joined": None}
            continue
        members[str(name)] = {
            "joined": start,
            **{v: score_member(**series[v][name], start=start) for v in trackers},
        }
    return {
        "scene": scenario.name,
        "frames": scenario.frames,
        "seconds": time.perf_counter() - started,
        "members": members,
    }


def _sheet_layout(scenario: Scenario) -> dict[int, Pose]:
    """The scene's sheet: ``sheet_from_marker`` by id (:func:`~ar_anchor.synthetic.scene.marker_sheet`'s)."""
    gap = scenario.marker_m / 2 if scenario.sheet_gap_m is None else scenario.sheet_gap_m
    markers, _ = marker_sheet(scenario.marker_ids, length_m=scenario.marker_m, cols=scenario.sheet_cols, gap_m=gap)
    return {m.marker_id: m.world_from_target for m in markers}


def scene_failures(scene: dict[str, Any]) -> list[str]:
    """The acceptance failures of one scene (empty: it passes)."""
    failures = []
    joined = {name: m for name, m in scene["members"].items() if m.get("joined") is not None}
    if not joined:
        return [f"{scene['scene']}: no group formed"]
    for name, member in joined.items():
        lone, grouped = member["lone"], member["groups"]
        if grouped.get("frames", 0) == 0:
            continue
        if grouped["wrong_pct"] > lone.get("wrong_pct", 0.0) + 1e-9:
            failures.append(
                f"{scene['scene']} {name}: wrong {grouped['wrong_pct']:.2f} % > lone {lone['wrong_pct']:.2f} %"
            )
        if grouped["wrong_tracked"]:
            failures.append(f"{scene['scene']} {name}: {grouped['wrong_tracked']} wrong tracked frames")
        if scene["scene"] == FAR_SCENE:
            for unit in ("jitter_deg", "jitter_mm"):
                if not grouped[unit] * JITTER_RATIO <= lone[unit]:
                    failures.append(
                        f"{scene['scene']} {name}: {unit} {grouped[unit]:.3g} not {JITTER_RATIO:g}x below "
                        f"lone {lone[unit]:.3g}"
                    )
    return failures


def run_groups_benchmark(
    quick: bool = False, progress: Callable[[int, int, str], None] | None = None, config: TrackerConfig | None = None
) -> dict[str, Any]:
    """Every sheet scene (``quick``: the near VGA one and the far one) rendered and tracked both ways,
    scored (:func:`score_member`) and checked against the acceptance; ``progress(i, total, name)`` per scene."""
    config = config or TrackerConfig()
    camera = CameraModel.from_fov(640, 480, 500.0)
    meta = machine_info()
    scenes = []
    chosen = _sheet_scenes(quick)
    for k, scenario in enumerate(chosen, start=1):
        if progress is not None:
            progress(k - 1, len(chosen), scenario.name)
        scenes.append(run_scene(scenario, config, camera))
    failures = [f for scene in scenes for f in scene_failures(scene)]
    meta["load_average_end"] = load_average()
    return {"scenes": scenes, "failures": failures, "passed": not failures, "machine": meta, "quick": quick}


def groups_markdown(result: dict[str, Any], command: str) -> str:
    """The report: a row per scene and member, the acceptance and the machine."""
    lines = report_head(
        "Learned rigid groups: each marker alone against its learned group",
        f"Produced by `{command}` (synthetic, hand-held webcam scenes of a 6-marker sheet, no layout given).",
    )
    lines += [
        "",
        "Per member, from the frame it joined its group to the end of the clip. Jitter: RMS of the "
        "frame-to-frame change of the output's error (rotation, position). Exact layout: for reference, "
        "the sheet's true layout configured as a board, each member the board's pose composed with it "
        "(what a written layout gives: the joint solve's own floor in the scene).",
        "",
    ]
    lines += [
        "| scene | marker | joined at frame | wrong % lone / groups | wrong tracked (groups) | "
        "jitter deg lone / groups | jitter mm lone / groups | jitter deg / mm, exact layout |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scene in result["scenes"]:
        for name, member in scene["members"].items():
            if member.get("joined") is None:
                lines.append(f"| {scene['scene']} | {name} | never | - | - | - | - | - |")
                continue
            lone, grouped, exact = member["lone"], member["groups"], member.get("layout", {})
            lines.append(
                f"| {scene['scene']} | {name} | {member['joined']} | {fmt(lone.get('wrong_pct'))} / "
                f"{fmt(grouped.get('wrong_pct'))} | {grouped.get('wrong_tracked', '-')} | "
                f"{fmt(lone.get('jitter_deg'), 3)} / {fmt(grouped.get('jitter_deg'), 3)} | "
                f"{fmt(lone.get('jitter_mm'), 3)} / {fmt(grouped.get('jitter_mm'), 3)} | "
                f"{fmt(exact.get('jitter_deg'), 3)} / {fmt(exact.get('jitter_mm'), 3)} |"
            )
    lines += ["", f"**Acceptance: {'PASS' if result['passed'] else 'FAIL'}**"]
    lines += [f"- {failure}" for failure in result["failures"]]
    lines += machine_lines(result["machine"])
    return "\n".join(lines) + "\n"


def write_groups_report(
    out: Path,
    *,
    quick: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench groups",
    config: TrackerConfig | None = None,
) -> dict:
    """Run the benchmark and write ``groups.json`` and ``groups.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    result = run_groups_benchmark(quick=quick, progress=progress, config=config)
    write_json(out / "groups.json", result)
    (out / "groups.md").write_text(groups_markdown(result, command))
    return result
